//! Server-side visibility: which treelets a client's view needs, found by casting the view's
//! rays through the server's own tree, so that pushes name what the view needs and nothing it
//! cannot see.
//!
//! [`push::plan_pushes`](super::push::plan_pushes) walks down from the listed treelets by
//! frustum and projected size alone: it cannot know what is hidden, and it cannot know what a
//! ray will meet *behind* a listed treelet once that one shows the ray passes through. The
//! server holds the whole tree, so it can answer "what does this view need" itself:
//! [`CutCaster::cut`] casts a grid of the view's rays (the client's own CPU traversal,
//! [`trace`], so both sides agree on where a ray stops) through a [`SlotBuffer`] that starts
//! with the root treelet alone. A ray that stops at a refinable leaf coarser than a pixel — the
//! client's own rule for asking — loads that leaf's treelet and is cast again, round after
//! round, until every ray stops where the whole tree would stop it. Everything loaded is the
//! view's cut ([`VisibleCut`]), parents first: the treelets holding the stops, their
//! ancestors, and the treelets rays only pass through (a coarse voxel is a hull of its subtree,
//! so without them the ray stops at the hull). A ray that has stopped stays stopped as more is
//! loaded (loading only refines hulls behind its stop or elsewhere), so only the rays that
//! asked are cast again.
//!
//! The grid is coarser than the client's frame, so a treelet met only between grid rays is
//! missed; the client's own feedback still asks for it. The buffer is bounded in bytes (node
//! records only); when it cannot take the next treelet, or a treelet cannot be read, the cut is
//! marked incomplete and the service keeps the frustum plan. Each round's rays are cast in
//! parallel on a pool of half the machine's cores, at least two (`cut_pool`). Pure
//! apart from the `fetch` closure that reads a node block, so the tests compare it with casts
//! over the fully resident scene.

use std::borrow::Borrow;
use std::collections::HashSet;
use std::sync::OnceLock;

use arbor_client_core::camera::Camera;
use arbor_client_core::incore::{IncoreView, SceneFrame};
use arbor_client_core::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig, SlotError};
use arbor_client_core::traverse::{Lod, trace};
use arbor_proto::wire::ViewHint;
use arbor_proto::{Node, SceneDescription, TreeletId};
use glam::DVec3;
use rayon::prelude::*;

use super::generations::GenerationCache;

/// The node records visible cuts are cast through, decoded and validated as a cut reads them
/// (no channels), kept server-wide between cuts within `visibility_node_cache_bytes` (two
/// generations, [`super::generations`]). A cut reads thousands of treelets and decoding them
/// (decompressing and validating the node block) was about half of its time: a fine cut reads
/// again the coarse cut it is cast from, a client raising its LOD bias step by step casts much
/// the same treelets again, and clients looking at the same place read the same ones. On the
/// 10⁸-point city it cut the server's CPU time per converging view by a third to a half
/// (docs/measurements.md, stop 48).
pub type NodeCache = GenerationCache<DecodedTreelet>;

/// A decoded treelet's own bytes: its node records and what holds them.
fn node_bytes(t: &DecodedTreelet) -> usize {
    size_of::<DecodedTreelet>()
        + t.treelet.nodes.capacity() * size_of::<Node>()
        + t.attributes
            .iter()
            .map(|(_, a)| size_of::<(arbor_proto::Channel, Vec<u8>)>() + a.capacity())
            .sum::<usize>()
}

impl NodeCache {
    /// A cache of at most `capacity` bytes of decoded treelets (0: nothing is kept, every cut
    /// decodes what it reads).
    pub fn for_nodes(capacity: usize) -> NodeCache {
        GenerationCache::new(capacity, node_bytes)
    }
}

