//! The real `arbor-server serve` binary's log lines on a pipe: plain text without a single ANSI
//! escape by default, one JSON object per line with `--log-format json`; and a warning an
//! operator needs at start (a scheduled copy named in the future).

use std::io::{BufRead as _, BufReader, Read};
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

const BIN: &str = env!("CARGO_BIN_EXE_arbor-server");

/// `arbor-server [global] serve … [serve_args]` on an empty pool in `dir`, logging at info.
fn serve_command(dir: &Path, global: &[&str], serve_args: &[&str]) -> Command {
    // An empty pool is enough to serve.
    drop(arbor_server::pool::Pool::open(&dir.join("pool")).unwrap());
    let mut command = Command::new(BIN);
    command
        .args(global)
        .args(["serve", "--db"])
        .arg(dir.join("pool"))
        .args(["--listen", "127.0.0.1:0", "--admin", "off", "--data-dir"])
        .arg(dir.join("state"))
        .args(serve_args)
        .env("RUST_LOG", "info");
    command
}

/// The lines `reader` gives, as they come, from a thread of their own.
fn lines_of(reader: impl Read + Send + 'static) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(reader).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// Asks a server to stop (SIGTERM).
fn sigterm(child: &std::process::Child) {
    let ok = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -TERM");
}

/// Serves an empty pool with `global` arguments and stderr on a pipe until it has printed its
/// addresses, stops it with SIGTERM and returns everything it logged.
fn serve_and_collect_log(global: &[&str]) -> String {
    let dir = tempfile::tempdir().unwrap();
    let mut child = serve_command(dir.path(), global, &[])
        .env_remove("NO_COLOR")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = lines_of(child.stdout.take().unwrap());
    loop {
        let line = stdout
            .recv_timeout(Duration::from_secs(30))
            .expect("serve printed its fingerprint line");
        if line.starts_with("fingerprint ") {
            break;
        }
    }
    sigterm(&child);
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
    let root = dir.path().join("copies");
    std::fs::create_dir_all(root.join("scheduled-2099-01-01T030000Z")).unwrap();
    let root = root.to_str().unwrap();
    let mut child = serve_command(
        dir.path(),
        &[],
        &["--copy-root", root, "--copy-at", "03:00"],
    )
    .stdout(Stdio::null())
    .stderr(Stdio::piped())
    .spawn()
    .unwrap();
    let stderr = lines_of(child.stderr.take().unwrap());
    let mut log = Vec::new();
    let warning = loop {
        match stderr.recv_timeout(Duration::from_secs(30)) {
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
    sigterm(&child);
    // The reader thread drains the rest of the log while the server stops.
    assert!(child.wait().unwrap().success());
}
