//! Tiled point sets as one scene, on the real scans: a set of tiles imports to exactly the scene
//! its single file gives; a bad tile, mixed coordinate systems and header counts past the
//! primitive limit are refused before the pool is touched, naming the tile.

use std::path::{Path, PathBuf};

use arbor_server::import::tiles::{TileOptions, expand_inputs, import_tiles};
use arbor_server::import::{ImportOptions, import_file};
use arbor_server::octree::{BuildOptions, DepthChoice};
use arbor_server::pipeline::{SceneImport, import_scene};
use arbor_server::pool::Pool;
use arbor_server::source::Source;

fn data(name: &str) -> PathBuf {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/points")
        .join(name);
    assert!(p.exists(), "the real scans in ../shared/data are required");
    p
}

/// Writes points `range` of `src` to `out`, LAZ when `compressed`, keeping the header's scale,
/// offset and CRS records; `edit` may change the header builder (e.g. its CRS records).
fn write_tile(
    src: &Path,
    out: &Path,
    range: std::ops::Range<usize>,
    compressed: bool,
    edit: impl FnOnce(&mut las::Builder),
) {
    let mut reader = las::Reader::from_path(src).unwrap();
    let mut builder = las::Builder::from(reader.header().clone());
    builder
        .vlrs
        .retain(|v| v.user_id != "laszip encoded" && v.user_id != "copc");
    builder.evlrs.clear();
    builder.point_format.is_compressed = compressed;
    edit(&mut builder);
    let header = builder.into_header().unwrap();
    let mut writer = las::Writer::from_path(out, header).unwrap();
    let all = reader.read_all().unwrap();
    for p in all.points().skip(range.start).take(range.len()) {
        writer.write_point(p.unwrap()).unwrap();
    }
    writer.close().unwrap();
}

fn options() -> BuildOptions {
    BuildOptions {
        depth: DepthChoice::Auto,
        progress: false,
        ..BuildOptions::default()
    }
}

/// Every stored block of two scenes, byte for byte, and their figures.
fn assert_same_scene(pool: &Pool, a: &str, b: &str) {
    let (sa, sb) = (pool.scene(a).unwrap(), pool.scene(b).unwrap());
    let (da, db) = (&sa.description, &sb.description);
    assert_eq!(da.treelet_count, db.treelet_count);
    assert_eq!(da.max_depth, db.max_depth);
    assert_eq!((da.origin, da.edge), (db.origin, db.edge));
    assert_eq!(da.layout, db.layout);
    assert_eq!(da.primitives, db.primitives);
    assert_eq!(da.stats.voxels, db.stats.voxels);
    assert_eq!(da.node_dictionary, db.node_dictionary);
    for id in sa.stored_ids() {
        let id = id.unwrap();
        assert_eq!(
            sa.nodes(id).unwrap(),
            sb.nodes(id).unwrap(),
            "treelet {}",
            id.0
        );
        for &c in da.layout.channels() {
            assert_eq!(
                sa.channel(c, id).unwrap(),
                sb.channel(c, id).unwrap(),
                "treelet {} {}",
                id.0,
                c.name()
            );
        }
    }
    assert_eq!(sa.stored_treelets().unwrap(), sb.stored_treelets().unwrap());
}

/// Lion split into three tiles (LAZ, LAS, LAZ) in file order imports to the very scene the
/// single file gives: same treelets, same bytes.
#[test]
fn tiled_import_equals_single_file_import() {
    let dir = tempfile::tempdir().unwrap();
    let lion = data("lion_takanawa.copc.laz");
    let tiles = dir.path().join("tiles");
    std::fs::create_dir(&tiles).unwrap();
    let n = 341_989;
    let cuts = [0, 100_000, 220_000, n];
    for (i, w) in cuts.windows(2).enumerate() {
        let ext = if i == 1 { "las" } else { "laz" };
        let out = tiles.join(format!("lion_{i}.{ext}"));
        write_tile(&lion, &out, w[0]..w[1], i != 1, |_| {});
    }
    let files = expand_inputs(std::slice::from_ref(&tiles)).unwrap();
    assert_eq!(files.len(), 3);
    let pool = Pool::open(&dir.path().join("pool")).unwrap();
    let single = SceneImport {
        name: "single".into(),
        input: lion,
        build: options(),
        ..SceneImport::default()
    };
    import_scene(&pool, &single).unwrap();
    let tiled = SceneImport {
        name: "tiled".into(),
        input: files[0].clone(),
        more_tiles: files[1..].to_vec(),
        build: options(),
        ..SceneImport::default()
    };
    let imported = import_scene(&pool, &tiled).unwrap();
    assert!(
        imported.description.source.contains("+ 2 more tiles"),
        "{}",
        imported.description.source
    );
    assert_same_scene(&pool, "single", "tiled");
}

