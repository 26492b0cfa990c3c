//! The GPU passes and the GPU upload on real scans: every scan with a different attribute
//! channel (colour, normals, density) is built into a real pool and decoded.
//!
//! - Twin test: fully and partially resident slot buffers, cameras orbiting outside and inside
//!   the scene; the GPU analysis (ratio 1: one sample per pixel) and image are compared with
//!   the CPU twins with the tolerances of `client/tests/gpu_compare/mod.rs`.
//! - Upload test: a slot buffer driven through cycles of inserts and evictions, uploaded at
//!   fill ratios 0, 0.6 and 1; after every upload the GPU arrays equal the CPU slot buffer
//!   byte for byte.
//!
//! Needs a wgpu adapter (lavapipe will do) and fails, never skips, without one. Run the `gpu_*`
//! test binaries one at a time: lavapipe uses every core.

#[path = "../../client/gpu/tests/gpu_compare/mod.rs"]
mod gpu_compare;

use std::collections::BTreeMap;
use std::sync::Arc;

use arbor_client_core::analysis::{AnalysisConfig, Feedback, grid_pixels};
use arbor_client_core::backend::{Backend, BackendError, PassInput};
use arbor_client_core::camera::{
    Camera, DEFAULT_DISTANCE_FACTOR, DEFAULT_FOV_Y, SplitMix64, WORLD_UP,
};
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::render::Light;
use arbor_client_core::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig};
use arbor_client_core::upload::{DEFAULT_FILL_RATIO, UploadPlan};
use arbor_client_gpu::{FeedbackMode, GpuBackend, GpuContext};
use arbor_proto::{Channel, SceneDescription};
use arbor_server::octree::{BuildOptions, DepthChoice};
use arbor_tests::support::{SCANS, build_file, decoded_treelets};
use glam::DVec3;
use gpu_compare::{Tally, compare, gpu};

/// A decoded real scan.
struct Scan {
    scene: SceneDescription,
    treelets: Vec<DecodedTreelet>,
    /// Child treelet ids of every treelet.
    children: Vec<Vec<u32>>,
}

fn load(name: &str, depth: u8) -> Scan {
    let rel = SCANS
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, r)| *r)
        .expect("known scan");
    let built = build_file(
        rel,
        name,
        &BuildOptions {
            depth: DepthChoice::Fixed(depth),
            treelet_bytes: 1024,
            ..BuildOptions::default()
        },
    );
    let scene = built.scene.description.clone();
    let treelets = decoded_treelets(&built.scene);
    let mut children = vec![Vec::new(); treelets.len()];
    for t in &treelets {
        let p = t.treelet.header.parent_id;
        if !p.is_none() {
            children[p.0 as usize].push(t.id().0);
        }
    }
    Scan {
        scene,
        treelets,
        children,
    }
}

/// Cameras around the scene (outside, at the default distance and closer) and inside it.
fn cameras(frame: &SceneFrame, seed: u64) -> Vec<Camera> {
    let mut rng = SplitMix64::new(seed);
    let centre = DVec3::from_array(frame.centre());
    let mut out = Vec::new();
    for i in 0..6 {
        let u = DVec3::new(
            rng.next_f64() * 2.0 - 1.0,
            rng.next_f64() * 2.0 - 1.0,
            (rng.next_f64() * 2.0 - 1.0) * 0.6,
        )
        .normalize();
        let dist = [DEFAULT_DISTANCE_FACTOR, 0.9, 0.3][i % 3] * frame.edge;
        let jitter = DVec3::new(rng.next_f64(), rng.next_f64(), rng.next_f64()) * 0.1 * frame.edge;
        out.push(
            Camera::look_at(
                centre + u * dist,
                centre + jitter,
                WORLD_UP,
                DEFAULT_FOV_Y,
                96,
                72,
            )
            .unwrap(),
        );
    }
    out
}

/// A slot buffer holding the root and the first `count` other treelets in id order (a parent
/// always precedes its children).
fn partial(scan: &Scan, channels: &[Channel], count: usize) -> SlotBuffer {
    let n = scan.scene.treelet_nodes;
    let config = SlotConfig {
        budget_bytes: (count as u64 + 1) * SlotBuffer::slot_bytes(n, channels),
        treelet_nodes: n,
        channels: channels.to_vec(),
        visibility_max: 1,
        load_limit: u32::MAX,
    };
    let mut b = SlotBuffer::new(config, scan.treelets[0].clone()).unwrap();
    for t in scan.treelets.iter().skip(1).take(count) {
        assert!(matches!(
            b.insert(t.clone()),
            InsertOutcome::Inserted { .. }
        ));
    }
    b
}

