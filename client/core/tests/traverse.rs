//! The CPU traversal against brute force on synthetic octrees with exactly known answers: for
//! every ray, hit/miss agree, the traced `t` is the smallest entry distance over all terminal
//! voxels, and the traced cell is one of the voxels tied there.

mod synth;

use std::collections::BTreeMap;
use std::sync::Mutex;

use arbor_client_core::incore::SceneFrame;
use arbor_client_core::traverse::{Lod, MAX_SCREEN_ERROR, Ray, screen_error, trace, trace_past};
use arbor_proto::{Cell, Node, TreeletId};
use glam::DVec3;
use synth::{Buffer, Reference, Rng, random_cells, single, single_refinable};

/// Largest |t_trace − t_brute| / edge seen by any test (printed with `--nocapture`).
static WORST: Mutex<f64> = Mutex::new(0.0);

const NO_LOD: f64 = 0.0;

fn lod(pixel_angle: f64, max_depth: u8) -> Lod {
    Lod {
        pixel_angle,
        lod_bias: 1.0,
        max_depth,
    }
}

/// Checks one ray; returns whether it hit.
fn check(b: &Buffer, r: &Reference, frame: &SceneFrame, ray: &Ray, lod: &Lod) -> bool {
    let view = b.view();
    let got = trace(&view, frame, ray, lod);
    let want = r.query(frame, ray, lod);
    match (&got, &want) {
        (None, None) => false,
        (Some(h), Some((t, cells))) => {
            let diff = (h.t - t).abs() / frame.edge;
            {
                let mut w = WORST.lock().unwrap();
                if diff > *w {
                    *w = diff;
                    eprintln!("worst t difference so far: {diff:e} edges");
                }
            }
            assert!(
                diff <= 1e-12,
                "t {} vs brute force {t} for {ray:?} {lod:?}",
                h.t
            );
            assert!(
                cells.contains(&h.cell),
                "hit {:?} at {} not among the voxels tied at {t}: {cells:?} ({ray:?})",
                h.cell,
                h.t
            );
            // The hit names the record of that voxel and its leafness.
            let node = view.nodes[h.node as usize];
            assert_eq!(h.leaf, r.leaves.contains(&h.cell), "{h:?}");
            if h.leaf {
                assert!(node.is_leaf());
                assert_eq!(h.subtreelet, TreeletId(node.first_child));
            } else {
                assert_eq!(h.subtreelet, TreeletId::NONE);
            }
            let size = frame.edge / 2f64.powi(i32::from(h.cell.depth));
            assert_eq!(
                h.error,
                screen_error(size, h.t, lod.pixel_angle, lod.lod_bias)
            );
            assert!(h.error.is_finite() && h.entry_axis < 3 && h.entry_sign.abs() == 1);
            true
        }
        _ => panic!("hit/miss disagree for {ray:?}: trace {got:?}, brute force {want:?}"),
    }
}

fn ray_to(origin: DVec3, target: DVec3) -> Ray {
    Ray {
        origin,
        dir: (target - origin).normalize(),
    }
}

fn leaf_cells(r: &Reference) -> Vec<Cell> {
    r.leaves.iter().copied().collect()
}

/// Random leaves at depth 4 plus a few coarser leaves, offset frame.
fn mixed_scene(seed: u64) -> (Buffer, Reference, SceneFrame) {
    let mut rng = Rng::new(seed);
    let mut leaves = random_cells(&mut rng, 4, 120);
    // Coarser leaves in octants no depth-4 leaf touches.
    for c in random_cells(&mut rng, 2, 12) {
        if !leaves.iter().any(|l| c.contains(l) || l.contains(&c)) {
            leaves.push(c);
        }
    }
    let frame = SceneFrame {
        origin: [-3.5, 2.25, 7.0],
        edge: 16.0,
        max_depth: 4,
    };
    let r = Reference::new(leaves);
    (single(&leaf_cells(&r), 2048, 4), r, frame)
}

