//! Shared support: building real and synthetic scenes into real sled pools, reading their leaf
//! voxels back, brute-force reference answers computed without the octree, and stopping the
//! helper processes tests start.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use arbor_proto::{Cell, Node, TreeletId, codec};
use arbor_server::octree::BuildOptions;
use arbor_server::octree::geometry::{Frame, boxes_overlap_open, triangle_touches_cell};
use arbor_server::octree::volume::Field;
use arbor_server::pipeline::{SceneImport, SourceImport, build_into_pool, import_scene};
use arbor_server::pool::{Pool, StoredScene};
use arbor_server::source::{Column, MeshSource, PointSource, Source};
use arbor_server::verify::verify_scene;
use tempfile::TempDir;

/// A real scan under `../shared/data`. Panics loudly if the shared data is missing: these tests
/// must not pass vacuously.
pub fn data(rel: &str) -> PathBuf {
    let p = crate::corpus::data_dir().join(rel);
    assert!(
        p.exists(),
        "real scan {} is missing: the tests need ../shared/data beside the project",
        p.display()
    );
    p
}

/// The six real scans, with short names.
pub const SCANS: [(&str, &str); 6] = [
    ("bunny", "meshes/stanford-bunny.obj"),
    ("igea", "meshes/igea.ply"),
    ("lucy", "meshes/lucy-100k.ply"),
    ("autzen", "points/autzen_trim.las"),
    ("lion", "points/lion_takanawa.copc.laz"),
    ("engine", "volumes/engine_256x256x128_u8.nrrd"),
];

/// A scene built into a real pool on disk, with its source kept for reference checks.
#[derive(Debug)]
pub struct Built {
    pub pool: Pool,
    pub scene: StoredScene,
    pub source: Source,
    pub pool_dir: TempDir,
    pub scratch: Scratch,
}

/// What holds a built scene's scratch files (its source's columns) until it is dropped.
#[derive(Debug)]
pub enum Scratch {
    /// The import's own, locked while it lives ([`arbor_server::scratch`]).
    Import(arbor_server::scratch::ScratchDir),
    /// The one a test made for its synthetic source.
    Test(TempDir),
}

/// The lion scan at depth 8 in 1 KiB treelets: a real tree of several treelet levels, quick to
/// build, for tests of the client core without a server.
pub fn small_lion() -> Built {
    lion_1k(arbor_server::octree::DepthChoice::Fixed(8))
}

/// The lion scan in 1 KiB treelets, to `depth`.
fn lion_1k(depth: arbor_server::octree::DepthChoice) -> Built {
    let rel = SCANS.iter().find(|(n, _)| *n == "lion").unwrap().1;
    let opts = BuildOptions {
        depth,
        treelet_bytes: 1024,
        ..BuildOptions::default()
    };
    build_file(rel, "lion", &opts)
}

/// A scene description and its treelets decoded, by id: what a client core needs to be driven
/// without a server.
pub type DecodedScene = (
    std::sync::Arc<arbor_proto::SceneDescription>,
    std::collections::HashMap<TreeletId, arbor_client_core::slots::DecodedTreelet>,
);

/// [`small_lion`], decoded.
pub fn small_lion_decoded() -> DecodedScene {
    decoded_scene(small_lion())
}

/// The whole lion scan in 1 KiB treelets (13,000 of them), decoded: a view of it at 256² needs
/// thousands of slots.
pub fn lion_1k_decoded() -> DecodedScene {
    decoded_scene(lion_1k(arbor_server::octree::DepthChoice::Auto))
}

fn decoded_scene(built: Built) -> DecodedScene {
    let treelets = decoded_treelets(&built.scene)
        .into_iter()
        .map(|t| (t.id(), t))
        .collect();
    (
        std::sync::Arc::new(built.scene.description.clone()),
        treelets,
    )
}

/// Imports a real scan and builds it into a fresh pool.
pub fn build_file(rel: &str, name: &str, opts: &BuildOptions) -> Built {
    let pool_dir = tempfile::tempdir().unwrap();
    let pool = Pool::open(pool_dir.path()).unwrap();
    let request = SceneImport {
        name: name.into(),
        input: data(rel),
        build: opts.clone(),
        ..SceneImport::default()
    };
    let imported = import_scene(&pool, &request).unwrap_or_else(|e| panic!("importing {rel}: {e}"));
    let scene = pool.scene(name).unwrap();
    Built {
        pool,
        scene,
        source: imported.source,
        pool_dir,
        scratch: Scratch::Import(imported.scratch),
    }
}

/// Builds a source into a fresh pool.
pub fn build_source(source: Source, scratch: TempDir, name: &str, opts: &BuildOptions) -> Built {
    let pool_dir = tempfile::tempdir().unwrap();
    let pool = Pool::open(pool_dir.path()).unwrap();
    let job = SourceImport {
        source: &source,
        name,
        label: name,
        build: opts,
        scratch: scratch.path(),
        replace: false,
    };
    build_into_pool(&pool, &job, None).unwrap_or_else(|e| panic!("building {name}: {e}"));
    let scene = pool.scene(name).unwrap();
    Built {
        pool,
        scene,
        source,
        pool_dir,
        scratch: Scratch::Test(scratch),
    }
}