/// The treelets a view needs, as [`CutCaster::cut`] found them.
#[derive(Clone, Debug, PartialEq)]
pub struct VisibleCut {
    /// The view it was computed for (`free_slots` is irrelevant to it).
    pub view: ViewHint,
    /// `(level, treelet)`: every treelet a ray needed loaded to stop where the whole tree stops
    /// it — those holding the stops, their ancestors, and those the rays pass through (a
    /// coarse voxel is a hull of its subtree: a ray meant to pass through stops at the hull
    /// until the subtree is there). Parents before children (by level — treelets above it —
    /// then id). The root treelet is left out: every client holds it.
    pub treelets: Vec<(u8, TreeletId)>,
    /// Every ray stopped where the view's LOD accepts it. `false`: the buffer ran out of room,
    /// a treelet could not be read and the rays that needed it stopped short, or the cast was
    /// abandoned.
    pub complete: bool,
    /// The cast was stopped once the cut had grown past what could still be worth following
    /// (the `worthwhile` test of [`CutCaster::cut_from`]); `treelets` is then what it held so far.
    pub abandoned: bool,
    /// Rays along the longer side of the frame it was cast with.
    pub grid: u32,
    /// Rays cast in all rounds.
    pub rays_cast: u64,
    /// How long the cast took.
    pub took: std::time::Duration,
}

impl VisibleCut {
    /// Whether this cut answers `view`: the same eye, directions, field of view, aspect and
    /// footprint, up to float noise (a client's hint and the same camera's `Hello` view
    /// converted to world units differ in the last bits).
    pub fn answers(&self, view: &ViewHint) -> bool {
        same_view(&self.view, view)
    }
}

/// Two hints describe the same view (everything but `free_slots`, relative 1e-5).
pub fn same_view(a: &ViewHint, b: &ViewHint) -> bool {
    let close = |x: f64, y: f64, scale: f64| (x - y).abs() <= 1e-5 * scale.max(1e-30);
    let scale = a
        .eye
        .iter()
        .chain(&b.eye)
        .fold(0.0f64, |m, v| m.max(v.abs()))
        .max(1.0);
    (0..3).all(|i| close(a.eye[i], b.eye[i], scale))
        && (0..3).all(|i| close(f64::from(a.forward[i]), f64::from(b.forward[i]), 1.0))
        && (0..3).all(|i| close(f64::from(a.up[i]), f64::from(b.up[i]), 1.0))
        && close(
            f64::from(a.tan_half_fov_y),
            f64::from(b.tan_half_fov_y),
            f64::from(a.tan_half_fov_y),
        )
        && close(
            f64::from(a.aspect),
            f64::from(b.aspect),
            f64::from(a.aspect),
        )
        && close(
            f64::from(a.footprint),
            f64::from(b.footprint),
            f64::from(a.footprint),
        )
}

/// Pixels along the longer side of the frame `view` was taken with, counted at its LOD bias (a
/// bias above 1 counts coarser pixels, as the client's own LOD does): a cut cast with more rays
/// than these only casts rays the client has no pixel for. At least 1.
pub fn frame_rays(view: &ViewHint) -> u32 {
    let rays = 2.0 * f64::from(view.tan_half_fov_y) * f64::from(view.aspect).max(1.0)
        / f64::from(view.footprint);
    // A checked hint keeps this finite; `as` saturates anyway.
    (rays.round() as u32).max(1)
}

/// The camera of `view` with `grid` rays along its longer side (at least one along the other).
/// The hint carries directions as `f32`: they are renormalised and `up` made orthogonal again.
pub fn grid_camera(view: &ViewHint, grid: u32) -> Camera {
    let v = |a: [f32; 3]| DVec3::new(f64::from(a[0]), f64::from(a[1]), f64::from(a[2]));
    let forward = v(view.forward).normalize_or_zero();
    let up_hint = v(view.up);
    let up = (up_hint - forward * forward.dot(up_hint)).normalize_or_zero();
    let aspect = f64::from(view.aspect);
    let grid = grid.max(1);
    let (width, height) = if aspect >= 1.0 {
        (grid, ((f64::from(grid) / aspect).round() as u32).max(1))
    } else {
        (((f64::from(grid) * aspect).round() as u32).max(1), grid)
    };
    Camera {
        position: DVec3::from_array(view.eye),
        forward,
        up,
        fov_y: 2.0 * f64::from(view.tan_half_fov_y).atan(),
        width,
        height,
    }
}