#[test]
fn random_rays_match_brute_force() {
    let (b, r, frame) = mixed_scene(1);
    let mut rng = Rng::new(2);
    let mut hits = 0;
    for i in 0..4000 {
        let ray = if i % 2 == 0 {
            ray_to(rng.point_in(&frame, 1.5), rng.point_in(&frame, 0.0))
        } else {
            Ray {
                origin: rng.point_in(&frame, 2.0),
                dir: rng.unit(),
            }
        };
        hits += usize::from(check(&b, &r, &frame, &ray, &lod(NO_LOD, 4)));
    }
    assert!(hits > 1000, "only {hits} hits: the test would be vacuous");
}

#[test]
fn random_rays_with_lod_stops_match_brute_force() {
    let (b, r, frame) = mixed_scene(3);
    let mut rng = Rng::new(4);
    let mut depths = [0usize; 5];
    for _ in 0..3000 {
        let ray = ray_to(rng.point_in(&frame, 3.0), rng.point_in(&frame, 0.0));
        let l = Lod {
            pixel_angle: rng.range(0.0, 0.3),
            lod_bias: rng.range(0.5, 2.0),
            max_depth: rng.below(5) as u8,
        };
        if check(&b, &r, &frame, &ray, &l) {
            let h = trace(&b.view(), &frame, &ray, &l).unwrap();
            depths[usize::from(h.cell.depth)] += 1;
        }
    }
    // Every stop depth occurs, intermediate ones included.
    assert!(depths.iter().all(|&n| n > 20), "{depths:?}");
}

/// Looking past earlier hits: each further stop is brute force's nearest stop with the voxels
/// passed taken as empty, with and without LOD stops, until the ray leaves the data.
#[test]
fn looking_past_hits_matches_brute_force() {
    let (b, r, frame) = mixed_scene(11);
    let view = b.view();
    let mut rng = Rng::new(12);
    let mut behind = 0;
    for i in 0..1500 {
        let ray = ray_to(rng.point_in(&frame, 2.0), rng.point_in(&frame, 0.0));
        let l = if i % 2 == 0 {
            lod(NO_LOD, 4)
        } else {
            Lod {
                pixel_angle: rng.range(0.0, 0.2),
                lod_bias: 1.0,
                max_depth: 4,
            }
        };
        let (mut nodes, mut cells) = (Vec::new(), Vec::new());
        let mut last_t = 0.0;
        for k in 0..6 {
            let got = trace_past(&view, &frame, &ray, &l, &nodes);
            let want = r.query_past(&frame, &ray, &l, &cells);
            match (got, want) {
                (None, None) => break,
                (Some(h), Some((t, tied))) => {
                    assert!((h.t - t).abs() / frame.edge <= 1e-12, "{} vs {t}", h.t);
                    assert!(tied.contains(&h.cell), "{:?} not in {tied:?}", h.cell);
                    assert!(h.t >= last_t, "looking past went backwards");
                    assert!(!nodes.contains(&h.node), "a skipped voxel was hit again");
                    if k > 0 {
                        behind += 1;
                    }
                    last_t = h.t;
                    nodes.push(h.node);
                    cells.push(h.cell);
                }
                (got, want) => panic!("hit/miss disagree past {k} hits: {got:?} vs {want:?}"),
            }
        }
        if nodes.is_empty() {
            assert!(trace(&view, &frame, &ray, &l).is_none());
        }
    }
    assert!(behind > 1000, "only {behind} hits behind others: vacuous");
}

/// Camera far away: every voxel is at about the same distance, so the projection stop picks
/// one depth everywhere.
#[test]
fn lod_stops_at_one_intermediate_depth() {
    let mut rng = Rng::new(5);
    let leaves = random_cells(&mut rng, 5, 300);
    let frame = SceneFrame {
        origin: [0.0; 3],
        edge: 1.0,
        max_depth: 5,
    };
    let r = Reference::new(leaves);
    let b = single(&leaf_cells(&r), 2048, 5);
    let centre = DVec3::splat(0.5);
    let dist = 1000.0;
    // size_3 = 1/8 ≤ t·pa for t ≥ dist − 1, and size_2 = 1/4 > t·pa for t ≤ dist + 1.
    let pa = 0.125 / (dist - 1.0) * 1.000_001;
    let mut hits = 0;
    for _ in 0..1500 {
        let eye = centre + rng.unit() * dist;
        let ray = ray_to(eye, rng.point_in(&frame, 0.0));
        let l = lod(pa, 5);
        if check(&b, &r, &frame, &ray, &l) {
            let h = trace(&b.view(), &frame, &ray, &l).unwrap();
            assert_eq!(h.cell.depth, 3, "{h:?}");
            assert!(!h.leaf && h.error <= 0.0 && h.error > -1.0, "{h:?}");
            hits += 1;
        }
    }
    assert!(hits > 300, "{hits}");
}