/// Copies a closed pool directory (sled's files and folders) to `to`: how replicas get their
/// own copy of a pool.
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

/// Replaces the scene `built` holds in its pool with a copy whose node block of each treelet is
/// what `node_block` makes of the stored one (channel blocks and description unchanged): how a
/// test damages a pool the way a faulty disk or a faulty tool would.
pub fn rewrite_node_blocks(built: &Built, node_block: impl Fn(TreeletId, &[u8]) -> Vec<u8>) {
    use arbor_server::octree::TreeletSink;
    let stored = &built.scene;
    let d = &stored.description;
    let channels = d.layout.channels().to_vec();
    let ids: Vec<TreeletId> = (0..d.treelet_count).map(TreeletId).collect();
    let nodes: Vec<(TreeletId, Vec<u8>)> = ids
        .iter()
        .map(|&id| (id, node_block(id, &stored.nodes(id).unwrap().unwrap())))
        .collect();
    let per_channel: Vec<(TreeletId, Vec<Vec<u8>>)> = ids
        .iter()
        .map(|&id| {
            let blocks = channels
                .iter()
                .map(|&c| stored.channel(c, id).unwrap().unwrap().to_vec())
                .collect();
            (id, blocks)
        })
        .collect();
    let mut import = built.pool.begin_import(&d.name, true).unwrap();
    import.set_channels(&channels).unwrap();
    import.put_nodes(nodes).unwrap();
    import.put_channels(per_channel).unwrap();
    import.commit(d).unwrap();
}

/// Asserts that `verify` finds no problem.
pub fn assert_verifies(scene: &StoredScene) {
    let r = verify_scene(scene).unwrap();
    assert!(
        r.is_ok(),
        "{}: {} problems, first: {:?}",
        scene.description.name,
        r.problem_count,
        &r.problems[..r.problems.len().min(5)]
    );
    assert_eq!(r.treelets, u64::from(scene.description.treelet_count));
}

/// Every final leaf voxel (first_child NONE) of a stored scene, at any depth.
pub fn final_leaves(scene: &StoredScene) -> Vec<Cell> {
    let d = &scene.description;
    let dictionaries = codec::PreparedDictionaries::of(d);
    let mut out = Vec::new();
    for id in 0..d.treelet_count {
        let bytes = scene.nodes(TreeletId(id)).unwrap().expect("treelet stored");
        let (t, places) = codec::decode_compressed_treelet_with_places_using(
            &bytes,
            d.max_depth,
            dictionaries.nodes(),
        )
        .unwrap();
        for (i, p) in places.iter().enumerate() {
            if p.is_leaf && t.nodes[i].first_child == Node::NONE {
                out.push(p.cell);
            }
        }
    }
    out
}

/// Final leaves at the target depth as integer triples, asserting there are no others and no
/// duplicates.
pub fn leaf_cells(scene: &StoredScene) -> BTreeSet<[u32; 3]> {
    let d = scene.description.max_depth;
    let leaves = final_leaves(scene);
    let mut set = BTreeSet::new();
    for c in &leaves {
        assert_eq!(c.depth, d, "final leaf above the target depth: {c:?}");
        assert!(set.insert([c.x, c.y, c.z]), "voxel {c:?} stored twice");
    }
    set
}

