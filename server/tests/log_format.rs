//! The real `arbor-server serve` binary's log lines on a pipe: plain text without a single ANSI
//! escape by default, one JSON object per line with `--log-format json`; and a warning an
//! operator needs at start (a scheduled copy named in the future).

use std::io::{BufRead as _, BufReader, Read as _};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

const BIN: &str = env!("CARGO_BIN_EXE_arbor-server");

/// Serves an empty pool with `extra` arguments and stderr on a pipe until it has printed its
/// addresses, stops it with SIGTERM and returns everything it logged.
fn serve_and_collect_log(extra: &[&str]) -> String {
    let dir = tempfile::tempdir().unwrap();
    // An empty pool is enough to serve.
    drop(arbor_server::pool::Pool::open(&dir.path().join("pool")).unwrap());
    let mut child = Command::new(BIN)
        .args(extra)
        .args(["serve", "--db"])
        .arg(dir.path().join("pool"))
        .args(["--listen", "127.0.0.1:0", "--admin", "off", "--data-dir"])
        .arg(dir.path().join("state"))
        .env("RUST_LOG", "info")
        .env_remove("NO_COLOR")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    loop {
        let line = rx
            .recv_timeout(Duration::from_secs(30))
            .expect("serve printed its fingerprint line");
        if line.starts_with("fingerprint ") {
            break;
        }
    }
    let ok = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -TERM");
    let mut log = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut log)
        .unwrap();
    let status = child.wait().unwrap();
    assert!(status.success(), "serve exited with {status}; log:\n{log}");
    log
}

#[test]
fn text_logs_on_a_pipe_have_no_colour_codes() {
    let log = serve_and_collect_log(&[]);
    assert!(
        log.lines().any(|l| l.contains("INFO")),
        "expected info lines, got:\n{log}"
    );
    assert!(
        !log.contains('\x1b'),
        "ANSI escape sequences in a log written to a pipe:\n{log:?}"
    );
}

#[test]
fn json_logs_are_one_object_per_line() {
    let log = serve_and_collect_log(&["--log-format", "json"]);
    let lines: Vec<&str> = log.lines().filter(|l| !l.trim().is_empty()).collect();
    assert!(lines.len() >= 2, "expected log lines, got:\n{log}");
    for line in &lines {
        let value: serde_json::Value = serde_json::from_str(line)
            .unwrap_or_else(|e| panic!("not a JSON object ({e}): {line}"));
        let object = value.as_object().expect("a JSON object per line");
        for key in ["timestamp", "level", "target"] {
            assert!(object.contains_key(key), "no `{key}` in {line}");
        }
        assert!(!line.contains('\x1b'), "escape sequence in {line:?}");
    }
    assert!(
        lines.iter().any(|l| l.contains("\"message\"")),
        "no event carried a message:\n{log}"
    );
}

/// A scheduled copy named after now under the copy root (a clock set back, a directory brought
/// in by hand) keeps the daemon from making up a missed copy at start; it says so, naming the
/// time.
#[test]
fn a_scheduled_copy_named_in_the_future_is_warned_of_at_start() {
    let dir = tempfile::tempdir().unwrap();
    drop(arbor_server::pool::Pool::open(&dir.path().join("pool")).unwrap());
    let root = dir.path().join("copies");
    std::fs::create_dir_all(root.join("scheduled-2099-01-01T030000Z")).unwrap();
    let mut child = Command::new(BIN)
        .args(["serve", "--db"])
        .arg(dir.path().join("pool"))
        .args(["--listen", "127.0.0.1:0", "--admin", "off", "--data-dir"])
        .arg(dir.path().join("state"))
        .arg("--copy-root")
        .arg(&root)
        .args(["--copy-at", "03:00"])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let mut log = Vec::new();
    let warning = loop {
        match rx.recv_timeout(Duration::from_secs(30)) {
            Ok(line) if line.contains("later than now") => break line,
            Ok(line) => log.push(line),
            Err(_) => {
                let _ = child.kill();
                panic!(
                    "no warning of the future copy; the log:\n{}",
                    log.join("\n")
                );
            }
        }
    };
    assert!(warning.contains("WARN"), "{warning}");
    assert!(warning.contains("2099-01-01 03:00:00 UTC"), "{warning}");
    let ok = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -TERM");
    assert!(child.wait().unwrap().success());
}