/// Depth limit below the tree's depth.
#[test]
fn max_depth_limits_the_descent() {
    let (b, r, frame) = mixed_scene(6);
    let mut rng = Rng::new(7);
    for md in 0..=4u8 {
        for _ in 0..300 {
            let ray = ray_to(rng.point_in(&frame, 1.0), rng.point_in(&frame, 0.0));
            if check(&b, &r, &frame, &ray, &lod(NO_LOD, md)) {
                let h = trace(&b.view(), &frame, &ray, &lod(NO_LOD, md)).unwrap();
                assert!(h.cell.depth <= md);
            }
        }
    }
}

/// A dense-ish grid of unit voxels (edge 8, depth 3) so cell boundaries are integers.
fn grid_scene(seed: u64, count: usize) -> (Buffer, Reference, SceneFrame) {
    let mut rng = Rng::new(seed);
    let r = Reference::new(random_cells(&mut rng, 3, count));
    let frame = SceneFrame {
        origin: [0.0; 3],
        edge: 8.0,
        max_depth: 3,
    };
    (single(&leaf_cells(&r), 2048, 3), r, frame)
}

#[test]
fn axis_parallel_rays_on_cell_boundaries() {
    let mut n = 0;
    let mut hits = 0;
    for seed in 10..14 {
        let (b, r, frame) = grid_scene(seed, 150);
        // Origins on the integer lattice (boundary planes, edges and corners) and at half
        // integers (cell interiors), outside and inside the cube.
        let coords: Vec<f64> = (-2..=20).map(|k| f64::from(k) * 0.5).collect();
        let mut rng = Rng::new(seed);
        for _ in 0..1500 {
            let o = DVec3::new(
                coords[rng.below(coords.len() as u64) as usize],
                coords[rng.below(coords.len() as u64) as usize],
                coords[rng.below(coords.len() as u64) as usize],
            );
            for a in 0..3 {
                for s in [-1.0, 1.0] {
                    let mut d = DVec3::ZERO;
                    d[a] = s;
                    hits += usize::from(check(
                        &b,
                        &r,
                        &frame,
                        &Ray { origin: o, dir: d },
                        &lod(NO_LOD, 3),
                    ));
                    n += 1;
                }
            }
        }
    }
    assert!(hits > n / 4, "{hits} of {n}");
}

#[test]
fn rays_parallel_to_coordinate_planes_on_boundaries() {
    let (b, r, frame) = grid_scene(20, 200);
    let mut rng = Rng::new(21);
    let mut hits = 0;
    for _ in 0..6000 {
        // One coordinate on an integer plane, direction in that plane.
        let a = rng.below(3) as usize;
        let mut o = rng.point_in(&frame, 0.3);
        o[a] = rng.below(9) as f64;
        let mut d = rng.unit();
        d[a] = 0.0;
        // Sometimes a lattice direction, so the ray also crosses edges and corners exactly.
        if rng.below(2) == 0 {
            for k in 0..3 {
                if k != a {
                    d[k] = rng.below(5) as f64 - 2.0;
                    o[k] = rng.below(11) as f64 - 1.0;
                }
            }
        }
        let Some(dir) = d.try_normalize() else {
            continue;
        };
        hits += usize::from(check(
            &b,
            &r,
            &frame,
            &Ray { origin: o, dir },
            &lod(NO_LOD, 3),
        ));
    }
    assert!(hits > 1000, "{hits}");
}