/// Fine cuts of a scene in a row that were not used before the next ones are skipped
/// ([`FineCutGate`]).
pub const FINE_CUTS_WASTED_BEFORE_SKIPPING: u32 = 4;
/// While a scene's fine cuts are skipped, every this many a fine cut is cast all the same, to
/// find out whether the views have changed (a client walking from a plaza into a building).
pub const FINE_CUT_PROBE_EVERY: u32 = 16;

/// Whether a scene's fine cuts are worth casting, learned from the last ones (one per scene,
/// shared by its connections). A fine cut is used when it is complete and followed; otherwise
/// it was work for nothing. Where the views of a scene see most of their frustum, or need more
/// than a cut's buffer holds, every fine cut is wasted: on the 10⁸-point city the fine cuts of
/// a converging 1024×768 view were three quarters of the server's CPU for it and none was used
/// (docs/measurements.md, stop 48). After [`FINE_CUTS_WASTED_BEFORE_SKIPPING`] wasted in a row
/// the scene's resting views keep their coarse cut (still followed where it saves) and only
/// every [`FINE_CUT_PROBE_EVERY`]th fine cut is cast; one that is used opens the gate again.
/// Plain data: the handler asks and records, the tests drive it directly.
#[derive(Debug, Default)]
pub struct FineCutGate {
    wasted_in_row: u32,
    skipped_in_row: u32,
}

impl FineCutGate {
    /// Whether the next fine cut should be cast; a `false` counts as one skipped.
    pub fn should_cast(&mut self) -> bool {
        if self.wasted_in_row < FINE_CUTS_WASTED_BEFORE_SKIPPING {
            return true;
        }
        self.skipped_in_row += 1;
        if self.skipped_in_row >= FINE_CUT_PROBE_EVERY {
            self.skipped_in_row = 0;
            return true;
        }
        false
    }

    /// A fine cut was cast: `used` when it was complete and followed.
    pub fn record(&mut self, used: bool) {
        if used {
            *self = FineCutGate::default();
        } else {
            self.wasted_in_row = self.wasted_in_row.saturating_add(1);
        }
    }
}

/// The [`FineCutGate`]s of every scene a service serves, by scene generation (unique in a pool).
/// A scene's served state is dropped when no connection holds it; what its fine cuts were
/// worth is kept here, so a city viewed by one client after another learns it once.
#[derive(Debug, Default)]
pub struct FineCutGates(std::sync::Mutex<rustc_hash::FxHashMap<u64, FineCutGate>>);

/// Generations [`FineCutGates`] keeps before it forgets them all (re-imports over months).
const MAX_GATED_GENERATIONS: usize = 4096;

impl FineCutGates {
    fn with<T>(&self, generation: u64, f: impl FnOnce(&mut FineCutGate) -> T) -> T {
        // Every call leaves each gate's two counters consistent.
        let mut gates = self.0.lock().unwrap_or_else(|p| p.into_inner());
        if gates.len() >= MAX_GATED_GENERATIONS && !gates.contains_key(&generation) {
            gates.clear();
        }
        f(gates.entry(generation).or_default())
    }

    /// [`FineCutGate::should_cast`] for the scene of `generation`.
    pub fn should_cast(&self, generation: u64) -> bool {
        self.with(generation, FineCutGate::should_cast)
    }

    /// [`FineCutGate::record`] for the scene of `generation`.
    pub fn record(&self, generation: u64, used: bool) {
        self.with(generation, |g| g.record(used));
    }
}