/// Brute force, without the octree: every target-depth cell that some primitive touches, found
/// per primitive by scanning the cells of its bounding box with the same predicate the builder
/// uses. Also returns how many primitives touch no cell at all (must be 0: coverage).
pub fn reference_cells(source: &Source, scene: &StoredScene) -> (BTreeSet<[u32; 3]>, u64) {
    let d = &scene.description;
    let frame = Frame::new(d.origin, d.edge, d.max_depth);
    let side = 1u64 << d.max_depth;
    let mut cells = BTreeSet::new();
    let mut uncovered = 0u64;
    // Cell index range that can touch the closed interval [lo, hi] in leaf units (one cell of
    // slack either side for boundaries and the touch tolerance).
    let range = |lo: f64, hi: f64| {
        let a = (lo.floor() - 1.0).max(0.0) as u64;
        let b = (hi.floor() as i64 + 1).clamp(0, side as i64 - 1) as u64;
        a..=b
    };
    match source {
        Source::Mesh(m) => {
            for t in m.triangles.iter() {
                let tri = t.map(|i| frame.to_leaf(m.positions[i as usize]));
                let lo = [0, 1, 2].map(|a| tri[0][a].min(tri[1][a]).min(tri[2][a]));
                let hi = [0, 1, 2].map(|a| tri[0][a].max(tri[1][a]).max(tri[2][a]));
                let mut any = false;
                for x in range(lo[0], hi[0]) {
                    for y in range(lo[1], hi[1]) {
                        for z in range(lo[2], hi[2]) {
                            let cell = Cell {
                                depth: d.max_depth,
                                x: x as u32,
                                y: y as u32,
                                z: z as u32,
                            };
                            if triangle_touches_cell(&tri, cell, d.max_depth) {
                                cells.insert([x as u32, y as u32, z as u32]);
                                any = true;
                            }
                        }
                    }
                }
                uncovered += u64::from(!any);
            }
        }
        Source::Points(p) => {
            for &q in p.positions.iter() {
                cells.insert(frame.leaf_cell(q));
            }
        }
        Source::Volume(v) => {
            let field = Field { vol: v };
            let iso = d
                .build
                .iso
                .expect("volume scenes record their iso threshold");
            let [dx, dy, dz] = v.dims;
            for k in 0..dz - 1 {
                for j in 0..dy - 1 {
                    for i in 0..dx - 1 {
                        if !field.crosses(i, j, k, iso) {
                            continue;
                        }
                        let (min, max) = field.cell_box([i, j, k]);
                        let (lo, hi) = (frame.to_leaf(min), frame.to_leaf(max));
                        let mut any = false;
                        for x in range(lo[0], hi[0]) {
                            for y in range(lo[1], hi[1]) {
                                for z in range(lo[2], hi[2]) {
                                    let cmin = [x as f64, y as f64, z as f64];
                                    let cmax = [cmin[0] + 1.0, cmin[1] + 1.0, cmin[2] + 1.0];
                                    if boxes_overlap_open(lo, hi, cmin, cmax) {
                                        cells.insert([x as u32, y as u32, z as u32]);
                                        any = true;
                                    }
                                }
                            }
                        }
                        uncovered += u64::from(!any);
                    }
                }
            }
        }
    }
    (cells, uncovered)
}

/// A synthetic point source.
pub fn points(scratch: &Path, pts: &[[f64; 3]]) -> Source {
    Source::Points(PointSource {
        positions: Column::from_slice(scratch, "pos", pts).unwrap(),
        colors: None,
        normals: None,
    })
}

/// A synthetic triangle mesh.
pub fn mesh(scratch: &Path, verts: &[[f64; 3]], tris: &[[u32; 3]]) -> Source {
    Source::Mesh(MeshSource {
        positions: Column::from_slice(scratch, "pos", verts).unwrap(),
        normals: None,
        colors: None,
        triangles: Column::from_slice(scratch, "tri", tris).unwrap(),
    })
}

/// Asserts two cell sets are equal, reporting only their differences.
pub fn assert_same_cells(what: &str, leaves: &BTreeSet<[u32; 3]>, reference: &BTreeSet<[u32; 3]>) {
    let extra: Vec<_> = leaves.difference(reference).collect();
    let missing: Vec<_> = reference.difference(leaves).collect();
    assert!(
        extra.is_empty() && missing.is_empty(),
        "{what}: {} leaves touch no primitive (e.g. {:?}); {} touched cells are not leaves (e.g. {:?}); {} leaves, {} reference cells",
        extra.len(),
        &extra[..extra.len().min(5)],
        missing.len(),
        &missing[..missing.len().min(5)],
        leaves.len(),
        reference.len()
    );
}

/// Every treelet of a stored scene, decoded with all of the scene's channels, in id order —
/// what a client holding the whole scene holds.
pub fn decoded_treelets(scene: &StoredScene) -> Vec<arbor_client_core::slots::DecodedTreelet> {
    let d = &scene.description;
    let channels = d.layout.channels().to_vec();
    let dictionaries = codec::PreparedDictionaries::of(d);
    (0..d.treelet_count)
        .map(|id| {
            let id = TreeletId(id);
            let nodes = scene.nodes(id).unwrap().expect("node block stored");
            let blocks: Vec<_> = channels
                .iter()
                .map(|&c| (c, scene.channel(c, id).unwrap().expect("channel stored")))
                .collect();
            let refs: Vec<_> = blocks.iter().map(|(c, v)| (*c, v.as_ref())).collect();
            arbor_client_core::slots::DecodedTreelet::from_blocks_prepared(
                id,
                &nodes,
                &refs,
                d,
                &dictionaries,
                &channels,
            )
            .unwrap_or_else(|e| panic!("decoding treelet {id}: {e}"))
        })
        .collect()
}

/// Stops `child` the way its own shutdown expects: SIGTERM, then SIGKILL if it has not exited
/// within `grace`; reaped either way. A server killed outright leaves what it cleans up on
/// SIGTERM behind (Xvfb its display's lock file and socket, nginx its workers). Does nothing to
/// a child already reaped, whose id may belong to another process by now.
pub fn terminate(child: &mut std::process::Child, grace: std::time::Duration) {
    if !matches!(child.try_wait(), Ok(None)) {
        return;
    }
    let _ = std::process::Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status();
    let deadline = std::time::Instant::now() + grace;
    while std::time::Instant::now() < deadline {
        if !matches!(child.try_wait(), Ok(None)) {
            return;
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    let _ = child.kill();
    let _ = child.wait();
}