#[test]
fn real_scans_match_the_cpu() {
    let mut gpu = gpu().lock().unwrap_or_else(|e| e.into_inner());
    for (name, depth) in [("lion", 8u8), ("bunny", 8), ("engine", 7)] {
        let scan = load(name, depth);
        let channels = scan.scene.layout.channels().to_vec();
        let frame = SceneFrame::of(&scan.scene);
        let full = SlotBuffer::fully_resident(&scan.scene, &channels, scan.treelets.clone())
            .expect("the whole scene fits");
        let half = partial(&scan, &channels, scan.treelets.len() / 3);
        for (what, slots) in [("fully resident", &full), ("a third resident", &half)] {
            let view = slots.view();
            gpu.load(&view).unwrap();
            let mut tally = Tally::default();
            for (i, cam) in cameras(&frame, u64::from(depth) * 7 + name.len() as u64)
                .iter()
                .enumerate()
            {
                let bias = if i % 2 == 0 { 1.0 } else { 0.25 };
                compare(&mut gpu, &view, &frame, cam, bias, &mut tally);
            }
            tally.assert_within(&format!(
                "{name} depth {depth} ({:?}, {} treelets, {what})",
                channels,
                scan.treelets.len()
            ));
        }
    }
}

/// Asserts the GPU arrays equal the CPU slot buffer byte for byte.
fn assert_same_bytes(gpu: &GpuBackend, slots: &SlotBuffer, what: &str) {
    let view = slots.view();
    assert!(
        gpu.read_back_nodes().expect("GPU read-back") == view.nodes,
        "{what}: GPU node records differ from the slot buffer"
    );
    for c in Channel::ALL {
        let gpu_bytes = gpu.read_back_attributes(c).expect("GPU read-back");
        assert_eq!(
            gpu_bytes.as_deref(),
            view.channel(c),
            "{what}: GPU {} array differs from the slot buffer",
            c.name()
        );
    }
}

