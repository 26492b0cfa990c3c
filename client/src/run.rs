//! The client cycle (DESIGN §1, §5): analysis → presort → request list → integrate arrivals →
//! upload plan → render, as an I/O-free core plus a thin headless shell.
//!
//! [`ClientCore`] is the quinn-proto-style part: treelets go in with
//! [`handle_treelet`](ClientCore::handle_treelet), a cycle runs in two calls ([`plan`]
//! returns the request list, [`integrate`] updates the slot buffer) and [`render`] draws; no
//! sockets, no clocks other than the phase timers, so tests drive it with treelets read straight
//! from a pool. [`run_headless`] connects it to a [`TreeletClient`]: it never waits on the
//! network inside the loop — whatever has arrived is integrated, the rest is drawn one level
//! coarser.
//!
//! [`plan`]: ClientCore::plan
//! [`integrate`]: ClientCore::integrate
//! [`render`]: ClientCore::render

use std::collections::{HashSet, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_proto::{Channel, SceneDescription, TreeletId};
use thiserror::Error;

use crate::analysis::{AnalysisConfig, Feedback};
use crate::backend::{Backend, CpuBackend};
use crate::camera::{Camera, CameraPath};
use crate::image::Image;
use crate::incore::SceneFrame;
use crate::net::{ClientConfig, ClientError, ClientEvent, ClientStats, TreeletClient};
use crate::presort::{Presort, PriorityPolicy};
use crate::render::{Light, render};
use crate::report::{CycleRecord, ErrorSummary, RunMeta, RunReport};
use crate::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig, SlotError};
use crate::upload::{DEFAULT_FILL_RATIO, UploadPlan};

/// Default per-cycle load limit (treelets inserted per cycle).
pub const DEFAULT_LOAD_LIMIT: u32 = 256;
/// Default cap on the request list.
pub const DEFAULT_MAX_REQUESTS: usize = 4096;

