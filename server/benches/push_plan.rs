//! What a resting view's push plans cost the server at city scale: the anchored plan
//! (`push::plan_pushes_anchored` with `push::PushAnchors`, as `service::handler` runs it on every
//! request list) against the plain plan below the listed items only, on the same lists.
//!
//! The scene is synthetic because the question is the plan's cost against the number of
//! treelets a view implies, which the shared scans are far too small to reach: a flat terrain
//! (a city's ground) in a unit cube, treelets three levels deep with 64 child treelets each, five
//! treelet levels (about 17 million treelets, a 10⁸-point city's worth at 4 KiB per treelet). The
//! camera hovers just above the ground looking over it, 1024×768, so the view implies tens of
//! thousands of treelets. A simulated client lists the `ARBOR_PLAN_LISTED` (default 64) children
//! of what it received nearest the eye, holds `ARBOR_PLAN_SLOTS` treelets (default 65,536:
//! 256 MiB of 4 KiB treelets) and announces the slots it has free; the link sends the first
//! `ARBOR_PLAN_SENT` (default 1,024) treelets of each list before the next list replaces it.
//! Plans are capped as the handler caps them (`push::push_cap`) for an in-flight window of
//! `ARBOR_PLAN_WINDOW` treelets (default 1,024, the default `window_max`; 0: no cap, up to the
//! free slots). `ARBOR_PLAN_SLOTS=1000000 ARBOR_PLAN_SENT=100000 ARBOR_PLAN_WINDOW=0` shows the
//! anchors filling up ([`PushAnchors::MAX`]).
//!
//! `cargo bench -p arbor-server --bench push_plan` prints, per list: treelets received, kept
//! for the view and open anchors; pushes planned and anchors closed; the anchored plan's time,
//! the time to keep its results (record, exhausted, sent), and the plain plan's time on the
//! same list (the lower bound: no anchors). Each plan runs twice and the second is timed, so
//! the shapes it reads are warm, as in the server's shape cache. The shapes go through a
//! [`ShapeCache`] of `ARBOR_PLAN_SHAPE_BYTES` (default the server's `shape_cache_bytes`,
//! 32 MiB), built on a miss as the server decodes them; the last line says how it served against
//! the distinct shapes the run touched (what a cache without a bound would hold).

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_proto::cell::Cell;
use arbor_proto::limits::MAX_REQUEST_ITEMS;
use arbor_proto::treelet::TreeletId;
use arbor_proto::wire::ViewHint;
use arbor_server::service::config::DEFAULT_SHAPE_CACHE_BYTES;
use arbor_server::service::push::{
    PushAnchors, TreeletShape, WorldCube, deep_list, deep_list_anchored, push_cap,
};
use arbor_server::service::shapes::{ShapeCache, shape_bytes};

/// Levels of the octree one treelet spans.
const SPAN: u8 = 3;
/// Treelet levels: roots at depths 0, 3, …, 12; the deepest have no child treelets.
const LEVELS: u8 = 5;
/// The ground's height in the unit cube.
const GROUND: f64 = 0.500_01;

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.replace('_', "").parse().ok())
        .unwrap_or(default)
}

/// Treelets per level: 64 per parent, so `64^level`.
fn level_offset(level: u8) -> u32 {
    (0..level).map(|l| 1u32 << (6 * u32::from(l))).sum()
}

/// The terrain's treelets, identified by level and their root cell's x / y at its depth.
struct Terrain {
    /// The server's shapes, for the plans and the anchors.
    shapes: ShapeCache,
    /// Every shape the server built, with its bytes: what a cache without a bound would hold.
    touched: HashMap<TreeletId, usize>,
    /// The simulated client's own knowledge of what it received (it orders its list by it),
    /// kept apart so that it does not count as the server's lookups.
    client: HashMap<TreeletId, Arc<TreeletShape>>,
}

impl Terrain {
    fn id(level: u8, x: u32, y: u32) -> TreeletId {
        let side = 1u32 << (SPAN * level);
        TreeletId(level_offset(level) + y * side + x)
    }

    fn locate(id: TreeletId) -> (u8, u32, u32) {
        let level = (0..LEVELS)
            .rev()
            .find(|&l| id.0 >= level_offset(l))
            .expect("level 0 starts at 0");
        let side = 1u32 << (SPAN * level);
        let i = id.0 - level_offset(level);
        (level, i % side, i / side)
    }

    fn ground_z(depth: u8) -> u32 {
        (GROUND * (1u64 << depth) as f64) as u32
    }

