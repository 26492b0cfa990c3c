//! What a visible cut costs the server (`service::visibility::CutCaster`, cast for a resting
//! view's pushes), apart from reading and decoding what it loads: the treelets are decoded from
//! the pool once, before the clock starts, and each cast fetches them from memory as from the
//! server's cut node cache. The views include the stiff ones: near the surface, and inside the
//! data (every ray starts in the same chain of nested treelets, so the cast takes a round per
//! treelet level for a few dozen treelets).
//!
//! Per view, best of [`ROUNDS`]: the cast at the server's default grid (128 rays along the
//! longer side), and at its fine grid (512) seeded with the coarse cut as the server casts it
//! (`CutCaster::cut_from`), with the treelets each holds and the rays it cast. Each cast runs
//! both ways in turns: with the treelets shared out of the map (`Arc`, as the server's cut node
//! cache hands them over since stop 60) and copied out of it (before). The last line is the
//! part of every cast that does not depend on the view: the cut's buffer of
//! `visibility_cache_bytes` (32 MiB by default) made and dropped, empty and holding the first
//! view's coarse cut, both ways in turns: with every slot's records written up front
//! (`SlotBuffer::new`, the casts before stop 61) and written as slots fill
//! (`SlotBuffer::new_growing`, the casts now).
//!
//! `cargo bench -p arbor-server --bench cuts`: lion (`../shared/data`) imported with 4 KiB
//! treelets into a temporary pool. `ARBOR_BENCH_POOL=DIR ARBOR_BENCH_SCENE=NAME`: a scene of an
//! existing pool instead (the city of `--bench scale`).

mod common;

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_client_core::camera::{Camera, CameraPath};
use arbor_client_core::cycle::view_hint;
use arbor_client_core::incore::SceneFrame;
use arbor_client_core::slots::{DecodedTreelet, InsertOutcome, SlotBuffer, SlotConfig};
use arbor_proto::wire::ViewHint;
use arbor_proto::{Node, TreeletId, codec};
use arbor_server::pool::Pool;
use arbor_server::service::config::{
    DEFAULT_VISIBILITY_CACHE_BYTES, DEFAULT_VISIBILITY_FINE_GRID, DEFAULT_VISIBILITY_GRID,
};
use arbor_server::service::visibility::CutCaster;
use glam::DVec3;

/// The daemon's allocator (`arbor-server`'s `main.rs`): what a freed buffer's pages cost when
/// the next one is made depends on it.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Runs of each measurement; the best counts.
const ROUNDS: usize = 5;

/// `f`'s result and how long it took.
fn timed<T>(f: impl FnOnce() -> T) -> (Duration, T) {
    let t = Instant::now();
    let out = f();
    (t.elapsed(), out)
}

