//! The client cycle (docs/design.md §1, §5): analysis → presort → request list → integrate arrivals →
//! upload → render, as an I/O-free state machine.
//!
//! [`ClientCore`] is the quinn-proto-style part: treelets go in with
//! [`handle_treelet`](ClientCore::handle_treelet); a cycle is [`analyse`] then [`presort`]
//! (which returns the request list; [`plan`] does both), [`integrate`] (updates the slot buffer)
//! then [`upload`], and [`render`] draws. No sockets and no clock: a shell (the session in
//! `arbor-client-session`) times the phases, connects the core to a treelet server and never
//! waits on the network inside the loop — whatever has arrived is integrated, the rest is drawn
//! one level coarser. Tests drive the core with treelets read straight from a pool.
//!
//! [`analyse`]: ClientCore::analyse
//! [`presort`]: ClientCore::presort
//! [`plan`]: ClientCore::plan
//! [`integrate`]: ClientCore::integrate
//! [`upload`]: ClientCore::upload
//! [`render`]: ClientCore::render

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::Arc;

use arbor_proto::limits::{MAX_TREELET_BYTES, NODE_BYTES};
use arbor_proto::wire::ViewHint;
use arbor_proto::{Cell, Channel, SceneDescription, TreeletId};
use rayon::prelude::*;
use thiserror::Error;

use crate::analysis::{AnalysisConfig, Feedback, grid_pixels};
use crate::backend::{Backend, BackendError, CpuBackend, PassInput, upload_all};
use crate::backoff::DecodeBackoff;
use crate::bias::{LodBiasControl, ViewNeed};
use crate::camera::Camera;
use crate::coverage::Coverage;
use crate::frustum::{FrustumRequest, FrustumSelector, screen_rect, world_box};
use crate::image::Image;
use crate::incore::{IncoreView, SceneFrame};
use crate::presort::{Presort, PriorityPolicy, RequestItem, centre_weight};
use crate::render::Light;
use crate::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig, SlotError};
use crate::summary::ErrorSummary;
use crate::traverse::{Lod, Ray, trace_past};
use crate::upload::{DEFAULT_FILL_RATIO, UploadPlan};

/// Default per-cycle load limit (treelets inserted per cycle).
pub const DEFAULT_LOAD_LIMIT: u32 = 1024;
/// Default cap on the request list.
pub const DEFAULT_MAX_REQUESTS: usize = 4096;
/// Integrations a pushed treelet waits in the backlog for its parent before it is dropped as an
/// orphan: treelets sent parent first travel on different streams and may arrive the other
/// way round, and a dropped push is not sent again within the server's redelivery guard (over
/// the link emulator the last treelets of a view came 100 ms late that way).
pub const ORPHAN_WAIT_INTEGRATIONS: u64 = 16;
/// Cycles without pushes after an eviction made room: the buffer is full, and a push would only
/// take a slot the next listed arrival evicts again (and the server would push it again).
pub const PUSH_PAUSE_CYCLES: u64 = 16;
/// A presort that knows the whole view frees, from what no pixel reaches, room for at most this
/// many integrations' worth of arrivals at the recent rate (the most treelets one integration
/// inserted lately, decaying by a quarter an integration), and never less than
/// [`MIN_OUTSIDE_EVICTION`]; the next presort frees more. A link delivers a long list over many
/// cycles, and a camera that moves sees another view by then: room made for the whole list at
/// once emptied the buffer of what lay outside the view long before the replacements came, and
/// an orbit brought it back into view to be fetched again (the 10⁸-point city orbiting at 1° a
/// cycle with 32 MiB over a 25 ms, 50 Mbit/s link: up to three quarters of the slots stood
/// empty for seconds while the link was full; at 2° a cycle with 16 MiB over 100 Mbit/s, 2.5–3
/// times the bytes; docs/measurements.md, stop 64).
pub const OUTSIDE_EVICTION_HORIZON: u32 = 4;
/// The least room [`OUTSIDE_EVICTION_HORIZON`] allows: a view that starts to refine after a
/// rest, whose recent rate is nought, still gets a list of some length at once.
pub const MIN_OUTSIDE_EVICTION: u32 = 256;

/// Why a core could not be built.
#[derive(Debug, Error)]
pub enum CoreError {
    /// The slot buffer refused the configuration or the root treelet.
    #[error("slot buffer: {0}")]
    Slots(#[from] SlotError),
    /// A parameter is out of range.
    #[error("invalid parameter: {0}")]
    Invalid(String),
}

/// What the core needs besides the scene.
#[derive(Clone, Debug)]
pub struct CoreConfig {
    /// Feedback ratio and LOD bias.
    pub analysis: AnalysisConfig,
    /// How requests are ranked.
    pub policy: PriorityPolicy,
    /// Cap on the request list (at most the protocol's).
    pub max_requests: usize,
    /// Slot buffer memory budget in bytes (nodes, attributes and bookkeeping).
    pub budget_bytes: u64,
    /// Treelets inserted per cycle at most.
    pub load_limit: u32,
    /// Upload range fill ratio (docs/design.md §5).
    pub fill_ratio: f32,
    /// Channels held and drawn (the scene's channels the client asked for).
    pub channels: Vec<Channel>,
    /// Shading of the render pass.
    pub light: Light,
    /// How the analysis pass picks its pixels.
    pub sampling: Sampling,
    /// Raise the LOD bias when the view needs more slots than the budget holds
    /// (docs/design.md §10).
    pub adjust_bias: bool,
    /// Send deep request lists: the view and each item's error with the list, so the server
    /// may push the descendants the view would refine (docs/design.md §10).
    pub deep_push: bool,
    /// Wall time the analysis pass may take per cycle, ms: with [`Sampling::Adaptive`] the
    /// shell divides it by the measured cost of a sample to size the pass
    /// ([`crate::coverage::SampleBudget`]).
    pub analysis_budget_ms: f64,
    /// Frustum prefetch: while the list from the view's samples has fewer items than this and
    /// the whole view is known, free slots are topped up with the frustum policy's candidates
    /// (refinable leaves in the frustum coarser than a pixel, largest first) at priorities below
    /// every sampled item. The link is nearly idle in that tail, and what lies in the frustum
    /// is what surfaces behind refined gaps and the next camera move need first. Never evicts
    /// for it; 0 turns it off. Ignored by [`PriorityPolicy::Frustum`], which lists the frustum
    /// anyway.
    pub prefetch_below: usize,
    /// Look-past requests: once the whole view is known, the rays of pixels still wanting
    /// refinement are traced again on the CPU as if their coarse hit were empty
    /// ([`crate::traverse::trace_past`]), up to this many coarse hits deep, and the treelets
    /// refining what they meet behind are requested below every sampled item. A coarse voxel
    /// is a hull of what it holds: once refined, the ray often passes through and meets a
    /// surface in another subtree, whose treelet the sampled list could only name one round
    /// trip later. 0 turns it off; ignored by [`PriorityPolicy::Frustum`].
    pub look_past: u8,
}

/// What a presort of the view's samples depended on, when nothing was in the backlog or on its
/// way.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct PresortKey {
    coverage: u64,
    inserted: u64,
    evicted: u64,
    /// [`DecodeBackoff::generation`].
    held: u64,
}

/// What a list must not name: treelets resident, waiting in the backlog, taken off the
/// connection and not yet handed over, or held off after failing to decode.
#[derive(Clone, Copy)]
struct Unlistable<'a> {
    slots: &'a SlotBuffer,
    backlog: &'a HashSet<TreeletId>,
    arriving: &'a HashSet<TreeletId>,
    undecodable: &'a DecodeBackoff,
    cycle: u64,
}

impl Unlistable<'_> {
    fn contains(&self, id: TreeletId) -> bool {
        self.backlog.contains(&id)
            || self.arriving.contains(&id)
            || self.slots.is_resident(id)
            || self.undecodable.holds(id, self.cycle)
    }
}

/// What a render depends on besides the scene and the light, which a core never changes: equal
/// keys, equal images.
#[derive(Clone, Copy, Debug, PartialEq)]
struct RenderKey {
    camera: Camera,
    lod_bias: u64,
    /// [`SlotBuffer::changes`].
    slot_changes: u64,
}

/// The pixels whose rays may meet the cubes of `cells` on `camera`'s image: each cell's screen
/// rectangle, one pixel wider on every side (rays go through pixel centres; the margin covers
/// rounding), clamped to the frame; none for a cell wholly behind the eye or off the frame.
/// `None` when their summed area reaches `max_share` of the frame, or a bound is not a number.
fn cell_rects(
    frame: &SceneFrame,
    camera: &Camera,
    cells: &[Cell],
    max_share: f64,
) -> Option<Vec<[u32; 4]>> {
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let mut rects = Vec::with_capacity(cells.len());
    let mut area = 0.0;
    for &cell in cells {
        let (min, max) = world_box(frame, cell);
        let Some(rect) = screen_rect(camera, min, max) else {
            continue;
        };
        if rect.iter().any(|v| v.is_nan()) {
            return None;
        }
        let [x0, y0, x1, y1] = rect;
        let (x0, y0) = ((x0 - 1.5).floor().max(0.0), (y0 - 1.5).floor().max(0.0));
        let (x1, y1) = (
            (x1 + 0.5).ceil().min(w - 1.0),
            (y1 + 0.5).ceil().min(h - 1.0),
        );
        if x0 > x1 || y0 > y1 {
            // Off the frame: no pixel's ray meets it.
            continue;
        }
        area += (x1 - x0 + 1.0) * (y1 - y0 + 1.0);
        if area >= max_share * w * h {
            return None;
        }
        rects.push([x0 as u32, y0 as u32, x1 as u32, y1 as u32]);
    }
    Some(rects)
}

