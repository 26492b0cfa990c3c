//! The CPU reference renderer: one ray per pixel centre through [`trace`], shaded from the
//! stored attributes with a directional light (docs/design.md §5, render pass).
//!
//! It is the ground truth the GPU renderer is compared with and what headless runs score
//! against, so it is a pure function of its inputs: rows run in parallel but every pixel is
//! computed independently with the same operations, giving bit-identical images on reruns.

use arbor_proto::Channel;
use glam::DVec3;
use rayon::prelude::*;

use crate::camera::{Camera, PixelRays};
use crate::image::Image;
use crate::incore::{IncoreView, SceneFrame};
use crate::traverse::{Hit, Lod, Ray, trace};

/// Albedo of voxels without colour or density (linear).
const NEUTRAL_ALBEDO: f32 = 0.6;

/// A directional light plus an ambient term.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Light {
    /// Direction *towards* the light (normalised when used).
    pub direction: DVec3,
    /// Fraction of the albedo seen regardless of orientation, in `0..=1`.
    pub ambient: f32,
}

impl Default for Light {
    /// From above and to one side, so that the three axis faces get three distinct shades.
    fn default() -> Self {
        Light {
            direction: DVec3::new(0.36, 0.48, 0.8),
            ambient: 0.25,
        }
    }
}

fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

fn linear_to_srgb8(c: f32) -> u8 {
    let c = if c.is_nan() { 0.0 } else { c.clamp(0.0, 1.0) };
    let s = if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5).clamp(0.0, 255.0) as u8
}

/// Colour of a hit voxel, RGBA8 with alpha 255.
///
/// Albedo: the Color channel if held, else density as a grey ramp if held, else a neutral grey.
/// Normal: the Normal channel if held, else the face the ray entered through. Two-sided Lambert
/// (the normal turned towards the viewer) plus ambient, lit in linear space, stored as sRGB.
pub fn shade(hit: &Hit, view: &IncoreView<'_>, ray: &Ray, light: &Light) -> [u8; 4] {
    let mut tmp = [0f32; 3];
    let albedo = if let Some(b) = view.attribute(Channel::Color, hit.node) {
        Channel::Color.decode(b, &mut tmp);
        tmp.map(srgb_to_linear)
    } else if let Some(b) = view.attribute(Channel::Density, hit.node) {
        Channel::Density.decode(b, &mut tmp);
        [tmp[0]; 3]
    } else {
        [NEUTRAL_ALBEDO; 3]
    };
    let normal = if let Some(b) = view.attribute(Channel::Normal, hit.node) {
        Channel::Normal.decode(b, &mut tmp);
        DVec3::new(f64::from(tmp[0]), f64::from(tmp[1]), f64::from(tmp[2]))
    } else {
        let mut n = [0.0; 3];
        n[usize::from(hit.entry_axis.min(2))] = f64::from(hit.entry_sign);
        DVec3::from_array(n)
    };
    // Two-sided: turn the normal towards the viewer (scan normals may point either way), then
    // Lambert, so the side of a surface the camera sees is lit as if it faced out.
    let n = normal.normalize_or_zero();
    let n = if n.dot(ray.dir) > 0.0 { -n } else { n };
    let diffuse = n.dot(light.direction.normalize_or_zero()).max(0.0) as f32;
    let ambient = light.ambient.clamp(0.0, 1.0);
    let k = ambient + (1.0 - ambient) * diffuse;
    let [r, g, b] = albedo.map(|a| linear_to_srgb8(a * k));
    [r, g, b, 255]
}

/// Renders `camera`'s frame: one ray per pixel centre, stopping where a voxel projects to at
/// most a pixel (times `lod_bias`), at a leaf or at the frame's depth. Misses are
/// `[0, 0, 0, 0]`.
pub fn render(
    view: &IncoreView<'_>,
    frame: &SceneFrame,
    camera: &Camera,
    lod_bias: f64,
    light: &Light,
) -> Image {
    let lod = Lod {
        pixel_angle: camera.pixel_angle(),
        lod_bias,
        max_depth: frame.max_depth,
    };
    let mut img = Image::new(camera.width, camera.height);
    let row_bytes = camera.width as usize * 4;
    if row_bytes == 0 {
        return img;
    }
    let rays = camera.pixel_rays();
    img.rgba
        .par_chunks_mut(row_bytes)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, px) in row.chunks_exact_mut(4).enumerate() {
                px.copy_from_slice(&render_pixel(view, frame, &rays, &lod, light, x, y));
            }
        });
    img
}

/// One pixel of [`render`].
fn render_pixel(
    view: &IncoreView<'_>,
    frame: &SceneFrame,
    rays: &PixelRays,
    lod: &Lod,
    light: &Light,
    x: usize,
    y: usize,
) -> [u8; 4] {
    let ray = rays.ray(x as f64 + 0.5, y as f64 + 0.5);
    trace(view, frame, &ray, lod).map_or([0; 4], |hit| shade(&hit, view, &ray, light))
}

/// [`render`] again of only the pixels in `rects` (`[x0, y0, x1, y1]`, inclusive, within the
/// frame) of `image`, which holds the same view rendered before: the pixels outside stay as
/// they are. Exact when every pixel whose ray meets a changed record lies in a rectangle. An
/// image of another size is rendered whole.
pub fn render_rects(
    view: &IncoreView<'_>,
    frame: &SceneFrame,
    camera: &Camera,
    lod_bias: f64,
    light: &Light,
    image: &mut Image,
    rects: &[[u32; 4]],
) {
    let lod = Lod {
        pixel_angle: camera.pixel_angle(),
        lod_bias,
        max_depth: frame.max_depth,
    };
    if (image.width, image.height) != (camera.width, camera.height) {
        *image = render(view, frame, camera, lod_bias, light);
        return;
    }
    let row_bytes = camera.width as usize * 4;
    if row_bytes == 0 {
        return;
    }
    let rays = camera.pixel_rays();
    image
        .rgba
        .par_chunks_mut(row_bytes)
        .enumerate()
        .for_each_init(Vec::new, |spans, (y, row)| {
            // The row's spans, merged: overlapping rectangles render each pixel once.
            spans.clear();
            let last = camera.width - 1;
            spans.extend(
                rects
                    .iter()
                    .filter(|r| (r[1]..=r[3]).contains(&(y as u32)) && r[0] <= last)
                    .map(|r| (r[0], r[2].min(last))),
            );
            spans.sort_unstable();
            let mut next = 0;
            for &(x0, x1) in spans.iter() {
                for x in x0.max(next)..=x1 {
                    let (x, at) = (x as usize, x as usize * 4);
                    row[at..at + 4]
                        .copy_from_slice(&render_pixel(view, frame, &rays, &lod, light, x, y));
                }
                next = next.max(x1 + 1);
            }
        });
}
