//! `arbor-server`: import scans into a treelet pool, inspect and verify it, serve it.

#![forbid(unsafe_code)]

mod admin_client;

use std::io::Write as _;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{Context, Result, bail};
use arbor_server::config_watch::{ConfigSnapshot, ConfigWatch};
use arbor_server::daemon::{AdminTokenOrigin, DaemonOptions};
use arbor_server::import::tiles::TileOptions;
use arbor_server::import::{Format, ImportOptions, RawSpec, SampleType};
use arbor_server::live_copy::CopySummary;
use arbor_server::live_import::ImportPriority;
use arbor_server::logging::LogFormat;
use arbor_server::octree::{BuildOptions, DepthChoice};
use arbor_server::periodic::{ClockTime, Schedule};
use arbor_server::pipeline::{SceneImport, import_scene};
use arbor_server::pool::Pool;
use arbor_server::service::config::{AdminTls, PoolPrewarm};
use arbor_server::service::{ConfigOverrides, ServeConfig};
use arbor_server::verify;
use clap::{ArgGroup, Args, Parser, Subcommand};

/// mimalloc rather than glibc's malloc: an import's threads (sled's inserts, the compressors,
/// the sort's rounds) waited on glibc's arena locks, and its pages are reused rather than
/// returned and faulted in again.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser, Debug)]
#[command(
    name = "arbor-server",
    version,
    about = "Arbor server: build sparse voxel octree treelet pools from scans and serve them",
    after_help = "Examples:\n  \
        arbor-server import --db pool --scene bunny --depth auto ../shared/data/meshes/stanford-bunny.obj\n  \
        arbor-server import --db pool --scene engine --iso 60 ../shared/data/volumes/engine_256x256x128_u8.nrrd\n  \
        arbor-server list --db pool\n  \
        arbor-server info --db pool --scene bunny\n  \
        arbor-server verify --db pool --scene bunny\n  \
        arbor-server remove --db pool --scene bunny\n  \
        arbor-server copy --db pool --to pool-new\n  \
        arbor-server serve --db pool --listen 0.0.0.0:4433"
)]
struct Cli {
    /// Log lines on stderr: `text` (coloured only on a terminal) or `json` (one object per line,
    /// for log shippers). `RUST_LOG` filters them (default `info`).
    #[arg(long, global = true, value_enum, default_value_t = LogFormat::Text)]
    log_format: LogFormat,
    #[command(subcommand)]
    command: Command,
}

/// `arbor-server import`'s arguments.
#[derive(Args, Debug)]
struct ImportArgs {
    /// Pool directory (created if missing).
    #[arg(long, required_unless_present = "server")]
    db: Option<PathBuf>,
    /// Import into a running daemon instead: its admin API (`http://127.0.0.1:9090`). The
    /// inputs are then paths under the daemon's `--import-root`, resolved by the daemon.
    #[arg(long, conflicts_with_all = ["db", "scratch", "format", "raw_dims"])]
    server: Option<admin_client::AdminUrl>,
    /// The admin token, for `--server` (default: $ARBOR_ADMIN_TOKEN).
    #[arg(long, requires = "server")]
    token_file: Option<PathBuf>,
    /// Scene name: 1-128 characters of A-Z a-z 0-9 . _ -
    #[arg(long)]
    scene: String,
    /// Target depth, or `auto` for the depth at which voxels reach the data's own resolution.
    #[arg(long, default_value = "auto", value_parser = parse_depth)]
    depth: DepthChoice,
    /// Treelet size in bytes of node records (1024..=16384, multiple of 8).
    #[arg(long, default_value_t = arbor_proto::limits::DEFAULT_TREELET_BYTES)]
    treelet_bytes: u32,
    /// Iso threshold for volumes (default: Otsu's threshold of the histogram).
    #[arg(long)]
    iso: Option<f32>,
    /// Input format, when the file extension does not tell.
    #[arg(long)]
    format: Option<Format>,
    /// Raw volume dimensions X,Y,Z.
    #[arg(long, value_parser = parse_dims)]
    raw_dims: Option<[u32; 3]>,
    /// Raw volume sample type: u8, u16 or f32.
    #[arg(long, default_value = "u8")]
    raw_type: SampleType,
    /// Raw volume sample spacing X,Y,Z.
    #[arg(long, value_parser = parse_spacing, default_value = "1,1,1")]
    raw_spacing: [f64; 3],
    /// Raw volume samples are big endian.
    #[arg(long)]
    raw_big_endian: bool,
    /// zstd compression level of stored blocks.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(i32).range(1..=22))]
    zstd_level: i32,
    /// Do not train per-scene zstd dictionaries.
    #[arg(long)]
    no_dictionary: bool,
    /// MiB of pending primitive lists held in memory before spilling to disk.
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u64).range(1..=1_048_576))]
    memory_budget_mib: u64,
    /// Scratch directory for the import's temporary files (default: the system temp dir).
    /// Scratch directories that killed imports left there are removed first.
    #[arg(long)]
    scratch: Option<PathBuf>,
    /// Replace an existing scene of the same name (atomically).
    #[arg(long)]
    replace: bool,
    /// Hide progress bars.
    #[arg(long)]
    quiet: bool,
    /// Import tiles whose coordinate systems differ (by default a set whose LAS headers declare
    /// different coordinate systems is refused, naming both files).
    #[arg(long)]
    allow_mixed_crs: bool,
    /// Input file; or several files, directories (their LAS, LAZ and PLY files) or patterns
    /// (`tiles/*.laz`, quoted so the shell leaves it) of point tiles, read as one scene.
    #[arg(required = true, num_args = 1..)]
    files: Vec<PathBuf>,
}

