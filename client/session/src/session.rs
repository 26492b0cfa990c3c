//! A streaming session: a [`TreeletClient`] connection feeding a [`ClientCore`], stepped one
//! cycle at a time by whoever owns the clock — the headless runner or the window viewer.
//!
//! Connecting is the only place that waits on the network (bounded by a timeout): one
//! connection whose `Hello` asks for the wanted channels the scene has (docs/design.md §7), the
//! root unasked and, given the first camera, the root's refinement for it; the session is
//! built once the root has arrived. After that, [`Session::step`] never waits: it takes
//! whatever has arrived.

use std::sync::Arc;
use std::time::{Duration, Instant};

use rayon::prelude::*;

use arbor_proto::codec::PreparedDictionaries;
use arbor_proto::wire::{HELLO_GRANT_AVAILABLE, HELLO_SEND_ROOT};
use arbor_proto::{Channel, SceneDescription, TreeletId};

use arbor_client_core::backend::{Backend, render_resident};
use arbor_client_core::camera::Camera;
use arbor_client_core::coverage::SampleBudget;
use arbor_client_core::cycle::{ClientCore, CoreConfig, CoreError};
use arbor_client_core::image::Image;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::render::Light;
use arbor_client_net::{ClientConfig, ClientEvent, ClientStats, ReceivedTreelet, TreeletClient};
use arbor_client_report::{CycleRecord, RunEvent};

use crate::RunError;
use crate::reference::fetch_ids;
use crate::stall::StallWatch;
use arbor_client_core::slots::{DecodedTreelet, SlotBuffer, SlotError};

/// How a session connects.
#[derive(Clone, Debug)]
pub struct SessionConfig {
    pub client: ClientConfig,
    /// `core.channels` are the wanted channels; the session keeps those the scene has.
    pub core: CoreConfig,
    /// How long to wait for `SceneInfo` and the root treelet.
    pub connect_timeout: Duration,
    /// The first cycle's camera placed in [`SceneFrame::UNIT`] (a camera path's camera for
    /// that frame), if known before connecting: sent in `Hello` so the server pushes its
    /// refinement at once ([`ClientCore::first_view_hint`]).
    pub first_camera: Option<Camera>,
}

/// What a step draws.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RenderMode {
    /// Nothing (the cycle still streams and integrates).
    Skip,
    /// Render and read back an [`Image`].
    Image,
    /// Render into the backend's own target (the viewer's window).
    InPlace,
}

/// One step's outcome.
#[derive(Debug)]
pub struct Step {
    pub record: CycleRecord,
    /// The frame, for [`RenderMode::Image`].
    pub image: Option<Image>,
    /// This step is the session's first exact convergence: every pixel of the view is known and
    /// none sees unloaded detail coarser than a pixel at the bias in effect (see
    /// [`Session::converged_at`]).
    pub converged_now: bool,
    /// This step's view is converged (every pixel known and final), whether or not an earlier
    /// one was: a viewer whose frame size changes asks this of each full-size frame.
    pub converged: bool,
    /// A stall found at this step, or progress again after one ([`StallWatch`]), for the
    /// report's events.
    pub stall: Option<RunEvent>,
}

/// A connected session.
#[derive(Debug)]
pub struct Session {
    client: TreeletClient,
    core: ClientCore,
    scene: Arc<SceneDescription>,
    channels: Vec<Channel>,
    /// The scene's zstd dictionaries, loaded once for every treelet received.
    dictionaries: PreparedDictionaries,
    started: Instant,
    /// The root treelet's wire bytes, received while connecting: counted with the first
    /// cycle's arrivals (the treelets that overtook it are handed to that cycle in `early`).
    root_bytes: Option<u64>,
    cycle: u32,
    budget: SampleBudget,
    converged_at: Option<u32>,
    stalls: StallWatch,
    peak_slots: u32,
    /// Treelets that arrived before the root (pushes for `Hello`'s view may overtake it),
    /// handed to the first step.
    early: Vec<ReceivedTreelet>,
}