/// Treelets a cut holds before [`CutCaster::cut_from`] first asks whether it is still worth
/// casting: below it the question (a walk of the frustum plan) costs about as much as the cast.
pub const FIRST_WORTH_CHECK: usize = 256;

/// Casts a scene's visible cuts: holds the root treelet's nodes and the buffer size a cut may
/// use; every cut builds its own buffer from them.
#[derive(Debug)]
pub struct CutCaster {
    config: SlotConfig,
    frame: SceneFrame,
    root: DecodedTreelet,
}

impl CutCaster {
    /// A caster whose cuts hold at most `budget_bytes` of node records (checked now: the root
    /// must fit).
    pub fn new(
        scene: &SceneDescription,
        budget_bytes: u64,
        root: DecodedTreelet,
    ) -> Result<CutCaster, SlotError> {
        let config = SlotConfig {
            budget_bytes,
            treelet_nodes: scene.treelet_nodes,
            channels: Vec::new(),
            visibility_max: 1,
            load_limit: u32::MAX,
        };
        SlotBuffer::new_growing(config.clone(), root.clone())?;
        Ok(CutCaster {
            config,
            frame: SceneFrame::of(scene),
            root,
        })
    }

    /// The cut of `view` with `grid` rays along the longer side of its frame
    /// ([`grid_camera`]), at the view's footprint ([`cast`](Self::cast)).
    pub fn cut<T: Borrow<DecodedTreelet>>(
        &self,
        view: &ViewHint,
        grid: u32,
        fetch: impl FnMut(TreeletId) -> Option<T> + Send,
    ) -> VisibleCut {
        self.cut_from(view, grid, &[], fetch, |_| true)
    }

    /// [`CutCaster::cut`], with the buffer first holding `seed` (`(level, treelet)`, parents
    /// first: a coarser cut of the same view). The result is `seed` plus what this grid's rays
    /// need beyond it: a ray passing through a seeded treelet does not name it again, but the
    /// seed is in the cut already. A finer grid after a coarser one then casts one full round
    /// and short ones for what the coarse rays missed, instead of every round from the root
    /// (engine at 512 rays after 128, on two shared cores: 100–150 ms from the root).
    ///
    /// `worthwhile(n)` says whether a cut of `n` treelets could still be worth following; it is
    /// asked each time the cut has doubled (from twice the seed, at least
    /// [`FIRST_WORTH_CHECK`] treelets). A cut only grows as it is cast, so once the answer is
    /// no the cast stops, [`VisibleCut::abandoned`]: at city scale most of a resting view's
    /// rays meet what the frustum plan pushes anyway, and a cut cast to the end only to be
    /// found not worth following cost the server several times what serving the view did
    /// (docs/measurements.md, stop 48).
    pub fn cut_from<T: Borrow<DecodedTreelet>>(
        &self,
        view: &ViewHint,
        grid: u32,
        seed: &[(u8, TreeletId)],
        fetch: impl FnMut(TreeletId) -> Option<T> + Send,
        worthwhile: impl FnMut(usize) -> bool + Send,
    ) -> VisibleCut {
        let start = std::time::Instant::now();
        let lod = Lod {
            pixel_angle: f64::from(view.footprint),
            lod_bias: 1.0,
            max_depth: self.frame.max_depth,
        };
        let cast = self.cast_from(&grid_camera(view, grid), &lod, seed, fetch, worthwhile);
        VisibleCut {
            view: *view,
            treelets: cast.treelets,
            complete: cast.complete,
            abandoned: cast.abandoned,
            grid,
            rays_cast: cast.rays_cast,
            took: start.elapsed(),
        }
    }

