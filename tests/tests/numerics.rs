//! Stiff and extreme builder cases against exact, independently computed answers: points exactly
//! on cell boundaries, degenerate and sliver triangles, non-finite coordinates, projected
//! coordinates with millimetre detail, depth 20+ on tiny inputs, one-point and one-triangle scenes.

use std::collections::BTreeSet;

use arbor_proto::Cell;
use arbor_proto::limits::MAX_DEPTH;
use arbor_server::octree::{BuildError, BuildOptions, DepthChoice, build_scene};
use arbor_server::pool::Pool;
use arbor_tests::support::{
    assert_same_cells, assert_verifies, build_source, final_leaves, leaf_cells, mesh, points,
    reference_cells,
};

fn fixed(depth: u8, treelet_bytes: u32) -> BuildOptions {
    BuildOptions {
        depth: DepthChoice::Fixed(depth),
        treelet_bytes,
        ..BuildOptions::default()
    }
}

#[test]
fn points_exactly_on_cell_boundaries() {
    // A lattice at every 1/8 of the unit cube, depth 3: every point sits on cell boundaries.
    // Cells are half open, so coordinate k/8 belongs to cell k, and the far face (k = 8) to cell 7.
    let scratch = tempfile::tempdir().unwrap();
    let mut pts = Vec::new();
    for x in 0..=8 {
        for y in 0..=8 {
            for z in [0, 8] {
                pts.push([f64::from(x) / 8.0, f64::from(y) / 8.0, f64::from(z) / 8.0]);
            }
        }
    }
    let source = points(scratch.path(), &pts);
    let b = build_source(source, scratch, "lattice", &fixed(3, 1024));
    assert_eq!(b.scene.description.edge, 1.0 * (1.0 + 1e-9));
    assert_verifies(&b.scene);
    let expected: BTreeSet<[u32; 3]> = pts
        .iter()
        .map(|p| p.map(|v| ((v * 8.0) as u32).min(7)))
        .collect();
    assert_eq!(leaf_cells(&b.scene), expected);
}

#[test]
fn degenerate_and_sliver_triangles_are_exact() {
    let scratch = tempfile::tempdir().unwrap();
    let verts = [
        // A regular triangle spanning the cube.
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 1.0],
        // A collinear (zero-area) triangle.
        [0.1, 0.1, 0.9],
        [0.5, 0.5, 0.9],
        [0.9, 0.9, 0.9],
        // A point triangle exactly on a cell corner.
        [0.5, 0.5, 0.5],
        // A sliver: 1e-12 wide, along a cell face.
        [0.25, 0.0, 0.75],
        [0.25, 1.0, 0.75],
        [0.25 + 1e-12, 1.0, 0.75],
    ];
    let tris = [[0, 1, 2], [3, 4, 5], [6, 6, 6], [7, 8, 9]];
    let source = mesh(scratch.path(), &verts, &tris);
    let b = build_source(source, scratch, "degenerate", &fixed(5, 1024));
    assert_verifies(&b.scene);
    let (reference, uncovered) = reference_cells(&b.source, &b.scene);
    assert_eq!(uncovered, 0);
    let leaves = leaf_cells(&b.scene);
    assert_same_cells("degenerate", &leaves, &reference);
    // The point triangle at (0.5,0.5,0.5) touches the 8 cells around that corner (closed boxes).
    let c = (0.5 / b.scene.description.edge * 32.0).floor() as u32;
    for dx in 0..2 {
        for dy in 0..2 {
            for dz in 0..2 {
                assert!(leaves.contains(&[c - dx, c - dy, c - dz]));
            }
        }
    }
}