impl Session {
    /// Connects, learns the scene, fetches the root treelet and builds the core on `backend`.
    /// Synchronous: call it from a thread that is not a tokio worker, with a handle to a running
    /// runtime (the connection task lives there).
    pub fn connect(
        config: SessionConfig,
        runtime: &tokio::runtime::Handle,
        backend: Box<dyn Backend>,
    ) -> Result<Self, RunError> {
        config.core.validate()?;
        let started = Instant::now();
        // One connection: the server grants the wanted channels the scene has and sends the
        // root unasked, so no probe connection and no root round trip.
        let wanted = config.core.channels.clone();
        let mut client = {
            let _guard = runtime.enter();
            TreeletClient::start(
                config
                    .client
                    .clone()
                    .with_channels(wanted.clone())
                    .with_hello_flags(HELLO_GRANT_AVAILABLE | HELLO_SEND_ROOT)
                    .with_hello_view(
                        config
                            .first_camera
                            .as_ref()
                            .and_then(|c| ClientCore::first_view_hint(&config.core, c)),
                    ),
            )?
        };
        let (scene, channels, dictionaries, (root, root_bytes), early) =
            match bootstrap(&mut client, &wanted, &config) {
                Ok(x) => x,
                Err(e) => {
                    runtime.block_on(client.close());
                    return Err(e);
                }
            };
        let config_budget_s = config.core.analysis_budget_ms / 1e3;
        let core = ClientCore::with_backend(
            scene.clone(),
            CoreConfig {
                channels: channels.clone(),
                ..config.core
            },
            root,
            backend,
        )?;
        Ok(Self {
            peak_slots: core.slots().used_slots(),
            client,
            core,
            scene,
            channels,
            dictionaries,
            started,
            root_bytes: Some(root_bytes),
            cycle: 0,
            budget: SampleBudget::new(config_budget_s),
            converged_at: None,
            stalls: StallWatch::default(),
            early,
        })
    }

    pub fn scene(&self) -> &Arc<SceneDescription> {
        &self.scene
    }

    /// The channels held (wanted ∩ the scene's).
    pub fn channels(&self) -> &[Channel] {
        &self.channels
    }

    pub fn core(&self) -> &ClientCore {
        &self.core
    }

    /// Makes `base` the configured LOD bias from the next step on
    /// ([`ClientCore::set_lod_bias`]): above 1 a coarser picture that needs fewer treelets,
    /// below 1 a finer one. Refused, changing nothing, when not finite and in (0, 1e6].
    pub fn set_lod_bias(&mut self, base: f64) -> Result<(), CoreError> {
        self.core.set_lod_bias(base)
    }

    pub fn client_stats(&self) -> ClientStats {
        self.client.stats()
    }

    /// The first cycle that completed convergence, if any.
    pub fn converged_at(&self) -> Option<u32> {
        self.converged_at
    }

    /// The most slots ever used.
    pub fn peak_slots(&self) -> u32 {
        self.peak_slots
    }

    /// When the session started connecting.
    pub fn started(&self) -> Instant {
        self.started
    }

