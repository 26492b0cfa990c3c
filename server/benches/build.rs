//! Build + compress throughput on the real scans in `../shared/data/` (no sled), plus one full
//! import into a real sled pool per file.
//!
//! `cargo bench -p arbor-server --bench build` builds every scan in four variants (treelet size
//! 1 KiB / 4 KiB × per-stream dictionaries on / off, depth auto), best of 3 runs each, into a
//! sink that only counts bytes; the 4 KiB + dictionary variant is then also imported into a sled
//! pool in a temporary directory to report the bytes on disk. `ARBOR_BENCH_QUICK=1` does one run
//! of the bunny and the engine only (smoke test). The table goes to stdout and, as CSV, to
//! `target/bench-build.csv`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use arbor_proto::{AttributeLayout, SceneDescription, TreeletId};
use arbor_server::import::{self, ImportOptions};
use arbor_server::octree::{self, BuildError, BuildOptions, TreeletSink};
use arbor_server::pipeline::{SourceImport, build_into_pool};
use arbor_server::pool::Pool;
use arbor_server::source::Source;

const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data/");
const CSV: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../target/bench-build.csv");

/// (scene name, path under `DATA`, part of the quick set)
const FILES: &[(&str, &str, bool)] = &[
    ("bunny", "meshes/stanford-bunny.obj", true),
    ("igea", "meshes/igea.ply", false),
    ("lucy", "meshes/lucy-100k.ply", false),
    ("autzen", "points/autzen_trim.las", false),
    ("lion", "points/lion_takanawa.copc.laz", false),
    ("engine", "volumes/engine_256x256x128_u8.nrrd", true),
];

/// (treelet bytes, dictionary)
const VARIANTS: &[(u32, bool)] = &[(1024, false), (1024, true), (4096, false), (4096, true)];

type BenchResult<T> = Result<T, Box<dyn std::error::Error>>;

/// A sink that keeps nothing and counts the compressed bytes it is handed.
#[derive(Debug, Default)]
struct CountingSink {
    treelets: u64,
    /// Treelets whose channel blocks arrived.
    with_channels: u64,
    node_bytes: u64,
    channel_bytes: Vec<u64>,
    last_id: Option<u32>,
    out_of_order: bool,
}

impl TreeletSink for CountingSink {
    fn start(&mut self, layout: &AttributeLayout) -> Result<(), BuildError> {
        self.channel_bytes = vec![0; layout.channels().len()];
        Ok(())
    }

    fn put_nodes(&mut self, blocks: Vec<(TreeletId, Vec<u8>)>) -> Result<(), BuildError> {
        for (id, b) in blocks {
            if self.last_id.is_some_and(|last| id.0 <= last) {
                self.out_of_order = true;
            }
            self.last_id = Some(id.0);
            self.treelets += 1;
            self.node_bytes += b.len() as u64;
        }
        Ok(())
    }

    fn put_channels(&mut self, blocks: Vec<(TreeletId, Vec<Vec<u8>>)>) -> Result<(), BuildError> {
        for (_, channels) in blocks {
            if channels.len() != self.channel_bytes.len() {
                return Err(BuildError::Sink(format!(
                    "{} channel blocks for {} channels",
                    channels.len(),
                    self.channel_bytes.len()
                )));
            }
            self.with_channels += 1;
            for (s, c) in self.channel_bytes.iter_mut().zip(&channels) {
                *s += c.len() as u64;
            }
        }
        Ok(())
    }
}

/// One file × variant.
#[derive(Debug)]
struct Row {
    file: &'static str,
    treelet_bytes: u32,
    dictionary: bool,
    /// Whether dictionaries were actually used (too few treelets gives none).
    dictionary_used: bool,
    primitives: u64,
    depth: u8,
    treelet_nodes: u32,
    treelets: u32,
    voxels: u64,
    leaf_voxels: u64,
    node_bytes: u64,
    channel_bytes: Vec<u64>,
    channel_names: Vec<&'static str>,
    raw_bytes: u64,
    /// Bytes of the trained dictionaries (stored once in the scene description, not in the
    /// treelet blocks, so not part of `compressed`).
    dictionary_bytes: u64,
    build: Duration,
    /// Full import into sled (4 KiB + dictionary only): seconds, bytes on disk.
    pool: Option<(Duration, u64)>,
}

