//! GPU timings of the client's passes on a real scan, on whatever adapter wgpu finds
//! (lavapipe on a machine without a GPU): the analysis pass (feedback of a 1024² frame at
//! ratio 8, and every pixel at ratio 1), the render pass at 1024² (in place, and with the
//! read-back to an image), and the slot upload (the whole buffer, and a 0.6-fill plan of a
//! tenth of the slots). GPU time from timestamp queries when the device has them, and always
//! the wall time of submit + wait; rays per second from the GPU time where there is one. The
//! CPU twins are timed beside them for scale.
//!
//! `cargo bench -p arbor-tests --bench gpu` (release). Prints a table; no assertion on time.

use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_client_core::analysis::{AnalysisConfig, Feedback, analyse};
use arbor_client_core::backend::{Backend, PassInput};
use arbor_client_core::camera::CameraPath;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::render::{Light, render};
use arbor_client_core::slots::SlotBuffer;
use arbor_client_core::upload::{DEFAULT_FILL_RATIO, UploadPlan};
use arbor_client_gpu::{GpuBackend, GpuContext};
use arbor_server::octree::BuildOptions;
use arbor_tests::support::{build_file, decoded_treelets};

const FRAME: u32 = 1024;
const REPS: u32 = 5;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// Runs `f` once to warm up, then `REPS` times: median wall ms and median GPU ms (if timed).
fn measure(mut f: impl FnMut() -> Option<f64>) -> (f64, Option<f64>) {
    f();
    let mut wall = Vec::new();
    let mut gpu = Vec::new();
    for _ in 0..REPS {
        let t = Instant::now();
        let g = f();
        wall.push(ms(t.elapsed()));
        gpu.extend(g);
    }
    (median(wall), (!gpu.is_empty()).then(|| median(gpu)))
}

fn row(what: &str, rays: u64, (wall, gpu): (f64, Option<f64>)) {
    let best = gpu.unwrap_or(wall);
    let gpu_col = gpu.map_or("—".to_string(), |g| format!("{g:.2}"));
    let rate = if rays > 0 {
        format!("{:.1} M rays/s", rays as f64 / best * 1e-3)
    } else {
        String::new()
    };
    println!("{what:<44} {wall:>10.2} {gpu_col:>10} {rate}");
}

fn main() {
    let ctx = Arc::new(GpuContext::new(None).expect("the GPU benchmark needs a wgpu adapter"));
    let built = build_file(
        "points/lion_takanawa.copc.laz",
        "lion",
        &BuildOptions {
            treelet_bytes: 4096,
            ..BuildOptions::default()
        },
    );
    let d = built.scene.description.clone();
    let channels = d.layout.channels().to_vec();
    let slots = SlotBuffer::fully_resident(&d, &channels, decoded_treelets(&built.scene))
        .expect("the whole scene fits");
    let frame = SceneFrame::of(&d);
    let camera = CameraPath::Static.camera(0, &frame, 7, FRAME, FRAME);
    let light = Light::default();
    let mut gpu = GpuBackend::new(ctx.clone());
    let timed = gpu.enable_pass_timing();
    println!(
        "adapter {}; lion, 4 KiB treelets ({} treelets, depth {}, {:.1} MiB uploaded), frame \
         {FRAME}², median of {REPS}; timestamp queries: {}",
        ctx.describe(),
        d.treelet_count,
        d.max_depth,
        (u64::from(slots.capacity()) * SlotBuffer::slot_data_bytes(d.treelet_nodes, &channels))
            as f64
            / (1 << 20) as f64,
        if timed { "yes" } else { "no (wall time only)" }
    );
    println!("{:<44} {:>10} {:>10}", "stage", "wall ms", "GPU ms");

    let per_slot = SlotBuffer::slot_data_bytes(d.treelet_nodes, &channels);
    let all = UploadPlan::new(&(0..slots.capacity()).collect::<Vec<_>>(), 1.0, per_slot);
    row(
        &format!("upload, whole buffer ({} slots)", slots.capacity()),
        0,
        measure(|| {
            gpu.upload(&slots, &all).expect("GPU upload");
            gpu.finish().expect("GPU idle");
            None
        }),
    );
    let tenth: Vec<u32> = (0..slots.capacity()).filter(|s| s % 10 == 3).collect();
    let plan = UploadPlan::new(&tenth, DEFAULT_FILL_RATIO, per_slot);
    row(
        &format!(
            "upload, {} dirty slots at fill 0.6 ({} ranges)",
            tenth.len(),
            plan.ranges.len()
        ),
        0,
        measure(|| {
            gpu.upload(&slots, &plan).expect("GPU upload");
            gpu.finish().expect("GPU idle");
            None
        }),
    );

    for ratio in [8, 1] {
        let config = AnalysisConfig {
            ratio,
            lod_bias: 1.0,
        };
        let mut fb = Feedback::default();
        let rays = u64::from(FRAME.div_ceil(ratio)).pow(2);
        row(
            &format!("analysis, ratio {ratio} ({rays} rays), with read-back"),
            rays,
            measure(|| {
                gpu.analyse_blocking(&slots, &frame, &camera, &config, 0, &mut fb)
                    .expect("GPU analysis");
                gpu.pass_times()
                    .expect("GPU timestamps")
                    .map(|t| t.analysis_ms)
            }),
        );
        row(
            &format!("  CPU twin, ratio {ratio}"),
            rays,
            measure(|| {
                analyse(&slots.view(), &frame, &camera, &config, 0, &mut fb);
                None
            }),
        );
    }
    let rays = u64::from(FRAME) * u64::from(FRAME);
    let analysis = AnalysisConfig::default();
    let input = PassInput {
        slots: &slots,
        frame: &frame,
        camera: &camera,
        analysis: &analysis,
        light: &light,
    };
    row(
        "render in place",
        rays,
        measure(|| {
            gpu.render_in_place(&input).expect("GPU render");
            gpu.finish().expect("GPU idle");
            gpu.pass_times()
                .expect("GPU timestamps")
                .map(|t| t.render_ms)
        }),
    );
    row(
        "render with read-back to an image",
        rays,
        measure(|| {
            gpu.render(&input).expect("GPU render");
            gpu.pass_times()
                .expect("GPU timestamps")
                .map(|t| t.render_ms)
        }),
    );
    row(
        "  CPU twin render",
        rays,
        measure(|| {
            render(&slots.view(), &frame, &camera, 1.0, &light);
            None
        }),
    );
    println!("upload stats: {:?}", gpu.stats);
}
