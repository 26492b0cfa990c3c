//! Every real scan imports and verifies at 1 and 4 KiB treelets, and its geometry equals a
//! brute-force classification of every primitive against every target-depth cell.

use arbor_server::octree::{BuildOptions, DepthChoice};
use arbor_tests::support::{
    SCANS, assert_same_cells, assert_verifies, build_file, leaf_cells, reference_cells,
};

fn opts(treelet_bytes: u32, depth: DepthChoice) -> BuildOptions {
    BuildOptions {
        depth,
        treelet_bytes,
        ..BuildOptions::default()
    }
}

fn import_and_verify(index: usize) {
    let (name, rel) = SCANS[index];
    for tb in [1024, 4096] {
        let b = build_file(rel, name, &opts(tb, DepthChoice::Auto));
        let d = &b.scene.description;
        assert_eq!(d.treelet_nodes, tb / 8);
        assert!(
            d.treelet_count > 1,
            "{name}: a real scan needs more than one treelet"
        );
        assert!(d.stats.leaf_voxels > 0);
        assert_verifies(&b.scene);
        // Auto depth stops at the data's own resolution: one level less would be coarser than it.
        let voxel = d.voxel_size(d.max_depth);
        assert!(
            voxel <= d.build.data_resolution * (1.0 + 1e-9),
            "{name}: voxel {voxel} coarser than data"
        );
        assert!(
            voxel * 2.0 > d.build.data_resolution,
            "{name}: depth beyond the data's detail"
        );
    }
}

#[test]
fn bunny_imports_and_verifies() {
    import_and_verify(0);
}
#[test]
fn igea_imports_and_verifies() {
    import_and_verify(1);
}
#[test]
fn lucy_imports_and_verifies() {
    import_and_verify(2);
}
#[test]
fn autzen_imports_and_verifies() {
    import_and_verify(3);
}
#[test]
fn lion_imports_and_verifies() {
    import_and_verify(4);
}
#[test]
fn engine_imports_and_verifies() {
    import_and_verify(5);
}

/// Geometry against brute force at a modest depth: the set of target-depth leaf voxels equals the
/// set of cells some primitive touches (so every leaf touches the input and every touched cell is
/// a leaf), and every primitive touches at least one cell.
fn geometry_matches_brute_force(index: usize, depth: u8, treelet_bytes: u32) {
    let (name, rel) = SCANS[index];
    let b = build_file(rel, name, &opts(treelet_bytes, DepthChoice::Fixed(depth)));
    assert_verifies(&b.scene);
    let leaves = leaf_cells(&b.scene);
    let (reference, uncovered) = reference_cells(&b.source, &b.scene);
    assert_eq!(uncovered, 0, "{name}: primitives not covered by any voxel");
    assert_same_cells(&format!("{name} at depth {depth}"), &leaves, &reference);
    assert!(
        leaves.len() > 100,
        "{name}: suspiciously few leaves ({})",
        leaves.len()
    );
}

#[test]
fn bunny_geometry_is_exact() {
    geometry_matches_brute_force(0, 6, 1024);
}
#[test]
fn igea_geometry_is_exact() {
    geometry_matches_brute_force(1, 6, 4096);
}
#[test]
fn lucy_geometry_is_exact() {
    geometry_matches_brute_force(2, 7, 1024);
}
#[test]
fn autzen_geometry_is_exact() {
    geometry_matches_brute_force(3, 8, 4096);
}
#[test]
fn lion_geometry_is_exact() {
    geometry_matches_brute_force(4, 8, 1024);
}
#[test]
fn engine_geometry_is_exact() {
    geometry_matches_brute_force(5, 6, 4096);
}

/// The memory budget bounds the builder's id lists and changes nothing in the result: a budget
/// far below the lists' size spills to disk and yields the very same scene, byte for byte.
#[test]
fn tiny_memory_budget_builds_the_same_scene() {
    for (index, treelet_bytes) in [(4, 1024), (1, 4096)] {
        let (name, rel) = SCANS[index];
        let roomy = build_file(rel, name, &opts(treelet_bytes, DepthChoice::Auto));
        let budget = 64 << 10;
        let tight = build_file(
            rel,
            name,
            &BuildOptions {
                memory_budget: budget,
                ..opts(treelet_bytes, DepthChoice::Auto)
            },
        );
        let (a, b) = (&roomy.scene.description, &tight.scene.description);
        assert_eq!(
            a.stats.spilled_bytes, 0,
            "{name}: the default budget should not spill"
        );
        assert!(
            b.stats.spilled_bytes > 1 << 20,
            "{name}: spilled only {}",
            b.stats.spilled_bytes
        );
        assert!(
            b.stats.peak_list_bytes <= budget as u64,
            "{name}: peak {} over the budget {budget}",
            b.stats.peak_list_bytes
        );
        assert!(
            a.stats.peak_list_bytes > budget as u64,
            "{name}: test budget not tight"
        );
        assert_eq!(a.treelet_count, b.treelet_count);
        assert_eq!(a.stats.voxels, b.stats.voxels);
        assert_eq!(a.stats.node_bytes, b.stats.node_bytes);
        assert_eq!(a.stats.channel_bytes, b.stats.channel_bytes);
        for id in 0..a.treelet_count {
            let id = arbor_proto::TreeletId(id);
            assert_eq!(
                roomy.scene.nodes(id).unwrap(),
                tight.scene.nodes(id).unwrap(),
                "{name} treelet {id}"
            );
        }
        assert_verifies(&tight.scene);
    }
}