    /// Casts the ray through every pixel centre of `camera` at `lod`, round after round, from
    /// the root alone (so that what it loads is exactly what its rays need: a treelet already
    /// held would let a ray pass through it unnoticed), loading what a ray stops at while
    /// coarser than a pixel, until every ray stops where the whole tree stops it. When a
    /// round's rays stop at few treelets (64 rays or more each), one
    /// ray per treelet is followed down its chain before the next round, loading what it
    /// needs. Treelets are read with `fetch` (node block only; `None`: not readable, the cast
    /// is then incomplete).
    pub fn cast<T: Borrow<DecodedTreelet>>(
        &self,
        camera: &Camera,
        lod: &Lod,
        fetch: impl FnMut(TreeletId) -> Option<T> + Send,
    ) -> Cast {
        self.cast_from(camera, lod, &[], fetch, |_| true)
    }

    /// [`CutCaster::cast`] with the buffer first holding `seed`, abandoned once `worthwhile`
    /// says no ([`CutCaster::cut_from`]); a seeded treelet that cannot be read or inserted
    /// leaves the cast incomplete.
    ///
    /// The whole cast — reading and decoding what it loads as well as its rays — runs on the
    /// cut threads ([`cut_pool`]), which yield to streaming.
    fn cast_from<T: Borrow<DecodedTreelet>>(
        &self,
        camera: &Camera,
        lod: &Lod,
        seed: &[(u8, TreeletId)],
        fetch: impl FnMut(TreeletId) -> Option<T> + Send,
        worthwhile: impl FnMut(usize) -> bool + Send,
    ) -> Cast {
        match cut_pool() {
            Some(pool) => pool.install(|| self.cast_on(camera, lod, seed, fetch, worthwhile, true)),
            None => self.cast_on(camera, lod, seed, fetch, worthwhile, false),
        }
    }

    /// [`CutCaster::cast_from`] on the calling thread, each round's rays in parallel on the
    /// current rayon pool when `parallel`.
    fn cast_on<T: Borrow<DecodedTreelet>>(
        &self,
        camera: &Camera,
        lod: &Lod,
        seed: &[(u8, TreeletId)],
        mut fetch: impl FnMut(TreeletId) -> Option<T>,
        worthwhile: impl FnMut(usize) -> bool,
        parallel: bool,
    ) -> Cast {
        let mut cast = Cast {
            treelets: Vec::new(),
            complete: true,
            abandoned: false,
            rays_cast: 0,
        };
        let Ok(mut slots) = SlotBuffer::new_growing(self.config.clone(), self.root.clone()) else {
            // `CutCaster::new` built the same buffer once already.
            cast.complete = false;
            return cast;
        };
        for &(level, id) in seed {
            match fetch(id).map(|t| slots.insert(t)) {
                Some(InsertOutcome::Inserted { .. }) => cast.treelets.push((level, id)),
                _ => cast.complete = false,
            }
        }
        let mut loader = Loader {
            next_check: (2 * cast.treelets.len()).max(FIRST_WORTH_CHECK),
            fetch,
            worthwhile,
        };
        let mut pending: Vec<(u32, u32)> = (0..camera.height)
            .flat_map(|y| (0..camera.width).map(move |x| (x, y)))
            .collect();
        let rays = camera.pixel_rays();
        let stop_short = |view: &IncoreView<'_>, (x, y): (u32, u32)| {
            let ray = rays.ray(f64::from(x) + 0.5, f64::from(y) + 0.5);
            trace(view, &self.frame, &ray, lod)
                .filter(|hit| hit.leaf && !hit.subtreelet.is_none() && hit.error > 0.0)
                .map(|hit| hit.subtreelet)
        };
        while !pending.is_empty() {
            cast.rays_cast += pending.len() as u64;
            // The rays of a round are independent; the buffer is only read until all are cast.
            let view = slots.view();
            let stops = |&p: &(u32, u32)| stop_short(&view, p).map(|id| (p, id));
            let stopped: Vec<((u32, u32), TreeletId)> = if parallel {
                pending.par_iter().filter_map(stops).collect()
            } else {
                pending.iter().filter_map(stops).collect()
            };
            let mut missing: Vec<TreeletId> = stopped.iter().map(|&(_, id)| id).collect();
            missing.sort_unstable();
            missing.dedup();
            let probe = missing.len() * PROBE_RAYS_PER_TREELET <= stopped.len();
            let mut progress = false;
            for id in missing {
                match loader.load(&mut slots, &mut cast, id) {
                    Load::Loaded => progress = true,
                    Load::Skipped => {}
                    Load::Stop => break,
                }
            }
            // Few treelets for many rays (a view from inside the data, a fly-in's end): the rays
            // stand in one chain of nested treelets, which a round would uncover one level at
            // a time, every ray cast again each time (inside lion: 12 rounds for 24 treelets).
            // One ray per treelet follows its chain down first; what it loads is what that ray
            // needs, so the cut is the same.
            if probe && progress && !cast.abandoned {
                let mut seen = HashSet::new();
                let probes = stopped.iter().filter(|&&(_, id)| seen.insert(id));
                'probes: for &(p, _) in probes {
                    for _ in 0..MAX_PROBE_STEPS {
                        cast.rays_cast += 1;
                        let Some(id) = stop_short(&slots.view(), p) else {
                            break;
                        };
                        match loader.load(&mut slots, &mut cast, id) {
                            Load::Loaded => {}
                            Load::Skipped => break,
                            Load::Stop => break 'probes,
                        }
                    }
                }
            }
            if !progress || cast.abandoned {
                // Nothing more can be loaded: those rays stop at the hulls they reached.
                break;
            }
            pending = stopped.into_iter().map(|(p, _)| p).collect();
        }
        cast.treelets.sort_unstable();
        cast
    }
}

