//! The analysis (feedback) pass, CPU twin of `shaders/analysis.wgsl` (docs/design.md §5): which
//! voxel each sampled ray stops at, how much coarser than a pixel it is, and which treelet would
//! refine it.
//!
//! The pass samples a *list of pixels* ([`analyse_pixels`]); which pixels, and how many per
//! cycle, is the sampler's business ([`crate::coverage`]). The classic plan is the thesis's
//! feedback grid ([`grid_pixels`]): `1/n` of the frame per axis, each element one pixel of its
//! `n × n` block, the sub-pixel moving every cycle in a fixed scrambled order so that `n²`
//! consecutive cycles sample every pixel exactly once. The ray of a sample is *the same ray* the
//! render pass casts for that pixel (its centre), which is what makes convergence exact.
//!
//! The GPU pass writes the same [`FeedbackSample`] records; the struct is `#[repr(C)]` and `Pod`
//! so the two can be compared word for word.

use arbor_proto::Node;
use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;

use crate::camera::{Camera, PixelRays};
use crate::incore::{IncoreView, SceneFrame};
use crate::traverse::{Lod, trace};

/// Default feedback ratio `n` (1/8 per axis worked in the thesis).
pub const DEFAULT_FEEDBACK_RATIO: u32 = 8;
/// Largest accepted feedback ratio.
pub const MAX_FEEDBACK_RATIO: u32 = 64;

/// One feedback element.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct FeedbackSample {
    /// Global incore index of the node the ray stopped at; [`FeedbackSample::NO_NODE`] for a
    /// miss.
    pub node: u32,
    /// Treelet id that refines the hit leaf, or [`Node::NONE`] (inner node hit, final leaf,
    /// miss).
    pub subtreelet: u32,
    /// Screen-space error of the hit voxel in octree levels (log domain, finite): > 0 means
    /// the voxel is coarser than a pixel.
    pub error: f32,
    /// Distance along the ray to the hit (0 when the camera is inside the voxel).
    pub t: f32,
}

impl FeedbackSample {
    /// `node` of a sample whose ray hit nothing.
    pub const NO_NODE: u32 = u32::MAX;
    /// A ray that hit nothing.
    pub const MISS: FeedbackSample = FeedbackSample {
        node: Self::NO_NODE,
        subtreelet: Node::NONE,
        error: 0.0,
        t: 0.0,
    };

    /// The ray hit a voxel.
    pub fn is_hit(&self) -> bool {
        self.node != Self::NO_NODE
    }

    /// A refinable leaf coarser than a pixel: loading its subtreelet would change the picture.
    pub fn wants_refinement(&self) -> bool {
        self.is_hit() && self.subtreelet != Node::NONE && self.error > 0.0
    }

    /// The error streaming can still remove at this sample (0 when nothing to load).
    pub fn refinable_error(&self) -> f32 {
        if self.wants_refinement() {
            self.error
        } else {
            0.0
        }
    }
}

/// Analysis parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AnalysisConfig {
    /// `n`: the feedback buffer is `ceil(width/n) × ceil(height/n)`.
    pub ratio: u32,
    /// Scales the pixel footprint of the LOD test (1 = stop at one pixel).
    pub lod_bias: f64,
}

impl Default for AnalysisConfig {
    fn default() -> Self {
        Self {
            ratio: DEFAULT_FEEDBACK_RATIO,
            lod_bias: 1.0,
        }
    }
}

/// Feedback of one analysis pass.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Feedback {
    /// The cycle whose pass this is (a pipelined backend hands it back a cycle later).
    pub cycle: u64,
    /// The pixels sampled, packed ([`pack_pixel`]).
    pub pixels: Vec<u32>,
    /// One sample per pixel, in the same order.
    pub samples: Vec<FeedbackSample>,
}

/// A pixel `(x, y)` in one word: `x | y << 16` (frames are at most 16384 pixels a side).
pub const fn pack_pixel(x: u32, y: u32) -> u32 {
    x | (y << 16)
}

/// The `(x, y)` of a packed pixel.
pub const fn unpack_pixel(p: u32) -> (u32, u32) {
    (p & 0xFFFF, p >> 16)
}

/// The pixels of the feedback grid at `ratio` in `cycle`, row-major: element `(fx, fy)` samples
/// pixel `(fx·n + ox, fy·n + oy)` with `(ox, oy) = jitter(cycle, n)`, leaving out pixels past the
/// frame's edge.
pub fn grid_pixels(width: u32, height: u32, ratio: u32, cycle: u64) -> Vec<u32> {
    let ratio = ratio.clamp(1, MAX_FEEDBACK_RATIO);
    let (fw, fh) = feedback_size(width, height, ratio);
    let (ox, oy) = jitter(cycle, ratio);
    let mut out = Vec::with_capacity((fw * fh) as usize);
    for fy in 0..fh {
        let py = fy * ratio + oy;
        if py >= height {
            continue;
        }
        for fx in 0..fw {
            let px = fx * ratio + ox;
            if px < width {
                out.push(pack_pixel(px, py));
            }
        }
    }
    out
}

/// Size of the feedback buffer for a frame.
pub fn feedback_size(width: u32, height: u32, ratio: u32) -> (u32, u32) {
    (width.div_ceil(ratio), height.div_ceil(ratio))
}

/// The sub-pixel sampled in `cycle`: a scrambled walk over all `n²` sub-pixels that visits
/// each exactly once per `n²` cycles (a step coprime with `n²` permutes the residues), so
/// consecutive cycles sample far-apart sub-pixels and a moving camera still sees the whole
/// block soon.
pub fn jitter(cycle: u64, ratio: u32) -> (u32, u32) {
    let cells = u64::from(ratio) * u64::from(ratio);
    let step = scramble_step(cells);
    let k = (cycle % cells) * step % cells;
    ((k % u64::from(ratio)) as u32, (k / u64::from(ratio)) as u32)
}