    /// One cycle (docs/design.md §1): analysis → presort → request list → take arrivals →
    /// integrate → upload → render. Never waits on the network. Arrivals are taken off the
    /// connection before the presort too, so the list does not name them, and decoded after
    /// the list is sent. `reference`, if given, is compared with
    /// the rendered image (RenderMode::Image only).
    pub fn step(
        &mut self,
        camera: &Camera,
        render: RenderMode,
        reference: Option<&Image>,
    ) -> Result<Step, RunError> {
        let cycle = self.cycle;
        self.cycle += 1;
        let t_analysis = Instant::now();
        let pixels = camera.width.saturating_mul(camera.height);
        let analysis = self.core.analyse(camera, self.budget.max_samples(pixels))?;
        let analysis_time = t_analysis.elapsed();
        let (measured, seconds) = self
            .core
            .backend()
            .analysis_cost()
            .unwrap_or((analysis.sampled, analysis_time.as_secs_f64()));
        self.budget.record(measured, seconds);
        // What arrived during the analysis is not to be listed again; it is decoded after the
        // list is on its way.
        let mut received = std::mem::take(&mut self.early);
        let mut connected = take_events(&mut self.client, &self.scene, &mut received)?;
        self.core.note_arriving(received.iter().map(|t| t.id));
        let t_presort = Instant::now();
        let plan = self.core.presort();
        let presort_time = t_presort.elapsed();
        let t_request = Instant::now();
        let requests_sent = plan.requests.len() as u32;
        match plan.view {
            Some(view) => {
                let items = plan
                    .requests
                    .iter()
                    .zip(&plan.errors)
                    .map(|(&(id, p), &e)| (id, p, e))
                    .collect();
                self.client.request_deep(items, view, plan.prefetch_from)?
            }
            None => self.client.request(plan.requests.clone())?,
        }
        let request_time = t_request.elapsed();
        let t_drain = Instant::now();
        connected |= take_events(&mut self.client, &self.scene, &mut received)?;
        let drained = decode_all(&received, &self.scene, &self.channels, &self.dictionaries);
        // What this cycle took off the connection, counted from the same treelets as its bytes
        // (the connection's own counter runs ahead: it counts what is queued for the session).
        let root_bytes = self.root_bytes.take();
        let (latency_p50_ms, latency_max_ms) = latency_stats(received.iter().map(|t| t.latency));
        let treelets_received = received.len() as u32 + u32::from(root_bytes.is_some());
        let bytes_received = drained.bytes + root_bytes.unwrap_or(0);
        for t in drained.treelets {
            self.core.handle_treelet(t);
        }
        if connected {
            // Maybe another replica, whose copies may decode.
            self.core.forget_undecodable();
        }
        for &id in &drained.undecodable {
            self.core.handle_undecodable(id);
        }
        let integration = self.core.integrate();
        let integrate_time = t_drain.elapsed();
        let t_upload = Instant::now();
        let upload = self.core.upload()?;
        let upload_time = t_upload.elapsed();
        self.peak_slots = self.peak_slots.max(self.core.slots().used_slots());

        let converged_now = self.converged_at.is_none() && plan.converged;
        if converged_now {
            self.converged_at = Some(cycle);
        }

        let t_render = Instant::now();
        let image = match render {
            RenderMode::Skip => None,
            RenderMode::Image => Some(self.core.render(camera)?),
            RenderMode::InPlace => {
                if !self.core.render_in_place(camera)? {
                    return Err(RunError::Invalid(format!(
                        "the {} backend cannot render in place",
                        self.core.backend_name()
                    )));
                }
                None
            }
        };
        let render_time = t_render.elapsed();
        let (image_rmse, differing_share) = match (reference, &image) {
            (Some(r), Some(i)) => compare(i, r)?,
            _ => (None, None),
        };
        let slots = self.core.slots();
        let record = CycleRecord {
            cycle,
            time_s: self.started.elapsed().as_secs_f64(),
            analysis_ms: ms(analysis_time),
            presort_ms: ms(presort_time),
            request_ms: ms(request_time),
            integrate_ms: ms(integrate_time),
            upload_ms: ms(upload_time),
            render_ms: ms(render_time),
            requests_sent,
            treelets_received,
            bytes_received,
            treelets_inserted: integration.inserted,
            slots_used: slots.used_slots(),
            slots_total: slots.capacity(),
            evictions: integration.evicted,
            dropped: integration.dropped + drained.undecodable.len() as u32,
            pushed: integration.pushed,
            push_dropped: integration.push_dropped,
            received_twice: integration.received_twice,
            upload_ranges: upload.ranges.len() as u32,
            upload_bytes: upload.bytes,
            samples: plan.samples,
            sampled: analysis.sampled as u32,
            known_share: plan.known_share,
            lod_bias: plan.lod_bias,
            error: plan.error,
            image_rmse,
            differing_share,
            latency_p50_ms,
            latency_max_ms,
        };
        tracing::debug!(
            cycle,
            requests = requests_sent,
            inserted = integration.inserted,
            slots = record.slots_used,
            error_max = record.error.max,
            "cycle"
        );
        let stall = self.stalls.observe(&record, plan.converged);
        Ok(Step {
            record,
            image,
            converged_now,
            converged: plan.converged,
            stall,
        })
    }

    /// Runs the passes on `backend` from now on, in place of one whose device was lost: the
    /// resident slots are uploaded to it and the session goes on where it was (see
    /// [`ClientCore::replace_backend`]); the connection is not touched.
    pub fn replace_backend(&mut self, backend: Box<dyn Backend>) -> Result<(), RunError> {
        Ok(self.core.replace_backend(backend)?)
    }

    /// Renders (and reads back) the current view outside a step, e.g. the frame of the cycle
    /// that turned out to be the last.
    pub fn render(&mut self, camera: &Camera) -> Result<Image, RunError> {
        Ok(self.core.render(camera)?)
    }

    /// Closes the connection gracefully.
    pub fn close(self, runtime: &tokio::runtime::Handle) -> ClientStats {
        let stats = self.client.stats();
        runtime.block_on(self.client.close());
        stats
    }
}

