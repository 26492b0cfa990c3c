//! The CPU traversal against brute force on real scans: each scan is built at a small depth
//! into a real pool, every treelet is decoded into a fully resident incore buffer, and for
//! thousands of random and axis-parallel rays the traced voxel must be the nearest of all final
//! leaves.
//!
//! Two buffers are checked: the client's own [`SlotBuffer::fully_resident`] (children patched
//! by the slot buffer), and a reference assembly written here from docs/design.md §5 alone (treelet
//! `i` in slot `i`). The second isolates the traversal; the first checks that the slot buffer
//! and the traversal agree on what a patched octree is.

use std::collections::BTreeMap;

use arbor_client_core::camera::SplitMix64;
use arbor_client_core::incore::{IncoreView, SceneFrame};
use arbor_client_core::slots::{DecodedTreelet, SlotBuffer};
use arbor_client_core::traverse::{Lod, Ray, trace};
use arbor_proto::{Cell, Node, TreeletId};
use arbor_server::octree::{BuildOptions, DepthChoice};
use arbor_tests::support::{SCANS, build_file, decoded_treelets, final_leaves};
use glam::DVec3;

/// The reference assembly: treelet `i` in slot `i`, patched in id order (parents first). A
/// treelet's root is reached at the record it patched in its parent (`live[slot]`), so that
/// record — not the slot's own node 0 — is the "leaf's parent" whose leaf bit is cleared when
/// the leaf's parent is a treelet root.
fn assemble(treelets: &[DecodedTreelet], n: u32) -> Vec<Node> {
    let mut nodes = vec![Node::default(); treelets.len() * n as usize];
    for (s, t) in treelets.iter().enumerate() {
        assert_eq!(t.id(), TreeletId(s as u32));
        nodes[s * n as usize..(s + 1) * n as usize].copy_from_slice(&t.treelet.nodes);
    }
    let mut live = vec![0u32; treelets.len()];
    for (c, t) in treelets.iter().enumerate().skip(1) {
        let h = t.treelet.header;
        let p = h.parent_id.0;
        assert!(p < c as u32, "parent {p} after child {c}");
        let local = |i: u16| {
            if i == 0 {
                live[p as usize]
            } else {
                p * n + u32::from(i)
            }
        };
        let site = local(h.parent_leaf_index);
        let leaf_parent = local(h.parent_leaf_parent_index);
        assert_eq!(
            nodes[site as usize],
            Node::leaf(c as u32),
            "treelet {c}'s leaf"
        );
        let root = t.treelet.nodes[0];
        if root.valid_mask != 0 {
            nodes[site as usize] = Node {
                first_child: (c as u32 * n + 1).wrapping_sub(site),
                ..root
            };
            nodes[leaf_parent as usize].leaf_mask &= !(1 << h.child_index_in_parent);
        } else {
            nodes[site as usize] = root;
        }
        live[c] = site;
    }
    nodes
}

/// Entry distance `max(t_enter, 0)` of the closed box of `cell`, camera-relative f64.
fn entry(frame: &SceneFrame, cell: &Cell, ray: &Ray) -> Option<f64> {
    let size = frame.edge / 2f64.powi(i32::from(cell.depth));
    let c = [cell.x, cell.y, cell.z];
    let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
    for (a, &ca) in c.iter().enumerate() {
        let rel = frame.origin[a] - ray.origin[a];
        let lo = rel + f64::from(ca) * size;
        let hi = rel + (f64::from(ca) + 1.0) * size;
        if ray.dir[a] == 0.0 {
            if lo > 0.0 || hi < 0.0 {
                return None;
            }
        } else {
            let (x, y) = (lo / ray.dir[a], hi / ray.dir[a]);
            t0 = t0.max(x.min(y));
            t1 = t1.min(x.max(y));
        }
    }
    (t0 <= t1 && t1 >= 0.0).then_some(t0.max(0.0))
}

struct Stats {
    rays: usize,
    hits: usize,
    worst: f64,
}