/// A round's rays per treelet they stop at, at or above which one ray per treelet follows its
/// chain before the next round ([`CutCaster::cast_from`]).
const PROBE_RAYS_PER_TREELET: usize = 64;

/// Most treelets one probing ray loads: deeper than any scene's chain of treelets.
const MAX_PROBE_STEPS: usize = 64;

/// What loading a treelet into a cast did.
enum Load {
    /// Inserted.
    Loaded,
    /// Not readable or not insertable: the cast is incomplete, and goes on.
    Skipped,
    /// The buffer is full or the cast was abandoned: load nothing more.
    Stop,
}

/// Loads treelets into a cast's buffer: reads them with `fetch`, and asks `worthwhile` each
/// time the cut has doubled since `next_check`.
struct Loader<F, W> {
    next_check: usize,
    fetch: F,
    worthwhile: W,
}

impl<F, W> Loader<F, W> {
    fn load<T>(&mut self, slots: &mut SlotBuffer, cast: &mut Cast, id: TreeletId) -> Load
    where
        F: FnMut(TreeletId) -> Option<T>,
        W: FnMut(usize) -> bool,
        T: Borrow<DecodedTreelet>,
    {
        if slots.free_slots() == 0 {
            cast.complete = false;
            return Load::Stop;
        }
        let Some(t) = (self.fetch)(id) else {
            cast.complete = false;
            return Load::Skipped;
        };
        let loaded = if let InsertOutcome::Inserted { slot, .. } = slots.insert(t) {
            cast.treelets.push((level_of(slots, slot), id));
            Load::Loaded
        } else {
            cast.complete = false;
            Load::Skipped
        };
        if cast.treelets.len() >= self.next_check {
            if !(self.worthwhile)(cast.treelets.len()) {
                cast.abandoned = true;
                cast.complete = false;
                return Load::Stop;
            }
            self.next_check = 2 * cast.treelets.len();
        }
        loaded
    }
}