/// Image RMSE and differing share of `image` against `reference`, as the report records them.
pub fn compare(image: &Image, reference: &Image) -> Result<(Option<f64>, Option<f64>), RunError> {
    Ok((
        Some(
            image
                .rmse(reference)
                .map_err(|e| RunError::Reference(e.to_string()))?,
        ),
        Some(image.differing_share(reference)),
    ))
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// What [`drain_events`] took.
pub(crate) struct Drained {
    pub(crate) treelets: Vec<DecodedTreelet>,
    bytes: u64,
    /// Treelets that failed to decode (logged and dropped: the server is at fault).
    pub(crate) undecodable: Vec<TreeletId>,
}

/// Takes every queued event without waiting and decodes the treelets among them.
pub(crate) fn drain_events(
    client: &mut TreeletClient,
    scene: &SceneDescription,
    channels: &[Channel],
    dictionaries: &PreparedDictionaries,
) -> Result<Drained, RunError> {
    let mut received = Vec::new();
    take_events(client, scene, &mut received)?;
    Ok(decode_all(&received, scene, channels, dictionaries))
}

/// Takes every queued event without waiting: the treelets received, undecoded, go to
/// `received`. Whether a connection (re)started among them.
pub(crate) fn take_events(
    client: &mut TreeletClient,
    scene: &SceneDescription,
    received: &mut Vec<ReceivedTreelet>,
) -> Result<bool, RunError> {
    let mut connected = false;
    while let Some(event) = client.try_next_event() {
        match event {
            ClientEvent::Treelet(t) => received.push(t),
            ClientEvent::Connected(s) => {
                if s.name != scene.name || s.treelet_count != scene.treelet_count {
                    return Err(RunError::Refused(format!(
                        "after reconnecting the server describes a different scene ({} with {} \
                         treelets)",
                        s.name, s.treelet_count
                    )));
                }
                connected = true;
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
    Ok(connected)
}

/// The median (the upper of the middle two) and the largest of the received treelets'
/// list-to-arrival `latencies`, ms, leaving out the zero ones: pushes arrive unnamed.
fn latency_stats(latencies: impl Iterator<Item = Duration>) -> (Option<f64>, Option<f64>) {
    let mut ms: Vec<f64> = latencies
        .filter(|l| !l.is_zero())
        .map(|l| l.as_secs_f64() * 1e3)
        .collect();
    if ms.is_empty() {
        return (None, None);
    }
    // A selection, not a sort: a cycle over a fast link takes thousands of arrivals.
    let middle = ms.len() / 2;
    let (_, &mut median, above) = ms.select_nth_unstable_by(middle, f64::total_cmp);
    let max = above.iter().copied().fold(median, f64::max);
    (Some(median), Some(max))
}

/// Decodes received treelets, keeping their order; undecodable ones are logged and counted.
pub(crate) fn decode_all(
    received: &[ReceivedTreelet],
    scene: &SceneDescription,
    channels: &[Channel],
    dictionaries: &PreparedDictionaries,
) -> Drained {
    let mut out = Drained {
        treelets: Vec::with_capacity(received.len()),
        bytes: received.iter().map(|t| t.wire_bytes as u64).sum(),
        undecodable: Vec::new(),
    };
    // Decompression is most of a cycle's work while a link delivers hundreds of treelets per
    // cycle: spread it over the cores, keeping the arrival order.
    let decoded: Vec<_> = received
        .par_iter()
        .map(|t| decode_received(t, scene, channels, dictionaries))
        .collect();
    for (t, d) in received.iter().zip(decoded) {
        match d {
            Ok(d) => out.treelets.push(d),
            Err(e) => {
                tracing::warn!(treelet = %t.id, "dropping undecodable treelet: {e}");
                out.undecodable.push(t.id);
            }
        }
    }
    out
}

/// Probes the scene and starts a client for the channels asked for that the scene has: the
/// scene, those channels, the client.
pub(crate) fn start_for_scene(
    client_config: &ClientConfig,
    wanted: &[Channel],
    timeout: Duration,
    runtime: &tokio::runtime::Handle,
) -> Result<(Arc<SceneDescription>, Vec<Channel>, TreeletClient), RunError> {
    let scene = probe_scene(client_config, timeout, runtime)?;
    let channels: Vec<Channel> = wanted
        .iter()
        .copied()
        .filter(|c| scene.layout.contains(*c))
        .collect();
    let client = {
        let _guard = runtime.enter();
        TreeletClient::start(client_config.clone().with_channels(channels.clone()))?
    };
    Ok((scene, channels, client))
}

/// Connects without channels just to read the scene description.
fn probe_scene(
    client: &ClientConfig,
    timeout: Duration,
    runtime: &tokio::runtime::Handle,
) -> Result<Arc<SceneDescription>, RunError> {
    let mut probe = {
        let _guard = runtime.enter();
        TreeletClient::start(client.clone().with_channels([]))?
    };
    let deadline = Instant::now() + timeout;
    let result = loop {
        match probe.try_next_event() {
            Some(ClientEvent::Connected(s)) => break Ok(s),
            Some(ClientEvent::Treelet(_)) => {}
            Some(ClientEvent::Disconnected {
                reason,
                reconnect_in: None,
                ..
            }) => break Err(RunError::Refused(reason)),
            Some(ClientEvent::Disconnected { reason, .. }) => {
                tracing::warn!("connection attempt failed, retrying: {reason}");
            }
            None if Instant::now() >= deadline => {
                break Err(RunError::Timeout(format!(
                    "no SceneInfo within {timeout:?} from {}:{}",
                    client.url.host, client.url.port
                )));
            }
            None => std::thread::sleep(Duration::from_millis(2)),
        }
    };
    // Dropping closes in the background: the session does not wait for the probe's goodbye.
    let _guard = runtime.enter();
    drop(probe);
    result
}

/// The scene, the channels held, its prepared dictionaries, the decoded root and what arrived
/// before it.
type Bootstrapped = (
    Arc<SceneDescription>,
    Vec<Channel>,
    PreparedDictionaries,
    (DecodedTreelet, u64),
    Vec<ReceivedTreelet>,
);

/// Waits (bounded) for `SceneInfo` and the root treelet the server sends unasked; returns the
/// scene, the channels granted (the wanted ones the scene stores), the root with its wire bytes,
/// and the treelets that overtook it.
fn bootstrap(
    client: &mut TreeletClient,
    wanted: &[Channel],
    config: &SessionConfig,
) -> Result<Bootstrapped, RunError> {
    let deadline = Instant::now() + config.connect_timeout;
    let mut scene: Option<(Arc<SceneDescription>, Vec<Channel>, PreparedDictionaries)> = None;
    let mut early = Vec::new();
    loop {
        while let Some(event) = client.try_next_event() {
            match event {
                ClientEvent::Connected(s) => {
                    let channels = wanted
                        .iter()
                        .copied()
                        .filter(|c| s.layout.contains(*c))
                        .collect();
                    let dictionaries = PreparedDictionaries::of(&s);
                    scene = Some((s, channels, dictionaries));
                }
                ClientEvent::Treelet(t) => match scene.take() {
                    Some((s, channels, dictionaries)) if t.id == s.root_treelet => {
                        let root = decode_received(&t, &s, &channels, &dictionaries)?;
                        let bytes = t.wire_bytes as u64;
                        return Ok((s, channels, dictionaries, (root, bytes), early));
                    }
                    other => {
                        scene = other;
                        early.push(t);
                    }
                },
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
    let (scene, channels, mut client) = start_for_scene(client_config, wanted, timeout, runtime)?;
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
    // Lower ids first: parents before children, so a partial fetch is still a valid cut.
    let ids: Vec<TreeletId> = (0..scene.treelet_count).map(TreeletId).collect();
    fetch_ids(client, scene, channels, &ids, timeout)
}

/// The reference image: what `camera` sees with the whole scene resident, rendered by
/// `backend` (the CPU twin or the GPU, so a run is compared with its own arithmetic).
pub fn reference_image(
    scene: &SceneDescription,
    channels: &[Channel],
    treelets: Vec<DecodedTreelet>,
    camera: &Camera,
    lod_bias: f64,
    light: &Light,
    backend: &mut dyn Backend,
) -> Result<Image, RunError> {
    let slots = SlotBuffer::fully_resident(scene, channels, treelets)?;
    Ok(render_resident(
        &slots,
        &SceneFrame::of(scene),
        camera,
        lod_bias,
        light,
        backend,
    )?)
}

/// Decodes a treelet message as the connection delivered it, for the core.
pub(crate) fn decode_received(
    received: &ReceivedTreelet,
    scene: &SceneDescription,
    channels: &[Channel],
    dictionaries: &PreparedDictionaries,
) -> Result<DecodedTreelet, SlotError> {
    let blocks: Vec<(Channel, &[u8])> = received.channels.iter().collect();
    DecodedTreelet::decode_message(
        received.id,
        received.used_nodes,
        &received.nodes,
        &blocks,
        scene,
        dictionaries,
        channels,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latency_stats_are_the_upper_median_and_the_largest_of_the_listed() {
        let ms = Duration::from_millis;
        assert_eq!(latency_stats([].into_iter()), (None, None));
        // Pushes (zero) are left out.
        assert_eq!(latency_stats([ms(0), ms(0)].into_iter()), (None, None));
        assert_eq!(
            latency_stats([ms(90), ms(0), ms(10), ms(50)].into_iter()),
            (Some(50.0), Some(90.0))
        );
        assert_eq!(
            latency_stats([ms(40), ms(10), ms(30), ms(20)].into_iter()),
            (Some(30.0), Some(40.0))
        );
        assert_eq!(latency_stats([ms(7)].into_iter()), (Some(7.0), Some(7.0)));
    }
}
