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

use std::collections::{HashSet, VecDeque};
use std::sync::Arc;

use arbor_proto::{Channel, SceneDescription, TreeletId};
use thiserror::Error;

use crate::analysis::{AnalysisConfig, Feedback};
use crate::backend::{Backend, CpuBackend, PassInput};
use crate::camera::Camera;
use crate::image::Image;
use crate::incore::SceneFrame;
use crate::presort::{Presort, PriorityPolicy};
use crate::render::Light;
use crate::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig, SlotError};
use crate::summary::ErrorSummary;
use crate::upload::{DEFAULT_FILL_RATIO, UploadPlan};

/// Default per-cycle load limit (treelets inserted per cycle).
pub const DEFAULT_LOAD_LIMIT: u32 = 256;
/// Requests sent even when the slot buffer has no room (it still learns what it misses).
pub const MIN_REQUESTS: usize = 16;
/// Default cap on the request list.
pub const DEFAULT_MAX_REQUESTS: usize = 4096;

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
        }
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
        if !(a.lod_bias.is_finite() && a.lod_bias > 0.0 && a.lod_bias <= 1e6) {
            return Err(CoreError::Invalid(format!(
                "LOD bias {} must be finite and in (0, 1e6]",
                a.lod_bias
            )));
        }
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
    /// Distinct refinable treelets seen (before the cap).
    pub distinct_requests: usize,
    /// Screen-space error of this cycle's samples.
    pub error: ErrorSummary,
    /// Samples that hit something.
    pub samples: u32,
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
}