#[test]
fn rays_through_cell_edges_and_corners() {
    let (b, r, frame) = grid_scene(30, 180);
    let mut rng = Rng::new(31);
    let mut hits = 0;
    let lattice = |rng: &mut Rng, lo: i64, hi: i64| {
        DVec3::new(
            (lo + rng.below((hi - lo) as u64) as i64) as f64,
            (lo + rng.below((hi - lo) as u64) as i64) as f64,
            (lo + rng.below((hi - lo) as u64) as i64) as f64,
        )
    };
    for i in 0..6000 {
        let (o, dir) = if i % 3 == 0 {
            // Exact diagonals from a lattice point: every axis crosses planes at the same t,
            // so the ray passes through cell corners.
            let o = lattice(&mut rng, -2, 11);
            let d = DVec3::new(
                if rng.below(2) == 0 { 1.0 } else { -1.0 },
                if rng.below(2) == 0 { 1.0 } else { -1.0 },
                if rng.below(2) == 0 { 1.0 } else { -1.0 },
            );
            (o, d.normalize())
        } else if i % 3 == 1 {
            // Along a face diagonal inside a boundary plane: crosses cell edges.
            let o = lattice(&mut rng, -2, 11);
            let mut d = DVec3::ONE;
            d[rng.below(3) as usize] = 0.0;
            if rng.below(2) == 0 {
                d = -d;
            }
            (o, d.normalize())
        } else {
            // Lattice point to lattice point.
            let o = lattice(&mut rng, -3, 12);
            let t = lattice(&mut rng, 0, 9);
            let Some(dir) = (t - o).try_normalize() else {
                continue;
            };
            (o, dir)
        };
        hits += usize::from(check(
            &b,
            &r,
            &frame,
            &Ray { origin: o, dir },
            &lod(NO_LOD, 3),
        ));
    }
    assert!(hits > 1000, "{hits}");
}

/// The degenerate orderings that front-to-back order alone gets wrong: a ray in the plane
/// between two siblings, nearer voxel in the higher-index sibling; and a ray grazing the edge
/// of a lower-index sibling where it enters another.
#[test]
fn degenerate_sibling_orders() {
    let frame = SceneFrame {
        origin: [0.0; 3],
        edge: 2.0,
        max_depth: 2,
    };
    // Children 0 (x ≤ 1) and 4 (x ≥ 1) span the same y and z; the ray runs along +y in the
    // plane x = 1 between them, so both are entered at t = 1 and child 0 is visited first,
    // but its voxel is farther (y from 0.5) than child 4's (y from 0).
    let c = |x, y, z| Cell { depth: 2, x, y, z };
    let r = Reference::new([c(1, 1, 0), c(2, 0, 0)]);
    let b = single(&leaf_cells(&r), 128, 2);
    let ray = Ray {
        origin: DVec3::new(1.0, -1.0, 0.25),
        dir: DVec3::Y,
    };
    assert!(check(&b, &r, &frame, &ray, &lod(NO_LOD, 2)));
    let h = trace(&b.view(), &frame, &ray, &lod(NO_LOD, 2)).unwrap();
    assert_eq!((h.cell, h.t), (c(2, 0, 0), 1.0));
}

#[test]
fn camera_inside_the_octree_and_inside_voxels() {
    let (b, r, frame) = mixed_scene(40);
    let mut rng = Rng::new(41);
    let mut zero = 0;
    for i in 0..4000 {
        let origin = if i % 2 == 0 {
            rng.point_in(&frame, 0.0)
        } else {
            // Inside (or on the boundary of) a leaf voxel.
            let leaves = leaf_cells(&r);
            let l = leaves[rng.below(leaves.len() as u64) as usize];
            let size = frame.edge / 2f64.powi(i32::from(l.depth));
            let pick = |rng: &mut Rng, c: u32| {
                let u = [0.0, 0.5, 1.0, rng.f()][rng.below(4) as usize];
                (f64::from(c) + u) * size
            };
            DVec3::new(
                frame.origin[0] + pick(&mut rng, l.x),
                frame.origin[1] + pick(&mut rng, l.y),
                frame.origin[2] + pick(&mut rng, l.z),
            )
        };
        let ray = Ray {
            origin,
            dir: rng.unit(),
        };
        if check(&b, &r, &frame, &ray, &lod(NO_LOD, 4)) {
            let h = trace(&b.view(), &frame, &ray, &lod(NO_LOD, 4)).unwrap();
            if h.t == 0.0 {
                zero += 1;
                assert_eq!(h.error, MAX_SCREEN_ERROR);
            }
        }
    }
    assert!(zero > 1000, "{zero} t = 0 hits");
}

