//! The HTML pages: the status page at `/` and the login form. Self-contained (no external assets),
//! one inline style sheet and, on the status page, a few lines of inline script that refresh the
//! live part every 2 s; the `Content-Security-Policy` admits exactly these two by their hashes.
//! Every string from outside (scene names, sources, peers, fingerprint) goes through [`escape`].

use std::fmt::Write as _;
use std::sync::atomic::Ordering;
use std::time::{Duration, SystemTime};

use arbor_proto::wire::ErrorCode;
use axum::http::HeaderValue;
use ring::digest;

use super::metrics::{PoolFigures, stream_bytes};
use super::views::kind_name;
use crate::live_copy::{CopyPhase, CopyStatus};
use crate::live_import::ImportStatus;
use crate::live_verify::{VerifyPhase, VerifyStatus};
use crate::pace::{PaceFigures, describe_rate};
use crate::periodic::{ScheduleFigures, utc_text};
use crate::service::state::{ServiceState, SessionInfo};

const STYLE: &str = r#"
:root{color-scheme:light dark;--fg:#1b1f23;--bg:#fff;--mut:#6a737d;--line:#e1e4e8;--ok:#1a7f37;--bad:#cf222e;--warn:#9a6700}
@media (prefers-color-scheme:dark){:root{--fg:#e6edf3;--bg:#0d1117;--mut:#8b949e;--line:#30363d;--ok:#3fb950;--bad:#f85149;--warn:#d29922}}
body{font:14px/1.45 system-ui,sans-serif;color:var(--fg);background:var(--bg);margin:0 auto;padding:1em 1.5em;max-width:78em}
header{display:flex;align-items:center;gap:1em;flex-wrap:wrap}
h1{font-size:1.4em;margin:.2em 0}h1 small{color:var(--mut);font-weight:normal}
h2{font-size:1.1em;margin:1.4em 0 .4em;border-bottom:1px solid var(--line)}
header form{margin-left:auto}
code{font:12px ui-monospace,monospace;word-break:break-all}
table{border-collapse:collapse;width:100%}th,td{padding:.25em .6em;border-bottom:1px solid var(--line);text-align:left;vertical-align:top}
th{color:var(--mut);font-weight:600}td.n,th.n{text-align:right;font-variant-numeric:tabular-nums}
table.kv{width:auto}table.kv th{font-weight:normal}
.badge{display:inline-block;padding:.1em .6em;border-radius:1em;color:#fff;font-weight:600}
.ok{background:var(--ok)}.bad{background:var(--bad)}.warn{background:var(--warn)}
.mut{color:var(--mut)}.stale{opacity:.5}
form.login{display:flex;flex-direction:column;gap:.6em;max-width:24em}
input[type=password]{font:inherit;padding:.4em}button{font:inherit;padding:.3em 1em}
p.err{color:var(--bad);font-weight:600}
footer{margin-top:2em;color:var(--mut)}footer a{color:inherit}
"#;

const SCRIPT: &str = r#"
(function(){var auto=document.getElementById('auto');
setInterval(function(){if(!auto.checked||document.hidden)return;var live=document.getElementById('live');
fetch(location.pathname,{credentials:'same-origin',cache:'no-store',redirect:'manual'}).then(function(r){
if(r.type==='opaqueredirect'||r.status===401){location.reload();return null;}return r.ok?r.text():null;
}).then(function(t){if(t===null)return;var n=new DOMParser().parseFromString(t,'text/html').getElementById('live');
if(n)live.replaceWith(n);}).catch(function(){live.classList.add('stale');});},2000);})();
"#;

/// Standard base64 with padding (for CSP hashes).
fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = u32::from(b[0]) << 16 | u32::from(b[1]) << 8 | u32::from(b[2]);
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(char::from(A[(n >> (18 - 6 * i) & 63) as usize]));
            } else {
                out.push('=');
            }
        }
    }
    out
}

