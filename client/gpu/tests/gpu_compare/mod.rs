//! Comparing the GPU passes with their CPU twins, shared by `client/tests/gpu_twin.rs`
//! (synthetic octrees) and `tests/tests/gpu_real.rs` (real scans, which includes this file by
//! path): the shared backend, the per-camera comparison and the tolerances.
//!
//! # Tolerances (f32 on the GPU against f64 on the CPU)
//!
//! The GPU keeps box faces exact in integers relative to the camera (see
//! `shaders/traverse.wgsl`), so what differs is f32 rounding of the ray direction (computed
//! from the camera basis in f32), of the slab divisions and of `t · unit`. Two references
//! separate the two effects: **A**, the CPU twin itself (f64 rays), and **B**, the CPU
//! traversal of the GPU's f32 ray ([`gpu_ray`]).
//!
//! - Against B (same ray, f32 arithmetic only): `|Δt| ≤ T_REL·t + T_ABS·edge` and
//!   `|Δerror| ≤ E_ABS` levels; the pixel colour within `CHANNEL_SAME` of B's shading. B is the
//!   GPU's ray exactly only where the device rounds like the CPU: lavapipe does, NVIDIA fuses
//!   the ray's multiply-adds and divides approximately, which turns the ray by an ulp or two,
//!   and a grazing entry face turns that into far more `t` than the arithmetic itself gives.
//!   So a GPU answer off B's is compared with the span of `t` (and of the error) that the rays
//!   within [`DIR_ULPS`] of B ([`near_rays`]) give at the same node.
//!   - `T_REL` = 1e-6 (at least 8 ulps): Vulkan allows a division 2.5 ulps, and
//!     the face's conversion and subtraction, the ray's normalisation and `t · unit` round
//!     once each. Measured (worst `|Δt|` over the tolerance at 5e-7, stop 36): lavapipe 0.35
//!     (B alone); an H100 0.996 against the span, and up to 5.0 against B alone.
//!   - `E_ABS` = 5e-6 levels (f32 `log2` of a ~30-level quantity): measured 3.8e-6 on both.
//!   - The colour: measured 0 on lavapipe, 1 on the H100 (`CHANNEL_SAME` = 1).
//! - Against A where the node agrees: `|Δt|/t ≤ T_REL_RAY` (measured 1.9e-5) and
//!   `|Δerror| ≤ E_ABS_RAY` (measured 2.9e-5, both from the cameras 1e-9 edges off a face,
//!   looking along it). Larger than against B because the f32 direction is off by up to
//!   ~1e-7 rad, and a grazing entry face amplifies that by 1/sin(angle).
//! - Node: a ray that passes a voxel edge, corner or silhouette within ~1e-7 rad may stop at
//!   another voxel (or miss). Every such sample must be *explained*: either a tie (both voxels
//!   entered at the same `t` within the `t` tolerance) or B — or a ray within a few f32 ulps of
//!   B ([`near_rays`]: the GPU may fuse multiply-adds, so B is its ray only to an ulp) — gives
//!   the GPU's answer. Measured: at most 0.24% of hits at another node (far cameras), 0.03% of
//!   samples hit/miss, 0.10% of pixels differing from A; asserted below `NODE_SHARE`,
//!   `MISS_SHARE`, `PIXEL_SHARE`. The same node can also show another entry face (another flat
//!   normal, up to 91 levels of a channel): those pixels are counted in the pixel share and
//!   explained by B like the nodes.
//! - Beyond the f32 limit (pixel angle below ~1e-7 rad, e.g. the whole scene in a frame from
//!   10^6 edges away) rays and faces are not resolved in f32; that case is printed, not
//!   asserted.
#![allow(dead_code)]

use std::sync::{Arc, Mutex, OnceLock};

