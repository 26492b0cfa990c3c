//! The Rust twins of every struct the WGSL passes share with the host, `#[repr(C)]` and `Pod`
//! so they are uploaded and read back as bytes, and the construction of the per-pass uniform.
//!
//! | WGSL (`shaders/`) | Rust |
//! |---|---|
//! | `Node` | [`arbor_proto::Node`] (`first_child`, then the masks in one word) |
//! | `FeedbackSample` | [`arbor_client_core::analysis::FeedbackSample`] |
//! | `FrameUniform` | [`FrameUniform`] |
//!
//! A test (`client/tests/gpu_twin.rs`) reads each struct's member offsets and size from naga's
//! layout of the WGSL and compares them with `offset_of!`/`size_of` here.
//!
//! [`FrameUniform::new`] does on the CPU in f64 everything the shader must not do in f32: the
//! camera position relative to the root's minimum corner in units of `edge / 2^31`, split into
//! an exact 64-bit integer and a fraction (see the header of `shaders/traverse.wgsl` for why
//! this keeps every depth precise), and the logarithm of the LOD footprint.

use arbor_proto::Channel;
use bytemuck::{Pod, Zeroable};

pub use arbor_client_core::analysis::FeedbackSample;
pub use arbor_proto::Node;

use arbor_client_core::camera::Camera;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::render::Light;
use arbor_client_core::traverse::{Lod, safe_log2};

/// `log2` of the unit: one unit is `edge / 2^UNIT_BITS`, the edge of a depth-31 voxel.
pub const UNIT_BITS: i32 = 31;
/// The camera may be at most this many units from the root's corner (2^30 root edges);
/// beyond, [`FrameUniform::new`] marks the frame invalid and every ray misses.
pub const MAX_CAMERA_UNITS: f64 = 2_305_843_009_213_693_952.0; // 2^61

/// `flags[0]` bit: the frame and camera are usable (CPU twin: `Setup::new` succeeds).
pub const FLAG_VALID: u32 = 1;
/// `flags[0]` bit: the projection stop is on (`pixel_angle > 0`).
pub const FLAG_PROJECT: u32 = 2;
/// `flags[0]` bit: the colour array is bound.
pub const FLAG_COLOR: u32 = 4;
/// `flags[0]` bit: the normal array is bound.
pub const FLAG_NORMAL: u32 = 8;
/// `flags[0]` bit: the density array is bound.
pub const FLAG_DENSITY: u32 = 16;

/// The uniform of both passes (WGSL `FrameUniform`, binding 0). All members are 16-byte
/// vectors so the WGSL uniform layout has no padding surprises.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct FrameUniform {
    /// Camera position in units from the root's minimum corner, integer part: high words
    /// (signed) of the 64-bit two's complement, per axis (`w` unused).
    pub cam_hi: [i32; 4],
    /// Low words of the same integers.
    pub cam_lo: [u32; 4],
    /// The fractional part, in `[0, 1]` units.
    pub cam_frac: [f32; 4],
    /// Camera forward (unit).
    pub forward: [f32; 4],
    /// Camera right (`forward × up`).
    pub right: [f32; 4],
    /// Camera up.
    pub up: [f32; 4],
    /// Direction towards the light, normalised (zero if none); `w`: ambient in `0..=1`.
    pub light: [f32; 4],
    /// `tan(fov_y/2)/height` (half a pixel's pitch at unit distance); unused; width, height.
    /// `Camera::ray`'s screen offsets are `(2·px − width)·x` and `(height − 2·py)·x`
    /// (`aspect/width = 1/height`). The brackets are exact in f32, so the centre row and column
    /// get exactly 0 on every device, with one rounding after them; the division the shader
    /// did before is allowed 2.5 ulps and rounds differently per vendor, which tilted the
    /// axis-parallel rays off their planes on NVIDIA.
    pub screen: [f32; 4],
    /// `pixel_angle · lod_bias`; `log2(pixel_angle) + log2(lod_bias)` (guarded like
    /// `trace::screen_error`); the unit `edge / 2^31` in world lengths; unused.
    pub lod: [f32; 4],
    /// Frame width, height; analysis: pixel-list length, invocations per dispatch row.
    pub image: [u32; 4],
    /// Unused (three words); deepest level (`min(max_depth, 31)`).
    pub sampling: [u32; 4],
    /// `FLAG_*` bits; unused.
    pub flags: [u32; 4],
}

fn v4(v: glam::DVec3, w: f32) -> [f32; 4] {
    [v.x as f32, v.y as f32, v.z as f32, w]
}

impl FrameUniform {
    /// The uniform for casting `camera`'s pixel rays into `frame` with `lod`, shading with
    /// `light`, with the attribute arrays of `channels` bound. The analysis pass's sample count
    /// and stride are zero; set them with [`FrameUniform::with_samples`].
    pub fn new(
        frame: &SceneFrame,
        camera: &Camera,
        lod: &Lod,
        light: &Light,
        channels: &[Channel],
    ) -> Self {
        let mut u = FrameUniform::zeroed();
        let origin = glam::DVec3::from_array(frame.origin);
        let scale = f64::from(UNIT_BITS).exp2();
        let p = (camera.position - origin) / frame.edge * scale;
        let mut valid = frame.edge > 0.0
            && frame.edge.is_finite()
            && camera.position.is_finite()
            && camera.forward.is_finite()
            && camera.forward != glam::DVec3::ZERO
            && (origin - camera.position).is_finite()
            && p.is_finite();
        for a in 0..3 {
            let pa = p[a];
            if !(pa.abs() < MAX_CAMERA_UNITS) {
                valid = false;
                continue;
            }
            let whole = pa.floor();
            let int = whole as i64;
            u.cam_hi[a] = (int >> 32) as i32;
            u.cam_lo[a] = int as u32;
            u.cam_frac[a] = (pa - whole) as f32;
        }
        let h = (camera.fov_y * 0.5).tan();
        u.forward = v4(camera.forward, 0.0);
        u.right = v4(camera.right(), 0.0);
        u.up = v4(camera.up, 0.0);
        u.light = v4(
            light.direction.normalize_or_zero(),
            light.ambient.clamp(0.0, 1.0),
        );
        u.screen = [
            (h / f64::from(camera.height)) as f32,
            0.0,
            camera.width as f32,
            camera.height as f32,
        ];
        u.lod = [
            (lod.pixel_angle * lod.lod_bias) as f32,
            (safe_log2(lod.pixel_angle) + safe_log2(lod.lod_bias)) as f32,
            (frame.edge / scale) as f32,
            0.0,
        ];
        u.image = [camera.width, camera.height, 0, 0];
        u.sampling = [
            0,
            0,
            0,
            u32::from(lod.max_depth.min(arbor_proto::limits::MAX_DEPTH)),
        ];
        let mut flags = 0;
        if valid {
            flags |= FLAG_VALID;
        }
        if lod.pixel_angle > 0.0 {
            flags |= FLAG_PROJECT;
        }
        for c in channels {
            flags |= match c {
                Channel::Color => FLAG_COLOR,
                Channel::Normal => FLAG_NORMAL,
                Channel::Density => FLAG_DENSITY,
            };
        }
        u.flags = [flags, 0, 0, 0];
        u
    }

    /// The uniform of an analysis pass over a list of `count` pixels, run in rows of `stride`
    /// invocations.
    pub fn with_samples(mut self, count: u32, stride: u32) -> Self {
        self.image[2] = count;
        self.image[3] = stride;
        self
    }
}