/// `--server` and its token: a command a running daemon does instead, on the pool it serves.
#[derive(Args, Debug)]
struct DaemonArgs {
    /// Ask a running daemon to do it, on the pool it serves: its admin API
    /// (`http://127.0.0.1:9090`). Ctrl-C cancels the job there.
    #[arg(long, conflicts_with = "db")]
    server: Option<admin_client::AdminUrl>,
    /// The admin token, for `--server` (default: $ARBOR_ADMIN_TOKEN).
    #[arg(long, requires = "server")]
    token_file: Option<PathBuf>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Import a scan (OBJ, PLY, LAS/LAZ, NRRD, raw volume), or a set of point tiles, into the
    /// pool as a new scene.
    #[command(after_help = "Examples:\n  \
        arbor-server import --db pool --scene lucy --treelet-bytes 1024 lucy.ply\n  \
        arbor-server import --db pool --scene city tiles/            (every LAS/LAZ/PLY file in tiles/, one scene)\n  \
        arbor-server import --db pool --scene city 'tiles/*.laz'     (a pattern, expanded by the server)\n  \
        arbor-server import --server http://127.0.0.1:9090 --token-file pool/admin-token --scene city tiles/\n  \
        arbor-server import --db pool --scene ct --raw-dims 256,256,128 --raw-type u8 --iso 80 ct.raw")]
    Import(ImportArgs),
    /// List the scenes in a pool.
    List {
        #[arg(long)]
        db: PathBuf,
    },
    /// Show a scene's figures: counts, depth, bytes, channels, build time.
    Info {
        #[arg(long)]
        db: PathBuf,
        #[arg(long)]
        scene: String,
    },
    /// Check every invariant of a scene; exit status 0 only if all hold, 2 if one is broken.
    /// Reads the pool without changing it, on every core, its memory bounded whatever the
    /// scene's size. sled locks a pool per process: for a pool a daemon serves, ask the daemon
    /// instead (`--server`), which checks the published scene while it keeps serving.
    #[command(after_help = "Examples:\n  \
        arbor-server verify --db pool --scene lion\n  \
        arbor-server verify --server http://127.0.0.1:9090 --token-file pool/admin-token --scene lion")]
    Verify {
        /// Pool directory (no process may hold it).
        #[arg(long, required_unless_present = "server")]
        db: Option<PathBuf>,
        #[command(flatten)]
        daemon: DaemonArgs,
        #[arg(long)]
        scene: String,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
    },
    /// Remove a scene.
    Remove {
        #[arg(long)]
        db: PathBuf,
        #[arg(long)]
        scene: String,
    },
    /// Copy a pool's scenes into a new pool directory, in this build's layout.
    ///
    /// What it is for: a pool made before 8 MiB log segments keeps sled's 512 KiB ones, and
    /// sled reads one header per segment when it opens (6 s for 1.5 GB on a disk held to 500
    /// reads a second); the copy has this build's segments and holds only the published scenes,
    /// none of the space replaced or removed ones left. The source is only read, but sled locks
    /// it: stop a server serving it first. The copy is written beside the destination as
    /// `.NAME.copy-partial`, opened again and compared with the source pack by pack, and only
    /// then renamed to the destination; a failed or killed copy leaves no pool there. The
    /// server's state files in the source directory (certificate, key, admin token, path memory)
    /// go with it; the list of hot pages does not (it names the old file's pages).
    ///
    /// A pool a daemon serves is copied by the daemon instead (`--server`, a backup or a new
    /// replica's pool while it keeps serving): into a new directory under its `--copy-root`,
    /// with the same check and rename, the scenes as published when asked for.
    #[command(after_help = "Examples:\n  \
        arbor-server copy --db pool --to pool-new\n  \
        arbor-server copy --db pool --to lion-only --scene lion\n  \
        arbor-server copy --server http://127.0.0.1:9090 --token-file pool/admin-token --to backup-2026-12-02\n\n\
        To replace a pool by its copy: stop the server, copy, then `mv pool pool-old && mv \
        pool-new pool`, start the server, and remove pool-old once it serves.")]
    Copy {
        /// Pool directory to copy (only read; no process may hold it).
        #[arg(long, required_unless_present = "server")]
        db: Option<PathBuf>,
        #[command(flatten)]
        daemon: DaemonArgs,
        /// New pool directory (must not exist); with `--server`, the new directory's name
        /// under the daemon's `--copy-root`.
        #[arg(long)]
        to: PathBuf,
        /// Copy only this scene (repeatable) [default: every scene].
        #[arg(long)]
        scene: Vec<String>,
        /// Hide the progress bar.
        #[arg(long)]
        quiet: bool,
    },
    /// Serve the pool's scenes to clients over QUIC, with an admin HTTP API.
    ///
    /// Once serving, prints one line each on stdout: `quic ADDR`, `admin ADDR` (or
    /// `admin off`), `fingerprint HEX` (SHA-256 of the certificate, what clients pin) and
    /// `admin-token-file PATH` (or `admin-token config` when the token is set in the config).
    /// Stops gracefully on SIGINT or SIGTERM (in-flight treelets may finish for
    /// `shutdown_grace_ms`, clients get `Goodbye` and close code ShuttingDown) and exits 0.
    /// On SIGHUP reads the `--config` file again and puts its scene rules and tokens, the TLS
    /// certificate and key, and the admin tokens in force: sessions whose token no longer opens
    /// their scene are closed (Unauthorized), all others go on; the next handshake gets the
    /// certificate read (renewals need no restart); a file that does not load, or a key that is
    /// not its certificate's, changes nothing (logged at ERROR, counted in /metrics). With
    /// `config_watch_secs` in the config file it does the same by itself when those files
    /// change.
    #[command(after_help = "Examples:\n  \
        arbor-server serve --db pool\n  \
        arbor-server serve --db pool --listen 0.0.0.0:4433 --admin 127.0.0.1:9090\n  \
        arbor-server serve --db pool --listen 127.0.0.1:0 --admin off --data-dir state\n  \
        arbor-server serve --db pool --import-root /srv/scans   (admin API may import files under it)\n  \
        arbor-server serve --db pool --check-every 24h          (checks every scene once a day)\n  \
        arbor-server serve --db pool --copy-root /srv/backups   (admin API may copy the pool there)\n  \
        arbor-server serve --db pool --copy-root /srv/backups --copy-every 1d --copy-keep 7\n  \
        arbor-server serve --db pool --copy-root /srv/backups --copy-at 03:00  (nightly, UTC)\n  \
        arbor-server serve --db pool --check-at \"Sun 04:00\"        (weekly, UTC)\n  \
        arbor-server serve --db pool --copy-root /srv/backups --copy-at \"03:00 Europe/Berlin\"  (nightly, local)\n  \
        arbor-server serve --db pool --check-every 24h --background-read-rate 20MB\n  \
        arbor-server serve --config /etc/arbor/serve.toml\n\n\
        Without --config every scene is public (development). The config file's keys are \
        documented in deploy/ and docs/config-schema.md; command-line flags override them.")]
    #[command(group(ArgGroup::new("copy_schedule").args(["copy_every", "copy_at"]).multiple(true)))]
    Serve {
        /// Pool directory (overrides `db` in the config).
        #[arg(long)]
        db: Option<PathBuf>,
        /// QUIC (UDP) listen address [default: 127.0.0.1:4433].
        #[arg(long)]
        listen: Option<SocketAddr>,
        /// Admin HTTP listen address, or `off` [default: 127.0.0.1:9090].
        #[arg(long, value_parser = parse_admin)]
        admin: Option<AdminArg>,
        /// Admin listener over HTTPS: `auto` (unless the admin address is loopback), `on`, or
        /// `off` (cleartext on any address) [default: auto].
        #[arg(long, value_enum)]
        admin_tls: Option<AdminTls>,
        /// TOML configuration file.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Directory for the self-signed certificate and the generated admin token
        /// [default: the pool directory].
        #[arg(long)]
        data_dir: Option<PathBuf>,
        /// Let the admin API import files under this directory into the served pool
        /// (`POST /v1/scenes`, `arbor-server import --server`); without it imports are refused.
        #[arg(long)]
        import_root: Option<PathBuf>,
        /// Where live imports put their scratch files [default: the system temp dir].
        #[arg(long)]
        import_scratch: Option<PathBuf>,
        /// How live imports share the CPU with streaming: `idle` (SCHED_IDLE: only CPU time
        /// streaming leaves; clients keep their rate, an import waits on saturated cores) or
        /// `low` (nice 10: an import always progresses, streaming slows while it runs).
        #[arg(long, value_enum, default_value_t = ImportPriority::Idle)]
        import_priority: ImportPriority,
        /// Let the admin API copy the served pool into new directories under this one
        /// (`POST /v1/copies`, `arbor-server copy --server`: backups, a new replica's pool)
        /// while serving; without it copies are refused.
        #[arg(long)]
        copy_root: Option<PathBuf>,
        /// Copy every published scene under --copy-root this often (`12h`, `1d`), into
        /// `scheduled-<UTC time>`, as `copy --server` would: backups without cron. Counted
        /// from the start, unless --copy-at pins it to the clock [default: never].
        #[arg(long, value_parser = parse_period, requires = "copy_root")]
        copy_every: Option<std::time::Duration>,
        /// Make the scheduled copies at this time of day, UTC unless a time zone follows
        /// (`03:00`, `23:30:15`, `"Sun 03:00"`, `"03:00 Europe/Berlin"`), and every
        /// --copy-every before and after it (a day, a week with a weekday, if not given; the
        /// period must divide a day or be whole days, whole weeks with a weekday). In a zone,
        /// a time the clock skips runs when it jumps, one it repeats runs once.
        #[arg(long, value_parser = parse_clock_time, requires = "copy_root")]
        copy_at: Option<ClockTime>,
        /// Scheduled copies kept: once one succeeds, older `scheduled-*` directories beyond
        /// this many are removed (`0`: keep every one). Nothing else under the root is touched.
        #[arg(long, default_value_t = 7, requires = "copy_schedule")]
        copy_keep: usize,
        /// Check every published scene this often (`90s`, `30m`, `24h`, `7d`), as `verify
        /// --server` would, at the import priority: damage that appears on disk is found
        /// without anyone asking (`arbor_scene_check_ok` in /metrics). Counted from the
        /// start, unless --check-at pins it to the clock [default: never].
        #[arg(long, value_parser = parse_period)]
        check_every: Option<std::time::Duration>,
        /// Check every published scene at this time of day, UTC unless a time zone follows
        /// (`04:00`, `"Sun 04:00"`, `"04:00 America/New_York"`), and every --check-every
        /// before and after it (a day, a week with a weekday, if not given).
        #[arg(long, value_parser = parse_clock_time)]
        check_at: Option<ClockTime>,
        /// Bytes per second that checks and copies may read from the pool together (`20MB`,
        /// `512KiB`, `off`), so that they leave the disk to serving; `PUT
        /// /v1/background-reads` changes it while serving [default: off].
        #[arg(long, value_parser = parse_background_rate)]
        background_read_rate: Option<BackgroundRate>,
        /// Read the pool's files into the page cache at start, so a fresh server's reads need
        /// not wait for the disk, the pages the last run had cached first: `auto` (the whole
        /// pool when it fits in half of the memory left, else only those pages), `always`, or
        /// `off` (overrides `pool_prewarm`) [default: auto].
        #[arg(long, value_enum)]
        pool_prewarm: Option<PoolPrewarm>,
    },
}