fn csp_hash(s: &str) -> String {
    format!(
        "'sha256-{}'",
        base64(digest::digest(&digest::SHA256, s.as_bytes()).as_ref())
    )
}

/// The policy of both pages: nothing but this origin, the inline style and the inline script.
pub(super) fn content_security_policy() -> HeaderValue {
    let v = format!(
        "default-src 'none'; style-src {}; script-src {}; connect-src 'self'; form-action 'self'; \
         frame-ancestors 'none'; base-uri 'none'",
        csp_hash(STYLE),
        csp_hash(SCRIPT)
    );
    HeaderValue::from_str(&v).expect("ASCII policy")
}

/// Escapes text for HTML element content and quoted attribute values.
pub(super) fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// `12345678` → `12 345 678` (narrow no-break spaces).
fn count(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::with_capacity(digits.len() * 2);
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push('\u{202f}');
        }
        out.push(c);
    }
    out
}

fn bytes(n: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = n as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{n} B")
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
}

fn duration(d: Duration) -> String {
    let s = d.as_secs();
    let (days, h, m, s) = (s / 86_400, s / 3600 % 24, s / 60 % 60, s % 60);
    if days > 0 {
        format!("{days} d {h:02}:{m:02}:{s:02}")
    } else {
        format!("{h:02}:{m:02}:{s:02}")
    }
}

fn head(title: &str) -> String {
    format!(
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
         <title>{}</title><style>{STYLE}</style></head>\n<body>\n",
        escape(title)
    )
}

/// The login form, with an optional message (wrong token, bad form).
pub(super) fn login_page(message: Option<&str>) -> String {
    let mut out = head("Arbor server · login");
    out.push_str("<header><h1>Arbor server <small>admin</small></h1></header>\n");
    if let Some(m) = message {
        let _ = writeln!(out, "<p class=\"err\">{}</p>", escape(m));
    }
    out.push_str(
        "<form class=\"login\" method=\"post\" action=\"/login\">\
         <label for=\"token\">Admin token</label>\
         <input type=\"password\" id=\"token\" name=\"token\" autocomplete=\"current-password\" \
         required autofocus>\
         <button type=\"submit\">Log in</button></form>\n\
         <p class=\"mut\">The token is the one the server was configured with; the browser keeps \
         it in an HttpOnly, SameSite=Strict cookie for this site.</p>\n</body></html>\n",
    );
    out
}

/// The background jobs the status page lists.
pub(super) struct Jobs<'a> {
    pub imports: &'a [ImportStatus],
    pub checks: &'a [VerifyStatus],
    pub copies: &'a [CopyStatus],
    /// The checks' and copies' reads (`None`: no scene manager).
    pub background: Option<PaceFigures>,
    /// The scheduled checks of every scene, if any.
    pub scheduled_checks: Option<ScheduleFigures>,
    /// The scheduled copies, if any, and how many were skipped.
    pub scheduled_copies: Option<(ScheduleFigures, u64)>,
}

/// The status page.
pub(super) fn status_page(
    state: &ServiceState,
    uptime: Duration,
    pool: &PoolFigures,
    jobs: &Jobs<'_>,
) -> String {
    let sessions = state.sessions();
    let mut out = head("Arbor server");
    let _ = writeln!(
        out,
        "<header><h1>Arbor server <small>{}</small></h1>\
         <form method=\"post\" action=\"/logout\"><button type=\"submit\">Log out</button></form>\
         </header>",
        escape(env!("CARGO_PKG_VERSION"))
    );
    out.push_str("<main id=\"live\">\n");
    status_section(&mut out, state, uptime, pool);
    traffic_section(&mut out, state, &sessions);
    scenes_section(&mut out, pool);
    imports_section(&mut out, jobs.imports);
    checks_section(&mut out, jobs.checks);
    copies_section(&mut out, jobs.copies);
    background_line(&mut out, jobs);
    schedule_line(&mut out, jobs);
    sessions_section(&mut out, &sessions);
    out.push_str("</main>\n");
    let _ = write!(
        out,
        "<footer><label><input type=\"checkbox\" id=\"auto\" checked> refresh every 2 s</label> · \
         JSON: <a href=\"/v1/server\">server</a>, <a href=\"/v1/scenes\">scenes</a>, \
         <a href=\"/v1/sessions\">sessions</a> · <a href=\"/metrics\">metrics</a></footer>\n\
         <script>{SCRIPT}</script>\n</body></html>\n"
    );
    out
}

