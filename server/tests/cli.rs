//! The `arbor-server` binary, run as a user would: import/list/info/verify/remove on a real scan,
//! every bad input of the corpus through the CLI (clear message, non-zero exit, no panic, pool
//! untouched), and imports killed with SIGKILL at many points (scene absent or complete, their
//! scratch directories removed by the next import).

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use arbor_server::pool::Pool;

#[path = "../../tests/src/corpus.rs"]
mod corpus;

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_arbor-server"));
    c.env("RUST_LOG", "warn");
    c
}

fn data(rel: &str) -> PathBuf {
    let p = corpus::data_dir().join(rel);
    assert!(p.exists(), "real scan {} missing", p.display());
    p
}

fn run(args: &[&str]) -> Output {
    bin().args(args).output().expect("running arbor-server")
}

fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn ok(args: &[&str]) -> String {
    let o = run(args);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{args:?} failed: {err}\n{out}");
    out
}

/// Runs with stdout a pipe whose reader is gone before anything is written.
fn with_stdout_closed(args: &[&str]) -> Output {
    let mut child = bin()
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("running arbor-server");
    drop(child.stdout.take());
    child.wait_with_output().unwrap()
}

/// What a server serving `db` logs at warning level until it serves; then it is stopped.
fn serve_log(db: &Path, data_dir: &Path) -> String {
    use std::io::BufRead as _;
    let mut child = bin()
        .args(["serve", "--listen", "127.0.0.1:0", "--admin", "off", "--db"])
        .arg(db)
        .arg("--data-dir")
        .arg(data_dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("running arbor-server serve");
    let mut lines = std::io::BufReader::new(child.stdout.take().unwrap()).lines();
    let serving = lines.any(|l| l.is_ok_and(|l| l.starts_with("quic ")));
    child.kill().unwrap();
    let out = child.wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(serving, "the server did not serve: {log}");
    log
}

fn db_arg(dir: &Path) -> String {
    dir.to_str().unwrap().to_owned()
}

#[test]
fn import_list_info_verify_remove() {
    let dir = tempfile::tempdir().unwrap();
    let db = db_arg(dir.path());
    let bunny = data("meshes/stanford-bunny.obj");
    let bunny = bunny.to_str().unwrap();
    let out = ok(&["import", "--db", &db, "--scene", "bunny", "--quiet", bunny]);
    assert!(out.contains("69451 primitives"), "{out}");
    assert!(out.contains("(auto)"), "{out}");
    let list = ok(&["list", "--db", &db]);
    assert!(
        list.lines()
            .any(|l| l.starts_with("bunny ") && l.contains("mesh") && l.contains("normal")),
        "{list}"
    );
    let info = ok(&["info", "--db", &db, "--scene", "bunny"]);
    for field in [
        "treelets",
        "voxels",
        "bytes/voxel",
        "build",
        "peak RSS",
        "channels         normal",
    ] {
        assert!(info.contains(field), "info lacks {field}: {info}");
    }
    let v = ok(&["verify", "--db", &db, "--scene", "bunny"]);
    assert!(v.contains("ok: every invariant holds"), "{v}");
    // A reader that leaves at once (`| head -0`) ends the output, not the command.
    for args in [
        &["list", "--db", &db][..],
        &["info", "--db", &db, "--scene", "bunny"],
        &["verify", "--db", &db, "--scene", "bunny"],
    ] {
        let o = with_stdout_closed(args);
        let err = text(&o).1;
        assert!(
            o.status.success() && !err.contains("panicked"),
            "{args:?}: {err}"
        );
    }
    // A second import of the same name is refused, --replace is accepted.
    let o = run(&["import", "--db", &db, "--scene", "bunny", "--quiet", bunny]);
    assert!(!o.status.success());
    assert!(text(&o).1.contains("already exists"), "{}", text(&o).1);
    ok(&[
        "import",
        "--db",
        &db,
        "--scene",
        "bunny",
        "--quiet",
        "--replace",
        "--treelet-bytes",
        "1024",
        bunny,
    ]);
    assert!(ok(&["info", "--db", &db, "--scene", "bunny"]).contains("of 1024 bytes"));
    ok(&["remove", "--db", &db, "--scene", "bunny"]);
    let o = run(&["info", "--db", &db, "--scene", "bunny"]);
    assert!(!o.status.success());
    assert!(
        text(&o).1.contains("no scene named \"bunny\""),
        "{}",
        text(&o).1
    );
    // A mistyped pool path is named, and nothing is made there: only import and serve make
    // pools.
    let missing = dir.path().join("mistyped");
    let missing_arg = db_arg(&missing);
    for args in [
        &["list", "--db", &missing_arg][..],
        &["info", "--db", &missing_arg, "--scene", "bunny"],
        &["verify", "--db", &missing_arg, "--scene", "bunny"],
        &["remove", "--db", &missing_arg, "--scene", "bunny"],
    ] {
        let o = run(args);
        let err = text(&o).1;
        assert!(!o.status.success(), "{args:?} accepted");
        assert!(err.contains("is not a pool directory"), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
        assert!(!missing.exists(), "{args:?} made a pool at a mistyped path");
    }
}

#[test]
fn help_has_examples_and_bad_parameters_are_named() {
    let h = ok(&["--help"]);
    assert!(h.contains("Examples:") && h.contains("import --db"), "{h}");
    let h = ok(&["import", "--help"]);
    assert!(h.contains("--depth") && h.contains("Examples:"), "{h}");
    let dir = tempfile::tempdir().unwrap();
    let db = db_arg(dir.path());
    let bunny = data("meshes/stanford-bunny.obj");
    for (args, needle) in [
        (vec!["--depth", "99"], "depth 99 exceeds"),
        (vec!["--depth", "deep"], "neither a depth nor 'auto'"),
        (vec!["--treelet-bytes", "100"], "treelet size"),
        (vec!["--treelet-bytes", "1000000"], "treelet size"),
        (vec!["--iso", "NaN"], "not a finite number"),
        (vec!["--raw-dims", "0,1,2"], "dimensions must be positive"),
        (vec!["--zstd-level", "99"], "zstd-level"),
    ] {
        let mut a = vec!["import", "--db", &db, "--scene", "x", "--quiet"];
        a.extend(args.iter());
        a.push(bunny.to_str().unwrap());
        let o = run(&a);
        let (_, err) = text(&o);
        assert!(!o.status.success(), "{args:?} accepted");
        assert!(err.contains(needle), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    let o = run(&[
        "import",
        "--db",
        &db,
        "--scene",
        "../evil",
        "--quiet",
        bunny.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(text(&o).1.contains("scene name"), "{}", text(&o).1);
    let h = ok(&["serve", "--help"]);
    assert!(h.contains("--check-every 24h"), "{h}");
    for (period, needle) in [
        ("24", "expected a whole number of s, m, h or d"),
        ("1.5h", "expected a whole number"),
        ("0s", "from 1 s to 100 years"),
        ("999999999999d", "from 1 s to 100 years"),
    ] {
        let o = run(&["serve", "--db", &db, "--check-every", period]);
        let (_, err) = text(&o);
        assert!(!o.status.success(), "--check-every {period} accepted");
        assert!(err.contains(needle), "{period}: {err}");
    }
    // Scheduled copies need a root; the number kept needs a schedule.
    assert!(h.contains("--copy-every 1d --copy-keep 7"), "{h}");
    for args in [
        &["--copy-every", "1d"][..],
        &["--copy-root", "x", "--copy-keep", "3"][..],
        &["--copy-root", "x", "--copy-every", "0s"][..],
    ] {
        let o = run(&[&["serve", "--db", &db][..], args].concat());
        let (_, err) = text(&o);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains("--copy-"), "{args:?}: {err}");
    }
    // Schedules pinned to the clock: times read or named, drifting periods refused before
    // serving, the number kept accepted with a clock time alone.
    assert!(h.contains("--copy-at 03:00"), "{h}");
    assert!(h.contains("--check-at \"Sun 04:00\""), "{h}");
    assert!(h.contains("--copy-at \"03:00 Europe/Berlin\""), "{h}");
    for (args, code, needle) in [
        (&["--check-at", "25:00"][..], 2, "expected a time of day"),
        (
            &["--check-at", "03:00 Mars/Olympus"][..],
            2,
            "'Mars/Olympus' is not a time zone",
        ),
        (
            &[
                "--copy-root",
                "x",
                "--copy-at",
                "03:00 Europe/Berlin",
                "--copy-every",
                "7h",
            ][..],
            1,
            "cannot keep the time 03:00 Europe/Berlin",
        ),
        (&["--copy-at", "03:00"][..], 2, "--copy-root"),
        (
            &["--check-at", "Sun 04:00", "--check-every", "1d"][..],
            1,
            "whole weeks",
        ),
        (
            &[
                "--copy-root",
                "x",
                "--copy-at",
                "03:00",
                "--copy-every",
                "7h",
            ][..],
            1,
            "must divide a day",
        ),
        (
            &[
                "--copy-root",
                "no-such-root",
                "--copy-at",
                "03:00",
                "--copy-keep",
                "3",
            ][..],
            1,
            "no-such-root",
        ),
    ] {
        let o = run(&[&["serve", "--db", &db][..], args].concat());
        let (_, err) = text(&o);
        assert_eq!(o.status.code(), Some(code), "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {err}");
    }
    // The background read rate: units read, absurd rates named.
    assert!(h.contains("--background-read-rate 20MB"), "{h}");
    for (rate, needle) in [
        ("fast", "expected a rate such as 20MB"),
        ("1.5MB", "expected a rate such as 20MB"),
        ("0", "outside 1 kB/s to 1 TB/s"),
        ("5000GB", "outside 1 kB/s to 1 TB/s"),
    ] {
        let o = run(&["serve", "--db", &db, "--background-read-rate", rate]);
        let (_, err) = text(&o);
        assert!(
            !o.status.success(),
            "--background-read-rate {rate} accepted"
        );
        assert!(err.contains(needle), "{rate}: {err}");
    }
    // Copies: a copy root that cannot be read is named before anything serves; `copy` needs a
    // source; `--to` with `--server` is a plain name, refused before any request.
    assert!(h.contains("--copy-root"), "{h}");
    let missing = dir.path().join("no-such-root");
    let o = run(&[
        "serve",
        "--db",
        &db,
        "--listen",
        "127.0.0.1:0",
        "--admin",
        "off",
        "--copy-root",
        missing.to_str().unwrap(),
    ]);
    let (_, err) = text(&o);
    assert!(!o.status.success() && err.contains("--copy-root"), "{err}");
    let o = run(&["copy", "--to", "x"]);
    assert!(
        !o.status.success() && text(&o).1.contains("--db"),
        "{}",
        text(&o).1
    );
    for to in ["../up", "a/b", ".hidden"] {
        let o = run(&["copy", "--server", "http://127.0.0.1:9", "--to", to]);
        let (_, err) = text(&o);
        assert_eq!(o.status.code(), Some(1), "{to}: {err}");
        assert!(
            err.contains("a directory name under the daemon's --copy-root"),
            "{to}: {err}"
        );
    }
}

#[test]
fn bad_inputs_fail_cleanly_and_leave_the_pool_untouched() {
    let dir = tempfile::tempdir().unwrap();
    let db = db_arg(dir.path());
    let bunny = data("meshes/stanford-bunny.obj");
    ok(&[
        "import",
        "--db",
        &db,
        "--scene",
        "good",
        "--quiet",
        "--depth",
        "5",
        bunny.to_str().unwrap(),
    ]);
    let before = ok(&["list", "--db", &db]);
    let files = tempfile::tempdir().unwrap();
    let cases = corpus::bad_inputs();
    assert!(cases.len() >= 20);
    let mut failures = Vec::new();
    for case in &cases {
        let path = files.path().join(&case.file_name);
        std::fs::write(&path, &case.bytes).unwrap();
        let mut args: Vec<String> = ["import", "--db", &db, "--scene", "bad", "--quiet"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        if let Some(r) = &case.raw {
            args.push(format!(
                "--raw-dims={},{},{}",
                r.dims[0], r.dims[1], r.dims[2]
            ));
            args.push(format!("--raw-type={}", r.sample.name()));
            args.push(format!(
                "--raw-spacing={},{},{}",
                r.spacing[0], r.spacing[1], r.spacing[2]
            ));
            if r.big_endian {
                args.push("--raw-big-endian".into());
            }
        }
        args.push(path.to_str().unwrap().to_owned());
        let o = bin().args(&args).output().unwrap();
        let (_, err) = text(&o);
        if o.status.success() {
            failures.push(format!("{}: accepted", case.name));
        } else if o.status.code() != Some(1) {
            failures.push(format!(
                "{}: exit {:?} (killed or panicked?)",
                case.name, o.status
            ));
        } else if err.contains("panicked") {
            failures.push(format!("{}: panicked: {err}", case.name));
        } else if !err.to_lowercase().contains(&case.expect.to_lowercase()) {
            failures.push(format!(
                "{}: message lacks {:?}: {err}",
                case.name, case.expect
            ));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} cases:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
    assert_eq!(
        ok(&["list", "--db", &db]),
        before,
        "a failed import changed the pool"
    );
    assert!(ok(&["verify", "--db", &db, "--scene", "good"]).contains("ok"));
    let pool = Pool::open(dir.path()).unwrap();
    assert_eq!(
        pool.stored_generations().len(),
        1,
        "a failed import left trees behind"
    );
}

/// `copy`: a new pool with the same scenes, the server's state files carried but not its list
/// of hot pages (it names the old file's pages); an existing destination and a pool in use by
/// another process are refused by name.
#[test]
fn copy_makes_a_new_pool_and_refuses_what_it_must_not_touch() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("pool");
    let (db_s, to) = (db_arg(&db), dir.path().join("copy"));
    let to_s = db_arg(&to);
    let bunny = data("meshes/stanford-bunny.obj");
    let bunny = bunny.to_str().unwrap();
    // A pool as made before 8 MiB segments: sled's defaults.
    drop(sled::open(&db).unwrap());
    ok(&[
        "import", "--db", &db_s, "--scene", "bunny", "--quiet", "--depth", "5", bunny,
    ]);
    for f in [
        "cert.pem",
        "key.pem",
        "admin-token",
        "path-memory.json",
        "pool-hot-pages.json",
    ] {
        std::fs::write(db.join(f), f).unwrap();
    }
    let out = ok(&["copy", "--db", &db_s, "--to", &to_s, "--quiet"]);
    assert!(out.contains("copied bunny: "), "{out}");
    assert!(
        out.contains("carried cert.pem, key.pem, admin-token, path-memory.json"),
        "{out}"
    );
    assert!(out.contains("checked against the source"), "{out}");
    assert!(!to.join("pool-hot-pages.json").exists());
    assert_eq!(
        std::fs::read_to_string(to.join("key.pem")).unwrap(),
        "key.pem"
    );
    let v = ok(&["verify", "--db", &to_s, "--scene", "bunny"]);
    assert!(v.contains("ok: every invariant holds"), "{v}");
    // `info` and a server's log tell an older pool from its copy.
    let older = ok(&["info", "--db", &db_s, "--scene", "bunny"]);
    assert!(
        older.contains("log segments     512 KiB (an older pool: `arbor-server copy`"),
        "{older}"
    );
    let copied = ok(&["info", "--db", &to_s, "--scene", "bunny"]);
    assert!(copied.contains("log segments     8192 KiB\n"), "{copied}");
    let log = serve_log(&db, &dir.path().join("state-old"));
    assert!(
        log.contains("small log segments") && log.contains("arbor-server copy --db POOL --to NEW"),
        "{log}"
    );
    let log = serve_log(&to, &dir.path().join("state-new"));
    assert!(!log.contains("small log segments"), "{log}");
    assert_eq!(
        ok(&["info", "--db", &to_s, "--scene", "bunny"])
            .lines()
            .nth(3),
        ok(&["info", "--db", &db_s, "--scene", "bunny"])
            .lines()
            .nth(3),
        "the same scene"
    );

    let o = run(&["copy", "--db", &db_s, "--to", &to_s]);
    assert!(!o.status.success());
    assert!(text(&o).1.contains("already exists"), "{}", text(&o).1);
    // A source that is no pool is named, and not created.
    let missing = dir.path().join("no-pool");
    let o = run(&[
        "copy",
        "--db",
        &db_arg(&missing),
        "--to",
        &db_arg(&dir.path().join("c2")),
    ]);
    assert!(!o.status.success());
    assert!(
        text(&o).1.contains("is not a pool directory"),
        "{}",
        text(&o).1
    );
    assert!(!missing.exists() && !dir.path().join("c2").exists());

    let held = Pool::open(&db).unwrap();
    let elsewhere = db_arg(&dir.path().join("elsewhere"));
    let o = run(&["copy", "--db", &db_s, "--to", &elsewhere]);
    let err = text(&o).1;
    assert!(!o.status.success());
    assert!(err.contains("in use by another process"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    drop(held);
}

#[test]
fn sigkill_mid_import_leaves_no_half_scene() {
    let dir = tempfile::tempdir().unwrap();
    let db = db_arg(dir.path());
    let bunny = data("meshes/stanford-bunny.obj");
    ok(&[
        "import",
        "--db",
        &db,
        "--scene",
        "good",
        "--quiet",
        "--depth",
        "5",
        bunny.to_str().unwrap(),
    ]);
    let lion = data("points/lion_takanawa.copc.laz");
    // The imports' scratch directories, to see what the killed ones leave.
    let scratch = dir.path().join("scratch");
    std::fs::create_dir(&scratch).unwrap();
    let scratch_dirs = || {
        std::fs::read_dir(&scratch)
            .unwrap()
            .filter(|e| {
                let e = e.as_ref().unwrap();
                e.file_name()
                    .to_string_lossy()
                    .starts_with(arbor_server::scratch::SCRATCH_PREFIX)
            })
            .count()
    };
    let import = |name: &str| {
        bin()
            .args([
                "import",
                "--db",
                &db,
                "--scene",
                name,
                "--quiet",
                "--treelet-bytes",
                "1024",
                "--scratch",
                scratch.to_str().unwrap(),
            ])
            .arg(&lion)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap()
    };
    // How long a whole import takes here, to spread the kills over it.
    let t = Instant::now();
    assert!(import("timing").wait().unwrap().success());
    let full = t.elapsed();
    ok(&["remove", "--db", &db, "--scene", "timing"]);
    let mut killed_mid_way = 0;
    for k in 0..8u32 {
        let name = format!("killed{k}");
        let mut child = import(&name);
        std::thread::sleep(full.mul_f64(f64::from(k) / 8.0 + 0.02));
        if child.try_wait().unwrap().is_none() {
            killed_mid_way += 1;
        }
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        let list = ok(&["list", "--db", &db]);
        assert!(list.contains("good "), "{list}");
        for line in list.lines().skip(1) {
            let scene = line.split_whitespace().next().unwrap();
            let v = ok(&["verify", "--db", &db, "--scene", scene]);
            assert!(
                v.contains("ok: every invariant holds"),
                "{scene} after kill {k}: {v}"
            );
        }
        if list.contains(&format!("{name} ")) {
            ok(&["remove", "--db", &db, "--scene", &name]);
        }
    }
    assert!(
        killed_mid_way >= 4,
        "only {killed_mid_way} kills landed during an import"
    );
    // A killed import cannot remove its scratch directory; the next import removes it.
    assert!(
        scratch_dirs() <= 1,
        "{} scratch directories of killed imports left: each import removes the earlier ones",
        scratch_dirs()
    );
    assert!(import("after").wait().unwrap().success());
    assert_eq!(scratch_dirs(), 0, "no scratch directory left");
    ok(&["remove", "--db", &db, "--scene", "after"]);
    // Reopened after the kills: only the surviving scene's trees remain on disk.
    let deadline = Instant::now() + Duration::from_secs(10);
    let pool = loop {
        match Pool::open(dir.path()) {
            Ok(p) => break p,
            Err(e) if Instant::now() > deadline => panic!("{e}"),
            Err(_) => std::thread::sleep(Duration::from_millis(50)),
        }
    };
    assert_eq!(
        pool.stored_generations(),
        vec![pool.scene("good").unwrap().generation]
    );
}