use arbor_client_core::analysis::{AnalysisConfig, Feedback, analyse};
use arbor_client_core::camera::Camera;
use arbor_client_core::incore::{IncoreView, SceneFrame};
use arbor_client_core::render::{Light, render, shade};
use arbor_client_core::traverse::{Hit, Lod, Ray, trace};
use arbor_client_gpu::{GpuBackend, GpuContext};
use glam::DVec3;

/// The one backend of a test binary, shared (tests take turns). Panics — the tests fail, they
/// do not skip — when there is no adapter.
pub fn gpu() -> &'static Mutex<GpuBackend> {
    static GPU: OnceLock<Mutex<GpuBackend>> = OnceLock::new();
    GPU.get_or_init(|| {
        let ctx = GpuContext::new(None).unwrap_or_else(|e| {
            panic!("the GPU tests need a wgpu adapter (Mesa lavapipe will do): {e}")
        });
        println!("adapter: {}", ctx.describe());
        Mutex::new(GpuBackend::new(Arc::new(ctx)))
    })
}

/// Relative tolerance of `t` against the CPU on the same ray (see the module docs: measured
/// up to 5.0e-7 on an H100, 1.7e-7 on lavapipe's Vulkan and 2.7e-7 on its GL backend).
pub const T_REL: f64 = 1e-6;
/// Absolute tolerance of `t`, in root edges (the camera fraction is rounded to 2^-24 units).
pub const T_ABS: f64 = 1e-9;
/// Tolerance of the screen error against the CPU on the same ray, in levels (measured 3.8e-6).
pub const E_ABS: f64 = 5e-6;
/// Largest |Δt| / t against the CPU twin's f64 ray where the node agrees (measured 1.9e-5).
pub const T_REL_RAY: f64 = 5e-5;
/// Largest |Δerror| against the CPU twin's f64 ray where the node agrees (measured 2.9e-5).
pub const E_ABS_RAY: f64 = 5e-5;
/// Largest share of hit samples stopping at another (tied) node.
pub const NODE_SHARE: f64 = 0.005;
/// Largest share of samples that hit on one side and miss on the other.
pub const MISS_SHARE: f64 = 0.001;
/// Largest share of pixels differing from the CPU twin's image at all.
pub const PIXEL_SHARE: f64 = 0.002;
/// Largest channel difference from the CPU shading of the GPU's ray.
pub const CHANNEL_SAME: u8 = 1;

/// The ray the GPU casts through `(px, py)`: `Camera::ray` evaluated in f32 with the shader's
/// operations (`camera_ray` in `traverse.wgsl`), widened to f64. The GPU may contract some of
/// them into fused multiply-adds, so this is the GPU's ray to within an ulp or so, not bit
/// for bit.
pub fn gpu_ray(camera: &Camera, px: f64, py: f64) -> Ray {
    let f = |v: DVec3| [v.x as f32, v.y as f32, v.z as f32];
    let (fw, rt, up) = (f(camera.forward), f(camera.right()), f(camera.up));
    let pitch = ((camera.fov_y * 0.5).tan() / f64::from(camera.height)) as f32;
    let sx = (2.0 * px as f32 - camera.width as f32) * pitch;
    let sy = (camera.height as f32 - 2.0 * py as f32) * pitch;
    let d: [f32; 3] = std::array::from_fn(|a| fw[a] + rt[a] * sx + up[a] * sy);
    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    Ray {
        origin: camera.position,
        dir: DVec3::new(
            f64::from(d[0] / len),
            f64::from(d[1] / len),
            f64::from(d[2] / len),
        ),
    }
}

/// Angle (radians, per axis) within which the GPU's ray direction is known: a few f32 ulps.
pub const DIR_ULPS: f64 = 3e-7;