#[test]
fn very_far_and_very_near_cameras() {
    let (b, r, frame) = mixed_scene(50);
    let centre = DVec3::from_array(frame.centre());
    let mut rng = Rng::new(51);
    let mut hits = 0;
    for i in 0..3000 {
        let dist = match i % 3 {
            0 => 1e6 * frame.edge,
            1 => 1e-9 * frame.edge,
            _ => rng.range(0.5, 1.0) * frame.edge,
        };
        // Near cameras sit just outside a face.
        let eye = if i % 3 == 1 {
            let mut p = rng.point_in(&frame, 0.0);
            p.x = frame.origin[0] - dist;
            p
        } else {
            centre + rng.unit() * dist
        };
        let ray = ray_to(eye, rng.point_in(&frame, 0.0));
        for pa in [NO_LOD, 1e-3] {
            hits += usize::from(check(&b, &r, &frame, &ray, &lod(pa, 4)));
        }
    }
    assert!(hits > 2000, "{hits}");
}

/// A single voxel at depth `d`, found from many directions; with `siblings`, plus a sibling
/// leaf every third level that may stand in front of it.
/// Returns how many of the 600 aimed rays stopped at the deepest voxel.
fn chain(d: u8, origin: [f64; 3], edge: f64, seed: u64, siblings: bool) -> usize {
    let mut rng = Rng::new(seed);
    let side = 1u64 << d;
    let target = Cell {
        depth: d,
        x: rng.below(side) as u32,
        y: rng.below(side) as u32,
        z: rng.below(side) as u32,
    };
    let mut leaves = vec![target];
    for k in (1..d).step_by(3).filter(|_| siblings) {
        // A sibling leaf of the chain's ancestor at depth k.
        let a = target.ancestor(k);
        let s = Cell { x: a.x ^ 1, ..a };
        leaves.push(s);
    }
    let frame = SceneFrame {
        origin,
        edge,
        max_depth: d,
    };
    let r = Reference::new(leaves);
    let b = single(&leaf_cells(&r), 128, d);
    let size = edge / 2f64.powi(i32::from(d));
    let centre = DVec3::new(
        origin[0] + (f64::from(target.x) + 0.5) * size,
        origin[1] + (f64::from(target.y) + 0.5) * size,
        origin[2] + (f64::from(target.z) + 0.5) * size,
    );
    let mut found = 0;
    for i in 0..600 {
        let dist = [1e-3, 0.7, 3.0][i % 3] * edge;
        let eye = centre + rng.unit() * dist;
        let ray = ray_to(eye, centre);
        if check(&b, &r, &frame, &ray, &lod(NO_LOD, d)) {
            let h = trace(&b.view(), &frame, &ray, &lod(NO_LOD, d)).unwrap();
            found += usize::from(h.cell == target);
        }
        // Random rays, mostly missing the chain.
        let ray = Ray {
            origin: rng.point_in(&frame, 1.0),
            dir: rng.unit(),
        };
        check(&b, &r, &frame, &ray, &lod(NO_LOD, d));
    }
    found
}

#[test]
fn deep_chains_20_24_31() {
    // Alone, the deepest voxel is found by every ray aimed at its centre; with siblings, by
    // those no sibling stands in front of.
    for (d, origin, edge, seed) in [
        (20, [0.0; 3], 1.0, 60),
        (24, [-1.5, 2.0, 0.25], 3.0, 61),
        (31, [0.0; 3], 1.0, 62),
        (31, [1e3, -7.0, 3.0], 1e4, 63),
    ] {
        assert_eq!(chain(d, origin, edge, seed, false), 600, "depth {d}");
        let found = chain(d, origin, edge, seed, true);
        assert!(found > 30, "depth {d}: found {found} times");
    }
}

