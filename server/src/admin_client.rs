//! The CLI's client of a running daemon's admin API: `arbor-server import --server ADMIN_URL`
//! asks it to import files under its import root (`POST /v1/scenes`) and follows the import
//! (`GET /v1/imports/{id}`); `arbor-server verify --server ADMIN_URL` asks it to check a scene
//! while it serves (`POST /v1/scenes/{name}/verify`) and follows the check
//! (`GET /v1/verifications/{id}`; Ctrl-C cancels it there). Plain HTTP/1.1 over a TCP
//! connection per request, enough for the loopback admin API; for anything else use the
//! documented `curl` lines (README).

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{Context, Result, bail};

/// An admin API address: `http://HOST:PORT`.
#[derive(Clone, Debug)]
pub struct AdminUrl {
    host_port: String,
}

impl std::str::FromStr for AdminUrl {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let rest = s.strip_prefix("http://").ok_or_else(|| {
            format!("'{s}': expected http://HOST:PORT (for https use the curl lines in the README)")
        })?;
        let host_port = rest.trim_end_matches('/');
        if host_port.is_empty() || host_port.contains('/') {
            return Err(format!("'{s}': expected http://HOST:PORT with no path"));
        }
        Ok(AdminUrl {
            host_port: host_port.to_owned(),
        })
    }
}

/// One request; returns the status code and the body.
fn request(
    url: &AdminUrl,
    token: &str,
    method: &str,
    path: &str,
    body: Option<&str>,
) -> Result<(u16, String)> {
    let mut stream = TcpStream::connect(&url.host_port)
        .with_context(|| format!("connecting to the admin API at {}", url.host_port))?;
    stream.set_read_timeout(Some(Duration::from_secs(60)))?;
    let body = body.unwrap_or("");
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {}\r\nAuthorization: Bearer {token}\r\n\
         Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        url.host_port,
        body.len()
    )?;
    let mut answer = Vec::new();
    stream.read_to_end(&mut answer)?;
    let answer = String::from_utf8_lossy(&answer);
    let (head, body) = answer
        .split_once("\r\n\r\n")
        .context("the admin API sent no complete HTTP answer")?;
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .context("the admin API's answer has no status")?;
    Ok((status, body.to_owned()))
}

/// The admin token: the file's contents, else `$ARBOR_ADMIN_TOKEN`.
pub fn token(token_file: Option<&Path>) -> Result<String> {
    let token = match token_file {
        Some(p) => std::fs::read_to_string(p)
            .with_context(|| format!("reading the admin token from {}", p.display()))?,
        None => std::env::var("ARBOR_ADMIN_TOKEN")
            .context("no admin token: pass --token-file or set ARBOR_ADMIN_TOKEN")?,
    };
    Ok(token.trim().to_owned())
}

/// Posts background work to `path`; the id of the job the daemon accepted (`202`), or an error
/// saying that it refused `what`, and why.
fn submit(url: &AdminUrl, token: &str, path: &str, body: Option<&str>, what: &str) -> Result<u64> {
    let (status, body) = request(url, token, "POST", path, body)?;
    let answer: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
    if status != 202 {
        bail!(
            "the server refused {what} ({status}): {}",
            answer["error"].as_str().unwrap_or(&body)
        );
    }
    answer["id"].as_u64().context("no job id in the answer")
}

/// Submits `job` (the JSON of `POST /v1/scenes`) and follows it, printing each change of
/// phase; returns the final status JSON, or an error naming why the import failed.
pub fn import(url: &AdminUrl, token: &str, job: &serde_json::Value) -> Result<serde_json::Value> {
    let id = submit(
        url,
        token,
        "/v1/scenes",
        Some(&job.to_string()),
        "the import",
    )?;
    eprintln!("import {id} queued on {}", url.host_port);
    let mut last = String::new();
    loop {
        std::thread::sleep(Duration::from_millis(500));
        let (status, body) = request(url, token, "GET", &format!("/v1/imports/{id}"), None)?;
        if status != 200 {
            bail!("import {id}: status {status}: {body}");
        }
        let s: serde_json::Value = serde_json::from_str(&body)?;
        let phase = s["phase"].as_str().unwrap_or("?").to_owned();
        let line = match (s["done"].as_u64(), s["total"].as_u64()) {
            (Some(d), Some(t)) if t > 0 => format!("{phase} {d}/{t}"),
            (Some(d), _) if d > 0 => format!("{phase} {d}"),
            _ => phase.clone(),
        };
        if line != last {
            eprintln!(
                "import {id}: {line} ({:.1} s)",
                s["seconds"].as_f64().unwrap_or(0.0)
            );
            last = line;
        }
        match phase.as_str() {
            "done" => return Ok(s),
            "failed" => bail!(
                "import {id} failed: {}",
                s["error"].as_str().unwrap_or("(no message)")
            ),
            _ => {}
        }
    }
}