impl Row {
    fn compressed(&self) -> u64 {
        self.node_bytes + self.channel_bytes.iter().sum::<u64>()
    }
    /// Used node records over the capacity of all treelets.
    fn fill(&self) -> f64 {
        let records = self.voxels + u64::from(self.treelets) - 1;
        records as f64 / (f64::from(self.treelets) * f64::from(self.treelet_nodes))
    }
    fn bytes_per_voxel(&self) -> f64 {
        self.compressed() as f64 / self.voxels as f64
    }
    fn secs(&self) -> f64 {
        self.build.as_secs_f64()
    }
    fn variant(&self) -> String {
        format!(
            "{}K{}",
            self.treelet_bytes / 1024,
            match (self.dictionary, self.dictionary_used) {
                (false, _) => "",
                (true, true) => "+dict",
                (true, false) => "+dict(none)",
            }
        )
    }
    fn channels(&self) -> String {
        self.channel_names
            .iter()
            .zip(&self.channel_bytes)
            .map(|(n, b)| format!("{n}={b}"))
            .collect::<Vec<_>>()
            .join(";")
    }
}

fn options(treelet_bytes: u32, dictionary: bool) -> BuildOptions {
    BuildOptions {
        treelet_bytes,
        dictionary,
        progress: false,
        ..Default::default()
    }
}

/// Builds once into a counting sink, in a fresh scratch directory.
fn build_counting(
    source: &Source,
    name: &str,
    label: &str,
    opts: &BuildOptions,
) -> BenchResult<(SceneDescription, CountingSink, Duration)> {
    let scratch = tempfile::Builder::new().prefix("arbor-bench-").tempdir()?;
    let mut sink = CountingSink::default();
    let t = Instant::now();
    let desc = octree::build_scene(source, name, label, opts, scratch.path(), &mut sink)?;
    let elapsed = t.elapsed();
    Ok((desc, sink, elapsed))
}

/// Full import into a fresh sled pool; returns the wall time (begin_import through commit and
/// flush) and the pool's bytes on disk.
fn build_pool(
    source: &Source,
    name: &str,
    label: &str,
    opts: &BuildOptions,
) -> BenchResult<(Duration, u64)> {
    let scratch = tempfile::Builder::new().prefix("arbor-bench-").tempdir()?;
    let dir = tempfile::Builder::new()
        .prefix("arbor-bench-pool-")
        .tempdir()?;
    let pool = Pool::open(dir.path())?;
    let t = Instant::now();
    let job = SourceImport {
        source,
        name,
        label,
        build: opts,
        scratch: scratch.path(),
        replace: false,
    };
    let desc = build_into_pool(&pool, &job, None)?;
    pool.flush()?;
    let elapsed = t.elapsed();
    let bytes = pool.disk_bytes()?;
    let stored = pool.scene(name)?.stored_treelets()?;
    if stored != desc.treelet_count as usize {
        eprintln!(
            "ANOMALY {name}: pool holds {stored} node blocks for {} treelets",
            desc.treelet_count
        );
    }
    Ok((elapsed, bytes))
}

