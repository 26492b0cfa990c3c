//! The real `arbor-client` binary against the real server (in-process, loopback QUIC) with its
//! standard output already closed, as under `arbor-client … | head -1` once `head` has gone.
//! Its closing lines then find no reader: that must end the output, not the command, so the
//! files it was asked for are written, it exits 0, and it neither panics nor reports an error.
//! (`server/tests/cli.rs` holds `arbor-server`'s commands to the same; the client's need a
//! server, hence this file, beside `cli.rs`, whose commands need none.)

use std::path::Path;
use std::process::{Output, Stdio};

use arbor_client_core::image::Image;
use arbor_tests::streaming::serve;

/// Runs `bin args` with its stdout a pipe whose reading end is closed before the command
/// writes anything.
fn with_stdout_closed(bin: &Path, args: &[String]) -> Output {
    let mut child = std::process::Command::new(bin)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("running arbor-client");
    drop(child.stdout.take());
    child.wait_with_output().unwrap()
}

fn assert_clean_exit(what: &str, o: &Output) {
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        o.status.success(),
        "{what} with stdout closed exited {:?}: {err}",
        o.status.code()
    );
    assert!(
        !err.contains("panicked") && !err.lines().any(|l| l.starts_with("error: ")),
        "{what} with stdout closed failed: {err}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn render_and_reference_write_their_files_when_stdout_is_closed() {
    let bin = Path::new(env!("CARGO_BIN_EXE_arbor-client"));
    let served = serve("points/lion_takanawa.copc.laz", "lion", 1024).await;
    let out = tempfile::tempdir().unwrap();
    let file = |name: &str| out.path().join(name).to_str().unwrap().to_owned();
    let mut connection = served.client_args("lion").to_vec();
    connection.extend(["--size", "64x64", "--backend", "cpu"].map(str::to_owned));

    let mut reference: Vec<String> = vec!["reference".into()];
    reference.extend(connection.iter().cloned());
    reference.extend(["--out".into(), file("reference.png")]);
    let o = tokio::task::spawn_blocking(move || with_stdout_closed(bin, &reference))
        .await
        .unwrap();
    assert_clean_exit("reference", &o);
    let picture = Image::load_png(Path::new(&file("reference.png"))).unwrap();
    assert!(picture.coverage() > 0, "the reference shows nothing");

    let mut render: Vec<String> = vec!["render".into()];
    render.extend(connection.iter().cloned());
    render.extend(
        [
            "--budget-mib",
            "12",
            "--cycles",
            "400",
            "--until-converged",
            "--reference",
            &file("reference.png"),
            "--out",
            &file("render.png"),
            "--report",
            &file("render.csv"),
        ]
        .map(str::to_owned),
    );
    let o = tokio::task::spawn_blocking(move || with_stdout_closed(bin, &render))
        .await
        .unwrap();
    assert_clean_exit("render", &o);
    let report = std::fs::read_to_string(file("render.csv")).unwrap();
    assert!(
        report.lines().count() > 2,
        "the report has no cycles:\n{report}"
    );
    let rendered = Image::load_png(Path::new(&file("render.png"))).unwrap();
    assert_eq!(
        rendered.coverage(),
        picture.coverage(),
        "the converged render covers other pixels than the reference"
    );
}
