//! The `arbor-client` binary refuses absurd parameters and unreachable servers with a clear
//! message and exit code 1 — never a panic, never a hang.

use std::process::Command;
use std::time::{Duration, Instant};

const FP: &str = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff";

fn run(args: &[&str]) -> (i32, String) {
    let t0 = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_arbor-client"))
        .args(args)
        .env("RUST_LOG", "error")
        .output()
        .expect("running arbor-client");
    assert!(
        t0.elapsed() < Duration::from_secs(30),
        "{args:?} took {:?}",
        t0.elapsed()
    );
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!stderr.contains("panicked"), "{args:?} panicked:\n{stderr}");
    (out.status.code().unwrap_or(-1), stderr)
}

fn render_with(extra: &[&str]) -> (i32, String) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("o.png");
    let mut args = vec![
        "render",
        "--server",
        "quic://127.0.0.1:9/scene",
        "--cert-fingerprint",
        FP,
        "--connect-timeout",
        "1",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let r = run(&args);
    assert!(
        !out.exists(),
        "{extra:?}: no image may be written on failure"
    );
    r
}

#[test]
fn absurd_parameters_are_refused_by_name() {
    let cases: &[(&[&str], &str)] = &[
        (&["--size", "0x10"], "size"),
        (&["--size", "100000x10"], "size"),
        (&["--size", "wide"], "WxH"),
        (&["--budget-mib", "NaN"], "budget"),
        (&["--budget-mib=-1"], "budget"),
        (&["--feedback-ratio", "0"], "feedback ratio"),
        (&["--feedback-ratio", "1000"], "feedback ratio"),
        (&["--lod-bias", "inf"], "LOD bias"),
        (&["--fill-ratio", "1.5"], "fill ratio"),
        (&["--load-limit", "0"], "load limit"),
        (&["--max-requests", "10000000"], "request cap"),
        (&["--camera-path", "spiral"], "spiral"),
        (&["--camera-path", "orbit:nan"], "orbit"),
        (&["--policy", "random"], "policy"),
        (&["--feedback", "sometimes"], "feedback"),
        (&["--channels", "colour"], "colour"),
        (&["--cycle-ms=-5"], "cycle time"),
        (&["--reference", "/nonexistent/ref.png"], "reference"),
    ];
    for (extra, needle) in cases {
        let (code, stderr) = render_with(extra);
        assert_eq!(code, 1, "{extra:?}: exit code\n{stderr}");
        assert!(
            stderr.contains(needle),
            "{extra:?}: message should name {needle:?}:\n{stderr}"
        );
    }
}

#[test]
fn bad_urls_and_fingerprints_are_refused() {
    for (args, needle) in [
        (
            vec![
                "render",
                "--server",
                "http://x:1/s",
                "--cert-fingerprint",
                FP,
            ],
            "quic",
        ),
        (
            vec!["render", "--server", "quic://x/s", "--cert-fingerprint", FP],
            "port",
        ),
        (
            vec![
                "render",
                "--server",
                "quic://127.0.0.1:9/s",
                "--cert-fingerprint",
                "abc",
            ],
            "hex",
        ),
        (
            vec!["render", "--server", "quic://127.0.0.1:9/s"],
            "fingerprint",
        ),
    ] {
        let mut args = args;
        args.extend(["--out", "/tmp/never-written-arbor.png"]);
        let (code, stderr) = run(&args);
        assert_eq!(code, 1, "{args:?}\n{stderr}");
        assert!(
            stderr.to_lowercase().contains(needle),
            "{args:?}: should mention {needle:?}:\n{stderr}"
        );
    }
}

#[test]
fn an_unreachable_server_times_out_with_a_message() {
    let (code, stderr) = render_with(&[]);
    assert_eq!(code, 1, "{stderr}");
    assert!(
        stderr.contains("SceneInfo") && stderr.contains("127.0.0.1:9"),
        "{stderr}"
    );
}

#[test]
fn view_takes_the_url_as_an_argument_or_with_server() {
    // Both spellings get past argument parsing (to the window system or the connection, which
    // fail here with their own message); giving both is a usage error.
    for args in [
        vec!["view", "quic://127.0.0.1:9/s"],
        vec!["view", "--server", "quic://127.0.0.1:9/s"],
    ] {
        let mut args = args;
        args.extend([
            "--cert-fingerprint",
            FP,
            "--connect-timeout",
            "1",
            "--backend",
            "cpu",
        ]);
        let (code, stderr) = run(&args);
        assert_eq!(code, 1, "{args:?}\n{stderr}");
        assert!(
            !stderr.contains("Usage")
                && (stderr.contains("SceneInfo") || stderr.contains("DISPLAY")),
            "{args:?}: {stderr}"
        );
    }
    let (code, stderr) = run(&[
        "view",
        "quic://127.0.0.1:9/s",
        "--server",
        "quic://127.0.0.1:9/s",
        "--cert-fingerprint",
        FP,
    ]);
    assert_eq!(code, 2, "{stderr}");
    let (code, stderr) = run(&["view", "--cert-fingerprint", FP]);
    assert_eq!(code, 1, "{stderr}");
    assert!(stderr.contains("quic://HOST:PORT/SCENE"), "{stderr}");
    for (extra, needle) in [
        ("--load-limit=0", "load limit"),
        ("--feedback-ratio=0", "feedback ratio"),
        ("--lod-bias=NaN", "LOD bias"),
        ("--moving-frame-ms=NaN", "moving frame time"),
        ("--moving-frame-ms=-5", "moving frame time"),
        ("--min-moving-scale=0", "smallest frame scale"),
        ("--min-moving-scale=1.5", "smallest frame scale"),
        ("--min-moving-scale=NaN", "smallest frame scale"),
        ("--camera-path=orbit:2", "moves by hand"),
        ("--camera-path=look:1,2,3:1,2,3", "the eye is the target"),
        ("--camera-path=look:1,2,3", "two points"),
    ] {
        let (code, stderr) = run(&[
            "view",
            "quic://127.0.0.1:9/s",
            "--cert-fingerprint",
            FP,
            extra,
        ]);
        assert_eq!(code, 1, "{extra}: {stderr}");
        assert!(
            stderr.contains(needle) && !stderr.contains("DISPLAY"),
            "{extra}: refused before any window, naming {needle:?}: {stderr}"
        );
    }
}

#[test]
fn help_has_examples() {
    let out = Command::new(env!("CARGO_BIN_EXE_arbor-client"))
        .arg("--help")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success());
    assert!(text.contains("Examples:") && text.contains("arbor-client render"));
}