fn bench_file(
    name: &'static str,
    rel: &str,
    runs: usize,
    anomalies: &mut Vec<String>,
) -> BenchResult<(Vec<Row>, Duration)> {
    let path = PathBuf::from(DATA).join(rel);
    let label = Path::new(rel)
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let import_scratch = tempfile::Builder::new()
        .prefix("arbor-bench-src-")
        .tempdir()?;
    let t = Instant::now();
    let source = import::import_file(&path, &ImportOptions::default(), import_scratch.path())?;
    let import_time = t.elapsed();
    eprintln!(
        "{name}: imported {} in {:.2} s",
        source.describe(),
        import_time.as_secs_f64()
    );

    let mut rows = Vec::new();
    for &(treelet_bytes, dictionary) in VARIANTS {
        let opts = options(treelet_bytes, dictionary);
        let mut best: Option<Duration> = None;
        let mut first: Option<(SceneDescription, CountingSink)> = None;
        for _ in 0..runs {
            let (desc, sink, elapsed) = build_counting(&source, name, &label, &opts)?;
            best = Some(best.map_or(elapsed, |b| b.min(elapsed)));
            match &first {
                None => first = Some((desc, sink)),
                Some((d, _)) => {
                    if d.stats.node_bytes != desc.stats.node_bytes
                        || d.stats.channel_bytes != desc.stats.channel_bytes
                        || d.treelet_count != desc.treelet_count
                        || d.stats.voxels != desc.stats.voxels
                    {
                        anomalies.push(format!(
                            "{name} {treelet_bytes} B dict={dictionary}: output differs between runs \
                             (treelets {} vs {}, bytes {} vs {})",
                            d.treelet_count,
                            desc.treelet_count,
                            d.stats.stored_bytes(),
                            desc.stats.stored_bytes()
                        ));
                    }
                }
            }
        }
        let (desc, sink) = first.ok_or("no run")?;
        let build = best.ok_or("no run")?;
        if sink.out_of_order {
            anomalies.push(format!(
                "{name} {treelet_bytes} B: node blocks reached the sink out of id order"
            ));
        }
        if sink.treelets != u64::from(desc.treelet_count)
            || sink.with_channels != sink.treelets
            || sink.node_bytes != desc.stats.node_bytes
            || sink.channel_bytes != desc.stats.channel_bytes
        {
            anomalies.push(format!(
                "{name} {treelet_bytes} B dict={dictionary}: sink counted {} treelets / {} node B / {:?} \
                 channel B, description says {} / {} / {:?}",
                sink.treelets,
                sink.node_bytes,
                sink.channel_bytes,
                desc.treelet_count,
                desc.stats.node_bytes,
                desc.stats.channel_bytes
            ));
        }
        if dictionary && !desc.build.dictionary {
            anomalies.push(format!(
                "{name} {treelet_bytes} B: dictionary requested but none trained ({} treelets)",
                desc.treelet_count
            ));
        }
        let pool = if treelet_bytes == 4096 && dictionary {
            let mut best: Option<(Duration, u64)> = None;
            for _ in 0..runs {
                let (t, bytes) = build_pool(&source, name, &label, &opts)?;
                best = Some(match best {
                    Some((bt, _)) if bt <= t => (bt, bytes),
                    _ => (t, bytes),
                });
            }
            best
        } else {
            None
        };
        let row = Row {
            file: name,
            treelet_bytes,
            dictionary,
            dictionary_used: desc.build.dictionary,
            primitives: desc.primitives,
            depth: desc.max_depth,
            treelet_nodes: desc.treelet_nodes,
            treelets: desc.treelet_count,
            voxels: desc.stats.voxels,
            leaf_voxels: desc.stats.leaf_voxels,
            node_bytes: desc.stats.node_bytes,
            channel_bytes: desc.stats.channel_bytes.clone(),
            channel_names: desc.layout.channels().iter().map(|c| c.name()).collect(),
            raw_bytes: desc.stats.raw_bytes,
            dictionary_bytes: (desc.node_dictionary.as_ref().map_or(0, Vec::len)
                + desc
                    .channel_dictionaries
                    .iter()
                    .map(|d| d.as_ref().map_or(0, Vec::len))
                    .sum::<usize>()) as u64,
            build,
            pool,
        };
        eprintln!(
            "{name} {}: {} treelets, {:.3} s",
            row.variant(),
            row.treelets,
            row.secs()
        );
        rows.push(row);
    }
    Ok((rows, import_time))
}

fn si(v: f64) -> String {
    if v >= 1e9 {
        format!("{:.2}G", v / 1e9)
    } else if v >= 1e6 {
        format!("{:.2}M", v / 1e6)
    } else if v >= 1e3 {
        format!("{:.1}k", v / 1e3)
    } else {
        format!("{v:.0}")
    }
}