/// `--admin ADDR|off`.
#[derive(Clone, Debug)]
struct AdminArg(Option<SocketAddr>);

fn parse_admin(s: &str) -> Result<AdminArg, String> {
    arbor_server::service::config::parse_admin_listen(s).map(AdminArg)
}

/// `--background-read-rate RATE|off`.
#[derive(Clone, Copy, Debug)]
struct BackgroundRate(Option<u64>);

fn parse_background_rate(s: &str) -> Result<BackgroundRate, String> {
    arbor_server::pace::parse_rate(s)
        .map(BackgroundRate)
        .map_err(|e| e.to_string())
}

fn parse_clock_time(s: &str) -> Result<ClockTime, String> {
    arbor_server::periodic::parse_clock_time(s).map_err(|e| e.to_string())
}

/// A period: a whole number with `s`, `m`, `h` or `d`, at least a second.
fn parse_period(s: &str) -> Result<std::time::Duration, String> {
    let bad = || format!("'{s}': expected a whole number of s, m, h or d (24h)");
    let unit = s.chars().last().ok_or_else(bad)?;
    let seconds = match unit {
        's' => 1,
        'm' => 60,
        'h' => 3_600,
        'd' => 86_400,
        _ => return Err(bad()),
    };
    let n: u64 = s[..s.len() - 1].parse().map_err(|_| bad())?;
    let total = n
        .checked_mul(seconds)
        .filter(|&t| (1..=100 * 365 * 86_400).contains(&t))
        .ok_or_else(|| format!("'{s}': a period from 1 s to 100 years"))?;
    Ok(std::time::Duration::from_secs(total))
}

