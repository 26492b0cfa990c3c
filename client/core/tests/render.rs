//! The CPU reference renderer on synthetic scenes: reruns are bit-identical, misses are
//! transparent, and the colour channel reaches the pixels.

mod synth;

use arbor_client_core::camera::{Camera, CameraPath};
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::render::{Light, render, shade};
use arbor_client_core::traverse::{Lod, trace};
use arbor_proto::Cell;
use glam::DVec3;
use synth::{Reference, Rng, random_cells, single};

fn scene() -> (synth::Buffer, SceneFrame) {
    let mut rng = Rng::new(7);
    let r = Reference::new(random_cells(&mut rng, 4, 400));
    let leaves: Vec<Cell> = r.leaves.iter().copied().collect();
    let mut b = single(&leaves, 2048, 4);
    // Red in the x < half of the cube, blue in the other: decides the colour by position.
    b.paint(|c| {
        if (u64::from(c.x) << (8 - c.depth)) < 128 && c.depth > 0 {
            [255, 0, 0]
        } else {
            [0, 0, 255]
        }
    });
    let frame = SceneFrame {
        origin: [-1.0, 2.0, 0.5],
        edge: 2.0,
        max_depth: 4,
    };
    (b, frame)
}

#[test]
fn rerender_is_bit_identical_and_misses_are_transparent() {
    let (b, frame) = scene();
    let cam = CameraPath::Static.camera(0, &frame, 3, 96, 64);
    let light = Light::default();
    let a = render(&b.view(), &frame, &cam, 1.0, &light);
    let again = render(&b.view(), &frame, &cam, 1.0, &light);
    assert_eq!(a, again);
    assert_eq!(a.differing_share(&again), 0.0);
    let covered = a.coverage();
    assert!(covered > 500 && covered < 96 * 64, "{covered}");
    let lod = Lod {
        pixel_angle: cam.pixel_angle(),
        lod_bias: 1.0,
        max_depth: frame.max_depth,
    };
    let mut misses = 0;
    for y in 0..64 {
        for x in 0..96 {
            let ray = cam.ray(f64::from(x) + 0.5, f64::from(y) + 0.5);
            let px = a.get(x, y).unwrap();
            match trace(&b.view(), &frame, &ray, &lod) {
                None => {
                    assert_eq!(px, [0, 0, 0, 0]);
                    misses += 1;
                }
                Some(h) => {
                    assert_eq!(px, shade(&h, &b.view(), &ray, &light));
                    assert_eq!(px[3], 255);
                }
            }
        }
    }
    assert!(misses > 100, "{misses}");
    // The 1.6-edge camera sees the whole cube with room to spare: corners miss.
    assert_eq!(a.get(0, 0), Some([0, 0, 0, 0]));
}

#[test]
fn shading_uses_the_colour_channel() {
    let (b, frame) = scene();
    // Each covered pixel takes the colour of the voxel its ray stops at.
    let c = DVec3::from_array(frame.centre());
    let mut counts = [0usize; 2];
    for eye in [c - DVec3::X * 5.0, c + DVec3::new(1.0, 2.0, 3.0)] {
        let cam = Camera::look_at(eye, c, DVec3::Z, 0.8, 48, 48).unwrap();
        let img = render(&b.view(), &frame, &cam, 1.0, &Light::default());
        let lod = Lod {
            pixel_angle: cam.pixel_angle(),
            lod_bias: 1.0,
            max_depth: frame.max_depth,
        };
        for y in 0..48 {
            for x in 0..48 {
                let ray = cam.ray(f64::from(x) + 0.5, f64::from(y) + 0.5);
                let p = img.get(x, y).unwrap();
                let Some(h) = trace(&b.view(), &frame, &ray, &lod) else {
                    continue;
                };
                let stored = &b.color.as_ref().unwrap()[h.node as usize * 3..][..3];
                assert_eq!(p[1], 0, "{p:?}");
                if stored[0] == 255 {
                    assert!(p[0] > 0 && p[2] == 0, "{p:?} for red {h:?}");
                    counts[0] += 1;
                } else {
                    assert!(p[2] > 0 && p[0] == 0, "{p:?} for blue {h:?}");
                    counts[1] += 1;
                }
            }
        }
    }
    assert!(counts[0] > 100 && counts[1] > 100, "{counts:?}");
    // Without colour: neutral grey.
    let mut grey = b.clone();
    grey.color = None;
    let cam = CameraPath::Static.camera(0, &frame, 3, 48, 48);
    let img = render(&grey.view(), &frame, &cam, 1.0, &Light::default());
    assert!(img.coverage() > 100);
    for p in img.rgba.chunks_exact(4).filter(|p| p[3] > 0) {
        assert!(p[0] == p[1] && p[1] == p[2] && p[0] > 0, "{p:?}");
    }
}

#[test]
fn faces_get_distinct_shades_without_normals() {
    let (mut b, frame) = scene();
    b.color = None;
    let cam = CameraPath::Static.camera(0, &frame, 11, 64, 64);
    let img = render(&b.view(), &frame, &cam, 1.0, &Light::default());
    let mut shades: Vec<u8> = img
        .rgba
        .chunks_exact(4)
        .filter(|p| p[3] > 0)
        .map(|p| p[0])
        .collect();
    shades.sort_unstable();
    shades.dedup();
    assert!(shades.len() >= 2, "{shades:?}");
}
