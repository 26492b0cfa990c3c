//! What the server's benches share: the scene they measure.

use std::path::{Path, PathBuf};

use arbor_server::octree::BuildOptions;
use arbor_server::pipeline::{SceneImport, import_scene};
use arbor_server::pool::Pool;
use tempfile::TempDir;

/// The pool directory and scene a bench measures, and the temporary directory that holds the
/// pool when the bench built it (keep it until the end).
pub struct BenchScene {
    pub dir: PathBuf,
    pub scene: String,
    pub _own: TempDir,
}

/// `ARBOR_BENCH_POOL=DIR ARBOR_BENCH_SCENE=NAME`: that scene of an existing pool (the city of
/// `--bench scale`); otherwise lion (`../shared/data`) imported with 4 KiB treelets into a
/// temporary pool, as `lion-4k`.
pub fn bench_scene() -> BenchScene {
    let own = tempfile::tempdir().unwrap();
    let (dir, scene) = match std::env::var_os("ARBOR_BENCH_POOL") {
        Some(dir) => (
            PathBuf::from(dir),
            std::env::var("ARBOR_BENCH_SCENE").expect("ARBOR_BENCH_SCENE names the scene"),
        ),
        None => {
            let dir = own.path().join("pool");
            let pool = Pool::open(&dir).unwrap();
            let request = SceneImport {
                name: "lion-4k".into(),
                input: lion(),
                build: BuildOptions {
                    treelet_bytes: 4096,
                    progress: false,
                    ..BuildOptions::default()
                },
                ..SceneImport::default()
            };
            import_scene(&pool, &request).unwrap();
            pool.flush().unwrap();
            (dir, "lion-4k".to_owned())
        }
    };
    BenchScene {
        dir,
        scene,
        _own: own,
    }
}

fn lion() -> PathBuf {
    let p = Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/points/lion_takanawa.copc.laz"
    ))
    .to_owned();
    assert!(
        p.exists(),
        "the real scans in ../shared/data are required: {p:?}"
    );
    p
}