/// Asks the daemon to check `scene` and follows the check, telling `progress` the treelets
/// planned and checked; returns the final status JSON (phase `ok` or `problems`), or an error
/// naming why the check failed. Once `interrupted` is set (Ctrl-C), the check is cancelled on
/// the daemon and this returns an error saying so.
pub fn verify(
    url: &AdminUrl,
    token: &str,
    scene: &str,
    interrupted: &AtomicBool,
    progress: &dyn Fn(u64, u64),
) -> Result<serde_json::Value> {
    // Checked here: a name with spaces or slashes would not even make a request line.
    arbor_proto::scene::validate_scene_name(scene).with_context(|| format!("--scene {scene:?}"))?;
    let path = format!("/v1/scenes/{scene}/verify");
    let id = submit(url, token, &path, None, &format!("to check {scene}"))?;
    follow(
        url,
        token,
        &format!("checking {scene} (verification {id})"),
        &format!("/v1/verifications/{id}"),
        &["ok", "problems"],
        interrupted,
        &|s| {
            progress(
                s["treelets_planned"].as_u64().unwrap_or(0),
                s["treelets_checked"].as_u64().unwrap_or(0),
            )
        },
    )
}

/// Asks the daemon to copy its pool (`scenes`, or every scene when empty) into the new
/// directory `to` under its copy root, and follows the copy, telling `progress` the bytes
/// planned and copied; returns the final status JSON (phase `done`), or an error naming why
/// the copy failed. Once `interrupted` is set (Ctrl-C), the copy is cancelled on the daemon
/// (which removes what it wrote) and this returns an error saying so.
pub fn copy(
    url: &AdminUrl,
    token: &str,
    to: &str,
    scenes: &[String],
    interrupted: &AtomicBool,
    progress: &dyn Fn(u64, u64),
) -> Result<serde_json::Value> {
    let body = serde_json::json!({ "to": to, "scenes": scenes }).to_string();
    let id = submit(
        url,
        token,
        "/v1/copies",
        Some(&body),
        &format!("the copy to {to}"),
    )?;
    follow(
        url,
        token,
        &format!("copying to {to} (copy {id})"),
        &format!("/v1/copies/{id}"),
        &["done"],
        interrupted,
        &|s| {
            progress(
                s["bytes_planned"].as_u64().unwrap_or(0),
                s["bytes_copied"].as_u64().unwrap_or(0),
            )
        },
    )
}

/// Follows the background job whose status is at `status_path` until its phase is one of
/// `ended` (returns that status) or `failed` / `cancelled` (an error naming `what` and why);
/// `progress` sees every status read. Once `interrupted` is set, cancels the job on the daemon
/// and fails saying so.
fn follow(
    url: &AdminUrl,
    token: &str,
    what: &str,
    status_path: &str,
    ended: &[&str],
    interrupted: &AtomicBool,
    progress: &dyn Fn(&serde_json::Value),
) -> Result<serde_json::Value> {
    loop {
        std::thread::sleep(Duration::from_millis(250));
        if interrupted.load(Ordering::Relaxed) {
            request(url, token, "DELETE", status_path, None)?;
            bail!("interrupted: {what} cancelled on the server");
        }
        let (status, body) = request(url, token, "GET", status_path, None)?;
        if status != 200 {
            bail!("{what}: status {status}: {body}");
        }
        let s: serde_json::Value = serde_json::from_str(&body)?;
        progress(&s);
        match s["phase"].as_str().unwrap_or("?") {
            phase if ended.contains(&phase) => return Ok(s),
            "failed" => bail!(
                "{what} failed on the server: {}",
                s["error"].as_str().unwrap_or("(no message)")
            ),
            "cancelled" => bail!("{what} was cancelled on the server"),
            _ => {}
        }
    }
}