/// A presort's result and its [`PresortKey`].
#[derive(Debug)]
struct PresortMemo {
    key: PresortKey,
    visible: Vec<u32>,
    requests: Vec<RequestItem>,
    distinct: usize,
}

/// Default [`CoreConfig::look_past`].
pub const DEFAULT_LOOK_PAST: u8 = 2;

/// Most pixels whose rays are traced again for [`CoreConfig::look_past`] in one cycle (an even
/// spread of the pixels still wanting refinement): the tail's pixels are few, and this bounds the
/// cycle's extra CPU work elsewhere.
const LOOK_PAST_PIXELS: usize = 1024;

/// Default [`CoreConfig::analysis_budget_ms`].
pub const DEFAULT_ANALYSIS_BUDGET_MS: f64 = 20.0;

/// Default [`CoreConfig::prefetch_below`]: over the link emulator (25 ms each way, 100 Mbit/s,
/// 512², 64 MiB) 64 made lion's camera jump 0.34 → 0.006 s and engine's 0.42 → 0.30 s for
/// 40 % more bytes on engine's first view (two thirds of the frustum policy's); 256 fetched
/// nearly the whole frustum on engine and slowed its first view.
pub const DEFAULT_PREFETCH_BELOW: usize = 64;

/// Largest share of the view still wanting refinement at which the prefetch around those
/// pixels starts, when the whole scene fits in half the buffer.
const DIRTY_PREFETCH_SHARE: f64 = 0.1;

/// The tail proper: at most this share of the view still wants refinement.
const TAIL_SHARE: f64 = 0.01;

/// Share of the frustum's refinable leaves the sampled list names at which a view counts as
/// open (little hidden) and the frustum is prefetched at once. Measured at 512² over the link:
/// lion 0.31–0.46 in every cycle, engine (a casing hiding its insides) 0.01–0.22.
const OPEN_VIEW_SHARE: f64 = 0.25;

/// Share of the view that must be known before it can count as open.
const OPEN_VIEW_KNOWN: f64 = 0.25;

/// Side of the screen tiles `DirtyTiles` marks, pixels.
pub const DIRTY_TILE: u32 = 8;

/// The screen tiles holding a known pixel that still wants refinement, and their neighbours.
struct DirtyTiles {
    /// Tiles per row and column.
    cols: u32,
    rows: u32,
    marked: Vec<bool>,
    any: bool,
}

impl DirtyTiles {
    fn of(coverage: &Coverage) -> Self {
        let (w, h) = coverage.size();
        let (cols, rows) = (w.div_ceil(DIRTY_TILE).max(1), h.div_ceil(DIRTY_TILE).max(1));
        let mut marked = vec![false; (cols * rows) as usize];
        let mut any = false;
        for (i, s) in coverage.known_samples() {
            if s.refinable_error() <= 0.0 {
                continue;
            }
            any = true;
            let (tx, ty) = ((i % w.max(1)) / DIRTY_TILE, (i / w.max(1)) / DIRTY_TILE);
            for y in ty.saturating_sub(1)..(ty + 2).min(rows) {
                for x in tx.saturating_sub(1)..(tx + 2).min(cols) {
                    marked[(y * cols + x) as usize] = true;
                }
            }
        }
        Self {
            cols,
            rows,
            marked,
            any,
        }
    }

    /// Whether the pixel rectangle `[x0, y0, x1, y1]` touches a marked tile (a rectangle with
    /// a non-finite bound touches every tile).
    fn covers(&self, rect: [f64; 4]) -> bool {
        if !self.any || !rect.iter().all(|v| v.is_finite()) {
            return self.any;
        }
        let tile = f64::from(DIRTY_TILE);
        let (width, height) = (f64::from(self.cols) * tile, f64::from(self.rows) * tile);
        if rect[2] < 0.0 || rect[3] < 0.0 || rect[0] >= width || rect[1] >= height {
            return false;
        }
        let index = |v: f64, n: u32| (v / tile).floor().clamp(0.0, f64::from(n - 1)) as u32;
        let (x0, x1) = (index(rect[0], self.cols), index(rect[2], self.cols));
        let (y0, y1) = (index(rect[1], self.rows), index(rect[3], self.rows));
        (y0..=y1).any(|y| (x0..=x1).any(|x| self.marked[(y * self.cols + x) as usize]))
    }
}

/// The [`ViewHint`] of `camera` at `bias` with `free_slots` (capped at the protocol's limit);
/// `None` when it would not pass [`ViewHint::check`]. What a deep list announces; the server
/// casts its visible cuts from it.
pub fn view_hint(camera: &Camera, bias: f64, free_slots: u32) -> Option<ViewHint> {
    let f32s = |v: glam::DVec3| [v.x as f32, v.y as f32, v.z as f32];
    let hint = ViewHint {
        eye: camera.position.to_array(),
        forward: f32s(camera.forward),
        up: f32s(camera.up),
        tan_half_fov_y: (camera.fov_y * 0.5).tan() as f32,
        aspect: (f64::from(camera.width) / f64::from(camera.height.max(1))) as f32,
        footprint: (camera.pixel_angle() * bias) as f32,
        free_slots: free_slots.min(ViewHint::MAX_FREE_SLOTS),
    };
    hint.check().is_ok().then_some(hint)
}

/// How the analysis pass picks its pixels each cycle.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Sampling {
    /// From what is known of the view ([`crate::coverage`]): pixels whose treelet arrived, then
    /// unknown ones, as many as the cycle's budget allows.
    #[default]
    Adaptive,
    /// The thesis's fixed grid: `1/n` of the frame per axis every cycle, jittered.
    Grid,
}

impl Sampling {
    /// Parses `adaptive` or `grid` (the CLI spelling).
    pub fn parse(text: &str) -> Option<Self> {
        match text {
            "adaptive" => Some(Self::Adaptive),
            "grid" => Some(Self::Grid),
            _ => None,
        }
    }
}

impl Default for CoreConfig {
    fn default() -> Self {
        Self {
            analysis: AnalysisConfig::default(),
            policy: PriorityPolicy::default(),
            max_requests: DEFAULT_MAX_REQUESTS,
            budget_bytes: 64 << 20,
            load_limit: DEFAULT_LOAD_LIMIT,
            fill_ratio: DEFAULT_FILL_RATIO,
            channels: vec![Channel::Color, Channel::Normal, Channel::Density],
            light: Light::default(),
            sampling: Sampling::default(),
            adjust_bias: true,
            deep_push: true,
            analysis_budget_ms: DEFAULT_ANALYSIS_BUDGET_MS,
            prefetch_below: DEFAULT_PREFETCH_BELOW,
            look_past: DEFAULT_LOOK_PAST,
        }
    }
}

/// Refuses a LOD bias that is not finite and in (0, 1e6].
fn validate_lod_bias(lod_bias: f64) -> Result<(), CoreError> {
    if lod_bias.is_finite() && lod_bias > 0.0 && lod_bias <= 1e6 {
        Ok(())
    } else {
        Err(CoreError::Invalid(format!(
            "LOD bias {lod_bias} must be finite and in (0, 1e6]"
        )))
    }
}

impl CoreConfig {
    /// Checks ranges that would otherwise only fail deep inside a cycle.
    pub fn validate(&self) -> Result<(), CoreError> {
        let a = &self.analysis;
        if !(1..=crate::analysis::MAX_FEEDBACK_RATIO).contains(&a.ratio) {
            return Err(CoreError::Invalid(format!(
                "feedback ratio {} not in 1..={}",
                a.ratio,
                crate::analysis::MAX_FEEDBACK_RATIO
            )));
        }
        validate_lod_bias(a.lod_bias)?;
        if !(0.0..=1.0).contains(&self.fill_ratio) {
            return Err(CoreError::Invalid(format!(
                "fill ratio {} not in 0..=1",
                self.fill_ratio
            )));
        }
        if self.load_limit == 0 || self.max_requests == 0 {
            return Err(CoreError::Invalid(
                "load limit and request cap must be at least 1".into(),
            ));
        }
        if !(self.analysis_budget_ms.is_finite()
            && self.analysis_budget_ms > 0.0
            && self.analysis_budget_ms <= 60_000.0)
        {
            return Err(CoreError::Invalid(format!(
                "analysis budget {} ms must be in (0, 60000]",
                self.analysis_budget_ms
            )));
        }
        if self.max_requests > arbor_proto::limits::MAX_REQUEST_ITEMS {
            return Err(CoreError::Invalid(format!(
                "request cap {} above the protocol's {}",
                self.max_requests,
                arbor_proto::limits::MAX_REQUEST_ITEMS
            )));
        }
        Ok(())
    }
}