#[test]
fn uploads_keep_the_gpu_buffer_equal_to_the_slot_buffer() {
    let ctx = gpu()
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .context()
        .clone();
    let scan = load("lion", 8);
    let channels = scan.scene.layout.channels().to_vec();
    let n = scan.scene.treelet_nodes;
    let per_slot = SlotBuffer::slot_data_bytes(n, &channels);
    let arrays = 1 + channels.len() as u64;
    println!(
        "lion: {} treelets, N = {n}, channels {channels:?}, {per_slot} bytes per slot",
        scan.treelets.len()
    );
    let mut summary = BTreeMap::new();
    for fill in [0.0, DEFAULT_FILL_RATIO, 1.0] {
        let mut backend = GpuBackend::new(ctx.clone());
        let capacity = 48;
        let config = SlotConfig {
            budget_bytes: capacity * SlotBuffer::slot_bytes(n, &channels),
            treelet_nodes: n,
            channels: channels.clone(),
            visibility_max: 2,
            load_limit: 16,
        };
        let mut slots = SlotBuffer::new(config, scan.treelets[0].clone()).unwrap();
        let mut rng = SplitMix64::new(0x5eed);
        let (mut calls, mut bytes, mut dirty_bytes) = (0u64, 0u64, 0u64);
        for cycle in 0..14 {
            slots.begin_cycle();
            let resident: Vec<u32> = (0..slots.capacity())
                .filter(|&s| slots.treelet_in(s).is_some())
                .collect();
            for &slot in &resident {
                if rng.next_u64().is_multiple_of(8) {
                    let mut x = Some(slot);
                    while let Some(y) = x {
                        slots.mark_visible(y);
                        x = slots.parent_slot(y);
                    }
                }
            }
            for _ in 0..24 {
                let slot = resident[(rng.next_u64() % resident.len() as u64) as usize];
                // An insert of this cycle may have evicted it.
                let Some(id) = slots.treelet_in(slot).map(|t| t.0) else {
                    continue;
                };
                let kids = &scan.children[id as usize];
                if !kids.is_empty() {
                    let kid = kids[(rng.next_u64() % kids.len() as u64) as usize];
                    slots.insert(scan.treelets[kid as usize].clone());
                }
            }
            let dirty = slots.take_dirty();
            let plan = UploadPlan::new(&dirty, fill, per_slot);
            backend.upload(&slots, &plan).unwrap();
            let st = backend.stats;
            println!(
                "fill {fill} cycle {cycle}: {} dirty, {} ranges, {} calls, {} bytes{}",
                dirty.len(),
                plan.ranges.len(),
                st.last_calls,
                st.last_bytes,
                if cycle == 0 {
                    " (first upload: everything)"
                } else {
                    ""
                }
            );
            assert_same_bytes(&backend, &slots, &format!("fill {fill} cycle {cycle}"));
            if cycle == 0 {
                assert_eq!(st.full_uploads, 1);
                assert_eq!(st.last_bytes, u64::from(slots.capacity()) * per_slot);
                continue;
            }
            assert_eq!(st.last_calls, plan.ranges.len() as u64 * arrays);
            assert_eq!(st.last_bytes, plan.bytes, "bytes written = bytes planned");
            // `take_dirty` can list a slot twice (dirtied, evicted, dirtied again in one
            // cycle); the plan counts it once.
            let mut distinct = dirty.clone();
            distinct.dedup();
            if fill == 1.0 {
                assert_eq!(st.last_bytes, distinct.len() as u64 * per_slot);
            }
            if fill == 0.0 && !dirty.is_empty() {
                assert_eq!(st.last_calls, arrays, "one call per array");
            }
            calls += st.last_calls;
            bytes += st.last_bytes;
            dirty_bytes += distinct.len() as u64 * per_slot;
        }
        assert!(slots.stats().evicted > 0, "the cycles must evict");
        summary.insert(format!("{fill}"), (calls, bytes, dirty_bytes));
    }
    for (fill, (calls, bytes, dirty)) in &summary {
        println!(
            "fill {fill}: {calls} calls, {bytes} bytes for {dirty} dirty bytes over 13 cycles"
        );
    }
}

