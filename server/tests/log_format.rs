//! The real `arbor-server serve` binary's log lines on a pipe: plain text without a single ANSI
//! escape by default, one JSON object per line with `--log-format json`.

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