/// The first half of a cycle: what was seen and what to ask for.
#[derive(Clone, Debug, Default)]
pub struct Plan {
    /// The request list, highest priority first.
    pub requests: Vec<(TreeletId, f32)>,
    /// Per request, the screen-space error (levels) measured at the leaf it refines.
    pub errors: Vec<f32>,
    /// Requests from this index on are the frustum prefetch ([`CoreConfig::prefetch_below`]):
    /// guesses, not what the samples or the look-past rays found (`requests.len()`: none). A
    /// deep list says so to the server, which sends them after a visible cut's pushes and
    /// keeps few in flight, so the next view's list does not queue behind them.
    pub prefetch_from: usize,
    /// The view of this cycle for a deep request list, when [`CoreConfig::deep_push`] is on and
    /// the view is expressible (see [`ViewHint::check`]).
    pub view: Option<ViewHint>,
    /// Distinct refinable treelets wanted (before the cap).
    pub distinct_requests: usize,
    /// Screen-space error over every known pixel of the view.
    pub error: ErrorSummary,
    /// Samples of this cycle's pass that hit something.
    pub samples: u32,
    /// The LOD bias this cycle's knowledge was gathered with.
    pub lod_bias: f64,
    /// The bias changed this cycle (the request list is empty: it was for the old target).
    pub bias_changed: bool,
    /// Share of the view's pixels known.
    pub known_share: f64,
    /// Every pixel is known and final: the image equals the fully resident render.
    pub converged: bool,
}

/// What this cycle's analysis pass did.
#[derive(Clone, Copy, Debug, Default)]
pub struct Analysis {
    /// Pixels sampled.
    pub sampled: usize,
}

/// The second half: what the slot buffer did.
#[derive(Clone, Debug)]
pub struct Integration {
    /// Treelets inserted into the slot buffer.
    pub inserted: u32,
    /// Treelets evicted to make room (descendants included).
    pub evicted: u32,
    /// Arrivals dropped: parent gone, no room, undecodable, or backlog overflow.
    pub dropped: u32,
    /// Of the inserted, treelets the server pushed (named by no recent list).
    pub pushed: u32,
    /// Pushed treelets dropped: parent not resident, or no free slot.
    pub push_dropped: u32,
    /// Arrivals already resident or already waiting: bytes the link carried for nothing.
    pub received_twice: u32,
}

/// The client's cycle state: slot buffer, presort, what is known of the view, the LOD bias,
/// arrivals waiting for a slot.
#[derive(Debug)]
pub struct ClientCore {
    scene: Arc<SceneDescription>,
    frame: SceneFrame,
    config: CoreConfig,
    slots: SlotBuffer,
    presort: Presort,
    /// The last presort of the view's samples and what it depended on: a view whose samples and
    /// resident set have not changed (a converged view, every cycle) gets it again instead of
    /// another pass over every known pixel (a million at 1024²).
    presort_memo: Option<PresortMemo>,
    /// [`Self::error_summary`]'s last result and the coverage generation it was made at.
    error_memo: Option<(u64, ErrorSummary)>,
    feedback: Feedback,
    coverage: Coverage,
    bias: LodBiasControl,
    /// The refinable leaves of resident treelets, for [`PriorityPolicy::Frustum`].
    frustum: Option<FrustumSelector>,
    /// The last full look at the view raised the bias: fill free slots only until one fits.
    bias_unsettled: bool,
    /// Treelets evicted by [`SlotBuffer::evict_outside`] since the last integration.
    evicted_outside: u32,
    /// Treelets inserted per integration lately: the most of the last one and three quarters of
    /// the rate before, so a burst is remembered for a few integrations
    /// ([`OUTSIDE_EVICTION_HORIZON`]).
    arrival_rate: u32,
    /// No pushes are announced before this cycle ([`PUSH_PAUSE_CYCLES`] after an eviction).
    pushes_paused_until: u64,
    /// The look-past's last traces and what they depended on ([`LookPastKey`]).
    look_past_memo: Option<(LookPastKey, Vec<(TreeletId, f32)>)>,
    /// The last image [`Self::render`] read back, and its key: an unchanged view is not
    /// rendered again (on the CPU twins a 1024² frame costs about 0.4 s on two cores, and most
    /// cycles of a refinement's tail change nothing).
    render_memo: Option<(RenderKey, Image)>,
    /// What the backend's own target holds since the last [`Self::render_in_place`], if that
    /// is known: the window viewer then skips the pass on idle frames.
    in_place: Option<RenderKey>,
    /// [`Self::skipped_renders`].
    skipped_renders: u64,
    /// [`Self::partial_renders`].
    partial_renders: u64,
    /// Integrations so far, and since which one each waiting orphan push has waited.
    integrations: u64,
    orphans_since: HashMap<TreeletId, u64>,
    /// Arrivals already resident or waiting, since the last integration.
    received_twice: u32,
    /// Treelets evicted since the view last changed: one asked for again is needed by the
    /// view although no pixel hits it, and is pinned ([`SlotBuffer::pin`]).
    evicted_in_view: HashSet<TreeletId>,
    /// Ids of the last two request lists: an arrival named by neither was pushed.
    listed: HashSet<TreeletId>,
    listed_previous: HashSet<TreeletId>,
    last_camera: Option<Camera>,
    backlog: VecDeque<DecodedTreelet>,
    backlog_ids: HashSet<TreeletId>,
    /// Received and not yet handed over ([`ClientCore::note_arriving`]): not to be listed.
    arriving: HashSet<TreeletId>,
    /// Arrivals that could not be decoded, held off the lists for a while
    /// ([`ClientCore::handle_undecodable`]).
    undecodable: DecodeBackoff,
    /// The last prefetch found nothing left in the frustum. Holds until the view or the
    /// resident set changes, so a converged view does not walk the frustum every cycle.
    frustum_exhausted: bool,
    backlog_dropped: u32,
    cycle: u64,
    backend: Box<dyn Backend>,
}

/// The fewest cycles a slot stays visible after it was last seen with adaptive sampling: feedback
/// may come back a few cycles late.
pub const MIN_VISIBILITY_CYCLES: usize = 8;

/// Cycles of the thesis's full round: n² for a feedback ratio n (at most `u16::MAX`).
fn grid_cycles(ratio: u32) -> usize {
    (ratio as usize * ratio as usize).clamp(1, usize::from(u16::MAX))
}

impl ClientCore {
    /// A core holding only the root treelet, running its passes on the CPU twins.
    pub fn new(
        scene: Arc<SceneDescription>,
        config: CoreConfig,
        root: DecodedTreelet,
    ) -> Result<Self, CoreError> {
        Self::with_backend(scene, config, root, Box::new(CpuBackend))
    }

    /// A core holding only the root treelet, running its passes on `backend`.
    pub fn with_backend(
        scene: Arc<SceneDescription>,
        config: CoreConfig,
        root: DecodedTreelet,
        backend: Box<dyn Backend>,
    ) -> Result<Self, CoreError> {
        config.validate()?;
        let max_slots = backend.max_slots(scene.treelet_nodes, &config.channels);
        let slot_bytes = SlotBuffer::slot_bytes(scene.treelet_nodes, &config.channels);
        let budget_bytes = config
            .budget_bytes
            .min(u64::from(max_slots).saturating_mul(slot_bytes));
        if budget_bytes < config.budget_bytes {
            tracing::warn!(
                "the {} backend holds at most {max_slots} slots: budget lowered from {} to {} bytes",
                backend.name(),
                config.budget_bytes,
                budget_bytes
            );
        }
        let frustum =
            (config.policy == PriorityPolicy::Frustum || config.prefetch_below > 0).then(|| {
                let mut f = FrustumSelector::default();
                f.add(&root.treelet, scene.max_depth);
                f
            });
        let slots = SlotBuffer::new(
            SlotConfig {
                budget_bytes,
                treelet_nodes: scene.treelet_nodes,
                channels: config.channels.clone(),
                visibility_max: grid_cycles(config.analysis.ratio) as u16,
                load_limit: config.load_limit,
            },
            root,
        )?;
        Ok(Self {
            frame: SceneFrame::of(&scene),
            presort: Presort::new(config.policy, config.max_requests),
            presort_memo: None,
            error_memo: None,
            coverage: Coverage::new(0, 0, config.analysis.ratio),
            bias: LodBiasControl::new(config.analysis.lod_bias),
            frustum,
            bias_unsettled: false,
            evicted_outside: 0,
            arrival_rate: 0,
            pushes_paused_until: 0,
            look_past_memo: None,
            render_memo: None,
            in_place: None,
            skipped_renders: 0,
            partial_renders: 0,
            integrations: 0,
            orphans_since: HashMap::new(),
            received_twice: 0,
            evicted_in_view: HashSet::new(),
            listed: HashSet::new(),
            listed_previous: HashSet::new(),
            last_camera: None,
            scene,
            config,
            slots,
            feedback: Feedback::default(),
            backlog: VecDeque::new(),
            backlog_ids: HashSet::new(),
            arriving: HashSet::new(),
            undecodable: DecodeBackoff::default(),
            frustum_exhausted: false,
            backlog_dropped: 0,
            cycle: 0,
            backend,
        })
    }

    /// The scene streamed.
    pub fn scene(&self) -> &Arc<SceneDescription> {
        &self.scene
    }

    /// Where the scene sits in the world.
    pub fn frame(&self) -> &SceneFrame {
        &self.frame
    }

