//! What building a treelet message costs the server when the message cache does not hold it,
//! the rule for a scan many times the cache (64 MiB by default; the 10⁸-point city's messages
//! are about 1.4 GB), and two of its parts measured both ways in one run:
//! * **pool reads**: one sled `get` per pack while a batch's consecutive ids stay in it
//!   (`StoredScene::nodes_of`, `channel_of`; the server since stop 59) against one per block
//!   (`nodes`, `channel`; before);
//! * **the used-node count** of the message header: from the raw length the zstd frame records
//!   (`codec::used_nodes_of_block`; since stop 59) against decompressing the node block for its
//!   treelet header (before).
//!
//! Per treelet, best of [`ROUNDS`]: the miss path as a stream asks for it
//! (`ServedScene::batch` of [`BATCH`] treelets adjacent in rank, here consecutive ids, with no
//! message cache: pool reads, header, one buffer), each part both ways on the same treelets, and
//! the miss path as it was (the path with each part's time now replaced by its time before).
//!
//! `cargo bench -p arbor-server --bench messages`: lion (`../shared/data`) imported with 4 KiB
//! treelets into a temporary pool. `ARBOR_BENCH_POOL=DIR ARBOR_BENCH_SCENE=NAME`: a scene of an
//! existing pool instead (the city of `--bench scale`); `ARBOR_BENCH_TREELETS=N`: the first N
//! treelets only (default all, at most 200,000); `ARBOR_BENCH_POOL_CACHE=B`: sled's page cache
//! in bytes (the server's `pool_cache_bytes`; default 128 MiB): a pool larger than it reads
//! pages from the file again.

mod common;

use std::sync::Arc;
use std::time::{Duration, Instant};

use arbor_proto::{TreeletId, codec};
use arbor_server::pool::Pool;
use arbor_server::service::shapes::ShapeCache;
use arbor_server::service::state::ServiceCaches;
use arbor_server::service::treelets::{MessageCache, ServedScene};
use arbor_server::service::visibility::NodeCache;

/// Runs of each measurement; the best counts.
const ROUNDS: usize = 3;
/// Treelets per batch, about what one stream of a whole-scene fetch carries.
const BATCH: usize = 36;

fn per_treelet(d: Duration, n: usize) -> f64 {
    d.as_secs_f64() * 1e6 / n as f64
}

/// The best of [`ROUNDS`] runs of `f`, per treelet of `n`.
fn best(n: usize, mut f: impl FnMut()) -> f64 {
    (0..ROUNDS)
        .map(|_| {
            let t = Instant::now();
            f();
            per_treelet(t.elapsed(), n)
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() {
    let bench = common::bench_scene();
    let (dir, scene) = (&bench.dir, &bench.scene);
    let cache = std::env::var("ARBOR_BENCH_POOL_CACHE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(arbor_server::pool::POOL_CACHE_BYTES);
    let pool = Pool::open_with_cache(dir, cache).unwrap();
    let stored = pool.scene(scene).unwrap();
    let d = stored.description.clone();
    let n = std::env::var("ARBOR_BENCH_TREELETS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(usize::MAX)
        .min(d.treelet_count as usize)
        .min(200_000);
    let channels = d.layout.channels().to_vec();
    let served = ServedScene::with_caches(
        stored.clone(),
        &ServiceCaches {
            messages: Arc::new(MessageCache::new(0)),
            shapes: Arc::new(ShapeCache::for_shapes(0)),
            cut_nodes: Arc::new(NodeCache::for_nodes(0)),
            fine_cuts: Arc::default(),
        },
    );
    let ids: Vec<TreeletId> = (0..n as u32).map(TreeletId).collect();
    let blocks: Vec<Vec<u8>> = ids
        .iter()
        .map(|&id| stored.nodes(id).unwrap().unwrap().to_vec())
        .collect();
    let dictionaries = codec::PreparedDictionaries::of(&d);
    let mut bytes = 0usize;
    // Once for the pool's pages, so that every round reads them warm.
    for b in ids.chunks(BATCH) {
        bytes += served
            .batch(b, &channels)
            .unwrap()
            .iter()
            .map(|c| c.len())
            .sum::<usize>();
    }

    let miss = best(n, || {
        for b in ids.chunks(BATCH) {
            std::hint::black_box(served.batch(b, &channels).unwrap());
        }
    });
    let reads_packed = best(n, || {
        for b in ids.chunks(BATCH) {
            std::hint::black_box(stored.nodes_of(b).unwrap());
            for &c in &channels {
                std::hint::black_box(stored.channel_of(c, b).unwrap());
            }
        }
    });
    let reads_each = best(n, || {
        for &id in &ids {
            std::hint::black_box(stored.nodes(id).unwrap());
            for &c in &channels {
                std::hint::black_box(stored.channel(c, id).unwrap());
            }
        }
    });
    let mut from_frames = 0u64;
    let frame = best(n, || {
        from_frames = blocks
            .iter()
            .map(|b| u64::from(codec::used_nodes_of_block(b).unwrap()))
            .sum();
    });
    let mut from_headers = 0u64;
    let decompressed = best(n, || {
        from_headers = blocks
            .iter()
            .map(|b| {
                let raw = codec::decompress_using(b, codec::MAX_RAW_TREELET, dictionaries.nodes())
                    .unwrap();
                u64::from(codec::decode_header(&raw).unwrap().0.used_nodes)
            })
            .sum();
    });
    assert_eq!(from_frames, from_headers, "the two counts disagree");

    println!(
        "{scene}: {n} of {} treelets, messages of {:.0} bytes on average ({} channels), {BATCH} \
         per batch, no message cache, a pool cache of {} MiB (best of {ROUNDS} runs, per \
         treelet)",
        d.treelet_count,
        bytes as f64 / n as f64,
        channels.len(),
        cache >> 20
    );
    println!("  miss path as served:                        {miss:7.2} µs");
    println!("  pool reads, one get per pack run (now):     {reads_packed:7.2} µs");
    println!("  pool reads, one get per block (before):     {reads_each:7.2} µs");
    println!("  used-node count from the frame (now):       {frame:7.3} µs");
    println!("  used-node count by decompressing (before):  {decompressed:7.2} µs");
    let before = miss - reads_packed + reads_each - frame + decompressed;
    println!(
        "  miss path as it was:                        {before:7.2} µs: {:.2}x the time now",
        before / miss
    );
}