/// Imports running, queued and finished (nothing when there were none).
fn imports_section(out: &mut String, imports: &[ImportStatus]) {
    if imports.is_empty() {
        return;
    }
    out.push_str(
        "<h2>Imports</h2>\n<table><tr><th class=\"n\">id</th><th>scene</th><th>phase</th>\
         <th class=\"n\">progress</th><th class=\"n\">time</th><th>inputs / result</th></tr>\n",
    );
    for i in imports.iter().rev() {
        let p = &i.progress;
        let progress = if p.total > 0 {
            format!("{} / {}", p.done, p.total)
        } else if p.done > 0 {
            p.done.to_string()
        } else {
            String::new()
        };
        let result = match (&i.error, i.treelets) {
            (Some(e), _) => format!("<span class=\"badge bad\">failed</span> {}", escape(e)),
            (None, Some(t)) => format!("{t} treelets, {} voxels", i.voxels.unwrap_or(0)),
            _ => escape(&i.inputs.join(", ")),
        };
        let phase = serde_json::to_value(p.phase)
            .ok()
            .and_then(|v| v.as_str().map(str::to_owned))
            .unwrap_or_default();
        let _ = writeln!(
            out,
            "<tr><td class=\"n\">{}</td><td>{}</td><td>{}</td><td class=\"n\">{}</td>\
             <td class=\"n\">{:.1} s</td><td>{}</td></tr>",
            i.id,
            escape(&i.scene),
            escape(&phase),
            progress,
            i.seconds,
            result
        );
    }
    out.push_str("</table>\n");
}

/// Scene checks running, queued and finished (nothing when there were none).
fn checks_section(out: &mut String, checks: &[VerifyStatus]) {
    if checks.is_empty() {
        return;
    }
    out.push_str(
        "<h2>Checks</h2>\n<table><tr><th class=\"n\">id</th><th>scene</th><th>phase</th>\
         <th class=\"n\">treelets</th><th class=\"n\">time</th><th>result</th></tr>\n",
    );
    for c in checks.iter().rev() {
        let result = match (c.phase, &c.report, &c.error) {
            (VerifyPhase::Ok, _, _) => {
                "<span class=\"badge ok\">every invariant holds</span>".into()
            }
            (VerifyPhase::Problems, Some(r), _) => format!(
                "<span class=\"badge bad\">{} problems</span> {}",
                r.problem_count,
                escape(r.problems.first().map_or("", String::as_str))
            ),
            (VerifyPhase::Failed, _, Some(e)) => {
                format!("<span class=\"badge bad\">failed</span> {}", escape(e))
            }
            _ => String::new(),
        };
        let _ = writeln!(
            out,
            "<tr><td class=\"n\">{}</td><td>{} <small>g{}</small></td><td>{}</td>\
             <td class=\"n\">{} / {}</td><td class=\"n\">{:.1} s</td><td>{}</td></tr>",
            c.id,
            escape(&c.scene),
            c.generation,
            c.phase.as_str(),
            c.treelets_checked,
            c.treelets_planned,
            c.seconds,
            result
        );
    }
    out.push_str("</table>\n");
}