    /// The slot buffer.
    pub fn slots(&self) -> &SlotBuffer {
        &self.slots
    }

    /// The configuration (budget as asked for; the slot buffer holds what the backend allows).
    pub fn config(&self) -> &CoreConfig {
        &self.config
    }

    /// The last feedback the backend handed back.
    pub fn feedback(&self) -> &Feedback {
        &self.feedback
    }

    /// What is known of the view.
    pub fn coverage(&self) -> &Coverage {
        &self.coverage
    }

    /// The LOD bias control (the bias in effect, when it was first raised).
    pub fn lod_bias(&self) -> &LodBiasControl {
        &self.bias
    }

    /// Makes `base` the configured LOD bias from the next cycle on (a viewer's quality keys):
    /// the view's knowledge and hints start afresh under it, as when the memory control moves
    /// the bias, and that control starts again around it. Refused, changing nothing, when `base` is not finite and in
    /// (0, 1e6].
    pub fn set_lod_bias(&mut self, base: f64) -> Result<(), CoreError> {
        validate_lod_bias(base)?;
        if base == self.bias.base() {
            return Ok(());
        }
        self.config.analysis.lod_bias = base;
        self.bias.set_base(base);
        // A new target, as when the memory control moves the bias: passes judged against the
        // old one are neither knowledge nor hints, and the control is no longer raising.
        self.coverage.reset_target(self.cycle);
        self.bias_unsettled = false;
        self.forget_pins();
        Ok(())
    }

    /// Cycles planned so far.
    pub fn cycle(&self) -> u64 {
        self.cycle
    }

    /// Arrivals waiting for a slot (beyond the load limit, or a pushed one for its parent).
    pub fn backlog_len(&self) -> usize {
        self.backlog.len()
    }

    /// Arrivals that will want a slot: the backlog and what was taken off the connection this
    /// cycle but is decoded only after the list is sent ([`Self::note_arriving`]). Room for
    /// requests and pushes is what the buffer has beyond these (a burst of arrivals, such as
    /// the pushes for `Hello`'s view on loopback, otherwise makes the next list ask for slots
    /// already spoken for, and the surplus is dropped on arrival).
    fn pending(&self) -> usize {
        self.backlog.len() + self.arriving.len()
    }

    /// Treelets the connection has received and the caller has yet to decode and hand over with
    /// [`handle_treelet`](Self::handle_treelet): the next [`presort`](Self::presort) does not
    /// list them. Taking arrivals off the connection just before the presort and decoding them
    /// after the list is sent keeps the list from naming what is already here without delaying
    /// it by the decoding (named, a treelet delivered longer ago than the server's redelivery
    /// guard is sent again). Forgotten at the next [`integrate`](Self::integrate).
    pub fn note_arriving(&mut self, ids: impl IntoIterator<Item = TreeletId>) {
        self.arriving.extend(ids);
    }

    /// Queues an arrived treelet for the next [`integrate`](Self::integrate). Duplicates and
    /// treelets already resident are ignored (and counted as received twice). The backlog is
    /// bounded (a few cycles of the load limit): past that the oldest arrival is dropped, to be
    /// requested again if still needed.
    pub fn handle_treelet(&mut self, treelet: DecodedTreelet) {
        let id = treelet.treelet.header.id;
        self.undecodable.decoded(id);
        if self.slots.is_resident(id) || !self.backlog_ids.insert(id) {
            self.received_twice += 1;
            return;
        }
        self.backlog.push_back(treelet);
        let cap = self.backlog_cap();
        while self.backlog.len() > cap {
            if let Some(old) = self.backlog.pop_front() {
                self.backlog_ids.remove(&old.treelet.header.id);
                self.orphans_since.remove(&old.treelet.header.id);
                self.backlog_dropped += 1;
            }
        }
    }

    /// A treelet arrived that could not be decoded (the caller logs why): it is held off the
    /// request lists for a while, longer after each failure ([`crate::backoff`]), so the server
    /// is not asked for the same bad bytes every cycle. A copy that decodes later, handed over
    /// with [`handle_treelet`](Self::handle_treelet), clears the hold.
    pub fn handle_undecodable(&mut self, id: TreeletId) {
        self.undecodable.failed(id, self.cycle);
    }

    /// Forgets every undecodable arrival: the connection now goes to a server (maybe another
    /// replica) whose copies may decode.
    pub fn forget_undecodable(&mut self) {
        self.undecodable.clear();
    }

    /// The undecodable arrivals and their holds.
    pub fn undecodable(&self) -> &DecodeBackoff {
        &self.undecodable
    }