/// The best of [`ROUNDS`] runs of `f`.
fn best(mut f: impl FnMut()) -> Duration {
    (0..ROUNDS)
        .map(|_| timed(&mut f).0)
        .min()
        .unwrap_or_default()
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// The view a client at `camera` announces.
fn hint(camera: &Camera) -> ViewHint {
    view_hint(camera, 1.0, ViewHint::MAX_FREE_SLOTS).expect("a valid view")
}

fn main() {
    let bench = common::bench_scene();
    let (dir, scene) = (&bench.dir, &bench.scene);
    let pool = Pool::open(dir).unwrap();
    let stored = pool.scene(scene).unwrap();
    let d = stored.description.clone();
    let dictionaries = codec::PreparedDictionaries::of(&d);
    let decode = |id: TreeletId| {
        let block = stored.nodes(id).ok()??;
        DecodedTreelet::from_blocks_prepared(id, &block, &[], &d, &dictionaries, &[]).ok()
    };
    let root = decode(d.root_treelet).expect("the root decodes");
    let budget = DEFAULT_VISIBILITY_CACHE_BYTES;
    let caster = CutCaster::new(&d, budget, root.clone()).unwrap();
    let frame = SceneFrame::of(&d);
    let c = DVec3::from_array(frame.centre());
    let e = frame.edge;
    let (w, h) = (1024, 768);
    let look = |eye: DVec3, target: DVec3, fov: f64| {
        Camera::look_at(eye, target, DVec3::Z, fov, w, h).unwrap()
    };
    let views: Vec<(&str, Camera)> = vec![
        ("static", CameraPath::Static.camera(0, &frame, 7, w, h)),
        (
            "orbit 90°",
            CameraPath::Orbit {
                degrees_per_cycle: 90.0,
            }
            .camera(1, &frame, 7, w, h),
        ),
        (
            "fly-in end",
            CameraPath::FlyIn { cycles: 1 }.camera(5, &frame, 7, w, h),
        ),
        ("near", look(c + DVec3::new(0.2, -0.7, 0.1) * e, c, 1.0)),
        ("inside", look(c, c + DVec3::new(1.0, 0.3, 0.1), 1.2)),
    ];

    // Everything any cast loads, decoded once.
    let mut decoded: HashMap<TreeletId, Arc<DecodedTreelet>> = HashMap::new();
    let mut fetch_all = |id: TreeletId| {
        if let Some(t) = decoded.get(&id) {
            return Some(DecodedTreelet::clone(t));
        }
        let t = Arc::new(decode(id)?);
        decoded.insert(id, t.clone());
        Some(DecodedTreelet::clone(&t))
    };
    for (_, camera) in &views {
        let coarse = caster.cut(&hint(camera), DEFAULT_VISIBILITY_GRID, &mut fetch_all);
        let seeded = &coarse.treelets;
        caster.cut_from(
            &hint(camera),
            DEFAULT_VISIBILITY_FINE_GRID,
            seeded,
            &mut fetch_all,
            |_| true,
        );
    }
    // Shared out of the map as the server shares them out of its cut node cache; the copies
    // it made before stop 60, for comparison.
    let fetch = |id: TreeletId| decoded.get(&id).cloned();
    let fetch_copied = |id: TreeletId| decoded.get(&id).map(|t| DecodedTreelet::clone(t));

    println!(
        "visible cuts of {} ({} treelets of {} nodes), a {} MiB cut buffer, best of {ROUNDS}",
        d.name,
        d.treelet_count,
        d.treelet_nodes,
        budget >> 20
    );
    println!(
        "{:<12} {:>9} {:>9} {:>15} {:>9} {:>9} {:>15}",
        "", "coarse", "", "cast ms", "fine", "", "cast ms"
    );
    println!(
        "{:<12} {:>9} {:>9} {:>15} {:>9} {:>9} {:>15}",
        "view", "treelets", "rays", "shared / copied", "treelets", "rays", "shared / copied"
    );
    // The first view's coarse cut, to fill the buffers of the last line with.
    let mut first_cut: Option<Vec<TreeletId>> = None;
    for (what, camera) in &views {
        let view = hint(camera);
        let mut row = format!("{what:<12}");
        let mut coarse = Vec::new();
        for grid in [DEFAULT_VISIBILITY_GRID, DEFAULT_VISIBILITY_FINE_GRID] {
            // In turns, so that a slow spell of the machine falls on both.
            let mut shared = Duration::MAX;
            let mut copied = Duration::MAX;
            let mut cut = None;
            for _ in 0..ROUNDS {
                let (t, c) = timed(|| caster.cut_from(&view, grid, &coarse, fetch, |_| true));
                shared = shared.min(t);
                let (t, _) =
                    timed(|| caster.cut_from(&view, grid, &coarse, fetch_copied, |_| true));
                copied = copied.min(t);
                cut = Some(c);
            }
            let cut = cut.expect("at least one round");
            row += &format!(
                " {:>9} {:>9} {:>7.2} / {:>5.2}",
                cut.treelets.len(),
                cut.rays_cast,
                ms(shared),
                ms(copied)
            );
            if first_cut.is_none() {
                first_cut = Some(cut.treelets.iter().map(|&(_, id)| id).collect());
            }
            coarse = cut.treelets;
        }
        println!("{row}");
    }

    let config = SlotConfig {
        budget_bytes: budget,
        treelet_nodes: d.treelet_nodes,
        channels: Vec::new(),
        visibility_max: 1,
        load_limit: u32::MAX,
    };
    let records = SlotBuffer::new(config.clone(), root.clone())
        .unwrap()
        .capacity() as usize
        * d.treelet_nodes as usize;
    let array = best(|| drop(std::hint::black_box(vec![Node::default(); records])));
    println!(
        "the cut buffer alone, made and dropped (its {} MiB node array written alone: {:.2} ms):",
        (records * std::mem::size_of::<Node>()) >> 20,
        ms(array)
    );
    // Each way in turns, empty and holding the first view's coarse cut (parents first, as cast).
    let filled = first_cut.unwrap_or_default();
    for (what, ids) in [("empty", &[][..]), ("first cut", &filled[..])] {
        let fill = |mut b: SlotBuffer| {
            let placed = ids
                .iter()
                .filter(|&id| matches!(b.insert(&*decoded[id]), InsertOutcome::Inserted { .. }))
                .count();
            assert_eq!(placed, ids.len(), "the cut's treelets fit the buffer");
            drop(std::hint::black_box(b));
        };
        let mut written = Duration::MAX;
        let mut growing = Duration::MAX;
        for _ in 0..ROUNDS {
            written = written
                .min(timed(|| fill(SlotBuffer::new(config.clone(), root.clone()).unwrap())).0);
            growing = growing.min(
                timed(|| fill(SlotBuffer::new_growing(config.clone(), root.clone()).unwrap())).0,
            );
        }
        println!(
            "  {what:<10} ({:>5} treelets) written up front {:>6.2} ms, growing as filled {:>6.2} ms",
            ids.len(),
            ms(written),
            ms(growing)
        );
    }
}