/// Pool copies running, queued and finished (nothing when there were none).
fn copies_section(out: &mut String, copies: &[CopyStatus]) {
    if copies.is_empty() {
        return;
    }
    out.push_str(
        "<h2>Copies</h2>\n<table><tr><th class=\"n\">id</th><th>to</th><th>phase</th>\
         <th class=\"n\">bytes</th><th class=\"n\">time</th><th>result</th></tr>\n",
    );
    for c in copies.iter().rev() {
        let result = match (c.phase, &c.error) {
            (CopyPhase::Done, _) => format!(
                "<span class=\"badge ok\">compared with the source</span> {}",
                escape(&c.path)
            ),
            (CopyPhase::Failed, Some(e)) => {
                format!("<span class=\"badge bad\">failed</span> {}", escape(e))
            }
            _ => String::new(),
        };
        let scenes: Vec<&str> = c.scenes.iter().map(|s| s.name.as_str()).collect();
        let _ = writeln!(
            out,
            "<tr><td class=\"n\">{}</td><td>{} <small>{}</small></td><td>{}</td>\
             <td class=\"n\">{} / {}</td><td class=\"n\">{:.1} s</td><td>{}</td></tr>",
            c.id,
            escape(&c.to),
            escape(&scenes.join(", ")),
            c.phase.as_str(),
            c.bytes_copied,
            c.bytes_planned,
            c.seconds,
            result
        );
    }
    out.push_str("</table>\n");
}

/// The pace of checks and copies, and what they read (nothing when no rate is set and no job
/// is listed).
fn background_line(out: &mut String, jobs: &Jobs<'_>) {
    let Some(b) = jobs.background else {
        return;
    };
    if b.read_bytes_per_second.is_none() && jobs.checks.is_empty() && jobs.copies.is_empty() {
        return;
    }
    let _ = writeln!(
        out,
        "<p>Background reads (checks, copies): at most {} · {:.1} MB read · waited {:.1} s</p>",
        escape(&describe_rate(b.read_bytes_per_second)),
        b.read_bytes as f64 / 1e6,
        b.waited_seconds
    );
}

/// When the scheduled checks and copies are next due (nothing without a schedule).
fn schedule_line(out: &mut String, jobs: &Jobs<'_>) {
    let due = |s: &ScheduleFigures| {
        let next = std::time::UNIX_EPOCH + Duration::from_secs_f64(s.next_due_unix.max(0.0));
        format!("{}, next {}", escape(&s.schedule), escape(&utc_text(next)))
    };
    let mut parts = Vec::new();
    if let Some(s) = &jobs.scheduled_checks {
        parts.push(format!("checks of every scene {}", due(s)));
    }
    if let Some((s, skipped)) = &jobs.scheduled_copies {
        let skipped = match skipped {
            0 => String::new(),
            n => {
                format!(" (<span class=\"badge warn\">{n} skipped</span>: the last had not ended)")
            }
        };
        parts.push(format!("copies of the pool {}{skipped}", due(s)));
    }
    if !parts.is_empty() {
        let _ = writeln!(out, "<p>Scheduled: {}</p>", parts.join(" · "));
    }
}

/// Readiness, certificate, uptime, pool size, the last reload.
fn status_section(out: &mut String, state: &ServiceState, uptime: Duration, pool: &PoolFigures) {
    let (class, word) = if state.is_shutting_down() {
        ("warn", "shutting down")
    } else if state.is_ready() {
        ("ok", "ready")
    } else {
        ("bad", "not ready")
    };
    let _ = writeln!(
        out,
        "<table class=\"kv\">\
         <tr><th>Status</th><td><span class=\"badge {class}\">{word}</span></td></tr>\
         <tr><th>Certificate SHA-256</th><td><code id=\"fingerprint\">{}</code></td></tr>\
         <tr><th>Certificates valid until</th><td>{}</td></tr>\
         <tr><th>Configuration</th><td>{}</td></tr>\
         <tr><th>Uptime</th><td>{}</td></tr>\
         <tr><th>Pool on disk</th><td>{}</td></tr></table>",
        escape(&state.fingerprint()),
        certificates_text(state),
        reload_text(state),
        duration(uptime),
        bytes(pool.disk_bytes)
    );
}