    /// What lists must not name now.
    fn unlistable(&self) -> Unlistable<'_> {
        Unlistable {
            slots: &self.slots,
            backlog: &self.backlog_ids,
            arriving: &self.arriving,
            undecodable: &self.undecodable,
            cycle: self.cycle,
        }
    }

    /// Cycles of the thesis's full round for this core's feedback ratio.
    fn grid_cycles(&self) -> usize {
        grid_cycles(self.config.analysis.ratio)
    }

    /// Whether lists carry the view, so the server may push: an arrival named by no recent list
    /// is then a push.
    fn pushes_asked(&self) -> bool {
        self.config.deep_push && self.config.policy != PriorityPolicy::Frustum
    }

    /// Most arrivals waiting for a slot: a few cycles of the load limit, or a quarter of the
    /// slots when that is more. Requests are capped by it too, so it must hold a link's worth
    /// in flight: a list cut to fit a small backlog cancels what is already on its way (measured
    /// with 1,024 on a 100 Mbit/s, 50 ms link: 200 ms without an arrival).
    fn backlog_cap(&self) -> usize {
        (self.config.load_limit as usize * 4)
            .max(self.slots.capacity() as usize / 4)
            .max(64)
    }

    /// Remembers what the slot buffer evicted (bounded: a view that evicts this much is
    /// thrashing anyway, and forgetting only costs a pin).
    fn note_evictions(&mut self) {
        if self.evicted_in_view.len() > 1 << 16 {
            self.evicted_in_view.clear();
        }
        self.evicted_in_view.extend(self.slots.take_evicted());
    }

    /// Forgets, from `cycle` on, what the view knew where evictions since the last call restored
    /// a leaf: a ray may have passed through the gaps of an evicted subtree on its way to
    /// another voxel, and the restored leaf is solid. Only the pixels whose rays may meet those
    /// leaves ([`Self::eviction_rects`]), or the whole view when that is not bounded.
    fn forget_evicted(&mut self, cycle: u64) {
        let roots = self.slots.take_evicted_roots();
        if roots.is_empty() {
            return;
        }
        match self.eviction_rects(&roots) {
            Some(rects) => self.coverage.forget(cycle, &rects),
            None => self.coverage.reset(cycle),
        }
    }

    /// The pixels whose rays may meet the leaves an eviction restored at `roots`: each cell's
    /// screen rectangle, one pixel wider on every side (rays go through pixel centres; the
    /// margin covers rounding), clamped to the frame; none for a cell wholly behind the eye.
    /// `None` — forget the whole view — when the rectangles would cover a quarter of it or
    /// more, or there is no camera yet.
    fn eviction_rects(&self, roots: &[Cell]) -> Option<Vec<[u32; 4]>> {
        cell_rects(&self.frame, &self.last_camera?, roots, 0.25)
    }

    /// The view changed (camera or LOD bias): what it needed no longer says anything.
    fn forget_pins(&mut self) {
        self.slots.unpin_all();
        self.evicted_in_view.clear();
        self.frustum_exhausted = false;
    }

    /// The analysis config of this cycle: the configured ratio, the bias in effect.
    fn analysis_config(&self) -> AnalysisConfig {
        AnalysisConfig {
            ratio: self.config.analysis.ratio,
            lod_bias: self.bias.bias(),
        }
    }

    /// Runs the analysis pass for `camera` over at most `max_samples` pixels (the caller's
    /// measured budget; at least the `1/n` grid's share) and takes what it found into the view's
    /// knowledge. A new camera (or frame size) starts the knowledge afresh.
    pub fn analyse(
        &mut self,
        camera: &Camera,
        max_samples: usize,
    ) -> Result<Analysis, BackendError> {
        let cycle = self.cycle;
        if self.coverage.size() != (camera.width, camera.height) {
            self.coverage = Coverage::new(camera.width, camera.height, self.config.analysis.ratio);
            self.coverage.reset(cycle);
            self.forget_pins();
        } else if self.last_camera.as_ref() != Some(camera) {
            self.coverage.reset(cycle);
            self.bias.view_changed();
            self.forget_pins();
        }
        self.last_camera = Some(*camera);
        let pixels = match self.config.sampling {
            Sampling::Adaptive => {
                // A slot stays visible for about two full looks at the view: the thesis's n²
                // cycles when a cycle samples 1/n² of it, a few when it samples all of it (a
                // moving camera's buffer would otherwise hold all it saw in the last n² cycles
                // and never make room for what comes into view).
                let per_look =
                    (camera.width as usize * camera.height as usize).div_ceil(max_samples.max(1));
                let span = (2 * per_look)
                    .max(MIN_VISIBILITY_CYCLES)
                    .min(self.grid_cycles());
                self.slots.set_visibility_max(span as u16);
                let slots = &self.slots;
                self.coverage
                    .plan(cycle, max_samples, |id| slots.is_resident(id))
            }
            Sampling::Grid => grid_pixels(
                camera.width,
                camera.height,
                self.config.analysis.ratio,
                cycle,
            ),
        };
        let mut feedback = std::mem::take(&mut self.feedback);
        let ran = self.run_pass(camera, |backend, input| {
            backend.analyse(input, &pixels, cycle, &mut feedback)
        });
        // On failure the feedback is whatever the backend left: not taken into the knowledge.
        if ran.is_ok() {
            self.coverage.handle_feedback(&feedback);
        }
        self.feedback = feedback;
        ran?;
        Ok(Analysis {
            sampled: pixels.len(),
        })
    }

    /// Presort of what is known: ages visibility, marks what is seen, adjusts the LOD bias when
    /// the view is fully known, and returns the request list to send (capped to the room the
    /// slot buffer has: a treelet that would be dropped for lack of room is not asked for).
    /// Ends the cycle's first half.
    pub fn presort(&mut self) -> Plan {
        let (visible, mut requests, distinct) = match self.config.policy {
            PriorityPolicy::Frustum => self.select_frustum(),
            _ => self.select_from_feedback(),
        };
        self.slots.begin_cycle();
        for &s in &visible {
            self.slots.mark_visible(s);
        }
        let cycle = self.cycle;
        let bias_in_effect = self.bias.bias();
        let mut bias_changed = false;
        let mut evicted = 0;
        let whole_view = self.coverage.known() == self.coverage.pixels();
        if self.config.adjust_bias {
            let pending = self.pending() as u32;
            let wanted = self.predicted_slots(&requests, false);
            // A part of the view that already wants more than the room is enough to raise (see
            // `LodBiasControl::raise_if_oversubscribed`): a camera that moves every cycle may
            // never let a slow pass know the whole view. The room is at least the free slots,
            // and finding it walks every slot record, so a part whose wants fit the free slots
            // (most cycles) is not asked about.
            if whole_view || wanted > self.slots.free_slots().saturating_sub(pending) {
                let need = ViewNeed {
                    visible_slots: visible.len() as u32,
                    wanted,
                    room: self.slots.room_outside(&visible).saturating_sub(pending),
                    capacity: self.slots.capacity(),
                };
                bias_changed = if whole_view {
                    self.bias.update(cycle, need)
                } else {
                    self.bias.raise_if_oversubscribed(cycle, need)
                };
                if bias_changed {
                    tracing::debug!(
                        cycle,
                        bias = self.bias.bias(),
                        ?need,
                        whole_view,
                        "LOD bias adjusted"
                    );
                    self.coverage.reset_target(cycle + 1);
                    self.forget_pins();
                    requests.clear();
                }
            }
            self.bias_unsettled = bias_changed;
        }
        if whole_view {
            // The whole view is known: make room from what no pixel reaches, for the arrivals
            // of the next few integrations.
            let free = self.slots.room().saturating_sub(self.pending() as u32);
            if !bias_changed && distinct as u32 > free {
                let soon = OUTSIDE_EVICTION_HORIZON
                    .saturating_mul(self.arrival_rate)
                    .max(MIN_OUTSIDE_EVICTION)
                    .saturating_sub(self.slots.free_slots());
                let count = (distinct as u32 - free).min(soon);
                if count > 0 {
                    evicted = self.slots.evict_outside(&visible, count);
                    self.forget_evicted(cycle + 1);
                }
            }
        }
        self.note_evictions();
        let mut prefetch_from = requests.len();
        if !bias_changed {
            self.look_past(&mut requests);
            prefetch_from = requests.len();
            self.prefetch(&mut requests);
        }
        // Ask for no more than could be inserted: with an oversubscribed budget the rest would
        // only be dropped on arrival, and so would arrivals beyond what the backlog holds. While
        // the bias is still rising, only free slots are filled: what an eviction would make room
        // for may not be wanted at the coarser target.
        let room = if self.bias_unsettled {
            self.slots.free_slots()
        } else {
            self.slots.room()
        };
        let room = (room as usize).min(self.backlog_cap());
        requests.truncate(room.saturating_sub(self.pending()));
        let prefetch_from = prefetch_from.min(requests.len());
        self.evicted_outside += evicted;
        let error = self.error_summary();
        let samples = self.feedback.samples.iter().filter(|s| s.is_hit()).count() as u32;
        let pixels = self.coverage.pixels().max(1);
        self.cycle += 1;
        self.listed_previous =
            std::mem::replace(&mut self.listed, requests.iter().map(|r| r.id).collect());
        let push_budget = self
            .predicted_slots(&requests, true)
            .saturating_sub(requests.len() as u32);
        Plan {
            view: self.view_hint(push_budget),
            errors: requests.iter().map(|r| r.error).collect(),
            prefetch_from,
            requests: requests.iter().map(|r| (r.id, r.priority)).collect(),
            distinct_requests: distinct,
            samples,
            error,
            lod_bias: bias_in_effect,
            bias_changed,
            known_share: f64::from(self.coverage.known()) / f64::from(pixels),
            converged: !bias_changed && self.coverage.converged(),
        }
    }

    /// The error of every known pixel, summarised; the last one again while the samples have
    /// not changed (its p95 is a selection over every known pixel).
    fn error_summary(&mut self) -> ErrorSummary {
        let generation = self.coverage.generation();
        if let Some((g, e)) = &self.error_memo
            && *g == generation
        {
            return *e;
        }
        let errors: Vec<f32> = self
            .coverage
            .known_samples()
            .map(|(_, s)| s.refinable_error())
            .collect();
        let error = ErrorSummary::from_samples(&errors, 1.0);
        self.error_memo = Some((generation, error));
        error
    }

    /// Visible slots and requests from every known pixel of the view.
    fn select_from_feedback(&mut self) -> (Vec<u32>, Vec<RequestItem>, usize) {
        // With nothing in the backlog or on its way, the presort reads only the samples and the
        // resident set.
        let held = self.undecodable.generation(self.cycle);
        let key = (self.backlog_ids.is_empty() && self.arriving.is_empty()).then(|| PresortKey {
            coverage: self.coverage.generation(),
            inserted: self.slots.stats().inserted,
            evicted: self.slots.stats().evicted,
            held,
        });
        if let (Some(key), Some(memo)) = (key, &self.presort_memo)
            && memo.key == key
        {
            let hit = (memo.visible.clone(), memo.requests.clone(), memo.distinct);
            // Every test run checks the memo against a fresh presort.
            #[cfg(debug_assertions)]
            assert_eq!(
                self.presort_samples(),
                hit,
                "a memoised presort differs from a fresh one"
            );
            return hit;
        }
        let (visible, requests, distinct) = self.presort_samples();
        self.presort_memo = key.map(|key| PresortMemo {
            key,
            visible: visible.clone(),
            requests: requests.clone(),
            distinct,
        });
        (visible, requests, distinct)
    }

    /// [`Self::select_from_feedback`] computed afresh.
    fn presort_samples(&mut self) -> (Vec<u32>, Vec<RequestItem>, usize) {
        let slots = &self.slots;
        let unlistable = Unlistable {
            slots,
            backlog: &self.backlog_ids,
            arriving: &self.arriving,
            undecodable: &self.undecodable,
            cycle: self.cycle,
        };
        let (w, h) = self.coverage.size();
        let centre = self.config.policy == PriorityPolicy::Centre;
        let weighted = self.coverage.known_samples().map(|(i, s)| {
            let weight = if centre {
                centre_weight(i % w.max(1), i / w.max(1), w, h)
            } else {
                1.0
            };
            (weight, s)
        });
        let sorted = self.presort.run_weighted(
            weighted,
            self.scene.treelet_nodes,
            slots.capacity(),
            |s| slots.parent_slot(s),
            |id| unlistable.contains(id),
            |id| slots.slot_of(id),
        );
        (
            sorted.visible_slots,
            sorted.requests,
            sorted.distinct_requests,
        )
    }

    /// Whether the whole scene fits in half the buffer: then nothing the look-past or the
    /// prefetch adds can ever stand in the view's way.
    fn scene_fits_half(&self) -> bool {
        self.scene.treelet_count as usize <= self.slots.capacity() as usize / 2
    }

    /// How many more requests the look-past and the prefetch may add to `requests`: only into
    /// the half of the buffer the view does not need (with a tight budget every slot stays the
    /// view's), counting what is resident, arriving and predicted below the list, and within
    /// the list's cap.
    fn room_beside_the_view(&self, requests: &[RequestItem]) -> usize {
        let taken = self.slots.used_slots() as usize
            + self.pending()
            + self.predicted_slots(requests, true) as usize;
        (self.slots.capacity() as usize / 2)
            .saturating_sub(taken)
            .min(self.config.max_requests.saturating_sub(requests.len()))
    }

    /// Look-past requests ([`CoreConfig::look_past`]), appended below every sampled item,
    /// into the half of the buffer the view does not need (as the prefetch); with a scene
    /// larger than that half, only in the tail proper.
    fn look_past(&mut self, requests: &mut Vec<RequestItem>) {
        let depth = usize::from(self.config.look_past);
        if self.config.policy == PriorityPolicy::Frustum || depth == 0 || self.bias_unsettled {
            return;
        }
        let Some(camera) = self.last_camera else {
            return;
        };
        let pixels = self.coverage.pixels().max(1);
        let dirty = self.coverage.dirty();
        if self.coverage.known() < pixels || dirty == 0 {
            return;
        }
        if !self.scene_fits_half() && f64::from(dirty) > TAIL_SHARE * f64::from(pixels) {
            return;
        }
        let free = self.room_beside_the_view(requests);
        if free == 0 {
            return;
        }
        // In the tail most cycles wait for arrivals: nothing sampled, nothing inserted, the
        // same rays would meet the same treelets.
        let stats = self.slots.stats();
        let key = LookPastKey {
            camera,
            bias: self.bias.bias().to_bits(),
            inserted: stats.inserted,
            evicted: stats.evicted,
            sampled: self.coverage.sampled_since_reset(),
            known: self.coverage.known(),
        };
        if self.look_past_memo.as_ref().is_none_or(|(k, _)| *k != key) {
            let behind = self.trace_behind(&camera, depth);
            self.look_past_memo = Some((key, behind));
        }
        let behind = self.look_past_memo.as_ref().map_or(&[][..], |(_, b)| b);
        let lowest = requests.iter().map(|r| r.priority).fold(1.0f32, f32::min);
        let mut seen: HashSet<TreeletId> = requests.iter().map(|r| r.id).collect();
        let unlistable = self.unlistable();
        let items = behind
            .iter()
            .copied()
            .filter(|&(id, _)| !unlistable.contains(id) && seen.insert(id))
            .take(free)
            .map(|(id, error)| RequestItem {
                id,
                error: error.min(ViewHint::MAX_ERROR),
                samples: 0,
                weight: 0.0,
                // Below every sampled item, above the prefetch.
                priority: lowest * 0.75 * (0.5 + 0.5 * error / (1.0 + error)),
            });
        requests.extend(items);
    }

    /// What the rays of (an even spread of at most [`LOOK_PAST_PIXELS`] of) the pixels still
    /// wanting refinement meet behind their coarse hits, up to `depth` coarse hits deep, the
    /// coarsest first; a treelet met by several rays comes several times.
    fn trace_behind(&self, camera: &Camera, depth: usize) -> Vec<(TreeletId, f32)> {
        let width = self.coverage.size().0.max(1);
        let wanting: Vec<u32> = self
            .coverage
            .known_samples()
            .filter(|(_, s)| s.wants_refinement())
            .map(|(i, _)| i)
            .collect();
        let stride = wanting.len().div_ceil(LOOK_PAST_PIXELS).max(1);
        let wanting: Vec<u32> = wanting.into_iter().step_by(stride).collect();
        let lod = Lod {
            pixel_angle: camera.pixel_angle(),
            lod_bias: self.bias.bias(),
            max_depth: self.frame.max_depth,
        };
        let (view, frame) = (self.slots.view(), self.frame);
        let rays = camera.pixel_rays();
        let mut behind: Vec<(TreeletId, f32)> = wanting
            .par_iter()
            .flat_map_iter(|&i| {
                let ray = rays.ray(f64::from(i % width) + 0.5, f64::from(i / width) + 0.5);
                looked_past(&view, &frame, &ray, &lod, depth)
            })
            .collect();
        // The coarsest first, should the room not take them all.
        behind.sort_by(|a, b| b.1.total_cmp(&a.1));
        behind
    }

    /// Tops the list up from the frustum ([`CoreConfig::prefetch_below`]) once the whole view
    /// is known (an open view once [`OPEN_VIEW_KNOWN`] of it is), at priorities below every
    /// listed item, while the resident treelets, the arrivals and what the list is predicted
    /// to need fill less than half the buffer:
    ///
    /// * in an **open** view — the samples name at least [`OPEN_VIEW_SHARE`] of the frustum's
    ///   refinable leaves, little is hidden — every frustum candidate, with its projected
    ///   error, so the server pushes its refinement too; only while the whole scene fits in
    ///   that half of the buffer, so nothing prefetched can stand in the view's way;
    /// * once at most [`DIRTY_PREFETCH_SHARE`] of the view wants refinement ([`TAIL_SHARE`]
    ///   when the scene does not fit in half the buffer), the candidates
    ///   whose box covers a pixel still wanting it (within [`DIRTY_TILE`] pixels), with their
    ///   projected errors. Refining a coarse voxel opens gaps through which a pixel's ray
    ///   reaches surfaces behind it, in subtrees no sample has named yet: without this each
    ///   such surface costs a round trip of its own, and the tail of a view is a chain of them;
    /// * in the tail proper (a short list, at most 1 % wanting more), the rest of the frustum,
    ///   without errors (no pushes below them): what the next camera move needs first.
    ///
    /// A prefetch that later had to be evicted for the view would restart what the view knows
    /// (measured with all free slots open to it, at 1.5× the view's need on loopback:
    /// convergence at cycle 90 instead of 27, hundreds dropped). A tail walk that finds nothing
    /// is not repeated until the view or the resident set changes.
    fn prefetch(&mut self, requests: &mut Vec<RequestItem>) {
        if self.config.policy == PriorityPolicy::Frustum
            || self.config.prefetch_below == 0
            || self.frustum_exhausted
            || self.bias_unsettled
        {
            return;
        }
        let (Some(camera), Some(frustum)) = (self.last_camera, &self.frustum) else {
            return;
        };
        let pixels = f64::from(self.coverage.pixels().max(1));
        let known_share = f64::from(self.coverage.known()) / pixels;
        let dirty_share = f64::from(self.coverage.dirty()) / pixels;
        // An open view is prefetched only when the whole scene fits in that half of the
        // buffer: then nothing prefetched can ever stand in the view's way (early in a view,
        // `used` is still small and says nothing about what the view will need). Then it may
        // start once a quarter of the view is known; everything else waits for the whole view.
        let scene_fits = self.scene_fits_half();
        let whole_view = known_share >= 1.0;
        let may_open = scene_fits && known_share >= OPEN_VIEW_KNOWN;
        if !(whole_view || may_open) {
            return;
        }
        let free = self.room_beside_the_view(requests);
        // Around dirty pixels from 10 % on when the scene fits, else only in the tail proper
        // (at 10 % a large scene's view may still need most of its slots).
        let dirty_from = if scene_fits {
            DIRTY_PREFETCH_SHARE
        } else {
            TAIL_SHARE
        };
        if free == 0 || (!scene_fits && (!whole_view || dirty_share > dirty_from)) {
            return;
        }
        let listed: HashSet<TreeletId> = requests.iter().map(|r| r.id).collect();
        let unlistable = self.unlistable();
        let (_, candidates) = frustum.select(&self.frame, &camera, self.bias.bias(), |id| {
            listed.contains(&id) || unlistable.contains(id)
        });
        // An open view: the samples name a good share of what the frustum offers (little is
        // hidden), so the rest of the frustum is mostly what refined gaps will reveal. The
        // samples name what the known part of the view wants: scaled to the whole view.
        let sampled = requests.len() as f64 / known_share;
        let named = sampled / (sampled + candidates.len() as f64).max(1.0);
        let open = scene_fits && named >= OPEN_VIEW_SHARE;
        if !open && (!whole_view || dirty_share > dirty_from) {
            return;
        }
        // The tail proper: a short list, at most 1 % of the view still wanting refinement. (A
        // short list alone also happens in the first cycles, when only the root's children can
        // be named.)
        let whole_frustum =
            whole_view && requests.len() < self.config.prefetch_below && dirty_share <= TAIL_SHARE;
        if whole_frustum {
            self.frustum_exhausted = candidates.is_empty();
        }
        // An open view takes every candidate: the dirty tiles are only needed otherwise.
        let dirty = (!open).then(|| DirtyTiles::of(&self.coverage));
        // Below every listed item: the open view's frustum or what lies around dirty pixels
        // first, larger projections first; priorities stay > 0.
        let lowest = requests.iter().map(|r| r.priority).fold(1.0f32, f32::min);
        let frame = self.frame;
        let (near, rest): (Vec<&FrustumRequest>, Vec<&FrustumRequest>) =
            candidates.iter().partition(|c| {
                let Some(dirty) = &dirty else {
                    return true;
                };
                let (min, max) = world_box(&frame, c.cell);
                screen_rect(&camera, min, max).is_some_and(|r| dirty.covers(r))
            });
        let near = near.into_iter().map(|c| RequestItem {
            id: c.id,
            error: c.error.min(ViewHint::MAX_ERROR),
            samples: 0,
            weight: 0.0,
            priority: lowest * 0.5 * (0.5 + 0.5 * c.error / (1.0 + c.error)),
        });
        let rest = rest
            .into_iter()
            .filter(|_| whole_frustum)
            .map(|c| RequestItem {
                id: c.id,
                error: 0.0,
                samples: 0,
                weight: 0.0,
                priority: lowest * 0.25 * c.error / (1.0 + c.error),
            });
        requests.extend(near.chain(rest).take(free));
    }

    /// Visible slots and requests of the frustum policy.
    fn select_frustum(&mut self) -> (Vec<u32>, Vec<RequestItem>, usize) {
        let Some(camera) = self.last_camera else {
            return (Vec::new(), Vec::new(), 0);
        };
        let Some(frustum) = &self.frustum else {
            return (Vec::new(), Vec::new(), 0);
        };
        let unlistable = self.unlistable();
        let (visible, requests) = frustum.select(&self.frame, &camera, self.bias.bias(), |id| {
            unlistable.contains(id)
        });
        let slots = &self.slots;
        let mut visible: Vec<u32> = visible.iter().filter_map(|&id| slots.slot_of(id)).collect();
        visible.sort_unstable();
        let distinct = requests.len();
        let requests = requests
            .iter()
            .take(self.config.max_requests)
            .map(|r| RequestItem {
                id: r.id,
                error: r.error,
                samples: 1,
                weight: 1.0,
                priority: r.error,
            })
            .collect();
        (visible, requests, distinct)
    }

    /// The view for a deep request list: the last camera, the bias in effect, and the slots the
    /// server may push into: free ones, at most `push_budget` (what the requested treelets are
    /// predicted to need below them, so occluded subtrees cannot flood the buffer). The frustum
    /// policy stands for the peers, which have no pushes: it sends plain lists.
    fn view_hint(&self, push_budget: u32) -> Option<ViewHint> {
        if !self.pushes_asked() {
            return None;
        }
        // The buffer was full lately: room for the listed items only.
        let push_budget = if self.cycle < self.pushes_paused_until {
            0
        } else {
            push_budget
        };
        let c = self.last_camera?;
        // Free slots, but no more than the backlog can take in: an arrival beyond it would
        // only be dropped.
        let free_slots = self
            .slots
            .free_slots()
            .min(self.backlog_cap() as u32)
            .saturating_sub(self.pending() as u32)
            .min(push_budget.saturating_add(self.listed.len() as u32));
        view_hint(&c, self.bias.bias(), free_slots)
    }

    /// The view for the first connection's `Hello` ([`arbor_proto::wire::HELLO_VIEW`]), of
    /// `camera` placed in [`SceneFrame::UNIT`]: the server then pushes the root's refinement
    /// for it before the client has sampled anything, one round trip before its first list
    /// could ask. `None` when the configuration asks for no pushes. The scene (and so the slot
    /// size) is not known yet: the free slots are a quarter of what the budget holds at the
    /// largest treelet size, as the backlog's quarter of the buffer later; the client's first
    /// list replaces the pushes anyway.
    pub fn first_view_hint(config: &CoreConfig, camera: &Camera) -> Option<ViewHint> {
        if !config.deep_push || config.policy == PriorityPolicy::Frustum {
            return None;
        }
        let largest = SlotBuffer::slot_bytes(MAX_TREELET_BYTES / NODE_BYTES, &config.channels);
        let surely_held = config.budget_bytes / largest.max(1);
        let free_slots = (surely_held / 4).max(64).min(surely_held);
        view_hint(
            camera,
            config.analysis.lod_bias,
            u32::try_from(free_slots).unwrap_or(u32::MAX),
        )
    }

    /// Slots the wanted treelets are predicted to take at the current bias, subtrees included:
    /// a wanted treelet covering `A` pixels will need about `2·A` leaf voxels at the end (a
    /// voxel stops at most a pixel wide), and a treelet holds about three quarters of its used
    /// nodes as leaves. Coarse, so the bias rises before the buffer fills with detail it would
    /// have to evict.
    fn predicted_slots(&self, requests: &[RequestItem], chains: bool) -> u32 {
        let used_per_treelet =
            self.scene.stats.voxels as f64 / f64::from(self.scene.treelet_count.max(1));
        let leaves = (0.75 * used_per_treelet).max(1.0);
        requests
            .iter()
            .map(|r| {
                let area = 2.0 * f64::from(r.samples) / leaves;
                // A treelet seen by a few pixels still needs its chain down to the error's
                // depth: room the server may push into, not a need the bias must make room for.
                let chain = if chains { f64::from(r.error) } else { 0.0 };
                area.max(chain).ceil().max(1.0)
            })
            .sum::<f64>()
            .min(f64::from(u32::MAX)) as u32
    }

    /// [`analyse`](Self::analyse) with the whole frame as budget, then
    /// [`presort`](Self::presort).
    pub fn plan(&mut self, camera: &Camera) -> Result<Plan, BackendError> {
        self.analyse(camera, usize::MAX)?;
        Ok(self.presort())
    }

    /// Inserts queued arrivals up to the load limit: listed ones first, then pushed ones, each
    /// parents before children (ids ascend down the tree), so a pushed treelet whose parent
    /// arrived in the same batch finds it. A pushed
    /// treelet (named by neither of the last two lists) takes only a free slot — it never
    /// displaces anything — and is dropped, and counted, when no slot is free, or when its
    /// parent is still not resident after [`ORPHAN_WAIT_INTEGRATIONS`] integrations (it waits
    /// in the backlog until then). An eviction can uncover a coarse leaf in front of a known
    /// pixel, so the pixels that may see it are forgotten (`forget_evicted`).
    pub fn integrate(&mut self) -> Integration {
        self.arriving.clear();
        let mut inserted = 0;
        let mut evicted = 0;
        let mut pushed = 0;
        let mut push_dropped = 0;
        let mut dropped = std::mem::take(&mut self.backlog_dropped);
        let (listed, previous) = (&self.listed, &self.listed_previous);
        let pushes_asked = self.pushes_asked();
        let is_push =
            |id: &TreeletId| pushes_asked && !listed.contains(id) && !previous.contains(id);
        // Listed arrivals first (they may evict), then pushes (free slots only); each by id.
        self.backlog.make_contiguous().sort_by_key(|t| {
            let id = t.treelet.header.id;
            (is_push(&id), id)
        });
        self.integrations += 1;
        let mut orphans = Vec::new();
        // Only as many as the load limit allows leave the backlog; the rest wait, in order.
        while self.slots.loads_left() > 0 {
            let Some(t) = self.backlog.pop_front() else {
                break;
            };
            let id = t.treelet.header.id;
            self.backlog_ids.remove(&id);
            let is_push = is_push(&id);
            if is_push && self.slots.free_slots() == 0 {
                self.orphans_since.remove(&id);
                push_dropped += 1;
                continue;
            }
            let parent = t.treelet.header.parent_id;
            if is_push && !parent.is_none() && !self.slots.is_resident(parent) {
                // Its parent may still be on its way: wait a few integrations for it.
                let since = *self.orphans_since.entry(id).or_insert(self.integrations);
                if self.integrations - since < ORPHAN_WAIT_INTEGRATIONS {
                    orphans.push(t);
                } else {
                    self.orphans_since.remove(&id);
                    push_dropped += 1;
                }
                continue;
            }
            self.orphans_since.remove(&id);
            if let Some(f) = &mut self.frustum {
                f.add(&t.treelet, self.scene.max_depth);
            }
            match self.slots.insert(t) {
                InsertOutcome::Inserted { evicted: e, .. } => {
                    inserted += 1;
                    evicted += e;
                    pushed += u32::from(is_push);
                    if self.evicted_in_view.remove(&id) {
                        self.slots.pin(id);
                    }
                }
                InsertOutcome::AlreadyResident => {}
                InsertOutcome::ParentMissing if is_push => push_dropped += 1,
                // The load limit was checked above; count it with the drops if it still hit.
                InsertOutcome::ParentMissing | InsertOutcome::NoRoom | InsertOutcome::LoadLimit => {
                    dropped += 1
                }
            }
        }
        for t in orphans {
            self.backlog_ids.insert(t.treelet.header.id);
            self.backlog.push_back(t);
        }
        if let Some(f) = &mut self.frustum {
            let slots = &self.slots;
            f.retain(|id| slots.is_resident(id));
        }
        self.forget_evicted(self.cycle);
        self.note_evictions();
        if evicted + self.evicted_outside > 0 {
            self.pushes_paused_until = self.cycle + PUSH_PAUSE_CYCLES;
        }
        if inserted + evicted + self.evicted_outside > 0 {
            // New refinable leaves, or old ones uncovered.
            self.frustum_exhausted = false;
        }
        self.arrival_rate = inserted.max(self.arrival_rate - self.arrival_rate / 4);
        Integration {
            inserted,
            evicted: evicted + std::mem::take(&mut self.evicted_outside),
            dropped,
            pushed,
            push_dropped,
            received_twice: std::mem::take(&mut self.received_twice),
        }
    }

    /// Plans the upload of what changed since the last upload (merged ranges) and hands it to
    /// the backend.
    pub fn upload(&mut self) -> Result<UploadPlan, BackendError> {
        let dirty = self.slots.take_dirty();
        let upload = UploadPlan::new(
            &dirty,
            self.config.fill_ratio,
            SlotBuffer::slot_data_bytes(self.scene.treelet_nodes, &self.config.channels),
        );
        self.backend.upload(&self.slots, &upload)?;
        Ok(upload)
    }

    /// The image of what is resident, seen from `camera` with the bias in effect.
    pub fn render(&mut self, camera: &Camera) -> Result<Image, BackendError> {
        let key = self.render_key(camera);
        let changed = self.slots.take_changed_cells();
        if let Some((k, image)) = &self.render_memo
            && *k == key
        {
            let image = image.clone();
            // Every test run checks the memo against a fresh render.
            #[cfg(debug_assertions)]
            assert!(
                image == self.render_afresh(camera, key)?,
                "a memoised render differs from a fresh one"
            );
            self.skipped_renders += 1;
            return Ok(image);
        }
        // The memo and the changed cells go together: a failed render below leaves neither.
        let previous = self.render_memo.take();
        // The same view, and only the slot arrays changed: where they did, if the backend can.
        if let Some((k, mut image)) = previous
            && (k.camera, k.lod_bias) == (key.camera, key.lod_bias)
            && self.backend.renders_rects()
            && let Some(rects) =
                changed.and_then(|cells| cell_rects(&self.frame, camera, &cells, f64::INFINITY))
        {
            self.drawing(key);
            self.run_pass(camera, |backend, input| {
                backend.render_rects(input, &mut image, &rects)
            })?;
            // Every test run checks the patched image against a fresh render.
            #[cfg(debug_assertions)]
            assert!(
                image == self.render_afresh(camera, key)?,
                "an image rendered again where the slots changed differs from a fresh one"
            );
            self.partial_renders += 1;
            self.render_memo = Some((key, image.clone()));
            return Ok(image);
        }
        let image = self.render_afresh(camera, key)?;
        self.render_memo = Some((key, image.clone()));
        Ok(image)
    }

    /// [`Self::render`] by the backend, of `key`.
    fn render_afresh(&mut self, camera: &Camera, key: RenderKey) -> Result<Image, BackendError> {
        self.drawing(key);
        self.run_pass(camera, |backend, input| backend.render(input))
    }

    /// A read-back render of `key` is about to run. The backend may draw it into its own
    /// target (the GPU one does), so the target holds what an in-place render left only if
    /// that was the same view.
    fn drawing(&mut self, key: RenderKey) {
        if self.in_place != Some(key) {
            self.in_place = None;
        }
    }

    /// Runs `pass` on the backend with what the passes read for `camera`.
    fn run_pass<T>(
        &mut self,
        camera: &Camera,
        pass: impl FnOnce(&mut dyn Backend, &PassInput<'_>) -> T,
    ) -> T {
        let analysis = self.analysis_config();
        let input = PassInput {
            slots: &self.slots,
            frame: &self.frame,
            camera,
            analysis: &analysis,
            light: &self.config.light,
        };
        pass(self.backend.as_mut(), &input)
    }

    /// The [`RenderKey`] of what `camera` sees now.
    fn render_key(&self, camera: &Camera) -> RenderKey {
        RenderKey {
            camera: *camera,
            lod_bias: self.bias.bias().to_bits(),
            slot_changes: self.slots.changes(),
        }
    }

    /// Renders into the backend's own target (see [`Backend::render_in_place`]).
    pub fn render_in_place(&mut self, camera: &Camera) -> Result<bool, BackendError> {
        let key = self.render_key(camera);
        if self.in_place == Some(key) {
            self.skipped_renders += 1;
            return Ok(true);
        }
        let drew = self.run_pass(camera, |backend, input| backend.render_in_place(input))?;
        self.in_place = drew.then_some(key);
        Ok(drew)
    }

    /// Renders (read back or in place) answered without the backend, because nothing the view
    /// shows had changed since the last one.
    pub fn skipped_renders(&self) -> u64 {
        self.skipped_renders
    }

    /// Read-back renders that drew only where the slot arrays had changed since the last one
    /// ([`Backend::render_rects`]).
    pub fn partial_renders(&self) -> u64 {
        self.partial_renders
    }

    /// Runs the passes on `backend` from now on, in place of one that failed (a lost device):
    /// every slot is uploaded to it at once, and nothing drawn by the old one is reused (the
    /// render memo and the in-place target go), and the pixels of the passes it had not answered
    /// are sampled first on the new one. What the core knows of the view, the resident
    /// treelets and the LOD bias stay: they live on the CPU side, so the run goes on from where
    /// it was instead of fetching the scene again.
    ///
    /// A backend that cannot hold the buffer's slots is refused with
    /// [`BackendError::OutOfMemory`], and the old one stays.
    pub fn replace_backend(&mut self, mut backend: Box<dyn Backend>) -> Result<(), BackendError> {
        let max_slots = backend.max_slots(self.scene.treelet_nodes, &self.config.channels);
        let capacity = self.slots.capacity();
        if max_slots < capacity {
            return Err(BackendError::OutOfMemory(format!(
                "the {} backend holds at most {max_slots} slots, the buffer has {capacity}",
                backend.name()
            )));
        }
        upload_all(&self.slots, backend.as_mut())?;
        tracing::info!(
            old = self.backend.name(),
            new = backend.name(),
            slots = capacity,
            "backend replaced"
        );
        self.backend = backend;
        self.render_memo = None;
        self.in_place = None;
        // The old backend's passes in flight, or the one that failed with it, will not answer.
        self.coverage.retry_unanswered();
        Ok(())
    }

    /// The backend running the passes.
    pub fn backend(&self) -> &dyn Backend {
        self.backend.as_ref()
    }

    /// Which backend runs the passes.
    pub fn backend_name(&self) -> String {
        self.backend.name()
    }
}