/// The odd step nearest `cells / φ` that is coprime with `cells`.
fn scramble_step(cells: u64) -> u64 {
    if cells <= 2 {
        return 1;
    }
    let mut s = ((cells as f64) * 0.618_033_988_75) as u64 | 1;
    while gcd(s, cells) != 1 {
        s += 2;
    }
    s % cells
}

fn gcd(mut a: u64, mut b: u64) -> u64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// Runs the analysis pass of `cycle` over the feedback grid of `config` (see [`grid_pixels`]).
pub fn analyse(
    view: &IncoreView<'_>,
    frame: &SceneFrame,
    camera: &Camera,
    config: &AnalysisConfig,
    cycle: u64,
    out: &mut Feedback,
) {
    let pixels = grid_pixels(camera.width, camera.height, config.ratio, cycle);
    analyse_pixels(view, frame, camera, config.lod_bias, &pixels, cycle, out);
}

/// Runs the analysis pass of `cycle` over `pixels` into `out` (reusing its allocations). Pixels
/// outside the frame give [`FeedbackSample::MISS`].
pub fn analyse_pixels(
    view: &IncoreView<'_>,
    frame: &SceneFrame,
    camera: &Camera,
    lod_bias: f64,
    pixels: &[u32],
    cycle: u64,
    out: &mut Feedback,
) {
    let lod = Lod {
        pixel_angle: camera.pixel_angle(),
        lod_bias,
        max_depth: frame.max_depth,
    };
    out.cycle = cycle;
    out.pixels.clear();
    out.pixels.extend_from_slice(pixels);
    out.samples.clear();
    out.samples.resize(pixels.len(), FeedbackSample::MISS);
    let rays = camera.pixel_rays();
    out.samples
        .par_chunks_mut(256)
        .zip(pixels.par_chunks(256))
        .for_each(|(samples, pixels)| {
            for (sample, &p) in samples.iter_mut().zip(pixels) {
                let (px, py) = unpack_pixel(p);
                if px < camera.width && py < camera.height {
                    *sample = sample_pixel(view, frame, &rays, &lod, px, py);
                }
            }
        });
}

/// The feedback sample of full-resolution pixel `(px, py)`: the render pass's ray for that
/// pixel ([`Camera::pixel_rays`]), traced with the same LOD rule.
pub fn sample_pixel(
    view: &IncoreView<'_>,
    frame: &SceneFrame,
    rays: &PixelRays,
    lod: &Lod,
    px: u32,
    py: u32,
) -> FeedbackSample {
    let ray = rays.ray(f64::from(px) + 0.5, f64::from(py) + 0.5);
    match trace(view, frame, &ray, lod) {
        None => FeedbackSample::MISS,
        Some(hit) => FeedbackSample {
            node: hit.node,
            subtreelet: if hit.leaf {
                hit.subtreelet.0
            } else {
                Node::NONE
            },
            error: hit.error,
            t: hit.t as f32,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jitter_covers_every_subpixel_once_per_round() {
        for n in [1u32, 2, 3, 4, 5, 8, 16] {
            for round in 0..3u64 {
                let mut seen = vec![false; (n * n) as usize];
                for c in 0..u64::from(n * n) {
                    let (x, y) = jitter(round * u64::from(n * n) + c, n);
                    assert!(x < n && y < n);
                    assert!(!seen[(y * n + x) as usize], "n={n}: ({x},{y}) twice");
                    seen[(y * n + x) as usize] = true;
                }
            }
        }
    }

    #[test]
    fn consecutive_jitters_move_apart() {
        let (a, b) = (jitter(0, 8), jitter(1, 8));
        let d = (a.0 as i32 - b.0 as i32).abs() + (a.1 as i32 - b.1 as i32).abs();
        assert!(d >= 2, "{a:?} then {b:?}");
    }

    #[test]
    fn grid_pixels_cover_every_pixel_once_per_round() {
        for (w, h, n) in [(13u32, 7u32, 4u32), (16, 16, 8), (5, 3, 1)] {
            let mut seen = vec![0u32; (w * h) as usize];
            for c in 0..u64::from(n * n) {
                for p in grid_pixels(w, h, n, c) {
                    let (x, y) = unpack_pixel(p);
                    assert!(x < w && y < h);
                    seen[(y * w + x) as usize] += 1;
                }
            }
            assert!(seen.iter().all(|&k| k == 1), "{w}x{h} n={n}: {seen:?}");
        }
        assert_eq!(unpack_pixel(pack_pixel(16383, 12000)), (16383, 12000));
    }

    #[test]
    fn feedback_size_rounds_up() {
        assert_eq!(feedback_size(1024, 768, 8), (128, 96));
        assert_eq!(feedback_size(100, 7, 8), (13, 1));
    }

    #[test]
    fn sample_predicates() {
        let s = FeedbackSample {
            node: 3,
            subtreelet: 9,
            error: 1.5,
            t: 2.0,
        };
        assert!(s.wants_refinement());
        assert_eq!(s.refinable_error(), 1.5);
        let lod_stop = FeedbackSample {
            subtreelet: Node::NONE,
            ..s
        };
        assert!(!lod_stop.wants_refinement());
        assert_eq!(lod_stop.refinable_error(), 0.0);
        assert!(!FeedbackSample::MISS.is_hit());
        assert_eq!(std::mem::size_of::<FeedbackSample>(), 16);
    }
}