    /// The server's shape of `id`, through its shape cache.
    fn shape(&mut self, id: TreeletId) -> Option<Arc<TreeletShape>> {
        let (level, x, y) = Self::locate(id);
        if level >= LEVELS {
            return None;
        }
        let touched = &mut self.touched;
        self.shapes.get_or_decode(0, id, || {
            let shape = Self::build(level, x, y);
            touched.insert(id, shape_bytes(&shape));
            Some(shape)
        })
    }

    /// The simulated client's shape of `id`.
    fn client_shape(&mut self, id: TreeletId) -> Option<Arc<TreeletShape>> {
        let (level, x, y) = Self::locate(id);
        if level >= LEVELS {
            return None;
        }
        Some(
            self.client
                .entry(id)
                .or_insert_with(|| Arc::new(Self::build(level, x, y)))
                .clone(),
        )
    }

    /// The shape of the treelet at `level` whose root cell is at `x`, `y`.
    fn build(level: u8, x: u32, y: u32) -> TreeletShape {
        let depth = SPAN * level;
        let root = Cell {
            depth,
            x,
            y,
            z: Self::ground_z(depth),
        };
        let below = depth + SPAN;
        let fan = 1u32 << SPAN;
        let children = if level + 1 < LEVELS {
            (0..fan * fan)
                .map(|k| {
                    let (cx, cy) = (x * fan + k % fan, y * fan + k / fan);
                    let cell = Cell {
                        depth: below,
                        x: cx,
                        y: cy,
                        z: Self::ground_z(below),
                    };
                    (Self::id(level + 1, cx, cy), cell)
                })
                .collect()
        } else {
            Vec::new()
        };
        TreeletShape { root, children }
    }
}