#[test]
fn huge_origin_coordinates() {
    let huge = [5e6, -5e6, 5e6 + 0.125];
    assert_eq!(chain(24, huge, 10.0, 70, false), 600);
    assert!(chain(24, huge, 10.0, 70, true) > 30);
    // A depth-31 voxel of a unit cube at 5e6 is smaller than the f64 spacing of world
    // coordinates there (2^-31 < ulp(5e6) ≈ 9.3e-10), so rays *aimed* from world space can
    // miss it; the traversal must still agree with brute force on every ray.
    chain(31, huge, 1.0, 71, false);
    chain(31, huge, 1.0, 71, true);
    let (b, r, mut frame) = mixed_scene(72);
    frame.origin = huge;
    let mut rng = Rng::new(73);
    for _ in 0..2000 {
        let ray = ray_to(rng.point_in(&frame, 1.0), rng.point_in(&frame, 0.0));
        check(&b, &r, &frame, &ray, &lod(NO_LOD, 4));
    }
}

/// Refinable leaves report their subtreelet; final leaves report none.
#[test]
fn refinable_leaves_report_their_subtreelet() {
    let mut rng = Rng::new(80);
    let leaves = random_cells(&mut rng, 3, 60);
    let refinable: BTreeMap<Cell, u32> = leaves[..20]
        .iter()
        .enumerate()
        .map(|(i, c)| (*c, 100 + i as u32))
        .collect();
    let b = single_refinable(&leaves[20..], &refinable, 2048, 6);
    let r = Reference::new(leaves.iter().copied());
    let frame = SceneFrame {
        origin: [0.0; 3],
        edge: 1.0,
        max_depth: 6,
    };
    let mut seen = 0;
    for _ in 0..2000 {
        let ray = ray_to(rng.point_in(&frame, 1.0), rng.point_in(&frame, 0.0));
        if check(&b, &r, &frame, &ray, &lod(NO_LOD, 6)) {
            let h = trace(&b.view(), &frame, &ray, &lod(NO_LOD, 6)).unwrap();
            match refinable.get(&h.cell) {
                Some(&id) => {
                    assert_eq!(h.subtreelet, TreeletId(id));
                    seen += 1;
                }
                None => assert_eq!(h.subtreelet, TreeletId::NONE),
            }
        }
    }
    assert!(seen > 100, "{seen}");
}

/// A child treelet patched into slot 1 below the root treelet in slot 0.
#[test]
fn two_slots_with_a_patched_child() {
    let n = 256;
    let max_depth = 6;
    let mut rng = Rng::new(90);
    let root_leaves = random_cells(&mut rng, 2, 20);
    let refined = root_leaves[0];
    let refinable = BTreeMap::from([(refined, 1u32), (root_leaves[1], 2u32)]);
    let finals: Vec<Cell> = root_leaves[2..].to_vec();
    let (t0, p0) = synth::build_treelet(0, Cell::ROOT, &finals, &refinable, n, max_depth);
    // The child: 40 voxels at depth 6 inside `refined`.
    let child_leaves: Vec<Cell> = random_cells(&mut rng, 4, 40)
        .into_iter()
        .map(|c| Cell {
            depth: 6,
            x: (refined.x << 4) | c.x,
            y: (refined.y << 4) | c.y,
            z: (refined.z << 4) | c.z,
        })
        .collect();
    let (t1, p1) = synth::build_treelet(1, refined, &child_leaves, &BTreeMap::new(), n, max_depth);
    let mut b = Buffer::new(n, 2);
    b.put(0, &t0, p0);
    b.put(1, &t1, p1);
    b.patch(0, refined, 1);
    let resident = finals
        .iter()
        .chain(&child_leaves)
        .copied()
        .chain([root_leaves[1]]);
    let r = Reference::new(resident);
    let frame = SceneFrame {
        origin: [2.0, 3.0, -1.0],
        edge: 4.0,
        max_depth,
    };
    let mut in_child = 0;
    for i in 0..4000 {
        // Half the rays aimed into the refined voxel.
        let target = if i % 2 == 0 {
            let s = frame.edge / 4.0;
            DVec3::new(
                frame.origin[0] + (f64::from(refined.x) + rng.f()) * s,
                frame.origin[1] + (f64::from(refined.y) + rng.f()) * s,
                frame.origin[2] + (f64::from(refined.z) + rng.f()) * s,
            )
        } else {
            rng.point_in(&frame, 0.0)
        };
        let ray = ray_to(rng.point_in(&frame, 1.0), target);
        if check(&b, &r, &frame, &ray, &lod(NO_LOD, max_depth)) {
            let h = trace(&b.view(), &frame, &ray, &lod(NO_LOD, max_depth)).unwrap();
            if h.cell.depth == 6 {
                assert_eq!(b.view().slot_of(h.node), 1);
                in_child += 1;
            }
        }
    }
    assert!(in_child > 100, "{in_child}");
}