/// The client's cycle state: slot buffer, presort, feedback, arrivals waiting for a slot.
#[derive(Debug)]
pub struct ClientCore {
    scene: Arc<SceneDescription>,
    frame: SceneFrame,
    config: CoreConfig,
    slots: SlotBuffer,
    presort: Presort,
    feedback: Feedback,
    backlog: VecDeque<DecodedTreelet>,
    backlog_ids: HashSet<TreeletId>,
    backlog_dropped: u32,
    cycle: u64,
    backend: Box<dyn Backend>,
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
        let slots = SlotBuffer::new(
            SlotConfig {
                budget_bytes,
                treelet_nodes: scene.treelet_nodes,
                channels: config.channels.clone(),
                visibility_max: (config.analysis.ratio * config.analysis.ratio)
                    .min(u32::from(u16::MAX)) as u16,
                load_limit: config.load_limit,
            },
            root,
        )?;
        Ok(Self {
            frame: SceneFrame::of(&scene),
            presort: Presort::new(config.policy, config.max_requests),
            scene,
            config,
            slots,
            feedback: Feedback::default(),
            backlog: VecDeque::new(),
            backlog_ids: HashSet::new(),
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

    /// The last cycle's feedback.
    pub fn feedback(&self) -> &Feedback {
        &self.feedback
    }

    /// Cycles planned so far.
    pub fn cycle(&self) -> u64 {
        self.cycle
    }

    /// Arrivals waiting for a slot (beyond the load limit).
    pub fn backlog_len(&self) -> usize {
        self.backlog.len()
    }

    /// Queues an arrived treelet for the next [`integrate`](Self::integrate). Duplicates and
    /// treelets already resident are ignored. The backlog is bounded (a few cycles of the load
    /// limit): past that the oldest arrival is dropped, to be requested again if still needed.
    pub fn handle_treelet(&mut self, treelet: DecodedTreelet) {
        let id = treelet.treelet.header.id;
        if self.slots.is_resident(id) || !self.backlog_ids.insert(id) {
            return;
        }
        self.backlog.push_back(treelet);
        let cap = (self.config.load_limit as usize * 4).max(64);
        while self.backlog.len() > cap {
            if let Some(old) = self.backlog.pop_front() {
                self.backlog_ids.remove(&old.treelet.header.id);
                self.backlog_dropped += 1;
            }
        }
    }

    /// Runs the analysis pass for `camera`; [`presort`](Self::presort) reads its feedback.
    pub fn analyse(&mut self, camera: &Camera) {
        let mut feedback = std::mem::take(&mut self.feedback);
        let input = pass_input(&self.slots, &self.frame, &self.config, camera);
        self.backend.analyse(&input, self.cycle, &mut feedback);
        self.feedback = feedback;
    }

    /// Presort of the latest feedback: ages visibility, marks what was seen and returns the
    /// request list to send. Ends the cycle's first half.
    pub fn presort(&mut self) -> Plan {
        let slots = &self.slots;
        let backlog = &self.backlog_ids;
        let sorted = self.presort.run(
            &self.feedback.samples,
            self.scene.treelet_nodes,
            slots.capacity(),
            |s| slots.parent_slot(s),
            |id| backlog.contains(&id) || slots.is_resident(id),
        );
        self.slots.begin_cycle();
        for &s in &sorted.visible_slots {
            self.slots.mark_visible(s);
        }
        // Ask for no more than could be inserted (a few always, so a full buffer still learns
        // what it is missing): with an oversubscribed budget the rest would only be dropped.
        let room = (self.slots.room() as usize).saturating_sub(self.backlog.len());
        let mut requests = sorted.requests;
        requests.truncate(room.max(MIN_REQUESTS));
        let errors: Vec<f32> = self
            .feedback
            .samples
            .iter()
            .filter(|s| s.is_hit())
            .map(|s| s.refinable_error())
            .collect();
        let ratio = f64::from(self.config.analysis.ratio);
        self.cycle += 1;
        Plan {
            requests: requests.iter().map(|r| (r.id, r.priority)).collect(),
            distinct_requests: sorted.distinct_requests,
            samples: errors.len() as u32,
            error: ErrorSummary::from_samples(&errors, ratio * ratio),
        }
    }

    /// [`analyse`](Self::analyse) then [`presort`](Self::presort).
    pub fn plan(&mut self, camera: &Camera) -> Plan {
        self.analyse(camera);
        self.presort()
    }

    /// Inserts queued arrivals up to the load limit.
    pub fn integrate(&mut self) -> Integration {
        let mut inserted = 0;
        let mut evicted = 0;
        let mut dropped = std::mem::take(&mut self.backlog_dropped);
        // Only as many as the load limit allows leave the backlog; the rest wait, in order.
        while self.slots.loads_left() > 0 {
            let Some(t) = self.backlog.pop_front() else {
                break;
            };
            self.backlog_ids.remove(&t.treelet.header.id);
            match self.slots.insert(t) {
                InsertOutcome::Inserted { evicted: e, .. } => {
                    inserted += 1;
                    evicted += e;
                }
                InsertOutcome::AlreadyResident => {}
                // The load limit was checked above; count it with the drops if it still hit.
                InsertOutcome::ParentMissing | InsertOutcome::NoRoom | InsertOutcome::LoadLimit => {
                    dropped += 1
                }
            }
        }
        Integration {
            inserted,
            evicted,
            dropped,
        }
    }

    /// Plans the upload of what changed since the last upload (merged ranges) and hands it to
    /// the backend.
    pub fn upload(&mut self) -> UploadPlan {
        let dirty = self.slots.take_dirty();
        let upload = UploadPlan::new(
            &dirty,
            self.config.fill_ratio,
            SlotBuffer::slot_data_bytes(self.scene.treelet_nodes, &self.config.channels),
        );
        self.backend.upload(&self.slots, &upload);
        upload
    }

    /// The image of what is resident, seen from `camera`.
    pub fn render(&mut self, camera: &Camera) -> Image {
        self.backend
            .render(&pass_input(&self.slots, &self.frame, &self.config, camera))
    }

    /// Renders into the backend's own target (see [`Backend::render_in_place`]).
    pub fn render_in_place(&mut self, camera: &Camera) -> bool {
        self.backend
            .render_in_place(&pass_input(&self.slots, &self.frame, &self.config, camera))
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

/// Everything a pass reads this cycle (disjoint borrows of the core's fields).
fn pass_input<'a>(
    slots: &'a SlotBuffer,
    frame: &'a SceneFrame,
    config: &'a CoreConfig,
    camera: &'a Camera,
) -> PassInput<'a> {
    PassInput {
        slots,
        frame,
        camera,
        analysis: &config.analysis,
        light: &config.light,
    }
}