fn parse_depth(s: &str) -> Result<DepthChoice, String> {
    if s.eq_ignore_ascii_case("auto") {
        return Ok(DepthChoice::Auto);
    }
    let d: u8 = s
        .parse()
        .map_err(|_| format!("'{s}' is neither a depth nor 'auto'"))?;
    if d > arbor_proto::limits::MAX_DEPTH {
        return Err(format!(
            "depth {d} exceeds the maximum {}",
            arbor_proto::limits::MAX_DEPTH
        ));
    }
    Ok(DepthChoice::Fixed(d))
}

fn parse_triple<T: std::str::FromStr>(s: &str) -> Result<[T; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(format!("'{s}': expected three comma-separated values"));
    }
    let mut out = Vec::with_capacity(3);
    for p in parts {
        out.push(
            p.parse::<T>()
                .map_err(|_| format!("'{p}' is not a valid number"))?,
        );
    }
    out.try_into().map_err(|_| "three values".to_string())
}

fn parse_dims(s: &str) -> Result<[u32; 3], String> {
    let d: [u32; 3] = parse_triple(s)?;
    if d.contains(&0) {
        return Err(format!("'{s}': dimensions must be positive"));
    }
    Ok(d)
}

fn parse_spacing(s: &str) -> Result<[f64; 3], String> {
    let d: [f64; 3] = parse_triple(s)?;
    if d.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(format!("'{s}': spacing must be finite and positive"));
    }
    Ok(d)
}

/// `writeln!` into a command's output text (a `String`: it cannot fail).
macro_rules! line {
    ($out:expr, $($arg:tt)*) => {{
        use std::fmt::Write as _;
        let _ = writeln!($out, $($arg)*);
    }};
}