/// The 26 rays whose directions differ from `ray`'s by ±[`DIR_ULPS`] or 0 per axis.
pub fn near_rays(ray: &Ray) -> impl Iterator<Item = Ray> + '_ {
    (0..27).filter(|&i| i != 13).map(move |i| {
        let o = DVec3::new(
            f64::from(i % 3) - 1.0,
            f64::from(i / 3 % 3) - 1.0,
            f64::from(i / 9) - 1.0,
        );
        Ray {
            origin: ray.origin,
            dir: (ray.dir + o * DIR_ULPS).normalize(),
        }
    })
}

/// Worst cases of one group of cameras. "A" is the CPU twin itself (f64 rays); "B" is the CPU
/// traversal of the GPU's f32 ray ([`gpu_ray`]), which separates what the f32 ray direction
/// changes (a different ray) from what f32 traversal arithmetic changes (the same ray).
#[derive(Debug, Default)]
pub struct Tally {
    samples: u64,
    hits: u64,
    /// Hits where the GPU stops at another node than A.
    node_diff: u64,
    /// Samples hitting on one side and missing on the other (against A).
    hit_miss: u64,
    /// Of those differences, the ones B does not reproduce and that are no tie either.
    unexplained: u64,
    subtreelet_diff: u64,
    /// Largest |Δt| / edge against A where the node agrees.
    dt_edge: f64,
    /// Largest |Δt| / t against A where the node agrees.
    dt_rel: f64,
    /// Largest |Δerror| against A where the node agrees.
    derr: f64,
    /// Largest |Δt| / (T_REL·t + T_ABS·edge) against B where the node agrees, or against the
    /// span of `t` that rays within [`DIR_ULPS`] of B give at that node where B alone is
    /// further off: ≤ 1 passes.
    dt_ratio_b: f64,
    /// Largest |Δerror| against B, or the span of the rays that close, where the node agrees.
    derr_b: f64,
    /// Largest |Δt| / tolerance against B alone (printed: 1.0 or less where the device rounds
    /// the ray exactly like B, as lavapipe does; NVIDIA contracts it into fused multiply-adds).
    dt_ratio_exact: f64,
    /// Largest |Δerror| against B alone (printed).
    derr_exact: f64,
    pixels: u64,
    /// Pixels differing from A's image at all.
    px_diff: u64,
    /// Largest channel difference from A where the node agrees with A.
    max_ch_same: u8,
    /// Largest channel difference from A anywhere.
    max_ch_any: u8,
    /// Largest channel difference from B's shading where the node agrees with B.
    max_ch_b: u8,
}

impl Tally {
    pub fn print(&self, name: &str) {
        let share = |n: u64, d: u64| n as f64 / d.max(1) as f64;
        println!(
            "{name}: {} samples, {} hits | vs CPU twin: other node {} ({:.5} of hits), \
             hit/miss {} ({:.5}), unexplained by the f32 ray {}, other subtreelet at same node \
             {}; same node: max |Δt|/edge {:.3e}, max |Δt|/t {:.3e}, max |Δerror| {:.3e}; \
             pixels differing {} of {} ({:.5}), max channel Δ same node {}, any {} | vs CPU on \
             the f32 ray: worst |Δt|/tolerance {:.3}, max |Δerror| {:.3e}, max channel Δ {} \
             (B alone: worst |Δt|/tolerance {:.3}, max |Δerror| {:.3e})",
            self.samples,
            self.hits,
            self.node_diff,
            share(self.node_diff, self.hits),
            self.hit_miss,
            share(self.hit_miss, self.samples),
            self.unexplained,
            self.subtreelet_diff,
            self.dt_edge,
            self.dt_rel,
            self.derr,
            self.px_diff,
            self.pixels,
            share(self.px_diff, self.pixels),
            self.max_ch_same,
            self.max_ch_any,
            self.dt_ratio_b,
            self.derr_b,
            self.max_ch_b,
            self.dt_ratio_exact,
            self.derr_exact,
        );
    }