/// The [`Backend`] methods the client core calls: the first upload allocates and uploads
/// everything, `analyse` hands back the *previous* cycle's feedback when pipelined (never
/// waiting; here the test waits between cycles so it has completed) and the cycle's own when
/// it waits (also right after a pipelined cycle), `render` and `render_in_place`.
#[test]
fn backend_trait_pipelines_feedback_by_one_cycle_or_waits_for_it() {
    let ctx = gpu()
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .context()
        .clone();
    let scan = load("lion", 8);
    let channels = scan.scene.layout.channels().to_vec();
    let frame = SceneFrame::of(&scan.scene);
    let slots = partial(&scan, &channels, scan.treelets.len() / 2);
    let mut backend = GpuBackend::new(ctx.clone());
    backend.set_feedback_mode(FeedbackMode::Pipelined);
    let mut waiting = GpuBackend::new(ctx.clone());
    waiting.set_feedback_mode(FeedbackMode::Wait);
    let software = ctx.is_software();
    let mut auto = GpuBackend::new(ctx.clone());
    let mut reference = GpuBackend::new(ctx);
    let max = backend.max_slots(scan.scene.treelet_nodes, &channels);
    println!(
        "max slots of N = {}: {max} ({} bytes per binding)",
        scan.scene.treelet_nodes,
        backend.max_binding_bytes()
    );
    assert_eq!(
        u64::from(max),
        backend.max_binding_bytes() / (u64::from(scan.scene.treelet_nodes) * 8)
    );
    let config = AnalysisConfig {
        ratio: 8,
        lod_bias: 1.0,
    };
    let cams = cameras(&frame, 5);
    let light = Light::default();
    let input = |camera| PassInput {
        slots: &slots,
        frame: &frame,
        camera,
        analysis: &config,
        light: &light,
    };
    let mut out = Feedback::default();
    let grid = |cam: &Camera, cycle: u64| grid_pixels(cam.width, cam.height, config.ratio, cycle);
    backend
        .analyse(&input(&cams[0]), &grid(&cams[0], 0), 0, &mut out)
        .unwrap();
    assert!(
        out.samples.is_empty(),
        "no feedback before the first read-back"
    );
    assert_eq!(backend.stats.full_uploads, 1);
    for cycle in 1..5u64 {
        backend.finish().unwrap();
        let cam = &cams[cycle as usize % cams.len()];
        backend
            .analyse(&input(cam), &grid(cam, cycle), cycle, &mut out)
            .unwrap();
        let prev = &cams[(cycle - 1) as usize % cams.len()];
        let mut expected = Feedback::default();
        reference
            .analyse_blocking(&slots, &frame, prev, &config, cycle - 1, &mut expected)
            .unwrap();
        assert_eq!(
            out,
            expected,
            "cycle {cycle} returns cycle {}'s feedback",
            cycle - 1
        );
        assert!(out.samples.iter().any(|s| s.is_hit()));
        // Waiting: this cycle's own feedback, read back already; except right after a
        // pipelined cycle, when what is in flight comes back first.
        let mut now = Feedback::default();
        waiting.set_feedback_mode(if cycle == 2 {
            FeedbackMode::Pipelined
        } else {
            FeedbackMode::Wait
        });
        waiting
            .analyse(&input(cam), &grid(cam, cycle), cycle, &mut now)
            .unwrap();
        match cycle {
            2 => {}
            3 => assert_eq!(
                now, out,
                "waiting after pipelining hands back cycle 2's pass"
            ),
            _ => {
                reference
                    .analyse_blocking(&slots, &frame, cam, &config, cycle, &mut expected)
                    .unwrap();
                assert_eq!(
                    now, expected,
                    "waiting, cycle {cycle} returns its own feedback"
                );
            }
        }
        // Auto, at this small frame: waits on a software adapter always, on a hardware one
        // while the waits are short (else an earlier pass of this run comes back).
        let mut auto_fb = Feedback::default();
        auto.analyse(&input(cam), &grid(cam, cycle), cycle, &mut auto_fb)
            .unwrap();
        if software {
            reference
                .analyse_blocking(&slots, &frame, cam, &config, cycle, &mut expected)
                .unwrap();
            assert_eq!(auto_fb, expected, "auto on a software adapter waits");
        } else {
            assert!(
                (1..=cycle).contains(&auto_fb.cycle),
                "auto returned cycle {}'s pass in cycle {cycle}",
                auto_fb.cycle
            );
        }
    }
    let image = backend.render(&input(&cams[0])).unwrap();
    assert_eq!(image, reference.render(&input(&cams[0])).unwrap());
    assert!(image.coverage() > 0);
    assert!(backend.render_in_place(&input(&cams[1])).unwrap());
    assert!(backend.target_view().is_some());
    assert_eq!(backend.stats.full_uploads, 1);
}

/// A context of its own (the faults below must not reach the shared one), half of lion
/// resident, and a camera on it.
fn own_device() -> (Arc<GpuContext>, SlotBuffer, SceneFrame, Camera) {
    let ctx = Arc::new(GpuContext::new(None).unwrap_or_else(|e| {
        panic!("the GPU tests need a wgpu adapter (Mesa lavapipe will do): {e}")
    }));
    let scan = load("lion", 8);
    let channels = scan.scene.layout.channels().to_vec();
    let frame = SceneFrame::of(&scan.scene);
    let slots = partial(&scan, &channels, scan.treelets.len() / 2);
    let camera = cameras(&frame, 5)[0];
    (ctx, slots, frame, camera)
}