/// Compares one ray; brute force over every final leaf.
fn check(view: &IncoreView<'_>, frame: &SceneFrame, leaves: &[Cell], ray: &Ray, s: &mut Stats) {
    let lod = Lod {
        pixel_angle: 0.0,
        lod_bias: 1.0,
        max_depth: frame.max_depth,
    };
    let got = trace(view, frame, ray, &lod);
    let mut best: Option<f64> = None;
    for c in leaves {
        if let Some(t) = entry(frame, c, ray) {
            best = Some(best.map_or(t, |b: f64| b.min(t)));
        }
    }
    s.rays += 1;
    match (got, best) {
        (None, None) => {}
        (Some(h), Some(t)) => {
            s.hits += 1;
            let diff = (h.t - t).abs() / frame.edge;
            s.worst = s.worst.max(diff);
            assert!(
                diff <= 1e-12,
                "t {} vs brute force {t} for {ray:?}: {h:?}, slot {:?}, in leaves {}",
                h.t,
                view.slot_of(h.node),
                leaves.contains(&h.cell)
            );
            assert!(
                leaves.contains(&h.cell),
                "{:?} is not a final leaf ({ray:?})",
                h.cell
            );
            assert_eq!(entry(frame, &h.cell, ray), Some(t), "{ray:?}");
            assert!(h.leaf && h.subtreelet == TreeletId::NONE, "{h:?}");
            assert_eq!(view.nodes[h.node as usize].first_child, Node::NONE);
        }
        (got, best) => panic!("hit/miss disagree for {ray:?}: trace {got:?}, brute force {best:?}"),
    }
}

/// Which incore buffer a check runs on.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Assembly {
    Reference,
    SlotBuffer,
}

fn scan(name: &str, depth: u8, assembly: Assembly) {
    let rel = SCANS
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, r)| *r)
        .expect("known scan");
    let b = build_file(
        rel,
        name,
        &BuildOptions {
            depth: DepthChoice::Fixed(depth),
            treelet_bytes: 1024,
            ..BuildOptions::default()
        },
    );
    let d = &b.scene.description;
    assert!(d.treelet_count > 1, "{name}: needs patched child treelets");
    let treelets = decoded_treelets(&b.scene);
    let reference_nodes = assemble(&treelets, d.treelet_nodes);
    let slot_buffer;
    let view = match assembly {
        Assembly::Reference => IncoreView {
            nodes: &reference_nodes,
            treelet_nodes: d.treelet_nodes,
            color: None,
            normal: None,
            density: None,
        },
        Assembly::SlotBuffer => {
            let channels = d.layout.channels().to_vec();
            slot_buffer =
                SlotBuffer::fully_resident(d, &channels, treelets).expect("the whole scene fits");
            slot_buffer.view()
        }
    };
    let frame = SceneFrame::of(d);
    let mut leaves = final_leaves(&b.scene);
    leaves.sort();
    assert!(leaves.len() > 100, "{name}: {} leaves", leaves.len());

    let mut rng = SplitMix64::new(u64::from(depth) * 1000 + name.len() as u64);
    let mut f = move || rng.next_f64();
    let e = frame.edge;
    let o = DVec3::from_array(frame.origin);
    let mut s = Stats {
        rays: 0,
        hits: 0,
        worst: 0.0,
    };
    // Random rays from around the cube towards points inside it (and a few from inside).
    for i in 0..3000 {
        let m = if i % 10 == 0 { 0.0 } else { 1.0 };
        let eye = o + DVec3::new(
            (f() * (1.0 + 2.0 * m) - m) * e,
            (f() * (1.0 + 2.0 * m) - m) * e,
            (f() * (1.0 + 2.0 * m) - m) * e,
        );
        let target = o + DVec3::new(f(), f(), f()) * e;
        let Some(dir) = (target - eye).try_normalize() else {
            continue;
        };
        check(&view, &frame, &leaves, &Ray { origin: eye, dir }, &mut s);
    }
    // Axis-parallel rays from outside, on the voxel grid's boundary planes, edges and at cell
    // centres.
    let side = 1u32 << depth;
    let size = e / f64::from(side);
    for i in 0..1500 {
        let a = i % 3;
        let sign = if (i / 3) % 2 == 0 { 1.0 } else { -1.0 };
        let mut p = [0.0; 3];
        for (k, v) in p.iter_mut().enumerate() {
            let cell = (f() * f64::from(side)) as u32;
            let frac = [0.0, 0.5, 0.0, 0.5, 0.25][(i + k) % 5];
            *v = frame.origin[k] + (f64::from(cell) + frac) * size;
        }
        p[a] = frame.origin[a] + if sign > 0.0 { -0.5 * e } else { 1.5 * e };
        let mut dir = DVec3::ZERO;
        dir[a] = sign;
        check(
            &view,
            &frame,
            &leaves,
            &Ray {
                origin: DVec3::from_array(p),
                dir,
            },
            &mut s,
        );
    }
    eprintln!(
        "{name} depth {depth} ({assembly:?}): {} treelets, {} leaves, {} rays, {} hits, worst |Δt|/edge {:e}",
        d.treelet_count,
        leaves.len(),
        s.rays,
        s.hits,
        s.worst
    );
    assert!(s.hits > s.rays / 10, "{name}: only {} hits", s.hits);
}