    pub fn assert_within(&self, name: &str) {
        self.print(name);
        let share = |n: u64, d: u64| n as f64 / d.max(1) as f64;
        assert!(self.hits > 0, "{name}: nothing hit");
        assert_eq!(
            self.subtreelet_diff, 0,
            "{name}: subtreelet differs at the same node"
        );
        assert_eq!(
            self.unexplained, 0,
            "{name}: differences the f32 ray does not explain"
        );
        assert!(self.dt_ratio_b <= 1.0, "{name}: t outside tolerance");
        assert!(self.derr_b <= E_ABS, "{name}: error outside tolerance");
        assert!(
            self.dt_rel <= T_REL_RAY,
            "{name}: t of the twin outside tolerance"
        );
        assert!(
            self.derr <= E_ABS_RAY,
            "{name}: error of the twin outside tolerance"
        );
        assert!(
            share(self.node_diff, self.hits) <= NODE_SHARE,
            "{name}: too many rays stop at another node"
        );
        assert!(
            share(self.hit_miss, self.samples) <= MISS_SHARE,
            "{name}: too many hit/miss disagreements"
        );
        assert!(
            share(self.px_diff, self.pixels) <= PIXEL_SHARE,
            "{name}: too many pixels differ from the CPU image"
        );
        assert!(
            self.max_ch_b <= CHANNEL_SAME,
            "{name}: pixel colour differs from the CPU shading of the same ray"
        );
    }
}

/// The feedback sample of `ray` as `analysis::sample_pixel` makes it.
pub fn sample(view: &IncoreView<'_>, frame: &SceneFrame, ray: &Ray, lod: &Lod) -> Option<Hit> {
    trace(view, frame, ray, lod)
}