#[test]
fn non_finite_coordinates_are_rejected_with_a_clear_error() {
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let scratch = tempfile::tempdir().unwrap();
        let source = points(
            scratch.path(),
            &[[0.0, 0.0, 0.0], [1.0, bad, 0.0], [2.0, 2.0, 2.0]],
        );
        let pool_dir = tempfile::tempdir().unwrap();
        let pool = Pool::open(pool_dir.path()).unwrap();
        let mut txn = pool.begin_import("bad", false).unwrap();
        let err = build_scene(
            &source,
            "bad",
            "bad",
            &BuildOptions::default(),
            scratch.path(),
            &mut txn,
        )
        .unwrap_err();
        assert!(
            matches!(err, BuildError::NonFinite { index: 1, .. }),
            "{err}"
        );
        assert!(
            err.to_string().contains("non-finite coordinate in point 1"),
            "{err}"
        );
        drop(txn);
        assert!(
            pool.scenes().unwrap().is_empty(),
            "a failed build left a scene"
        );
    }
}

#[test]
fn projected_coordinates_keep_millimetres() {
    // 1024 points 1 mm apart at UTM-like coordinates (~5e5 m, ~5e6 m): in f32 these would
    // collapse onto a few positions; here each lands in its own millimetre voxel.
    let scratch = tempfile::tempdir().unwrap();
    let pts: Vec<[f64; 3]> = (0..1024)
        .map(|i| {
            [
                512_345.0 + f64::from(i) * 0.001,
                5_012_345.5 + f64::from(i % 7) * 0.001,
                127.25,
            ]
        })
        .collect();
    let source = points(scratch.path(), &pts);
    let b = build_source(source, scratch, "utm", &BuildOptions::default());
    let d = &b.scene.description;
    assert_verifies(&b.scene);
    // Every point's nearest neighbour is √2 mm away (1 mm in x and in y); auto depth reaches
    // that: 1.023 m / 2^10 < √2 mm < 1.023 m / 2^9.
    let spacing = 0.001 * 2f64.sqrt();
    assert!(
        (d.build.data_resolution - spacing).abs() < 1e-9,
        "{}",
        d.build.data_resolution
    );
    assert_eq!(d.max_depth, 10);
    assert_eq!(d.origin[0], 512_345.0);
    let leaves = leaf_cells(&b.scene);
    assert_eq!(leaves.len(), 1024, "millimetre points merged");
    let (reference, _) = reference_cells(&b.source, &b.scene);
    assert_same_cells("utm", &leaves, &reference);
}

#[test]
fn depth_twenty_and_beyond_on_tiny_inputs() {
    for depth in [20, 24, MAX_DEPTH] {
        // Two triangles a few target-depth cells wide at opposite corners of the unit cube: a
        // tiny input whose tree is `depth` levels deep, small enough to check by brute force.
        let cell = 1.0 / (1u64 << depth) as f64;
        let s = 5.5 * cell;
        let verts = [
            [0.0, 0.0, 0.0],
            [s, 0.3 * s, 0.1 * s],
            [0.2 * s, s, 0.7 * s],
            [1.0, 1.0, 1.0],
            [1.0 - s, 1.0, 1.0 - 0.5 * s],
            [1.0, 1.0 - s, 1.0 - s],
        ];
        let scratch = tempfile::tempdir().unwrap();
        let source = mesh(scratch.path(), &verts, &[[0, 1, 2], [3, 4, 5]]);
        let b = build_source(source, scratch, "deep-tri", &fixed(depth, 1024));
        assert_eq!(b.scene.description.max_depth, depth);
        assert_verifies(&b.scene);
        let (reference, uncovered) = reference_cells(&b.source, &b.scene);
        assert_eq!(uncovered, 0);
        let leaves = leaf_cells(&b.scene);
        assert!(leaves.len() > 10, "depth {depth}: {} leaves", leaves.len());
        assert_same_cells(&format!("triangles at depth {depth}"), &leaves, &reference);

        let scratch = tempfile::tempdir().unwrap();
        let pts = [
            [0.0, 0.0, 0.0],
            [1e-7, 2e-7, 0.0],
            [1.0, 1.0, 1.0],
            [0.5, 0.5 + 1e-9, 0.5],
        ];
        let source = points(scratch.path(), &pts);
        let b = build_source(source, scratch, "deep-pts", &fixed(depth, 1024));
        assert_eq!(b.scene.description.max_depth, depth);
        assert_verifies(&b.scene);
        let leaves = leaf_cells(&b.scene);
        let (reference, _) = reference_cells(&b.source, &b.scene);
        assert_same_cells(&format!("points at depth {depth}"), &leaves, &reference);
        // The two points 1e-7 apart separate by depth 24 (cell ~6e-8).
        let expect = if depth >= 24 { 4 } else { 3 };
        assert_eq!(leaves.len(), expect, "depth {depth}");
    }
}