#[test]
fn bunny_traces_like_brute_force() {
    scan("bunny", 6, Assembly::Reference);
}

#[test]
fn lion_traces_like_brute_force() {
    scan("lion", 5, Assembly::Reference);
}

#[test]
fn engine_traces_like_brute_force() {
    scan("engine", 5, Assembly::Reference);
}

#[test]
fn bunny_slot_buffer_traces_like_brute_force() {
    scan("bunny", 6, Assembly::SlotBuffer);
}

#[test]
fn lion_slot_buffer_traces_like_brute_force() {
    scan("lion", 5, Assembly::SlotBuffer);
}

#[test]
fn engine_slot_buffer_traces_like_brute_force() {
    scan("engine", 5, Assembly::SlotBuffer);
}

/// Every voxel a traversal can reach in `view`, with its leafness and, for leaves, the stored
/// `first_child` (the refining treelet or NONE). Walks from global 0 like the caster does.
fn reachable(view: &IncoreView<'_>) -> BTreeMap<Cell, (bool, u32)> {
    let mut out = BTreeMap::new();
    let root = view.nodes[0];
    let mut stack = vec![(0u32, Cell::ROOT, root.valid_mask == 0)];
    while let Some((g, cell, leaf)) = stack.pop() {
        let n = view.nodes[g as usize];
        out.insert(cell, (leaf, if leaf { n.first_child } else { 0 }));
        if leaf {
            continue;
        }
        for (i, k) in n.children() {
            let c = g.wrapping_add(n.first_child).wrapping_add(k);
            stack.push((c, cell.child(i), n.leaf_mask & (1 << i) != 0));
        }
    }
    out
}

/// The slot buffer's patched octree is the reference assembly's, voxel for voxel.
#[test]
fn slot_buffer_reaches_the_same_octree() {
    let b = build_file(
        "meshes/stanford-bunny.obj",
        "bunny",
        &BuildOptions {
            depth: DepthChoice::Fixed(6),
            treelet_bytes: 1024,
            ..BuildOptions::default()
        },
    );
    let d = &b.scene.description;
    let treelets = decoded_treelets(&b.scene);
    let nodes = assemble(&treelets, d.treelet_nodes);
    let reference = reachable(&IncoreView {
        nodes: &nodes,
        treelet_nodes: d.treelet_nodes,
        color: None,
        normal: None,
        density: None,
    });
    let leaves: Vec<Cell> = final_leaves(&b.scene);
    let ref_leaves: Vec<Cell> = reference
        .iter()
        .filter(|(_, (leaf, _))| *leaf)
        .map(|(c, _)| *c)
        .collect();
    let mut sorted = leaves.clone();
    sorted.sort();
    assert_eq!(
        ref_leaves, sorted,
        "reference assembly leaves = final leaves"
    );
    let channels = d.layout.channels().to_vec();
    let buf = SlotBuffer::fully_resident(d, &channels, treelets).expect("the whole scene fits");
    let got = reachable(&buf.view());
    let diff: Vec<_> = reference
        .iter()
        .filter(|(c, v)| got.get(c) != Some(v))
        .map(|(c, v)| (c, v, got.get(c)))
        .take(5)
        .collect();
    assert!(
        diff.is_empty() && got.len() == reference.len(),
        "{} voxels reached in the slot buffer, {} in the reference; first differences \
         (cell, reference (leaf, first_child), slot buffer): {diff:?}",
        got.len(),
        reference.len()
    );
}