fn normalize(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

/// Just above the ground near one side, looking across it and slightly down.
fn view(free_slots: u32) -> ViewHint {
    let forward = normalize([0.0, 1.0, -0.15]);
    let up = normalize([0.0, 0.15, 1.0]);
    let tan_half_fov_y = (30f32.to_radians()).tan();
    ViewHint {
        eye: [0.5, 0.05, GROUND + 0.01],
        forward: forward.map(|v| v as f32),
        up: up.map(|v| v as f32),
        tan_half_fov_y,
        aspect: 1024.0 / 768.0,
        footprint: 2.0 * tan_half_fov_y / 768.0,
        free_slots,
    }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn main() {
    let listed_per_list = env_usize("ARBOR_PLAN_LISTED", 64);
    let slots = env_usize("ARBOR_PLAN_SLOTS", 65_536);
    let max_lists = env_usize("ARBOR_PLAN_LISTS", 400);
    let sent_per_list = env_usize("ARBOR_PLAN_SENT", 1024);
    // The handler caps a list's pushes by the connection's in-flight window; 0: no cap (up to
    // the client's free slots, as before the cap).
    let window = env_usize("ARBOR_PLAN_WINDOW", 1024);
    let max_items = |listed: usize| {
        if window == 0 {
            MAX_REQUEST_ITEMS
        } else {
            (listed + push_cap(window)).min(MAX_REQUEST_ITEMS)
        }
    };
    let cube = WorldCube {
        origin: [0.0; 3],
        edge: 1.0,
    };
    let shape_cache_bytes = env_usize("ARBOR_PLAN_SHAPE_BYTES", DEFAULT_SHAPE_CACHE_BYTES as usize);
    let mut terrain = Terrain {
        shapes: ShapeCache::for_shapes(shape_cache_bytes),
        touched: HashMap::new(),
        client: HashMap::new(),
    };
    let mut anchors = PushAnchors::default();
    // The simulated client: what it received, and the children of those it has not yet listed
    // (the frontier), nearest the eye first.
    let mut received: HashSet<TreeletId> = HashSet::new();
    let mut frontier: Vec<TreeletId> = vec![TreeletId::ROOT];
    let eye = view(0).eye;
    let distance = |terrain: &mut Terrain, id: TreeletId| {
        let s = terrain
            .client_shape(id)
            .expect("frontier treelets have shapes");
        let (min, max) = cube.cell_box(s.root);
        (0..3)
            .map(|a| {
                let c = 0.5 * (min[a] + max[a]) - eye[a];
                c * c
            })
            .sum::<f64>()
    };
    println!(
        "push plans of a resting view: terrain of {} treelets, {listed_per_list} listed per list, a client of {slots} slots, {sent_per_list} sent per list, window {window} (0: no cap)",
        level_offset(LEVELS)
    );
    println!(
        "{:>5} {:>8} {:>8} {:>8} {:>7} {:>7} {:>9} {:>9} {:>9}",
        "list", "received", "kept", "open", "pushes", "closed", "plan ms", "keep ms", "plain ms"
    );
    let (mut anchored_total, mut plain_total, mut lists) = (Duration::ZERO, Duration::ZERO, 0);
    let mut worst = (0usize, Duration::ZERO);
    for list in 0..max_lists {
        let free = slots.saturating_sub(received.len());
        let view = view(u32::try_from(free).unwrap_or(u32::MAX));
        frontier.retain(|id| !received.contains(id));
        let mut keyed: Vec<(f64, TreeletId)> = frontier
            .iter()
            .map(|&id| (distance(&mut terrain, id), id))
            .collect();
        keyed.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let items: Vec<(TreeletId, f32, f32)> = keyed
            .iter()
            .take(listed_per_list.min(free))
            .enumerate()
            .map(|(rank, &(_, id))| (id, 1.0 - rank as f32 * 1e-4, ViewHint::MAX_ERROR))
            .collect();
        // Each variant runs twice and the second is timed: the first warms the shapes it
        // reaches, as the server's shape cache is warm once a view has been served a while.
        let cap = max_items(items.len());
        let plain_plan = deep_list(cube, &view, &items, cap, |id| terrain.shape(id));
        let started = Instant::now();
        let again = deep_list(cube, &view, &items, cap, |id| terrain.shape(id));
        let plain = started.elapsed();
        assert_eq!(plain_plan, again, "the plain plan is deterministic");

        anchors.for_view(&view);
        let plan_now = |terrain: &mut Terrain, anchors: &PushAnchors| {
            deep_list_anchored(
                cube,
                &view,
                &items,
                anchors.roots(&items),
                |id| anchors.sent_limit(id),
                cap,
                |id| terrain.shape(id),
            )
            .1
        };
        let warm = plan_now(&mut terrain, &anchors);
        let started = Instant::now();
        let plan = plan_now(&mut terrain, &anchors);
        let planned = started.elapsed();
        assert_eq!(warm, plan, "the anchored plan is deterministic");
        let started = Instant::now();
        anchors.record(&items, &plan.pushes, |id| terrain.shape(id));
        anchors.note_exhausted(&plan.exhausted);
        // What the link sends before the next list replaces this one.
        let sent: Vec<TreeletId> = items
            .iter()
            .map(|i| i.0)
            .chain(plan.pushes.iter().map(|p| p.0))
            .take(sent_per_list)
            .collect();
        anchors.note_sent(&sent);
        let kept = started.elapsed();
        let total = planned + kept;
        anchored_total += total;
        plain_total += plain;
        lists += 1;
        if total > worst.1 {
            worst = (list, total);
        }
        let done = plan.pushes.is_empty() && items.is_empty();
        if list < 5 || list % 10 == 0 || done {
            println!(
                "{list:>5} {:>8} {:>8} {:>8} {:>7} {:>7} {:>9.3} {:>9.3} {:>9.3}",
                received.len(),
                anchors.len(),
                anchors.open_len(),
                plan.pushes.len(),
                plan.exhausted.len(),
                ms(planned),
                ms(kept),
                ms(plain),
            );
        }
        for &id in &sent {
            if received.insert(id)
                && let Some(s) = terrain.client_shape(id)
            {
                frontier.extend(s.children.iter().filter_map(|&(child, cell)| {
                    let (min, max) = cube.cell_box(cell);
                    view.box_error(min, max)
                        .is_some_and(|e| e > 0.0)
                        .then_some(child)
                }));
            }
        }
        if done {
            break;
        }
    }
    println!(
        "{lists} lists, {} treelets received, anchors {}: anchored plan {:.3} ms a list on average (worst {:.3} ms, list {}), plain plan {:.3} ms",
        received.len(),
        if anchors.is_full() {
            "full"
        } else {
            "not full"
        },
        ms(anchored_total) / lists as f64,
        ms(worst.1),
        worst.0,
        ms(plain_total) / lists as f64,
    );
    let f = terrain.shapes.figures();
    println!(
        "shape cache of {:.1} MiB: {} shapes in {:.1} MiB held, {} hits, {} misses; the run touched {} distinct shapes, {:.1} MiB",
        shape_cache_bytes as f64 / 1048576.0,
        f.entries,
        f.bytes as f64 / 1048576.0,
        f.hits,
        f.misses,
        terrain.touched.len(),
        terrain.touched.values().sum::<usize>() as f64 / 1048576.0,
    );
}
