//! The reference image of a view without holding the whole scene: fetch only the treelets the
//! camera's fully refined cut needs, breadth first over what the camera refines.
//!
//! Round by round: every pixel of the frame is sampled against what is resident (the render
//! pass's own ray and LOD rule, [`analyse_pixels`]); the treelets refining the leaves that
//! pixels want refined (a refinable leaf coarser than a pixel) are fetched, one level deeper
//! than the round before; this repeats until no pixel wants refinement. By the convergence rule
//! of the client cycle (ARCHITECTURE.md, "Convergence is exact": a pixel differs from the fully
//! resident render only if its terminal voxel is a refinable leaf coarser than a pixel), the
//! picture then equals the whole-scene reference bit for bit, while the client held only the
//! cut. The cut is found by the CPU twin of the analysis; the final render runs on the backend
//! asked for.
//!
//! Memory: the fetched treelets, kept decoded, and a slot buffer sized to exactly them (rebuilt
//! each round as the cut grows) — about twice the cut, never the scene.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_client_core::analysis::{Feedback, analyse_pixels, pack_pixel};
use arbor_client_core::backend::{Backend, render_resident};
use arbor_client_core::camera::Camera;
use arbor_client_core::image::Image;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::render::Light;
use arbor_client_core::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig, SlotError};
use arbor_client_net::{ClientConfig, TreeletClient};
use arbor_proto::codec::PreparedDictionaries;
use arbor_proto::{Channel, SceneDescription, TreeletId};

use crate::RunError;
use crate::session::{drain_events, start_for_scene};

/// What a streamed reference needs besides the connection.
#[derive(Clone, Copy)]
pub struct ReferenceView<'a> {
    /// The camera, made once the scene's frame is known.
    pub camera: &'a dyn Fn(&SceneFrame) -> Camera,
    /// LOD bias of the picture (1: stop at a pixel).
    pub lod_bias: f64,
    /// The render's shading.
    pub light: &'a Light,
}

impl std::fmt::Debug for ReferenceView<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ReferenceView")
            .field("lod_bias", &self.lod_bias)
            .field("light", self.light)
            .finish_non_exhaustive()
    }
}

/// A reference rendered from the view's cut.
#[derive(Debug)]
pub struct StreamedReference {
    pub scene: Arc<SceneDescription>,
    /// The channels fetched: those asked for that the scene has.
    pub channels: Vec<Channel>,
    pub image: Image,
    /// Treelets fetched (the cut), of the scene's `treelet_count`.
    pub treelets: u32,
    /// Rounds of refinement (levels of treelets below the root).
    pub rounds: u32,
    /// Largest bytes held for the cut at once: decoded treelets plus the slot buffer.
    pub peak_cut_bytes: u64,
    /// Time spent fetching and analysing.
    pub seconds: f64,
}