#[test]
fn one_point_scene() {
    let scratch = tempfile::tempdir().unwrap();
    let source = points(scratch.path(), &[[3.5, -2.0, 1e6]]);
    let b = build_source(source, scratch, "one-point", &BuildOptions::default());
    let d = &b.scene.description;
    // No spacing to measure: auto depth builds nothing beyond the root voxel.
    assert_eq!(d.max_depth, 0);
    assert_eq!(d.treelet_count, 1);
    assert_eq!(d.stats.voxels, 1);
    assert_verifies(&b.scene);
    assert_eq!(final_leaves(&b.scene), vec![Cell::ROOT]);

    let scratch = tempfile::tempdir().unwrap();
    let source = points(scratch.path(), &[[3.5, -2.0, 1e6]]);
    let b = build_source(source, scratch, "one-point-deep", &fixed(12, 1024));
    assert_verifies(&b.scene);
    assert_eq!(
        b.scene.description.stats.voxels, 13,
        "a chain of 12 single children"
    );
    assert_eq!(leaf_cells(&b.scene).len(), 1);
}

#[test]
fn one_triangle_scene() {
    let scratch = tempfile::tempdir().unwrap();
    let verts = [[10.0, 10.0, 10.0], [11.0, 10.0, 10.0], [10.0, 11.0, 10.0]];
    let source = mesh(scratch.path(), &verts, &[[0, 1, 2]]);
    let b = build_source(source, scratch, "one-tri", &BuildOptions::default());
    let d = &b.scene.description;
    // Mean edge (1+1+√2)/3 ≈ 1.14 over a 1-unit cube: one level is already finer than the data.
    assert_eq!(d.max_depth, 0);
    assert_verifies(&b.scene);
    let scratch = tempfile::tempdir().unwrap();
    let source = mesh(scratch.path(), &verts, &[[0, 1, 2]]);
    let b = build_source(source, scratch, "one-tri-8", &fixed(8, 1024));
    assert_verifies(&b.scene);
    let (reference, uncovered) = reference_cells(&b.source, &b.scene);
    assert_eq!(uncovered, 0);
    assert_same_cells("one triangle", &leaf_cells(&b.scene), &reference);
}

#[test]
fn absurd_parameters_are_rejected() {
    let scratch = tempfile::tempdir().unwrap();
    let source = points(scratch.path(), &[[0.0; 3], [1.0; 3]]);
    let pool_dir = tempfile::tempdir().unwrap();
    let pool = Pool::open(pool_dir.path()).unwrap();
    let mut txn = pool.begin_import("p", false).unwrap();
    for (opts, msg) in [
        (
            BuildOptions {
                treelet_bytes: 100,
                ..BuildOptions::default()
            },
            "treelet size",
        ),
        (
            BuildOptions {
                treelet_bytes: 1 << 20,
                ..BuildOptions::default()
            },
            "treelet size",
        ),
        (
            BuildOptions {
                depth: DepthChoice::Fixed(40),
                ..BuildOptions::default()
            },
            "depth 40",
        ),
    ] {
        let err = build_scene(&source, "p", "p", &opts, scratch.path(), &mut txn).unwrap_err();
        assert!(err.to_string().contains(msg), "{err}");
    }
}