fn main() -> BenchResult<()> {
    let quick = std::env::var("ARBOR_BENCH_QUICK").is_ok_and(|v| !v.is_empty() && v != "0");
    let runs = if quick { 1 } else { 3 };
    let mut rows = Vec::new();
    let mut imports = Vec::new();
    let mut anomalies = Vec::new();
    for &(name, rel, in_quick) in FILES {
        if quick && !in_quick {
            continue;
        }
        let (r, import_time) = bench_file(name, rel, runs, &mut anomalies)?;
        rows.extend(r);
        imports.push((name, import_time));
    }

    let mut out = String::new();
    writeln!(
        out,
        "Arbor build benchmark: build + compress into a counting sink (no sled), depth auto, zstd level {}, \
         best of {runs} run{}, {} rayon threads",
        BuildOptions::default().zstd_level,
        if runs == 1 { "" } else { "s" },
        rayon::current_num_threads()
    )?;
    writeln!(
        out,
        "fill = used node records / (treelets x nodes per treelet); bytes = compressed nodes + channels\n"
    )?;
    writeln!(
        out,
        "{:<7} {:<8} {:>9} {:>3} {:>8} {:>10} {:>6} {:>10} {:>11} {:>11} {:>6} {:>8} {:>9} {:>9} | {:>7} {:>11} {:>5}",
        "file",
        "variant",
        "prims",
        "dep",
        "treelets",
        "voxels",
        "fill",
        "node B",
        "channel B",
        "total B",
        "B/vox",
        "build s",
        "prims/s",
        "voxels/s",
        "pool s",
        "pool disk B",
        "disk/B"
    )?;
    writeln!(out, "{}", "-".repeat(162))?;
    for (i, r) in rows.iter().enumerate() {
        if i > 0 && rows[i - 1].file != r.file {
            writeln!(out)?;
        }
        let (pool_s, pool_b, ratio) = match r.pool {
            Some((t, b)) => (
                format!("{:.3}", t.as_secs_f64()),
                b.to_string(),
                format!("{:.2}", b as f64 / r.compressed() as f64),
            ),
            None => (String::new(), String::new(), String::new()),
        };
        writeln!(
            out,
            "{:<7} {:<8} {:>9} {:>3} {:>8} {:>10} {:>5.1}% {:>10} {:>11} {:>11} {:>6.3} {:>8.3} {:>9} {:>9} | {:>7} {:>11} {:>5}",
            r.file,
            r.variant(),
            r.primitives,
            r.depth,
            r.treelets,
            r.voxels,
            100.0 * r.fill(),
            r.node_bytes,
            r.channel_bytes.iter().sum::<u64>(),
            r.compressed(),
            r.bytes_per_voxel(),
            r.secs(),
            si(r.primitives as f64 / r.secs()),
            si(r.voxels as f64 / r.secs()),
            pool_s,
            pool_b,
            ratio
        )?;
    }

    writeln!(
        out,
        "\nImport (file -> disk-backed columns), once per file:"
    )?;
    for (name, t) in &imports {
        writeln!(out, "  {name:<7} {:>8.3} s", t.as_secs_f64())?;
    }

    writeln!(out, "\nPer-channel compressed bytes (4K+dict):")?;
    for r in rows
        .iter()
        .filter(|r| r.treelet_bytes == 4096 && r.dictionary)
    {
        writeln!(
            out,
            "  {:<7} nodes={} {}  (raw {} B, ratio {:.2}x, leaf voxels {})",
            r.file,
            r.node_bytes,
            r.channels().replace(';', " "),
            r.raw_bytes,
            r.raw_bytes as f64 / r.compressed() as f64,
            r.leaf_voxels
        )?;
    }

    let mut files: Vec<&str> = rows.iter().map(|r| r.file).collect();
    files.dedup();
    let get = |f: &str, tb: u32, d: bool| {
        rows.iter()
            .find(|r| r.file == f && r.treelet_bytes == tb && r.dictionary == d)
    };
    let ratio = |a: u64, b: u64| a as f64 / b as f64;

    writeln!(
        out,
        "\nDictionary vs no dictionary (ratios dict/nodict, < 1 = dictionaries help)"
    )?;
    writeln!(
        out,
        "{:<7} | {:>9} {:>9} {:>9} {:>9} {:>11} {:>9} | {:>9} {:>9} {:>9} {:>11}",
        "file",
        "B/vox 1K",
        "nodes 1K",
        "chans 1K",
        "dicts B",
        "+dicts 1K",
        "time 1K",
        "B/vox 4K",
        "nodes 4K",
        "chans 4K",
        "+dicts 4K",
    )?;
    writeln!(out, "{}", "-".repeat(117))?;
    for &f in &files {
        let (Some(a0), Some(a1), Some(b0), Some(b1)) = (
            get(f, 1024, false),
            get(f, 1024, true),
            get(f, 4096, false),
            get(f, 4096, true),
        ) else {
            continue;
        };
        let chans = |r: &Row| r.channel_bytes.iter().sum::<u64>();
        writeln!(
            out,
            "{:<7} | {:>9.3} {:>9.3} {:>9.3} {:>9} {:>11.3} {:>9.2} | {:>9.3} {:>9.3} {:>9.3} {:>11.3}",
            f,
            a1.bytes_per_voxel() / a0.bytes_per_voxel(),
            ratio(a1.node_bytes, a0.node_bytes),
            ratio(chans(a1), chans(a0)),
            a1.dictionary_bytes,
            ratio(a1.compressed() + a1.dictionary_bytes, a0.compressed()),
            a1.secs() / a0.secs(),
            b1.bytes_per_voxel() / b0.bytes_per_voxel(),
            ratio(b1.node_bytes, b0.node_bytes),
            ratio(chans(b1), chans(b0)),
            ratio(b1.compressed() + b1.dictionary_bytes, b0.compressed()),
        )?;
    }
    writeln!(
        out,
        "(nodes/chans: compressed node / channel bytes; dicts B: bytes of the trained dictionaries at 1K, \
         stored once in the scene description and not counted in B/vox; +dicts: total ratio counting them; \
         time: build seconds)"
    )?;

    writeln!(out, "\n1 KiB vs 4 KiB treelets (dictionary variants)")?;
    writeln!(
        out,
        "{:<7} | {:>9} {:>9} {:>8} | {:>8} {:>8} {:>8} | {:>8} {:>8} | {:>8} {:>8}",
        "file",
        "tl 1K",
        "tl 4K",
        "1K/4K",
        "B/vox 1K",
        "B/vox 4K",
        "1K/4K",
        "fill 1K",
        "fill 4K",
        "s 1K",
        "s 4K"
    )?;
    writeln!(out, "{}", "-".repeat(104))?;
    for &f in &files {
        let (Some(a1), Some(b1)) = (get(f, 1024, true), get(f, 4096, true)) else {
            continue;
        };
        writeln!(
            out,
            "{:<7} | {:>9} {:>9} {:>8.2} | {:>8.3} {:>8.3} {:>8.3} | {:>7.1}% {:>7.1}% | {:>8.3} {:>8.3}",
            f,
            a1.treelets,
            b1.treelets,
            f64::from(a1.treelets) / f64::from(b1.treelets),
            a1.bytes_per_voxel(),
            b1.bytes_per_voxel(),
            a1.bytes_per_voxel() / b1.bytes_per_voxel(),
            100.0 * a1.fill(),
            100.0 * b1.fill(),
            a1.secs(),
            b1.secs()
        )?;
    }
    if !anomalies.is_empty() {
        writeln!(out, "\nAnomalies:")?;
        for a in &anomalies {
            writeln!(out, "  {a}")?;
        }
    }
    // Rows without a pool figure end in padding.
    let out: Vec<&str> = out.lines().map(str::trim_end).collect();
    println!("{}", out.join("\n"));

    let mut csv = String::from(
        "file,treelet_bytes,dictionary,dictionary_used,primitives,depth,treelet_nodes,treelets,voxels,\
         leaf_voxels,fill,node_bytes,channel_bytes,compressed_bytes,raw_bytes,dictionary_bytes,bytes_per_voxel,build_seconds,\
         primitives_per_second,voxels_per_second,pool_seconds,pool_disk_bytes,channels\n",
    );
    for r in &rows {
        let (pool_s, pool_b) = match r.pool {
            Some((t, b)) => (format!("{:.6}", t.as_secs_f64()), b.to_string()),
            None => (String::new(), String::new()),
        };
        writeln!(
            csv,
            "{},{},{},{},{},{},{},{},{},{},{:.6},{},{},{},{},{},{:.6},{:.6},{:.1},{:.1},{},{},{}",
            r.file,
            r.treelet_bytes,
            r.dictionary,
            r.dictionary_used,
            r.primitives,
            r.depth,
            r.treelet_nodes,
            r.treelets,
            r.voxels,
            r.leaf_voxels,
            r.fill(),
            r.node_bytes,
            r.channel_bytes.iter().sum::<u64>(),
            r.compressed(),
            r.raw_bytes,
            r.dictionary_bytes,
            r.bytes_per_voxel(),
            r.secs(),
            r.primitives as f64 / r.secs(),
            r.voxels as f64 / r.secs(),
            pool_s,
            pool_b,
            r.channels()
        )?;
    }
    let csv_path = PathBuf::from(CSV);
    if let Some(dir) = csv_path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(&csv_path, csv)?;
    println!("\nCSV written to {}", csv_path.display());
    Ok(())
}