/// A truncated third tile fails the whole import: the error names that tile and the place,
/// and the pool holds nothing of it.
#[test]
fn bad_tile_leaves_the_pool_untouched() {
    let dir = tempfile::tempdir().unwrap();
    let autzen = data("autzen_trim.las");
    let mut files = Vec::new();
    for (i, r) in [0..40_000, 40_000..80_000, 80_000..110_000]
        .into_iter()
        .enumerate()
    {
        let out = dir.path().join(format!("autzen_{i}.las"));
        write_tile(&autzen, &out, r, false, |_| {});
        files.push(out);
    }
    let bytes = std::fs::read(&files[2]).unwrap();
    std::fs::write(&files[2], &bytes[..bytes.len() - 5_000]).unwrap();
    let pool_dir = dir.path().join("pool");
    let pool = Pool::open(&pool_dir).unwrap();
    let request = SceneImport {
        name: "autzen".into(),
        input: files[0].clone(),
        more_tiles: files[1..].to_vec(),
        build: options(),
        ..SceneImport::default()
    };
    let e = import_scene(&pool, &request).unwrap_err().to_string();
    assert!(e.contains("autzen_2.las"), "{e}");
    assert!(e.contains("truncated LAS point data"), "{e}");
    assert!(pool.scenes().unwrap().is_empty());
    assert!(pool.stored_generations().is_empty());
    // The same set without the bad tile imports.
    let request = SceneImport {
        more_tiles: files[1..2].to_vec(),
        ..request
    };
    let d = import_scene(&pool, &request).unwrap().description;
    assert_eq!(d.primitives, 80_000);
}

/// Tiles with different coordinate systems are refused naming both files, unless allowed; tiles
/// with their own scale and offset are read in their own frame.
#[test]
fn coordinate_systems_and_per_file_transforms() {
    let dir = tempfile::tempdir().unwrap();
    let autzen = data("autzen_trim.las");
    let a = dir.path().join("a.las");
    let b = dir.path().join("b.las");
    let c = dir.path().join("c.laz");
    write_tile(&autzen, &a, 0..50_000, false, |_| {});
    write_tile(&autzen, &b, 50_000..110_000, false, |h| {
        for v in h.vlrs.iter_mut().filter(|v| v.record_id == 2112) {
            v.data = b"PROJCS[\"WGS 84 / UTM zone 10N\"]\0".to_vec();
        }
    });
    // Another scale and offset: coordinates stay the same to within the coarser scale.
    write_tile(&autzen, &c, 50_000..110_000, true, |h| {
        h.transforms.x = las::Transform {
            scale: 0.001,
            offset: 600_000.0,
        };
        h.transforms.y = las::Transform {
            scale: 0.04,
            offset: 200_000.0,
        };
    });
    let scratch = tempfile::tempdir().unwrap();
    let e = import_tiles(
        &[a.clone(), b.clone()],
        &TileOptions::default(),
        scratch.path(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("a.las") && e.contains("b.las"), "{e}");
    assert!(e.contains("WGS 84 / UTM zone 10N"), "{e}");
    assert!(e.contains("--allow-mixed-crs"), "{e}");
    let allowed = TileOptions {
        allow_mixed_crs: true,
    };
    let mixed = import_tiles(&[a.clone(), b], &allowed, scratch.path()).unwrap();
    assert_eq!(mixed.primitive_count(), 110_000);

    let scratch = tempfile::tempdir().unwrap();
    let Source::Points(tiled) =
        import_tiles(&[a, c], &TileOptions::default(), scratch.path()).unwrap()
    else {
        panic!("points expected")
    };
    let whole_scratch = tempfile::tempdir().unwrap();
    let Source::Points(whole) =
        import_file(&autzen, &ImportOptions::default(), whole_scratch.path()).unwrap()
    else {
        panic!("points expected")
    };
    assert_eq!(tiled.positions.len(), whole.positions.len());
    let worst = tiled
        .positions
        .iter()
        .zip(whole.positions.iter())
        .map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).abs()).fold(0.0, f64::max))
        .fold(0.0, f64::max);
    // Half the coarser scale (0.04) at most, and more than the source's own 0.01 steps.
    assert!(worst <= 0.02 + 1e-9, "worst coordinate difference {worst}");
    assert!(
        worst > 0.005,
        "the second tile was really rescaled: {worst}"
    );
    assert_eq!(tiled.colors.as_deref(), whole.colors.as_deref());
}

/// A LAZ header declaring more points than one scene can index is refused by the header pass,
/// before any point is decoded (nothing that large is allocated or read).
#[test]
fn header_counts_past_the_primitive_limit_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let lion = data("lion_takanawa.copc.laz");
    let tile = dir.path().join("huge.laz");
    write_tile(&lion, &tile, 0..1_000, true, |_| {});
    let mut bytes = std::fs::read(&tile).unwrap();
    // LAS 1.4: legacy 32-bit count at 107 (0 when the count needs 64 bits), 64-bit count at 247.
    bytes[107..111].copy_from_slice(&0u32.to_le_bytes());
    bytes[247..255].copy_from_slice(&5_000_000_000u64.to_le_bytes());
    std::fs::write(&tile, &bytes).unwrap();
    let scratch = tempfile::tempdir().unwrap();
    let e = import_tiles(
        &[tile.clone(), tile],
        &TileOptions::default(),
        scratch.path(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("huge.laz"), "{e}");
    assert!(
        e.contains("5000000000 points") && e.contains("4294967295"),
        "{e}"
    );
}