/// What the look-past's traces depend on: the camera and bias, the resident set (inserted and
/// evicted only grow), and the view's samples (the count since the last reset only grows, and
/// a forgetting lowers what is known).
#[derive(Clone, Copy, Debug, PartialEq)]
struct LookPastKey {
    camera: Camera,
    bias: u64,
    inserted: u64,
    evicted: u64,
    sampled: u64,
    known: u32,
}

/// The treelets a ray needs behind its first coarse hit: it is traced again past each coarse
/// refinable leaf it stops at, up to `depth` more, and the subtreelet of each coarse leaf met
/// behind is named with its error. Stops at the first hit that is not a coarse refinable leaf
/// (a final leaf or a fine enough voxel: the ray really ends there).
fn looked_past(
    view: &IncoreView<'_>,
    frame: &SceneFrame,
    ray: &Ray,
    lod: &Lod,
    depth: usize,
) -> Vec<(TreeletId, f32)> {
    let mut passed = Vec::with_capacity(depth + 1);
    let mut behind = Vec::new();
    while passed.len() <= depth {
        let Some(hit) = trace_past(view, frame, ray, lod, &passed) else {
            break;
        };
        if !(hit.leaf && hit.subtreelet != TreeletId::NONE && hit.error > 0.0) {
            break;
        }
        if !passed.is_empty() {
            behind.push((hit.subtreelet, hit.error));
        }
        passed.push(hit.node);
    }
    behind
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::CameraPath;

    #[test]
    fn dirty_tiles_cover_rectangles_touching_a_marked_tile_only() {
        // 4 × 3 tiles of 8 pixels, the tile (2, 1) marked.
        let mut marked = vec![false; 12];
        marked[4 + 2] = true;
        let tiles = DirtyTiles {
            cols: 4,
            rows: 3,
            marked,
            any: true,
        };
        assert!(tiles.covers([16.0, 8.0, 16.5, 8.5]));
        assert!(tiles.covers([0.0, 0.0, 31.9, 23.9]));
        assert!(tiles.covers([23.9, 15.9, 100.0, 100.0]));
        assert!(!tiles.covers([0.0, 0.0, 15.9, 23.9]));
        assert!(!tiles.covers([24.0, 0.0, 31.0, 23.0]));
        // Wholly off the frame: not covered; a non-finite bound: covered.
        assert!(!tiles.covers([-50.0, -50.0, -1.0, 10.0]));
        assert!(!tiles.covers([32.0, 0.0, 40.0, 10.0]));
        assert!(tiles.covers([f64::NAN, 0.0, 1.0, 1.0]));
        let none = DirtyTiles {
            cols: 4,
            rows: 3,
            marked: vec![false; 12],
            any: false,
        };
        assert!(!none.any && !none.covers([0.0, 0.0, 32.0, 24.0]));
    }

    #[test]
    fn the_first_view_hint_is_the_unit_frame_camera_within_what_the_budget_surely_holds() {
        let camera = CameraPath::Static.camera(0, &SceneFrame::UNIT, 7, 512, 256);
        let config = CoreConfig::default();
        let hint = ClientCore::first_view_hint(&config, &camera).unwrap();
        assert_eq!(hint.eye, camera.position.to_array());
        assert_eq!(hint.aspect, 2.0);
        assert!((f64::from(hint.footprint) - camera.pixel_angle()).abs() < 1e-9);
        let largest = SlotBuffer::slot_bytes(MAX_TREELET_BYTES / NODE_BYTES, &config.channels);
        let surely = config.budget_bytes / largest;
        assert_eq!(u64::from(hint.free_slots), surely / 4);
        // A budget of a few slots: no more than it holds; the peers' policy and a client
        // without pushes send no view.
        let tiny = CoreConfig {
            budget_bytes: 3 * largest,
            ..CoreConfig::default()
        };
        assert_eq!(
            ClientCore::first_view_hint(&tiny, &camera)
                .unwrap()
                .free_slots,
            3
        );
        for config in [
            CoreConfig {
                policy: PriorityPolicy::Frustum,
                ..CoreConfig::default()
            },
            CoreConfig {
                deep_push: false,
                ..CoreConfig::default()
            },
        ] {
            assert_eq!(ClientCore::first_view_hint(&config, &camera), None);
        }
    }
}