/// Fetches the cut of `view` and renders it with `backend`.
pub fn streamed_reference(
    client_config: &ClientConfig,
    wanted: &[Channel],
    view: &ReferenceView<'_>,
    timeout: Duration,
    runtime: &tokio::runtime::Handle,
    backend: &mut dyn Backend,
) -> Result<StreamedReference, RunError> {
    let started = Instant::now();
    let (scene, channels, mut client) = start_for_scene(client_config, wanted, timeout, runtime)?;
    let frame = SceneFrame::of(&scene);
    let camera = (view.camera)(&frame);
    let cut = refine_cut(
        &mut client,
        &scene,
        &channels,
        &frame,
        &camera,
        view,
        timeout,
    );
    runtime.block_on(client.close());
    let (slots, rounds, peak_cut_bytes) = cut?;
    let image = render_resident(&slots, &frame, &camera, view.lod_bias, view.light, backend)?;
    Ok(StreamedReference {
        treelets: slots.used_slots(),
        scene,
        channels,
        image,
        rounds,
        peak_cut_bytes,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// The rounds: fetch, place, sample every pixel, collect what they want refined.
fn refine_cut(
    client: &mut TreeletClient,
    scene: &Arc<SceneDescription>,
    channels: &[Channel],
    frame: &SceneFrame,
    camera: &Camera,
    view: &ReferenceView<'_>,
    timeout: Duration,
) -> Result<(SlotBuffer, u32, u64), RunError> {
    let pixels: Vec<u32> = (0..camera.height)
        .flat_map(|y| (0..camera.width).map(move |x| pack_pixel(x, y)))
        .collect();
    let mut kept: Vec<DecodedTreelet> = Vec::new();
    let mut wanted = vec![TreeletId::ROOT];
    let mut feedback = Feedback::default();
    let (mut rounds, mut peak) = (0u32, 0u64);
    loop {
        kept.extend(fetch_ids(client, scene, channels, &wanted, timeout)?);
        kept.sort_by_key(DecodedTreelet::id);
        let slots = place(scene, channels, &kept)?;
        let decoded: u64 = kept.iter().map(decoded_bytes).sum();
        let held = decoded + u64::from(slots.capacity()) * slot_bytes(scene, channels);
        peak = peak.max(held);
        analyse_pixels(
            &slots.view(),
            frame,
            camera,
            view.lod_bias,
            &pixels,
            u64::from(rounds),
            &mut feedback,
        );
        let next: BTreeSet<u32> = feedback
            .samples
            .iter()
            .filter(|s| s.wants_refinement())
            .map(|s| s.subtreelet)
            .filter(|&id| !slots.is_resident(TreeletId(id)))
            .collect();
        tracing::info!(
            round = rounds,
            resident = kept.len(),
            wanted = next.len(),
            "reference cut"
        );
        if next.is_empty() {
            return Ok((slots, rounds, peak));
        }
        wanted = next.into_iter().map(TreeletId).collect();
        rounds += 1;
        drop(slots);
    }
}

fn slot_bytes(scene: &SceneDescription, channels: &[Channel]) -> u64 {
    SlotBuffer::slot_bytes(scene.treelet_nodes, channels)
}

fn decoded_bytes(t: &DecodedTreelet) -> u64 {
    (std::mem::size_of_val(t.treelet.nodes.as_slice())
        + t.attributes.iter().map(|(_, a)| a.len()).sum::<usize>()) as u64
}

/// A slot buffer holding exactly `kept` (sorted by id, so parents go first).
fn place(
    scene: &SceneDescription,
    channels: &[Channel],
    kept: &[DecodedTreelet],
) -> Result<SlotBuffer, RunError> {
    let config = SlotConfig {
        budget_bytes: kept.len() as u64 * slot_bytes(scene, channels),
        treelet_nodes: scene.treelet_nodes,
        channels: channels.to_vec(),
        visibility_max: 1,
        load_limit: u32::MAX,
    };
    let mut rest = kept.iter().cloned();
    let root = rest.next().ok_or(SlotError::Incomplete {
        expected: 1,
        found: 0,
    })?;
    let mut slots = SlotBuffer::new(config, root)?;
    for t in rest {
        let id = t.id();
        match slots.insert(t) {
            InsertOutcome::Inserted { .. } => {}
            outcome => return Err(SlotError::NotPlaced { id, outcome }.into()),
        }
    }
    Ok(slots)
}

/// Fetches exactly `ids`, in batches of the protocol's list size, in the given order.
pub(crate) fn fetch_ids(
    client: &mut TreeletClient,
    scene: &SceneDescription,
    channels: &[Channel],
    ids: &[TreeletId],
    timeout: Duration,
) -> Result<Vec<DecodedTreelet>, RunError> {
    let dictionaries = PreparedDictionaries::of(scene);
    let mut out = Vec::with_capacity(ids.len());
    for batch in ids.chunks(arbor_proto::limits::MAX_REQUEST_ITEMS) {
        let mut missing: BTreeSet<u32> = batch.iter().map(|t| t.0).collect();
        let list = batch
            .iter()
            .enumerate()
            .map(|(i, &t)| (t, (batch.len() - i) as f32))
            .collect();
        client.request(list)?;
        let mut deadline = Instant::now() + timeout;
        while !missing.is_empty() {
            let drained = drain_events(client, scene, channels, &dictionaries)?;
            if !drained.undecodable.is_empty() {
                return Err(RunError::Refused(format!(
                    "{} treelets from the server did not decode",
                    drained.undecodable.len()
                )));
            }
            if drained.treelets.is_empty() {
                if Instant::now() >= deadline {
                    return Err(RunError::Timeout(format!(
                        "{} of {} treelets of this round missing after {timeout:?}",
                        missing.len(),
                        ids.len()
                    )));
                }
                std::thread::sleep(Duration::from_millis(1));
                continue;
            }
            deadline = Instant::now() + timeout;
            for t in drained.treelets {
                if missing.remove(&t.id().0) {
                    out.push(t);
                }
            }
        }
    }
    Ok(out)
}