/// Writes a command's output to stdout. A reader that has gone away (`| head`) ends the
/// output, not the command, and is no error: the exit status still says how the command went.
fn emit(text: &str) -> Result<()> {
    let mut out = std::io::stdout().lock();
    match out.write_all(text.as_bytes()).and_then(|()| out.flush()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        r => r.context("writing to stdout"),
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    arbor_server::logging::init(cli.log_format);
    match run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Opens an existing pool for `list`, `info` and `remove` (none is made at a mistyped path).
fn open(db: &Path) -> Result<Pool> {
    Pool::open_existing(db).with_context(|| format!("opening pool {}", db.display()))
}

fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::Import(args) => import(args),
        Command::List { db } => {
            let pool = open(&db)?;
            let mut out = String::new();
            line!(
                out,
                "{:<20} {:>6} {:>9} {:>5} {:>6} {:>9} {:>10} {:>11} {:>6} {:>8} {:>8}  channels",
                "scene",
                "kind",
                "prims",
                "depth",
                "tl KiB",
                "treelets",
                "voxels",
                "pool bytes",
                "B/vox",
                "build s",
                "RSS MiB"
            );
            for d in pool.scenes()? {
                let bytes = d.stats.stored_bytes();
                line!(
                    out,
                    "{:<20} {:>6} {:>9} {:>5} {:>6} {:>9} {:>10} {:>11} {:>6.2} {:>8.2} {:>8.1}  {}",
                    d.name,
                    format!("{:?}", d.source_kind).to_lowercase(),
                    d.primitives,
                    d.max_depth,
                    d.build.treelet_bytes / 1024,
                    d.treelet_count,
                    d.stats.voxels,
                    bytes,
                    bytes as f64 / d.stats.voxels.max(1) as f64,
                    d.stats.build_seconds,
                    d.stats.peak_rss_bytes as f64 / f64::from(1 << 20),
                    channel_names(&d)
                );
            }
            emit(&out)?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Info { db, scene } => {
            let pool = open(&db)?;
            let s = pool.scene(&scene)?;
            let mut text = info_text(&s.description, Some(pool.disk_bytes()?));
            line!(
                text,
                "log segments     {} KiB{}",
                pool.segment_bytes() >> 10,
                if pool.segment_bytes() < arbor_server::pool::POOL_SEGMENT_BYTES {
                    " (an older pool: `arbor-server copy` makes a copy that opens faster)"
                } else {
                    ""
                }
            );
            emit(&text)?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Verify {
            db,
            daemon: DaemonArgs { server, token_file },
            scene,
            quiet,
        } => {
            let bar = progress_bar(quiet, "verifying [{bar:40}] {pos}/{len} treelets");
            let r = match (db, server) {
                (_, Some(url)) => verify_remote(&url, token_file.as_deref(), &scene, &bar),
                (Some(db), None) => verify::verify_pool_scene(
                    &db,
                    &scene,
                    &verify::VerifyOptions::default(),
                    &|p| match p {
                        verify::VerifyProgress::Planned { treelets } => bar.set_length(treelets),
                        verify::VerifyProgress::Checked(n) => bar.inc(n),
                    },
                )
                .with_context(|| format!("verifying {scene} in {}", db.display())),
                (None, None) => unreachable!("clap requires --db or --server"),
            };
            bar.finish_and_clear();
            let r = r?;
            let mut out = String::new();
            line!(
                out,
                "{scene}: {} treelets, {} voxels ({} at the target depth)",
                r.treelets,
                r.voxels,
                r.leaf_voxels
            );
            let code = if r.is_ok() {
                line!(out, "ok: every invariant holds");
                ExitCode::SUCCESS
            } else {
                for p in &r.problems {
                    line!(out, "problem: {p}");
                }
                line!(out, "FAILED: {} problems", r.problem_count);
                ExitCode::from(2)
            };
            emit(&out)?;
            Ok(code)
        }
        Command::Remove { db, scene } => {
            let pool = open(&db)?;
            pool.remove(&scene)?;
            emit(&format!("removed {scene}\n"))?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Copy {
            db,
            daemon: DaemonArgs { server, token_file },
            to,
            scene,
            quiet,
        } => match (db, server) {
            (_, Some(url)) => copy_remote(&url, token_file.as_deref(), &to, &scene, quiet),
            (Some(db), None) => copy(&db, &to, &scene, quiet),
            (None, None) => unreachable!("clap requires --db or --server"),
        },
        Command::Serve {
            db,
            listen,
            admin,
            admin_tls,
            config,
            data_dir,
            import_root,
            import_scratch,
            import_priority,
            copy_root,
            copy_every,
            copy_at,
            copy_keep,
            check_every,
            check_at,
            background_read_rate,
            pool_prewarm,
        } => {
            // Refused before anything starts: a weekday with a daily period, a period that
            // would drift from the clock time.
            Schedule::new(check_every, check_at.clone()).context("--check-every/--check-at")?;
            Schedule::new(copy_every, copy_at.clone()).context("--copy-every/--copy-at")?;
            let overrides = ConfigOverrides {
                db,
                listen,
                admin_listen: admin.map(|a| a.0),
                admin_tls,
                data_dir,
                pool_prewarm,
            };
            let file = config;
            let config = ServeConfig::load(file.as_deref(), &overrides)?;
            let reload = ConfigSource { file, overrides };
            let rt = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .thread_name("arbor-serve")
                .build()
                .context("starting the tokio runtime")?;
            let options = DaemonOptions {
                import_root,
                import_scratch,
                import_priority,
                check_every,
                check_at,
                copy_root,
                copy_every,
                copy_at,
                copy_keep: std::num::NonZeroUsize::new(copy_keep),
                background_read_rate: background_read_rate.and_then(|r| r.0),
            };
            let result = rt.block_on(serve(config, options, reload));
            rt.shutdown_timeout(std::time::Duration::from_secs(1));
            result?;
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// `arbor-server import`: parse, build and commit one scene, then print its figures.
fn import(args: ImportArgs) -> Result<ExitCode> {
    if let Some(url) = &args.server {
        return import_remote(url, &args);
    }
    let ImportArgs {
        db,
        server: _,
        token_file: _,
        scene,
        depth,
        treelet_bytes,
        iso,
        format,
        raw_dims,
        raw_type,
        raw_spacing,
        raw_big_endian,
        zstd_level,
        no_dictionary,
        memory_budget_mib,
        scratch,
        replace,
        quiet,
        allow_mixed_crs,
        files,
    } = args;
    let mut files = arbor_server::import::tiles::expand_inputs(&files)?.into_iter();
    let file = files.next().context("no input file")?;
    let more_tiles: Vec<PathBuf> = files.collect();
    arbor_proto::treelet::nodes_for_bytes(treelet_bytes)?;
    if let Some(i) = iso
        && !i.is_finite()
    {
        bail!("--iso {i} is not a finite number");
    }
    let db = db.context("--db is required without --server")?;
    let pool = Pool::open(&db).with_context(|| format!("opening pool {}", db.display()))?;
    let request = SceneImport {
        name: scene,
        input: file,
        more_tiles,
        import: ImportOptions {
            format,
            raw: raw_dims.map(|dims| RawSpec {
                dims,
                sample: raw_type,
                spacing: raw_spacing,
                big_endian: raw_big_endian,
            }),
            tiles: TileOptions { allow_mixed_crs },
        },
        build: BuildOptions {
            depth,
            treelet_bytes,
            iso,
            zstd_level,
            dictionary: !no_dictionary,
            memory_budget: (memory_budget_mib as usize) << 20,
            progress: !quiet,
        },
        replace,
        scratch_parent: scratch,
    };
    let desc = import_scene(&pool, &request)?.description;
    emit(&info_text(&desc, Some(pool.disk_bytes()?)))?;
    Ok(ExitCode::SUCCESS)
}

/// `arbor-server copy`: copy the scenes, with a progress bar over their stored bytes, then
/// print what was copied.
/// A progress bar for a long command (hidden with `--quiet`); its length comes later.
/// `template` is the bar's start; elapsed time and the estimate follow.
fn progress_bar(quiet: bool, template: &str) -> indicatif::ProgressBar {
    use indicatif::{ProgressBar, ProgressStyle};
    if quiet {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::no_length();
    bar.set_style(
        ProgressStyle::with_template(&format!("{template} [{{elapsed_precise}}, eta {{eta}}]"))
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar
}

fn copy(db: &Path, to: &Path, scenes: &[String], quiet: bool) -> Result<ExitCode> {
    use arbor_server::pool::copy::{CopyOptions, CopyProgress, copy_pool};
    let bar = progress_bar(quiet, "copying [{bar:40}] {bytes}/{total_bytes}");
    let options = CopyOptions {
        scenes,
        carry_files: &arbor_server::live_copy::CARRIED_FILES,
        ..CopyOptions::default()
    };
    let report = copy_pool(db, to, &options, &|p| match p {
        CopyProgress::Planned { bytes } => bar.set_length(bytes),
        CopyProgress::Copied(n) => bar.inc(n),
    });
    bar.finish_and_clear();
    let report = report.with_context(|| format!("copying {} to {}", db.display(), to.display()))?;
    let (source_disk_bytes, reopens) = (report.source_disk_bytes, report.reopens);
    let report = CopySummary::from(report);
    let mut out = copied_lines(&report);
    line!(
        out,
        "{}: {} bytes on disk ({} in {}), written in {:.1} s, checked against the source in {:.1} s \
         (both pools opened again {} times, to bound sled's memory)",
        to.display(),
        report.disk_bytes,
        source_disk_bytes,
        db.display(),
        report.copy_seconds,
        report.check_seconds,
        reopens
    );
    emit(&out)?;
    Ok(ExitCode::SUCCESS)
}

/// `verify --server`: the check, run by the daemon on the scene it publishes; the report it
/// answers.
fn verify_remote(
    url: &admin_client::AdminUrl,
    token_file: Option<&Path>,
    scene: &str,
    bar: &indicatif::ProgressBar,
) -> Result<verify::VerifyReport> {
    let token = admin_client::token(token_file)?;
    let interrupted = ctrl_c_flag()?;
    let done = admin_client::verify(url, &token, scene, &interrupted, &|planned, checked| {
        bar.set_length(planned);
        bar.set_position(checked);
    })?;
    serde_json::from_value(done["report"].clone())
        .context("the daemon's answer has no readable report")
}

/// What a copy wrote, a line per scene and one for the carried files.
fn copied_lines(report: &CopySummary) -> String {
    let mut out = String::new();
    for s in &report.scenes {
        line!(
            out,
            "copied {}: {} packs, {} bytes",
            s.name,
            s.packs,
            s.bytes
        );
    }
    if !report.carried.is_empty() {
        line!(out, "carried {}", report.carried.join(", "));
    }
    out
}

/// A flag set once Ctrl-C is pressed (watched on a thread of its own).
fn ctrl_c_flag() -> Result<Arc<AtomicBool>> {
    let interrupted = Arc::new(AtomicBool::new(false));
    let flag = interrupted.clone();
    let signals = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the Ctrl-C watcher")?;
    std::thread::spawn(move || {
        signals.block_on(async {
            if tokio::signal::ctrl_c().await.is_ok() {
                flag.store(true, Ordering::Relaxed);
            }
        })
    });
    Ok(interrupted)
}

/// `copy --server`: the daemon copies the pool it serves into `to` under its copy root.
fn copy_remote(
    url: &admin_client::AdminUrl,
    token_file: Option<&Path>,
    to: &Path,
    scenes: &[String],
    quiet: bool,
) -> Result<ExitCode> {
    let to = to
        .to_str()
        .filter(|t| arbor_server::live_copy::validate_destination(t).is_ok())
        .with_context(|| {
            format!(
                "--to {}: with --server, a directory name under the daemon's --copy-root \
                 (letters, digits, '-', '_', '.'; not starting with '.')",
                to.display()
            )
        })?;
    let token = admin_client::token(token_file)?;
    let interrupted = ctrl_c_flag()?;
    let bar = progress_bar(quiet, "copying [{bar:40}] {bytes}/{total_bytes}");
    let done = admin_client::copy(url, &token, to, scenes, &interrupted, &|planned, copied| {
        bar.set_length(planned);
        bar.set_position(copied);
    });
    bar.finish_and_clear();
    let done = done?;
    let report: CopySummary = serde_json::from_value(done["report"].clone())
        .context("the daemon's answer has no readable report")?;
    let mut out = copied_lines(&report);
    line!(
        out,
        "{}: {} bytes on disk, written in {:.1} s, checked against the served pool in {:.1} s",
        done["path"].as_str().unwrap_or(to),
        report.disk_bytes,
        report.copy_seconds,
        report.check_seconds
    );
    emit(&out)?;
    Ok(ExitCode::SUCCESS)
}

/// `import --server`: the same import, run by a daemon on files under its import root.
fn import_remote(url: &admin_client::AdminUrl, args: &ImportArgs) -> Result<ExitCode> {
    let token = admin_client::token(args.token_file.as_deref())?;
    let depth = match args.depth {
        DepthChoice::Auto => serde_json::json!("auto"),
        DepthChoice::Fixed(d) => serde_json::json!(d),
    };
    let inputs: Vec<String> = args.files.iter().map(|p| p.display().to_string()).collect();
    let job = serde_json::json!({
        "scene": args.scene,
        "inputs": inputs,
        "replace": args.replace,
        "depth": depth,
        "treelet_bytes": args.treelet_bytes,
        "iso": args.iso,
        "memory_budget_mib": args.memory_budget_mib,
        "allow_mixed_crs": args.allow_mixed_crs,
    });
    let done = admin_client::import(url, &token, &job)?;
    let mut out = String::new();
    line!(
        out,
        "imported {}: {} treelets, {} voxels, {} primitives in {:.1} s",
        args.scene,
        done["treelets"],
        done["voxels"],
        done["primitives"],
        done["seconds"].as_f64().unwrap_or(0.0)
    );
    emit(&out)?;
    Ok(ExitCode::SUCCESS)
}

/// Where `serve`'s configuration came from, to read it again on SIGHUP.
struct ConfigSource {
    file: Option<PathBuf>,
    overrides: ConfigOverrides,
}

impl ConfigSource {
    /// What a reload of `file` reads now (the configuration and the files it names).
    fn snapshot(&self, file: &Path, data_dir: &Path) -> ConfigSnapshot {
        ConfigSnapshot::read(file, &self.overrides, data_dir)
    }

    /// Puts `now`'s scene rules, certificates and admin tokens in force
    /// ([`arbor_server::daemon::Reloader`]); a configuration that does not load leaves
    /// everything as it was. Other changed settings are named: they apply at the next start.
    /// `why` (SIGHUP, a change seen) starts every log line.
    fn reload(
        why: &str,
        file: &Path,
        now: &ConfigSnapshot,
        running: &ServeConfig,
        reloader: &arbor_server::daemon::Reloader,
    ) {
        let loaded = match now.config() {
            Ok(config) => reloader
                .reload(config)
                .map(|done| (config, done))
                .map_err(|e| e.to_string()),
            Err(e) => {
                reloader.record_unloadable();
                Err(e.to_owned())
            }
        };
        let (config, done) = match loaded {
            Ok(c) => c,
            Err(e) => {
                tracing::error!(
                    config = %file.display(),
                    "{why}: the configuration does not load, nothing changes: {e}"
                );
                return;
            }
        };
        tracing::info!(
            config = %file.display(),
            scenes = config.scenes.len(),
            sessions_closed = done.sessions.shut_out,
            sessions_kept = done.sessions.kept,
            fingerprint = %done.fingerprint,
            "{why}: scene rules, certificates and admin tokens read again and in force"
        );
        if done.certificate_changed {
            tracing::warn!(
                fingerprint = %done.fingerprint,
                "{why}: a new certificate is presented to QUIC clients from now on; open \
                 sessions go on, and clients that pin the old fingerprint are refused"
            );
        }
        if done.admin_certificate_changed {
            tracing::info!("{why}: the admin listener presents a new certificate");
        }
        if done.admin_token_changed {
            tracing::info!("{why}: the admin token changed; the old one is refused");
        }
        let mut rest = config.clone();
        rest.scenes = running.scenes.clone();
        rest.default_access = running.default_access;
        rest.tls = running.tls.clone();
        rest.admin_identity = running.admin_identity.clone();
        rest.admin_token = running.admin_token.clone();
        rest.probe_token = running.probe_token.clone();
        if rest != *running {
            tracing::warn!(
                config = %file.display(),
                "{why}: settings other than the scene rules, certificates and admin tokens \
                 changed; they apply at the next start"
            );
        }
    }
}

/// Runs the service until SIGINT or SIGTERM, then shuts it down gracefully; on SIGHUP, and when
/// `config_watch_secs` finds the files changed, it reads the scene rules, certificates and admin
/// tokens again ([`ConfigSource::reload`]).
async fn serve(config: ServeConfig, options: DaemonOptions, source: ConfigSource) -> Result<()> {
    use tokio::signal::unix::{SignalKind, signal};
    if !config.transparent_huge_pages {
        // Process-wide, before the service allocates its caches: the allocator's requests for
        // huge pages are then ignored (`transparent_huge_pages` in the config).
        if let Err(e) = rustix::thread::disable_transparent_huge_pages(true) {
            tracing::warn!("could not turn transparent huge pages off: {e}");
        }
    }
    // Handlers first, so a signal that arrives right after the addresses are printed is not lost.
    let mut term = signal(SignalKind::terminate()).context("installing the SIGTERM handler")?;
    let mut int = signal(SignalKind::interrupt()).context("installing the SIGINT handler")?;
    let mut hup = signal(SignalKind::hangup()).context("installing the SIGHUP handler")?;
    let running = config.clone();
    let data_dir = running.data_dir().to_path_buf();
    // What the start reads, taken before it: a change in between is seen at the first look.
    let (mut watch, mut looks) = match &source.file {
        Some(file) if running.config_watch_secs > 0 => {
            let mut looks =
                tokio::time::interval(std::time::Duration::from_secs(running.config_watch_secs));
            looks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            let watch = ConfigWatch::new(source.snapshot(file, &data_dir));
            (Some((watch, file)), Some(looks))
        }
        _ => (None, None),
    };
    let server = arbor_server::daemon::start_with(config, options).await?;
    announce(&server);
    let reloader = server.reloader();
    let trigger = server.shutdown_trigger();
    let mut stopped = std::pin::pin!(server.wait());
    let signal = loop {
        tokio::select! {
            _ = term.recv() => break "SIGTERM",
            _ = int.recv() => break "SIGINT",
            _ = hup.recv() => match &source.file {
                None => tracing::warn!("SIGHUP: no --config file to read again; nothing changes"),
                Some(file) => {
                    let now = source.snapshot(file, &data_dir);
                    ConfigSource::reload("SIGHUP", file, &now, &running, &reloader);
                    if let Some((watch, _)) = &mut watch {
                        watch.reloaded(now);
                    }
                }
            },
            () = next_look(&mut looks) => {
                if let Some((watch, file)) = &mut watch
                    && watch.observe(source.snapshot(file, &data_dir))
                {
                    let now = watch.applied();
                    ConfigSource::reload("configuration changed", file, now, &running, &reloader);
                }
            }
            () = &mut stopped => bail!("the service stopped on its own"),
        }
    };
    tracing::info!("{signal}: shutting down gracefully");
    trigger.trigger();
    stopped.await;
    Ok(())
}

/// The next look at the configuration's files; never, without `config_watch_secs`.
async fn next_look(looks: &mut Option<tokio::time::Interval>) {
    match looks {
        Some(looks) => {
            looks.tick().await;
        }
        None => std::future::pending().await,
    }
}

/// Prints the serving lines on stdout (see `serve --help`) in one write, so that a reader
/// that stops at the line it wanted (a script, a test harness) cannot close the pipe between
/// two of them. The service is up by then: if stdout is gone it goes on serving, with a
/// warning in the log, rather than stopping for want of an audience.
fn announce(server: &arbor_server::daemon::RunningServer) {
    use std::fmt::Write as _;
    let mut lines = String::new();
    let _ = writeln!(lines, "quic {}", server.quic_addr);
    let _ = match server.admin_addr {
        Some(a) => writeln!(lines, "admin {a}"),
        None => writeln!(lines, "admin off"),
    };
    let _ = writeln!(lines, "fingerprint {}", server.fingerprint);
    let _ = match &server.admin_token_origin {
        AdminTokenOrigin::Config => writeln!(lines, "admin-token config"),
        AdminTokenOrigin::File(p) | AdminTokenOrigin::Generated { path: p, .. } => {
            writeln!(lines, "admin-token-file {}", p.display())
        }
    };
    let mut out = std::io::stdout().lock();
    if let Err(e) = out.write_all(lines.as_bytes()).and_then(|()| out.flush()) {
        tracing::warn!("could not print the serving lines on stdout ({e}); serving on");
    }
}

fn channel_names(d: &arbor_proto::SceneDescription) -> String {
    d.layout
        .channels()
        .iter()
        .map(|c| c.name())
        .collect::<Vec<_>>()
        .join(",")
}

fn info_text(d: &arbor_proto::SceneDescription, disk: Option<u64>) -> String {
    let mut out = String::new();
    let s = &d.stats;
    let pool_bytes = s.stored_bytes();
    line!(out, "scene            {}", d.name);
    line!(out, "source           {}", d.source);
    line!(
        out,
        "kind             {:?}, {} primitives",
        d.source_kind,
        d.primitives
    );
    line!(
        out,
        "depth            {} ({}), data resolution {:.6}",
        d.max_depth,
        match d.build.requested_depth {
            Some(_) => "fixed",
            None => "auto",
        },
        d.build.data_resolution
    );
    line!(
        out,
        "root cube        origin {:?}, edge {}",
        d.origin,
        d.edge
    );
    line!(
        out,
        "treelets         {} of {} bytes ({} nodes)",
        d.treelet_count,
        d.build.treelet_bytes,
        d.treelet_nodes
    );
    line!(
        out,
        "voxels           {} ({} at the target depth)",
        s.voxels,
        s.leaf_voxels
    );
    line!(out, "channels         {}", channel_names(d));
    if let Some(iso) = d.build.iso {
        line!(out, "iso threshold    {iso}");
    }
    line!(
        out,
        "bytes            {} compressed ({} nodes + {:?} channels), {} raw, {:.2} bytes/voxel",
        pool_bytes,
        s.node_bytes,
        s.channel_bytes,
        s.raw_bytes,
        pool_bytes as f64 / s.voxels.max(1) as f64
    );
    line!(
        out,
        "compression      zstd level {}, dictionaries {}",
        d.build.zstd_level,
        if d.build.dictionary { "yes" } else { "no" }
    );
    let mib = |b: u64| b as f64 / f64::from(1 << 20);
    line!(
        out,
        "build            {:.2} s, peak RSS {:.1} MiB ({:.1} MiB anonymous), id lists peak {:.1} MiB, spilled {:.1} MiB",
        s.build_seconds,
        mib(s.peak_rss_bytes),
        mib(s.peak_anon_bytes),
        mib(s.peak_list_bytes),
        mib(s.spilled_bytes)
    );
    if let Some(b) = disk {
        line!(out, "pool on disk     {b} bytes (whole database)");
    }
    out
}