/// Compares the GPU passes with the CPU twins for one camera on the loaded buffer `view`.
pub fn compare(
    gpu: &mut GpuBackend,
    view: &IncoreView<'_>,
    frame: &SceneFrame,
    camera: &Camera,
    lod_bias: f64,
    tally: &mut Tally,
) {
    let config = AnalysisConfig { ratio: 1, lod_bias };
    let lod = Lod {
        pixel_angle: camera.pixel_angle(),
        lod_bias,
        max_depth: frame.max_depth,
    };
    let light = Light::default();
    let mut cpu = Feedback::default();
    let mut gpu_fb = Feedback::default();
    analyse(view, frame, camera, &config, 0, &mut cpu);
    gpu.analyse_loaded(frame, camera, &config, 0, &mut gpu_fb)
        .expect("GPU analysis");
    assert_eq!(cpu.pixels, gpu_fb.pixels);
    assert_eq!(
        cpu.pixels.len(),
        (camera.width * camera.height) as usize,
        "ratio 1 samples every pixel, row-major"
    );
    assert_eq!(cpu.samples.len(), gpu_fb.samples.len());
    let a_img = render(view, frame, camera, lod_bias, &light);
    let g_img = gpu
        .render_loaded(frame, camera, lod_bias, &light)
        .expect("GPU render");
    assert_eq!((a_img.width, a_img.height), (g_img.width, g_img.height));
    let w = camera.width as usize;
    for (k, (c, g)) in cpu.samples.iter().zip(&gpu_fb.samples).enumerate() {
        tally.samples += 1;
        tally.pixels += 1;
        let (px, py) = ((k % w) as f64 + 0.5, (k / w) as f64 + 0.5);
        let ray_b = gpu_ray(camera, px, py);
        let b = sample(view, frame, &ray_b, &lod);
        let pa = &a_img.rgba[k * 4..k * 4 + 4];
        let pg = &g_img.rgba[k * 4..k * 4 + 4];
        let d_a = pa
            .iter()
            .zip(pg)
            .map(|(x, y)| x.abs_diff(*y))
            .max()
            .unwrap_or(0);
        tally.px_diff += u64::from(d_a > 0);
        tally.max_ch_any = tally.max_ch_any.max(d_a);
        // Against B: the same f32 ray.
        let agrees = |h: &Option<Hit>| match h {
            None => !g.is_hit(),
            Some(h) => g.is_hit() && h.node == g.node,
        };
        let same_b = agrees(&b);
        // The GPU's direction is B's to within a few f32 ulps (fused multiply-adds): a GPU
        // answer that a ray that close gives too is explained by the f32 ray.
        let near_b = || same_b || near_rays(&ray_b).any(|r| agrees(&sample(view, frame, &r, &lod)));
        if let (Some(h), true) = (&b, same_b) {
            let (g_t, g_error) = (f64::from(g.t), f64::from(g.error));
            let tol = |t: f64| T_REL * t + T_ABS * frame.edge;
            let exact_ratio = (h.t - g_t).abs() / tol(h.t);
            let exact_error = (f64::from(h.error) - g_error).abs();
            tally.dt_ratio_exact = tally.dt_ratio_exact.max(exact_ratio);
            tally.derr_exact = tally.derr_exact.max(exact_error);
            let (mut ratio, mut derr) = (exact_ratio, exact_error);
            if ratio > 1.0 || derr > E_ABS {
                // Not B's own answer: the GPU's ray is B's to a few ulps only, and where the
                // ray grazes the entry face that moves `t` by far more than the arithmetic
                // does. Explained if it lies in the span the rays that close give at this node.
                let mut t_span = (h.t, h.t);
                let mut error_span = (f64::from(h.error), f64::from(h.error));
                for r in near_rays(&ray_b) {
                    if let Some(n) = sample(view, frame, &r, &lod).filter(|n| n.node == g.node) {
                        t_span = (t_span.0.min(n.t), t_span.1.max(n.t));
                        let e = f64::from(n.error);
                        error_span = (error_span.0.min(e), error_span.1.max(e));
                    }
                }
                let outside = |x: f64, (lo, hi): (f64, f64)| (lo - x).max(x - hi).max(0.0);
                ratio = outside(g_t, t_span) / tol(g_t.clamp(t_span.0, t_span.1));
                derr = outside(g_error, error_span);
            }
            tally.dt_ratio_b = tally.dt_ratio_b.max(ratio);
            tally.derr_b = tally.derr_b.max(derr);
        }
        // The colour: the CPU shading of B, or failing that of a ray a few ulps from it.
        let colour_diff = |h: &Option<Hit>, r: &Ray| {
            let rgba = h.as_ref().map_or([0; 4], |h| shade(h, view, r, &light));
            rgba.iter()
                .zip(pg)
                .map(|(x, y)| x.abs_diff(*y))
                .max()
                .unwrap_or(0)
        };
        let mut d_b = colour_diff(&b, &ray_b);
        if d_b > CHANNEL_SAME {
            for r in near_rays(&ray_b) {
                d_b = d_b.min(colour_diff(&sample(view, frame, &r, &lod), &r));
            }
        }
        tally.max_ch_b = tally.max_ch_b.max(d_b);
        // Against A: the CPU twin.
        if c.is_hit() != g.is_hit() {
            tally.hit_miss += 1;
            tally.unexplained += u64::from(!near_b());
            continue;
        }
        if !c.is_hit() {
            continue;
        }
        tally.hits += 1;
        let dt = (f64::from(c.t) - f64::from(g.t)).abs();
        if c.node != g.node {
            tally.node_diff += 1;
            let tie = dt <= T_REL * f64::from(c.t) + T_ABS * frame.edge;
            tally.unexplained += u64::from(!tie && !near_b());
            continue;
        }
        if c.subtreelet != g.subtreelet {
            tally.subtreelet_diff += 1;
        }
        tally.max_ch_same = tally.max_ch_same.max(d_a);
        tally.dt_edge = tally.dt_edge.max(dt / frame.edge);
        tally.dt_rel = tally.dt_rel.max(dt / f64::from(c.t).max(1e-300));
        tally.derr = tally
            .derr
            .max((f64::from(c.error) - f64::from(g.error)).abs());
    }
}