/// Why a run could not start or go on.
#[derive(Debug, Error)]
pub enum RunError {
    /// The connection could not be set up (bad URL, certificate, configuration).
    #[error("client: {0}")]
    Client(#[from] ClientError),
    /// The slot buffer refused the configuration or the root treelet.
    #[error("slot buffer: {0}")]
    Slots(#[from] SlotError),
    /// No `SceneInfo` or no root treelet within the connect timeout.
    #[error("{0}")]
    Timeout(String),
    /// The server refused the client for good (token, scene, certificate).
    #[error("server refused the connection: {0}")]
    Refused(String),
    /// A parameter is out of range.
    #[error("invalid parameter: {0}")]
    Invalid(String),
    /// The reference image does not fit the run.
    #[error("reference image: {0}")]
    Reference(String),
}

/// What the core needs besides the scene.
#[derive(Clone, Debug)]
pub struct CoreConfig {
    pub analysis: AnalysisConfig,
    pub policy: PriorityPolicy,
    pub max_requests: usize,
    /// Slot buffer memory budget in bytes (nodes, attributes and bookkeeping).
    pub budget_bytes: u64,
    pub load_limit: u32,
    /// Upload range fill ratio (DESIGN §5).
    pub fill_ratio: f32,
    /// Channels held and drawn (the scene's channels the client asked for).
    pub channels: Vec<Channel>,
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
    pub fn validate(&self) -> Result<(), RunError> {
        let a = &self.analysis;
        if !(1..=crate::analysis::MAX_FEEDBACK_RATIO).contains(&a.ratio) {
            return Err(RunError::Invalid(format!(
                "feedback ratio {} not in 1..={}",
                a.ratio,
                crate::analysis::MAX_FEEDBACK_RATIO
            )));
        }
        if !(a.lod_bias.is_finite() && a.lod_bias > 0.0 && a.lod_bias <= 1e6) {
            return Err(RunError::Invalid(format!(
                "LOD bias {} must be finite and in (0, 1e6]",
                a.lod_bias
            )));
        }
        if !(0.0..=1.0).contains(&self.fill_ratio) {
            return Err(RunError::Invalid(format!(
                "fill ratio {} not in 0..=1",
                self.fill_ratio
            )));
        }
        if self.load_limit == 0 || self.max_requests == 0 {
            return Err(RunError::Invalid(
                "load limit and request cap must be at least 1".into(),
            ));
        }
        if self.max_requests > arbor_proto::limits::MAX_REQUEST_ITEMS {
            return Err(RunError::Invalid(format!(
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
    pub analysis: Duration,
    pub presort: Duration,
}

/// The second half: what the slot buffer did.
#[derive(Clone, Debug)]
pub struct Integration {
    pub inserted: u32,
    pub evicted: u32,
    /// Arrivals dropped: parent gone, no room, undecodable, or backlog overflow.
    pub dropped: u32,
    pub upload: UploadPlan,
    pub integrate: Duration,
    pub upload_time: Duration,
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
    ) -> Result<Self, RunError> {
        Self::with_backend(scene, config, root, Box::new(CpuBackend))
    }

    /// A core holding only the root treelet, running its passes on `backend`.
    pub fn with_backend(
        scene: Arc<SceneDescription>,
        config: CoreConfig,
        root: DecodedTreelet,
        backend: Box<dyn Backend>,
    ) -> Result<Self, RunError> {
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

    pub fn scene(&self) -> &Arc<SceneDescription> {
        &self.scene
    }

    pub fn frame(&self) -> &SceneFrame {
        &self.frame
    }

    pub fn slots(&self) -> &SlotBuffer {
        &self.slots
    }

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

    /// Analysis and presort for `camera`; ages visibility and marks what was seen. Returns the
    /// request list to send.
    pub fn plan(&mut self, camera: &Camera) -> Plan {
        let t0 = Instant::now();
        self.backend.analyse(
            &self.slots,
            &self.frame,
            camera,
            &self.config.analysis,
            self.cycle,
            &mut self.feedback,
        );
        let analysis = t0.elapsed();
        let t1 = Instant::now();
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
        let presort = t1.elapsed();
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
            requests: sorted.requests.iter().map(|r| (r.id, r.priority)).collect(),
            distinct_requests: sorted.distinct_requests,
            samples: errors.len() as u32,
            error: ErrorSummary::from_samples(&errors, ratio * ratio),
            analysis,
            presort,
        }
    }

    /// Inserts queued arrivals up to the load limit and plans the upload of what changed.
    pub fn integrate(&mut self) -> Integration {
        let t0 = Instant::now();
        let mut inserted = 0;
        let mut evicted = 0;
        let mut dropped = std::mem::take(&mut self.backlog_dropped);
        let mut kept = VecDeque::new();
        while let Some(t) = self.backlog.pop_front() {
            let id = t.treelet.header.id;
            match self.slots.insert(t.clone()) {
                InsertOutcome::Inserted { evicted: e, .. } => {
                    inserted += 1;
                    evicted += e;
                }
                InsertOutcome::AlreadyResident => {}
                InsertOutcome::ParentMissing | InsertOutcome::NoRoom => dropped += 1,
                InsertOutcome::LoadLimit => {
                    kept.push_back(t);
                    continue;
                }
            }
            self.backlog_ids.remove(&id);
        }
        self.backlog = kept;
        let integrate = t0.elapsed();
        let t1 = Instant::now();
        let dirty = self.slots.take_dirty();
        let upload = UploadPlan::new(
            &dirty,
            self.config.fill_ratio,
            SlotBuffer::slot_data_bytes(self.scene.treelet_nodes, &self.config.channels),
        );
        self.backend.upload(&self.slots, &upload);
        Integration {
            inserted,
            evicted,
            dropped,
            upload,
            integrate,
            upload_time: t1.elapsed(),
        }
    }

    /// The image of what is resident, seen from `camera`.
    pub fn render(&mut self, camera: &Camera) -> Image {
        self.backend.render(
            &self.slots,
            &self.frame,
            camera,
            self.config.analysis.lod_bias,
            &self.config.light,
        )
    }

    /// Renders into the backend's own target (see [`Backend::render_in_place`]).
    pub fn render_in_place(&mut self, camera: &Camera) -> bool {
        self.backend.render_in_place(
            &self.slots,
            &self.frame,
            camera,
            self.config.analysis.lod_bias,
            &self.config.light,
        )
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

/// A headless run: connection, camera path, cycle count and outputs.
#[derive(Clone, Debug)]
pub struct HeadlessConfig {
    pub client: ClientConfig,
    pub core: CoreConfig,
    pub camera_path: CameraPath,
    pub seed: u64,
    pub width: u32,
    pub height: u32,
    /// Upper bound on cycles.
    pub cycles: u32,
    /// A cycle takes at least this long (the rest is slept), like a frame-rate cap.
    pub min_cycle: Duration,
    /// How long to wait for `SceneInfo` and the root treelet.
    pub connect_timeout: Duration,
    /// Compared with every rendered frame (image RMSE and differing share in the report).
    pub reference: Option<Image>,
    /// Stop as soon as the view has converged (see [`HeadlessRun::converged_at`]).
    pub until_converged: bool,
    /// Also render cycles in between (1 = every cycle); the last cycle is always rendered.
    pub render_every: u32,
}

/// What a headless run produced.
#[derive(Debug)]
pub struct HeadlessRun {
    pub report: RunReport,
    /// The last rendered frame.
    pub image: Image,
    /// The cycle (0-based) at which `n²` consecutive cycles had asked for nothing: every pixel
    /// was sampled once and no sample saw unloaded detail coarser than a pixel, so the image is
    /// the fully resident scene's. `None` if that never happened.
    pub converged_at: Option<u32>,
    /// The most slots ever used, and the capacity.
    pub peak_slots: u32,
    pub capacity: u32,
    /// Bytes per slot (nodes, attributes, bookkeeping).
    pub slot_bytes: u64,
    pub client: ClientStats,
    pub scene: Arc<SceneDescription>,
}

/// Runs a headless session: connect, fetch the root, then `cycles` cycles. Synchronous: call it
/// from a thread that is not a tokio worker, with a handle to a running runtime (the connection
/// lives there).
pub fn run_headless(
    config: HeadlessConfig,
    runtime: &tokio::runtime::Handle,
) -> Result<HeadlessRun, RunError> {
    run_headless_observed(config, runtime, |_| {})
}

/// What an observer of [`run_headless_observed`] sees after each cycle.
#[derive(Debug)]
pub struct CycleView<'a> {
    pub record: &'a CycleRecord,
    pub camera: &'a Camera,
    /// The frame, when this cycle rendered one.
    pub image: Option<&'a Image>,
    pub slots: &'a SlotBuffer,
}

/// [`run_headless`], calling `observer` after every cycle (tests check each frame with it).
pub fn run_headless_observed(
    config: HeadlessConfig,
    runtime: &tokio::runtime::Handle,
    observer: impl FnMut(&CycleView<'_>),
) -> Result<HeadlessRun, RunError> {
    config.core.validate()?;
    if config.width == 0 || config.height == 0 || config.render_every == 0 {
        return Err(RunError::Invalid(
            "frame size and render interval must be at least 1".into(),
        ));
    }
    if let Some(r) = &config.reference
        && (r.width != config.width || r.height != config.height)
    {
        return Err(RunError::Reference(format!(
            "{}×{} but the run renders {}×{}",
            r.width, r.height, config.width, config.height
        )));
    }
    let started = Instant::now();
    // The server refuses channels a scene lacks, so learn the layout first and ask for the
    // wanted channels the scene has (DESIGN §7: nothing is sent that is not drawn).
    let layout = {
        let mut probe = {
            let _guard = runtime.enter();
            TreeletClient::start(config.client.clone().with_channels([]))?
        };
        let scene = wait_for_scene(&mut probe, &config);
        runtime.block_on(probe.close());
        scene?.layout.clone()
    };
    let mut config = config;
    let channels: Vec<Channel> = config
        .core
        .channels
        .iter()
        .copied()
        .filter(|c| layout.contains(*c))
        .collect();
    config.core.channels = channels.clone();
    config.client = config.client.with_channels(channels);
    let mut client = {
        let _guard = runtime.enter();
        TreeletClient::start(config.client.clone())?
    };
    let result = cycle_loop(&config, &mut client, started, observer);
    runtime.block_on(client.close());
    result
}

fn wait_for_scene(
    client: &mut TreeletClient,
    config: &HeadlessConfig,
) -> Result<Arc<SceneDescription>, RunError> {
    let deadline = Instant::now() + config.connect_timeout;
    loop {
        while let Some(event) = client.try_next_event() {
            match event {
                ClientEvent::Connected(s) => return Ok(s),
                ClientEvent::Treelet(_) => {}
                ClientEvent::Disconnected {
                    reason,
                    reconnect_in: None,
                    ..
                } => return Err(RunError::Refused(reason)),
                ClientEvent::Disconnected { reason, .. } => {
                    tracing::warn!("connection attempt failed, retrying: {reason}");
                }
            }
        }
        if Instant::now() >= deadline {
            return Err(RunError::Timeout(format!(
                "no SceneInfo within {:?} from {}:{}",
                config.connect_timeout, config.client.url.host, config.client.url.port
            )));
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

fn cycle_loop(
    config: &HeadlessConfig,
    client: &mut TreeletClient,
    started: Instant,
    mut observer: impl FnMut(&CycleView<'_>),
) -> Result<HeadlessRun, RunError> {
    let (scene, root) = bootstrap(config, client)?;
    let channels = config.core.channels.clone();
    let mut core = ClientCore::new(scene.clone(), config.core.clone(), root)?;
    let frame = *core.frame();
    let ratio = config.core.analysis.ratio;
    let round = ratio * ratio;
    let mut report = RunReport {
        meta: RunMeta {
            scene: scene.name.clone(),
            server: format!(
                "quic://{}:{}/{}",
                config.client.url.host, config.client.url.port, config.client.url.scene
            ),
            width: config.width,
            height: config.height,
            feedback_ratio: ratio,
            budget_mib: config.core.budget_bytes as f64 / (1024.0 * 1024.0),
            camera_path: config.camera_path.to_string(),
            treelet_bytes: scene.treelet_nodes * arbor_proto::limits::NODE_BYTES,
        },
        records: Vec::new(),
    };
    let mut image = Image::new(config.width, config.height);
    let mut quiet_cycles = 0u32;
    let mut converged_at = None;
    let mut peak_slots = core.slots().used_slots();
    let mut last_stats = client.stats();
    for cycle in 0..config.cycles {
        let cycle_start = Instant::now();
        let camera =
            config
                .camera_path
                .camera(cycle, &frame, config.seed, config.width, config.height);
        let plan = core.plan(&camera);
        let t_request = Instant::now();
        let requests_sent = plan.requests.len() as u32;
        client.request(plan.requests.clone())?;
        let request_time = t_request.elapsed();
        let t_drain = Instant::now();
        let (received, received_bytes, undecodable) = drain_events(client, &scene, &channels)?;
        for t in received {
            core.handle_treelet(t);
        }
        let drain_time = t_drain.elapsed();
        let integration = core.integrate();
        peak_slots = peak_slots.max(core.slots().used_slots());
        let last = cycle + 1 == config.cycles;
        quiet_cycles = if plan.error.max > 0.0 || !camera_is_static(config) {
            0
        } else {
            quiet_cycles + 1
        };
        let converged_now = converged_at.is_none() && quiet_cycles >= round;
        if converged_now {
            converged_at = Some(cycle);
        }
        let stop = last || (converged_now && config.until_converged);
        let t_render = Instant::now();
        let rendered = stop || cycle % config.render_every == 0;
        if rendered {
            image = core.render(&camera);
        }
        let render_time = t_render.elapsed();
        let (image_rmse, differing_share) = match (&config.reference, rendered) {
            (Some(r), true) => (
                Some(
                    image
                        .rmse(r)
                        .map_err(|e| RunError::Reference(e.to_string()))?,
                ),
                Some(image.differing_share(r)),
            ),
            _ => (None, None),
        };
        let stats = client.stats();
        let record = CycleRecord {
            cycle,
            time_s: started.elapsed().as_secs_f64(),
            analysis_ms: ms(plan.analysis),
            presort_ms: ms(plan.presort),
            request_ms: ms(request_time),
            integrate_ms: ms(drain_time + integration.integrate),
            upload_ms: ms(integration.upload_time),
            render_ms: ms(render_time),
            requests_sent,
            treelets_received: (stats.treelets_received - last_stats.treelets_received) as u32,
            bytes_received: received_bytes,
            treelets_inserted: integration.inserted,
            slots_used: core.slots().used_slots(),
            slots_total: core.slots().capacity(),
            evictions: integration.evicted,
            dropped: integration.dropped + undecodable,
            upload_ranges: integration.upload.ranges.len() as u32,
            upload_bytes: integration.upload.bytes,
            samples: plan.samples,
            error: plan.error,
            image_rmse,
            differing_share,
        };
        tracing::debug!(
            cycle,
            requests = requests_sent,
            inserted = integration.inserted,
            slots = record.slots_used,
            error_max = record.error.max,
            "cycle"
        );
        observer(&CycleView {
            record: &record,
            camera: &camera,
            image: rendered.then_some(&image),
            slots: core.slots(),
        });
        report.records.push(record);
        last_stats = stats;
        if stop {
            break;
        }
        if let Some(rest) = config.min_cycle.checked_sub(cycle_start.elapsed()) {
            std::thread::sleep(rest);
        }
    }
    Ok(HeadlessRun {
        report,
        image,
        converged_at,
        peak_slots,
        capacity: core.slots().capacity(),
        slot_bytes: SlotBuffer::slot_bytes(scene.treelet_nodes, &channels),
        client: client.stats(),
        scene,
    })
}

fn camera_is_static(config: &HeadlessConfig) -> bool {
    matches!(config.camera_path, CameraPath::Static)
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// Takes every queued event without waiting: decoded treelets, their wire bytes, and the
/// number that failed to decode (logged and dropped; the server is at fault, the run goes on).
fn drain_events(
    client: &mut TreeletClient,
    scene: &SceneDescription,
    channels: &[Channel],
) -> Result<(Vec<DecodedTreelet>, u64, u32), RunError> {
    let mut out = Vec::new();
    let mut bytes = 0u64;
    let mut bad = 0u32;
    while let Some(event) = client.try_next_event() {
        match event {
            ClientEvent::Treelet(t) => {
                bytes += t.wire_bytes as u64;
                match DecodedTreelet::decode(&t, scene, channels) {
                    Ok(d) => out.push(d),
                    Err(e) => {
                        tracing::warn!(treelet = %t.id, "dropping undecodable treelet: {e}");
                        bad += 1;
                    }
                }
            }
            ClientEvent::Connected(s) => {
                if s.name != scene.name || s.treelet_count != scene.treelet_count {
                    return Err(RunError::Refused(format!(
                        "after reconnecting the server describes a different scene ({} with {} \
                         treelets)",
                        s.name, s.treelet_count
                    )));
                }
            }
            ClientEvent::Disconnected {
                reason,
                reconnect_in: None,
                ..
            } => return Err(RunError::Refused(reason)),
            ClientEvent::Disconnected { reason, .. } => {
                tracing::warn!("connection lost, reconnecting: {reason}");
            }
        }
    }
    Ok((out, bytes, bad))
}

/// Waits (bounded) for `SceneInfo` and the root treelet.
fn bootstrap(
    config: &HeadlessConfig,
    client: &mut TreeletClient,
) -> Result<(Arc<SceneDescription>, DecodedTreelet), RunError> {
    let deadline = Instant::now() + config.connect_timeout;
    let mut scene: Option<Arc<SceneDescription>> = None;
    loop {
        while let Some(event) = client.try_next_event() {
            match event {
                ClientEvent::Connected(s) => {
                    client.request(vec![(s.root_treelet, f32::MAX)])?;
                    scene = Some(s);
                }
                ClientEvent::Treelet(t) => {
                    if let Some(s) = &scene
                        && t.id == s.root_treelet
                    {
                        let root = DecodedTreelet::decode(&t, s, &config.core.channels)?;
                        return Ok((s.clone(), root));
                    }
                }
                ClientEvent::Disconnected {
                    reason,
                    reconnect_in: None,
                    ..
                } => return Err(RunError::Refused(reason)),
                ClientEvent::Disconnected { reason, .. } => {
                    tracing::warn!("connection attempt failed, retrying: {reason}");
                }
            }
        }
        if Instant::now() >= deadline {
            return Err(RunError::Timeout(format!(
                "no {} within {:?} from {}:{}",
                if scene.is_some() {
                    "root treelet"
                } else {
                    "SceneInfo"
                },
                config.connect_timeout,
                config.client.url.host,
                config.client.url.port
            )));
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Fetches every treelet of the scene over the connection (requests in id order, in batches of
/// at most the protocol's list size) — how `arbor-client reference` gets the whole scene
/// without reading the server's pool.
pub fn fetch_all(
    client_config: &ClientConfig,
    wanted: &[Channel],
    timeout: Duration,
    runtime: &tokio::runtime::Handle,
) -> Result<FetchedScene, RunError> {
    let probe_config = HeadlessConfig {
        client: client_config.clone().with_channels([]),
        core: CoreConfig::default(),
        camera_path: CameraPath::Static,
        seed: 0,
        width: 1,
        height: 1,
        cycles: 0,
        min_cycle: Duration::ZERO,
        connect_timeout: timeout,
        reference: None,
        until_converged: false,
        render_every: 1,
    };
    let mut probe = {
        let _guard = runtime.enter();
        TreeletClient::start(probe_config.client.clone())?
    };
    let scene = wait_for_scene(&mut probe, &probe_config);
    runtime.block_on(probe.close());
    let scene = scene?;
    let channels: Vec<Channel> = wanted
        .iter()
        .copied()
        .filter(|c| scene.layout.contains(*c))
        .collect();
    let mut client = {
        let _guard = runtime.enter();
        TreeletClient::start(client_config.clone().with_channels(channels.clone()))?
    };
    let result = fetch_batches(&mut client, &scene, &channels, timeout);
    runtime.block_on(client.close());
    Ok(FetchedScene {
        treelets: result?,
        scene,
        channels,
    })
}

/// A whole scene fetched by [`fetch_all`].
#[derive(Debug)]
pub struct FetchedScene {
    pub scene: Arc<SceneDescription>,
    /// The channels fetched: those asked for that the scene has.
    pub channels: Vec<Channel>,
    /// Every treelet, in id order.
    pub treelets: Vec<DecodedTreelet>,
}

fn fetch_batches(
    client: &mut TreeletClient,
    scene: &Arc<SceneDescription>,
    channels: &[Channel],
    timeout: Duration,
) -> Result<Vec<DecodedTreelet>, RunError> {
    let count = scene.treelet_count;
    let batch = arbor_proto::limits::MAX_REQUEST_ITEMS as u32;
    let mut got: Vec<Option<DecodedTreelet>> = vec![None; count as usize];
    let mut have = 0u32;
    let mut start = 0u32;
    while start < count {
        let end = (start + batch).min(count);
        // Lower ids first: parents before children, so a partial fetch is still a valid cut.
        let list = (start..end)
            .filter(|&i| got[i as usize].is_none())
            .map(|i| (TreeletId(i), (count - i) as f32))
            .collect();
        client.request(list)?;
        let deadline = Instant::now() + timeout;
        loop {
            let missing = (start..end).any(|i| got[i as usize].is_none());
            if !missing {
                break;
            }
            let (arrived, _, bad) = drain_events(client, scene, channels)?;
            if bad > 0 {
                return Err(RunError::Refused(format!(
                    "{bad} treelets from the server did not decode"
                )));
            }
            if arrived.is_empty() {
                if Instant::now() >= deadline {
                    return Err(RunError::Timeout(format!(
                        "fetched {have} of {count} treelets; nothing new within {timeout:?}"
                    )));
                }
                std::thread::sleep(Duration::from_millis(1));
                continue;
            }
            for t in arrived {
                let i = t.treelet.header.id.0 as usize;
                if i < got.len() && got[i].is_none() {
                    got[i] = Some(t);
                    have += 1;
                }
            }
        }
        tracing::info!("fetched {have} of {count} treelets");
        start = end;
    }
    Ok(got.into_iter().flatten().collect())
}

/// The reference image: what `camera` sees with the whole scene resident.
pub fn reference_image(
    scene: &SceneDescription,
    channels: &[Channel],
    treelets: Vec<DecodedTreelet>,
    camera: &Camera,
    lod_bias: f64,
    light: &Light,
) -> Result<Image, RunError> {
    let slots = SlotBuffer::fully_resident(scene, channels, treelets)?;
    Ok(render(
        &slots.view(),
        &SceneFrame::of(scene),
        camera,
        lod_bias,
        light,
    ))
}