/// Root in slot 0, child A in slot 2, A's child B in slot 1: B's root sits *before* its
/// parent's slot, so the patched offset is negative (wrapping).
#[test]
fn three_slots_with_a_child_in_a_lower_slot() {
    let n = 256;
    let max_depth = 8;
    let mut rng = Rng::new(100);
    let synth::LowerSlotChain {
        buffer: b,
        root_leaves,
        a_leaves,
        b_cell,
        b_leaves,
        ..
    } = synth::lower_slot_chain(&mut rng, n, max_depth, 0);
    let patched =
        b.nodes[(2 * n) as usize + b.places[2].iter().position(|p| p.cell == b_cell).unwrap()];
    assert!(
        patched.first_child > u32::MAX / 2,
        "offset {} should be negative",
        patched.first_child
    );
    let resident = root_leaves[1..]
        .iter()
        .chain(&a_leaves[1..])
        .chain(&b_leaves)
        .copied();
    let r = Reference::new(resident);
    let frame = SceneFrame {
        origin: [0.0; 3],
        edge: 1.0,
        max_depth,
    };
    let size_b = frame.edge / 2f64.powi(i32::from(b_cell.depth));
    let mut in_b = 0;
    for i in 0..4000 {
        let target = if i % 2 == 0 {
            DVec3::new(
                (f64::from(b_cell.x) + rng.f()) * size_b,
                (f64::from(b_cell.y) + rng.f()) * size_b,
                (f64::from(b_cell.z) + rng.f()) * size_b,
            )
        } else {
            rng.point_in(&frame, 0.0)
        };
        let ray = ray_to(rng.point_in(&frame, 1.0), target);
        if check(&b, &r, &frame, &ray, &lod(NO_LOD, max_depth)) {
            let h = trace(&b.view(), &frame, &ray, &lod(NO_LOD, max_depth)).unwrap();
            if b_cell.contains(&h.cell) {
                assert_eq!(b.view().slot_of(h.node), 1);
                in_b += 1;
            }
        }
    }
    assert!(in_b > 300, "{in_b}");
}