/// When each listener's certificate expires, escaped.
fn certificates_text(state: &ServiceState) -> String {
    let at = |t: i64| {
        let t = std::time::UNIX_EPOCH + Duration::from_secs(u64::try_from(t).unwrap_or(0));
        utc_text(t)
    };
    let parts: Vec<String> = state
        .certificates()
        .into_iter()
        .map(|(listener, c)| match c.not_after_unix {
            Some(t) => format!("{listener} {}", at(t)),
            None => format!("{listener} (expiry not read)"),
        })
        .collect();
    escape(&parts.join(" · "))
}

/// How the last reload of the configuration went, escaped HTML.
fn reload_text(state: &ServiceState) -> String {
    let r = state.reloads();
    let since = std::time::UNIX_EPOCH + Duration::from_secs_f64(r.last_success_unix.max(0.0));
    let loaded = escape(&format!("in force since {}", utc_text(since)));
    let counts = format!("{} reloads applied, {} failed", r.applied, r.failed);
    if r.last_successful {
        format!("{loaded} · {counts}")
    } else {
        format!(
            "<span class=\"badge bad\">the last reload failed</span> (see the log) · {loaded} · \
             {counts}"
        )
    }
}

/// Counters and the error table.
fn traffic_section(out: &mut String, state: &ServiceState, sessions: &[SessionInfo]) {
    let m = &state.metrics;
    let load = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    out.push_str("<h2>Traffic</h2>\n<table class=\"kv\">");
    let queued: u64 = sessions.iter().map(|s| s.queue_depth).sum();
    let in_flight: u64 = sessions.iter().map(|s| s.in_flight).sum();
    let rows: [(&str, String); 12] = [
        ("Connections open", count(load(&m.connections_open))),
        ("Connections accepted", count(load(&m.connections_accepted))),
        ("Connections refused", count(load(&m.connections_rejected))),
        ("Request lists", count(load(&m.request_lists))),
        ("Requested items", count(load(&m.request_items))),
        ("Treelets sent", count(load(&m.treelets_sent))),
        ("Treelet bytes sent", bytes(load(&m.treelet_bytes_sent))),
        ("Treelet streams", count(load(&m.treelet_streams))),
        ("Treelets cancelled", count(load(&m.treelets_cancelled))),
        ("Queued now", count(queued)),
        ("In flight now", count(in_flight)),
        ("Latencies measured", count(m.request_to_send.count())),
    ];
    for (k, v) in rows {
        let _ = write!(out, "<tr><th>{k}</th><td class=\"n\">{v}</td></tr>");
    }
    out.push_str("</table>\n<h2>Errors</h2>\n");
    let errors: Vec<_> = ErrorCode::ALL
        .iter()
        .map(|&c| (c, m.errors(c)))
        .filter(|&(_, n)| n > 0)
        .collect();
    if errors.is_empty() {
        out.push_str("<p class=\"mut\">None.</p>\n");
    } else {
        out.push_str("<table class=\"kv\">");
        for (c, n) in errors {
            let _ = write!(
                out,
                "<tr><th>{}</th><td class=\"n\">{}</td></tr>",
                escape(c.name()),
                count(n)
            );
        }
        out.push_str("</table>\n");
    }
}