/// A lost device (destroyed here, as a driver reset or a removed GPU loses it) makes every
/// stage, in every feedback mode, return [`BackendError::DeviceLost`] — before it, wgpu's
/// default handler panicked on the first command the lost device refused, and the read-back
/// asserted its mapping.
#[test]
fn every_stage_of_a_lost_device_reports_the_loss() {
    let (ctx, slots, frame, camera) = own_device();
    let config = AnalysisConfig {
        ratio: 8,
        lod_bias: 1.0,
    };
    let light = Light::default();
    let input = PassInput {
        slots: &slots,
        frame: &frame,
        camera: &camera,
        analysis: &config,
        light: &light,
    };
    let pixels = grid_pixels(camera.width, camera.height, config.ratio, 0);
    let mut backends: Vec<GpuBackend> = [
        FeedbackMode::Wait,
        FeedbackMode::Pipelined,
        FeedbackMode::Auto,
    ]
    .into_iter()
    .map(|mode| {
        let mut b = GpuBackend::timed(ctx.clone());
        b.set_feedback_mode(mode);
        b
    })
    .collect();
    let mut out = Feedback::default();
    for b in &mut backends {
        b.analyse(&input, &pixels, 0, &mut out)
            .expect("a healthy device analyses");
        b.render(&input).expect("a healthy device renders");
    }
    ctx.device.destroy();
    let lost = |what: &str, r: Result<(), BackendError>| match r {
        Err(BackendError::DeviceLost(reason)) => {
            assert!(reason.contains("destroyed"), "{what}: reason {reason:?}");
        }
        other => panic!("{what}: expected the device's loss, got {other:?}"),
    };
    for (i, b) in backends.iter_mut().enumerate() {
        for cycle in 1..4 {
            lost(
                &format!("backend {i}, analysis of cycle {cycle}"),
                b.analyse(&input, &pixels, cycle, &mut out),
            );
        }
        let all: Vec<u32> = (0..slots.capacity()).collect();
        let per_slot =
            SlotBuffer::slot_data_bytes(slots.config().treelet_nodes, &slots.config().channels);
        lost(
            "upload",
            b.upload(&slots, &UploadPlan::new(&all, 0.0, per_slot)),
        );
        lost("render", b.render(&input).map(drop));
        lost("render in place", b.render_in_place(&input).map(drop));
        lost("load", b.load(&slots.view()));
        lost(
            "blocking analysis",
            b.analyse_blocking(&slots, &frame, &camera, &config, 9, &mut out),
        );
        lost("node read-back", b.read_back_nodes().map(drop));
        lost("finish", b.finish());
    }
    let error = backends[0].render(&input).unwrap_err();
    assert_eq!(error.to_string(), "the GPU device was lost (destroyed)");
}

/// A command the device refuses (here a write past a buffer's end, made on the backend's own
/// queue) is recorded rather than left to wgpu's default handler, which panics: the backend's
/// next call returns it as [`BackendError::Device`], and so does every call after it.
#[test]
fn a_refused_command_is_an_error_of_the_next_call() {
    let (ctx, slots, frame, camera) = own_device();
    let mut backend = GpuBackend::new(ctx.clone());
    backend.set_feedback_mode(FeedbackMode::Wait);
    let config = AnalysisConfig::default();
    let light = Light::default();
    let input = PassInput {
        slots: &slots,
        frame: &frame,
        camera: &camera,
        analysis: &config,
        light: &light,
    };
    backend.render(&input).expect("a healthy device renders");
    let small = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("four bytes"),
        size: 4,
        usage: wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    ctx.queue.write_buffer(&small, 0, &[0u8; 64]);
    for _ in 0..2 {
        match backend.render(&input) {
            Err(BackendError::Device(message)) => {
                assert!(message.contains("Validation"), "{message}");
            }
            other => panic!("expected the refused write, got {other:?}"),
        }
    }
}

/// `auto` runs on a hardware adapter and takes the CPU twins, saying why, when the only
/// adapter is a software one (lavapipe in CI), which is slower than the twins on the same
/// cores; `gpu` runs on whatever adapter there is.
#[test]
fn auto_takes_the_cpu_twins_over_a_software_adapter() {
    let ctx = gpu()
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .context()
        .clone();
    let auto = arbor_client_gpu::create_backend(arbor_client_gpu::BackendChoice::Auto)
        .expect("auto never fails");
    if ctx.is_software() {
        assert_eq!(auto.backend.name(), "cpu");
        let reason = auto.fallback.expect("auto says why it took the twins");
        assert!(
            reason.contains("software") && reason.contains(&ctx.info.name),
            "{reason}"
        );
    } else {
        assert!(auto.fallback.is_none(), "{:?}", auto.fallback);
        assert!(auto.backend.name().contains(&ctx.info.name));
    }
    let gpu_choice = arbor_client_gpu::create_backend(arbor_client_gpu::BackendChoice::Gpu)
        .expect("an adapter is there");
    assert!(gpu_choice.fallback.is_none());
    assert!(
        gpu_choice.backend.name().contains(&ctx.info.name),
        "{}",
        gpu_choice.backend.name()
    );
}