#[test]
fn bad_rays_and_garbage_buffers_never_panic() {
    let (b, _, frame) = mixed_scene(110);
    let view = b.view();
    let l = lod(1e-3, 4);
    for (o, d) in [
        (DVec3::NAN, DVec3::X),
        (DVec3::ZERO, DVec3::NAN),
        (DVec3::ZERO, DVec3::ZERO),
        (DVec3::INFINITY, DVec3::X),
        (DVec3::splat(1e308), DVec3::NEG_X),
    ] {
        assert_eq!(trace(&view, &frame, &Ray { origin: o, dir: d }, &l), None);
    }
    let ray = Ray {
        origin: DVec3::splat(-10.0),
        dir: DVec3::ONE.normalize(),
    };
    for bad in [
        SceneFrame { edge: 0.0, ..frame },
        SceneFrame {
            edge: f64::NAN,
            ..frame
        },
        SceneFrame {
            edge: -1.0,
            ..frame
        },
        SceneFrame {
            origin: [f64::INFINITY, 0.0, 0.0],
            ..frame
        },
    ] {
        assert_eq!(trace(&view, &bad, &ray, &l), None);
    }
    // Empty buffer.
    let empty = arbor_client_core::incore::IncoreView { nodes: &[], ..view };
    assert_eq!(trace(&empty, &frame, &ray, &l), None);
    // Random records: offsets anywhere, cycles, inner nodes without children.
    let mut rng = Rng::new(111);
    for round in 0..200 {
        let nodes: Vec<Node> = (0..64)
            .map(|_| Node {
                first_child: if rng.below(2) == 0 {
                    rng.below(70) as u32
                } else {
                    rng.0.next_u64() as u32
                },
                valid_mask: rng.below(256) as u8,
                leaf_mask: rng.below(256) as u8,
                spare: 0,
            })
            .collect();
        let v = arbor_client_core::incore::IncoreView {
            nodes: &nodes,
            treelet_nodes: 16,
            color: None,
            normal: None,
            density: None,
        };
        let deep = SceneFrame {
            max_depth: 31,
            ..frame
        };
        for _ in 0..20 {
            let ray = ray_to(rng.point_in(&deep, 1.0), rng.point_in(&deep, 0.0));
            let l = lod(if round % 2 == 0 { 0.0 } else { 1e-4 }, 31);
            if let Some(h) = trace(&v, &deep, &ray, &l) {
                assert!((h.node as usize) < nodes.len() && h.error.is_finite());
            }
        }
    }
}

#[test]
fn screen_error_is_always_finite() {
    let vals = [
        0.0,
        -0.0,
        -3.0,
        5e-324,
        f64::MIN_POSITIVE,
        1e-200,
        1.0,
        3.5,
        1e200,
        f64::MAX,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NAN,
    ];
    for a in vals {
        for b in vals {
            for c in vals {
                for d in vals {
                    let e = screen_error(a, b, c, d);
                    assert!(
                        e.is_finite() && e.abs() <= MAX_SCREEN_ERROR,
                        "{a} {b} {c} {d}"
                    );
                }
            }
        }
    }
    // One pixel exactly: 0; twice the distance: one level finer.
    assert_eq!(screen_error(0.01, 10.0, 1e-3, 1.0), 0.0);
    assert!((screen_error(0.01, 20.0, 1e-3, 1.0) + 1.0).abs() < 1e-6);
    // Monotone in depth: each level halves the voxel.
    for d in 0..31 {
        let e = screen_error(1.0 / 2f64.powi(d), 5.0, 1e-3, 1.0);
        let f = screen_error(1.0 / 2f64.powi(d + 1), 5.0, 1e-3, 1.0);
        assert!((e - f - 1.0).abs() < 1e-4);
    }
}

/// Coordinates that are often exactly on the grid (integers, halves) and otherwise arbitrary.
fn coordinate() -> impl proptest::strategy::Strategy<Value = f64> {
    use proptest::prelude::*;
    prop_oneof![
        (-4i32..13).prop_map(f64::from),
        (-8i32..26).prop_map(|k| f64::from(k) * 0.5),
        -20.0..28.0f64,
    ]
}

/// Direction components: often exactly zero (axis- and plane-parallel rays).
fn component() -> impl proptest::strategy::Strategy<Value = f64> {
    use proptest::prelude::*;
    prop_oneof![Just(0.0), Just(1.0), Just(-1.0), -1.0..1.0f64]
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(2000))]

    #[test]
    fn proptest_rays_match_brute_force(
        o in [coordinate(), coordinate(), coordinate()],
        d in [component(), component(), component()],
        pa in proptest::prop_oneof![proptest::strategy::Just(0.0), 0.0..0.2f64],
    ) {
        use std::sync::OnceLock;
        static SCENE: OnceLock<(Buffer, Reference, SceneFrame)> = OnceLock::new();
        let (b, r, frame) = SCENE.get_or_init(|| grid_scene(120, 160));
        if let Some(dir) = DVec3::from_array(d).try_normalize() {
            let ray = Ray { origin: DVec3::from_array(o), dir };
            check(b, r, frame, &ray, &lod(pa, 3));
        }
    }
}