/// One row per scene.
fn scenes_section(out: &mut String, pool: &PoolFigures) {
    let _ = writeln!(out, "<h2>Scenes ({})</h2>", pool.scenes.len());
    if pool.scenes.is_empty() {
        out.push_str("<p class=\"mut\">The pool holds no scene.</p>\n");
    } else {
        out.push_str(
            "<table><tr><th>Name</th><th>Kind</th><th class=\"n\">Depth</th>\
             <th class=\"n\">Treelets</th><th class=\"n\">Voxels</th><th>Channels</th>\
             <th class=\"n\">Compressed</th><th class=\"n\">B/voxel</th><th>Source</th></tr>\n",
        );
        for d in &pool.scenes {
            let streams = stream_bytes(d);
            let total: u64 = streams.iter().map(|&(_, b)| b).sum();
            let channels: Vec<_> = d.layout.channels().iter().map(|c| c.name()).collect();
            let _ = writeln!(
                out,
                "<tr><td>{}</td><td>{}</td><td class=\"n\">{}</td><td class=\"n\">{}</td>\
                 <td class=\"n\">{}</td><td>{}</td><td class=\"n\">{}</td><td class=\"n\">{:.2}</td>\
                 <td>{}</td></tr>",
                escape(&d.name),
                kind_name(d.source_kind),
                d.max_depth,
                count(u64::from(d.treelet_count)),
                count(d.stats.voxels),
                escape(&channels.join(", ")),
                bytes(total),
                total as f64 / d.stats.voxels.max(1) as f64,
                escape(&d.source)
            );
        }
        out.push_str("</table>\n");
    }
}

/// One row per live connection.
fn sessions_section(out: &mut String, sessions: &[SessionInfo]) {
    let _ = writeln!(out, "<h2>Sessions ({})</h2>", sessions.len());
    if sessions.is_empty() {
        out.push_str("<p class=\"mut\">No live connection.</p>\n");
    } else {
        let now = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        out.push_str(
            "<table><tr><th class=\"n\">Id</th><th>Peer</th><th>Scene</th><th>Channels</th>\
             <th class=\"n\">Connected</th><th class=\"n\">Lists</th><th class=\"n\">Treelets</th>\
             <th class=\"n\">Sent</th><th class=\"n\">Queued</th><th class=\"n\">In flight</th></tr>\n",
        );
        for s in sessions {
            let age = Duration::from_secs_f64((now - s.connected_at).clamp(0.0, 1e12));
            let _ = writeln!(
                out,
                "<tr><td class=\"n\">{}</td><td>{}</td><td>{}</td><td>{}</td><td class=\"n\">{}</td>\
                 <td class=\"n\">{}</td><td class=\"n\">{}</td><td class=\"n\">{}</td>\
                 <td class=\"n\">{}</td><td class=\"n\">{}</td></tr>",
                s.id,
                escape(&s.peer.to_string()),
                if s.scene.is_empty() {
                    "<span class=\"mut\">(handshake)</span>".to_owned()
                } else {
                    escape(&s.scene)
                },
                escape(&s.channels.join(", ")),
                duration(age),
                count(s.request_lists),
                count(s.treelets_sent),
                bytes(s.bytes_sent),
                count(s.queue_depth),
                count(s.in_flight)
            );
        }
        out.push_str("</table>\n");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn helpers() {
        assert_eq!(base64(b""), "");
        assert_eq!(base64(b"f"), "Zg==");
        assert_eq!(base64(b"fo"), "Zm8=");
        assert_eq!(base64(b"foo"), "Zm9v");
        assert_eq!(base64(b"foobar"), "Zm9vYmFy");
        assert_eq!(
            escape("<a href=\"x\">'&'</a>"),
            "&lt;a href=&quot;x&quot;&gt;&#39;&amp;&#39;&lt;/a&gt;"
        );
        assert_eq!(count(1_234_567), "1\u{202f}234\u{202f}567");
        assert_eq!(count(12), "12");
        assert_eq!(bytes(1023), "1023 B");
        assert_eq!(bytes(1536), "1.5 KiB");
        assert_eq!(duration(Duration::from_secs(90_061)), "1 d 01:01:01");
    }

    #[test]
    fn policy_names_the_inline_style_and_script() {
        let p = content_security_policy();
        let p = p.to_str().unwrap();
        assert!(
            p.contains(&csp_hash(STYLE)) && p.contains(&csp_hash(SCRIPT)),
            "{p}"
        );
        assert!(!p.contains("unsafe-inline"));
    }
}