/// The threads visible cuts cast their rays on, shared by every scene: half the machine's cores,
/// so on a larger server the cuts of resting views leave the other half to streaming, but at
/// least two: a cut is a burst of tens of milliseconds that decides how soon a view's pushes
/// are exact. On the two cores the refine bench shares with its client, engine's jump (medians
/// of five, alternating) took 0.160 / 0.165 s first contact and 0.166 / 0.156 s returning with
/// one thread, 0.153 / 0.172 s and 0.136 / 0.153 s with two (docs/measurements.md, stop 47).
/// `None` (casting on the calling thread) if the pool cannot be built.
fn cut_pool() -> Option<&'static rayon::ThreadPool> {
    static POOL: OnceLock<Option<rayon::ThreadPool>> = OnceLock::new();
    POOL.get_or_init(|| {
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
        rayon::ThreadPoolBuilder::new()
            .num_threads((cores / 2).max(2))
            .thread_name(|i| format!("arbor-cut-{i}"))
            .start_handler(|_| yield_to_streaming())
            .build()
            .map_err(|e| tracing::warn!("no thread pool for visible cuts, casting on one: {e}"))
            .ok()
    })
    .as_ref()
}

/// How much nicer than the rest of the server the cut threads run: a cut is a burst of
/// background work for one resting view, and on a busy server it should not take the cores
/// from streaming every client's lists (5 steps nicer, a cut thread gets about a quarter of a
/// core that a streaming thread wants).
pub const CUT_NICE: i32 = 5;

/// Makes the calling thread [`CUT_NICE`] steps nicer than it was (a per-thread attribute on
/// Linux, inherited from the thread that built the pool), at most 19; a refusal is logged and
/// the cuts run at the server's priority.
fn yield_to_streaming() {
    let tid = rustix::thread::gettid();
    let nicer = rustix::process::getpriority_process(Some(tid))
        .and_then(|now| rustix::process::setpriority_process(Some(tid), (now + CUT_NICE).min(19)));
    if let Err(e) = nicer {
        tracing::warn!("could not make a cut thread {CUT_NICE} steps nicer: {e}");
    }
}

/// What [`CutCaster::cast`] loaded.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Cast {
    /// `(level, treelet)`, parents first, as in [`VisibleCut::treelets`].
    pub treelets: Vec<(u8, TreeletId)>,
    /// Every ray stopped where the whole tree stops it.
    pub complete: bool,
    /// Stopped because `worthwhile` said no ([`VisibleCut::abandoned`]).
    pub abandoned: bool,
    /// Rays cast in all rounds.
    pub rays_cast: u64,
}

/// A resident treelet's level: the number of treelets above it (a parent's level is below its
/// children's, so sorting by level sends parents first).
fn level_of(slots: &SlotBuffer, slot: u32) -> u8 {
    let mut level = 0u8;
    let mut s = slots.parent_slot(slot);
    while let Some(p) = s {
        level = level.saturating_add(1);
        s = slots.parent_slot(p);
    }
    level
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scene_whose_fine_cuts_go_unused_casts_only_probes_until_one_is_used() {
        let mut gate = FineCutGate::default();
        // Open at first, and while fewer than the limit were wasted in a row.
        for _ in 0..FINE_CUTS_WASTED_BEFORE_SKIPPING - 1 {
            assert!(gate.should_cast());
            gate.record(false);
        }
        assert!(gate.should_cast());
        gate.record(true);
        for _ in 0..FINE_CUTS_WASTED_BEFORE_SKIPPING {
            assert!(gate.should_cast(), "a used cut starts the count again");
            gate.record(false);
        }
        // Closed: one probe in every FINE_CUT_PROBE_EVERY.
        for round in 0..3 {
            for skip in 1..FINE_CUT_PROBE_EVERY {
                assert!(!gate.should_cast(), "round {round}, skip {skip}");
            }
            assert!(gate.should_cast(), "round {round}: the probe");
            gate.record(false);
        }
        // A used probe opens the gate.
        for _ in 1..FINE_CUT_PROBE_EVERY {
            assert!(!gate.should_cast());
        }
        assert!(gate.should_cast());
        gate.record(true);
        for _ in 0..FINE_CUTS_WASTED_BEFORE_SKIPPING {
            assert!(gate.should_cast());
            gate.record(false);
        }
        assert!(!gate.should_cast());
    }
}
