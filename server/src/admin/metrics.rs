//! `/metrics`: the service's own metrics ([`ServiceState::render_prometheus`]) followed by the
//! admin API's gauges of the process and the pool. Every family here is new (none of the
//! service's names), each declared once with HELP and TYPE before its samples.

use std::time::Duration;

use arbor_proto::SceneDescription;

use crate::live_copy::{CopyFigures, OUTCOMES as COPY_OUTCOMES};
use crate::live_verify::{CheckFigures, OUTCOMES};
use crate::pace::PaceFigures;
use crate::pool::{Pool, PoolError, PoolReadBuckets};
use crate::prometheus::{Histogram, Kind, PromText};
use crate::service::state::ServiceState;

/// Prometheus text exposition format 0.0.4.
pub(super) const CONTENT_TYPE: &str = "text/plain; version=0.0.4; charset=utf-8";

/// What the admin API reads from the pool for one answer.
#[derive(Debug)]
pub(super) struct PoolFigures {
    pub scenes: Vec<SceneDescription>,
    /// Each scene's name and published generation, in `scenes`' order.
    pub generations: Vec<(String, u64)>,
    pub disk_bytes: u64,
}

impl PoolFigures {
    /// Blocking: decodes the catalogue (once) and sizes the database directory.
    pub(super) fn read(pool: &Pool) -> Result<Self, PoolError> {
        let (generations, scenes) = pool
            .published()?
            .into_iter()
            .map(|(g, d)| ((d.name.clone(), g), d))
            .unzip();
        Ok(Self {
            scenes,
            generations,
            disk_bytes: pool.disk_bytes()?,
        })
    }
}

/// Compressed bytes of a scene: nodes, then each channel with its name.
pub(super) fn stream_bytes(d: &SceneDescription) -> Vec<(&'static str, u64)> {
    let mut v = vec![("nodes", d.stats.node_bytes)];
    v.extend(
        d.layout
            .channels()
            .iter()
            .zip(&d.stats.channel_bytes)
            .map(|(c, &b)| (c.name(), b)),
    );
    v
}

/// The whole `/metrics` body. `pool` is `None` when the pool could not be read: its families are
/// still declared, without samples, and `arbor_pool_readable` is 0.
/// `reads` are the pool handle's block read times, which need no catalogue read; `checks` the
/// scene checks' figures (`None`: no scene manager, or the catalogue could not be read);
/// `copies` the pool copies' and `background` their and the checks' reads (`None`: no scene
/// manager).
pub(super) fn render(
    state: &ServiceState,
    uptime: Duration,
    reads: &Histogram<PoolReadBuckets>,
    pool: Option<&PoolFigures>,
    checks: Option<&CheckFigures>,
    copies: Option<&CopyFigures>,
    background: Option<&PaceFigures>,
) -> String {
    let mut p = PromText::default();
    state.write_prometheus(&mut p);
    p.family(
        "arbor_build_info",
        Kind::Gauge,
        "Always 1; the server's version in a label.",
    )
    .sample(
        "arbor_build_info",
        &[("version", env!("CARGO_PKG_VERSION"))],
        1,
    )
    .single(
        "arbor_ready",
        Kind::Gauge,
        "1 when the service is ready (pool open, endpoint bound, not shutting down), else 0.",
        u8::from(state.is_ready()),
    )
    .single(
        "arbor_shutting_down",
        Kind::Gauge,
        "1 once graceful shutdown has begun, else 0.",
        u8::from(state.is_shutting_down()),
    )
    .single(
        "arbor_uptime_seconds",
        Kind::Gauge,
        "Seconds since the service started its admin API.",
        uptime.as_secs_f64(),
    )
    .single(
        "arbor_pool_readable",
        Kind::Gauge,
        "1 when the pool's catalogue could be read for this scrape, else 0.",
        u8::from(pool.is_some()),
    );
    p.family("arbor_pool_scenes", Kind::Gauge, "Scenes in the pool.");
    if let Some(pool) = pool {
        p.sample("arbor_pool_scenes", &[], pool.scenes.len());
    }
    p.family(
        "arbor_pool_disk_bytes",
        Kind::Gauge,
        "Bytes the pool database occupies on disk.",
    );
    if let Some(pool) = pool {
        p.sample("arbor_pool_disk_bytes", &[], pool.disk_bytes);
    }
    reads.write(
        &mut p,
        "arbor_pool_read_seconds",
        "Time of each read of a pack of treelet blocks from the pool (building a message, a \
         shape or a cut's nodes that no cache held). Reads slower than a few microseconds \
         decoded their page from the file: if many are, raise pool_cache_bytes.",
    );
    p.family(
        "arbor_memory_bound_bytes",
        Kind::Gauge,
        "The most memory the service's own bounds let it hold, by part, for the scenes the pool \
         holds now (runtime, allocator slack and admin API on top).",
    );
    if let Some(bound) = state.memory_bound() {
        let bound = pool.map_or(bound, |p| bound.with_scenes(p.scenes.len()));
        for (part, bytes) in bound.parts() {
            p.sample("arbor_memory_bound_bytes", &[("part", part)], bytes);
        }
    }
    reload_families(&mut p, state);
    scene_families(&mut p, pool.map_or(&[][..], |p| &p.scenes[..]));
    check_families(&mut p, checks);
    copy_families(&mut p, copies);
    background_families(&mut p, background);
    p.finish()
}

/// The configuration's reloads and the certificates the listeners present.
fn reload_families(p: &mut PromText, state: &ServiceState) {
    let reloads = state.reloads();
    p.family(
        "arbor_config_reloads_total",
        Kind::Counter,
        "Reloads of the configuration (SIGHUP: scene rules, certificates, admin tokens) since \
         the start, by outcome: applied, or failed (something did not load; nothing changed).",
    )
    .sample(
        "arbor_config_reloads_total",
        &[("outcome", "applied")],
        reloads.applied,
    )
    .sample(
        "arbor_config_reloads_total",
        &[("outcome", "failed")],
        reloads.failed,
    )
    .single(
        "arbor_config_last_reload_successful",
        Kind::Gauge,
        "0 when the last reload of the configuration failed (the server serves on under what \
         it had; its log names the file at ERROR), else 1.",
        u8::from(reloads.last_successful),
    )
    .single(
        "arbor_config_last_reload_success_timestamp_seconds",
        Kind::Gauge,
        "When the configuration in force was loaded (the start, or the last reload applied), \
         seconds since the Unix epoch.",
        reloads.last_success_unix,
    );
    p.family(
        "arbor_tls_certificate_expiry_timestamp_seconds",
        Kind::Gauge,
        "When the certificate a listener presents now expires (its notAfter), seconds since the \
         Unix epoch, by listener: quic, and admin when the admin API speaks HTTPS.",
    );
    for (listener, certificate) in state.certificates() {
        if let Some(t) = certificate.not_after_unix {
            p.sample(
                "arbor_tls_certificate_expiry_timestamp_seconds",
                &[("listener", listener)],
                t,
            );
        }
    }
}

/// What checks and copies read, how long the pace held them, and the pace.
fn background_families(p: &mut PromText, background: Option<&PaceFigures>) {
    p.family(
        "arbor_pool_background_read_bytes_total",
        Kind::Counter,
        "Bytes of packs that scene checks and pool copies read from the served pool since the \
         start (not counted in arbor_pool_read_seconds).",
    );
    if let Some(b) = background {
        p.sample("arbor_pool_background_read_bytes_total", &[], b.read_bytes);
    }
    p.family(
        "arbor_pool_background_wait_seconds_total",
        Kind::Counter,
        "Seconds checks and copies waited to keep --background-read-rate since the start.",
    );
    if let Some(b) = background {
        p.sample(
            "arbor_pool_background_wait_seconds_total",
            &[],
            b.waited_seconds,
        );
    }
    p.family(
        "arbor_pool_background_read_rate_bytes",
        Kind::Gauge,
        "Bytes per second checks and copies may read together; no sample without a limit.",
    );
    if let Some(rate) = background.and_then(|b| b.read_bytes_per_second) {
        p.sample("arbor_pool_background_read_rate_bytes", &[], rate);
    }
}

/// The pool copies' counters and when the last one succeeded.
fn copy_families(p: &mut PromText, copies: Option<&CopyFigures>) {
    p.family(
        "arbor_pool_copies_total",
        Kind::Counter,
        "Copies of the served pool (POST /v1/copies, copy --server) ended since the start, by \
         outcome: done, failed, cancelled.",
    );
    if let Some(c) = copies {
        for (outcome, n) in COPY_OUTCOMES.iter().zip(c.ended) {
            p.sample(
                "arbor_pool_copies_total",
                &[("outcome", outcome.as_str())],
                n,
            );
        }
    }
    p.family(
        "arbor_pool_copy_last_done_seconds",
        Kind::Gauge,
        "When the last copy that succeeded ended, seconds since the Unix epoch (alert when it \
         is older than the backup period); no sample before the first.",
    );
    if let Some(t) = copies.and_then(|c| c.last_done_unix) {
        p.sample("arbor_pool_copy_last_done_seconds", &[], t);
    }
    p.family(
        "arbor_pool_copies_skipped_total",
        Kind::Counter,
        "Scheduled copies (serve --copy-every/--copy-at) not made because the last one had not \
         ended (a period shorter than a copy, or a copy held back by the background read rate).",
    );
    if let Some(c) = copies {
        p.sample("arbor_pool_copies_skipped_total", &[], c.skipped);
    }
    p.family(
        "arbor_pool_copy_next_scheduled_seconds",
        Kind::Gauge,
        "When the next scheduled copy is due, seconds since the Unix epoch (alert when it is \
         in the past: the schedule stopped); no sample without a schedule.",
    );
    if let Some(s) = copies.and_then(|c| c.scheduled.as_ref()) {
        p.sample(
            "arbor_pool_copy_next_scheduled_seconds",
            &[],
            s.next_due_unix,
        );
    }
    p.family(
        "arbor_pool_copy_period_seconds",
        Kind::Gauge,
        "The scheduled copies' period (serve --copy-every/--copy-at), in seconds (alert when \
         the last good copy is older than two); no sample without a schedule.",
    );
    if let Some(s) = copies.and_then(|c| c.scheduled.as_ref()) {
        p.sample("arbor_pool_copy_period_seconds", &[], s.period_seconds);
    }
}

/// The scene checks' counters and each published scene's last check.
fn check_families(p: &mut PromText, checks: Option<&CheckFigures>) {
    p.family(
        "arbor_scene_checks_total",
        Kind::Counter,
        "Checks of published scenes (POST /v1/scenes/{name}/verify, serve --check-every) ended \
         since the start, by outcome: ok, problems (an invariant broken), failed (the pool could \
         not be read), cancelled.",
    );
    if let Some(c) = checks {
        for (outcome, n) in OUTCOMES.iter().zip(c.ended) {
            p.sample(
                "arbor_scene_checks_total",
                &[("outcome", outcome.as_str())],
                n,
            );
        }
    }
    p.family(
        "arbor_scene_check_next_scheduled_seconds",
        Kind::Gauge,
        "When the next check of every scene (serve --check-every/--check-at) is due, seconds \
         since the Unix epoch; no sample without a schedule.",
    );
    if let Some(s) = checks.and_then(|c| c.scheduled.as_ref()) {
        p.sample(
            "arbor_scene_check_next_scheduled_seconds",
            &[],
            s.next_due_unix,
        );
    }
    p.family(
        "arbor_scene_check_period_seconds",
        Kind::Gauge,
        "The scheduled checks' period (serve --check-every/--check-at), in seconds (alert when \
         a scene's last check is older than two); no sample without a schedule.",
    );
    if let Some(s) = checks.and_then(|c| c.scheduled.as_ref()) {
        p.sample("arbor_scene_check_period_seconds", &[], s.period_seconds);
    }
    let last = checks.map(|c| &c.last);
    let each =
        |p: &mut PromText, name: &str, value: &dyn Fn(&crate::live_verify::LastCheck) -> f64| {
            for (scene, l) in last.into_iter().flatten() {
                p.sample(name, &[("scene", scene)], value(l));
            }
        };
    p.family(
        "arbor_scene_check_ok",
        Kind::Gauge,
        "1 when the last check of the scene as published now found every invariant holding, 0 \
         when it found a broken one or could not read the scene; no sample before its first \
         check.",
    );
    each(p, "arbor_scene_check_ok", &|l| {
        f64::from(u8::from(l.outcome == crate::live_verify::VerifyPhase::Ok))
    });
    p.family(
        "arbor_scene_check_problems",
        Kind::Gauge,
        "Broken invariants the last check of the scene as published now found.",
    );
    each(p, "arbor_scene_check_problems", &|l| l.problems as f64);
    p.family(
        "arbor_scene_check_end_seconds",
        Kind::Gauge,
        "When the last check of the scene as published now ended, seconds since the Unix epoch \
         (alert when it is older than the check period).",
    );
    each(p, "arbor_scene_check_end_seconds", &|l| l.ended_unix);
}

/// Per-scene gauges.
fn scene_families(p: &mut PromText, scenes: &[SceneDescription]) {
    p.family("arbor_scene_treelets", Kind::Gauge, "Treelets of a scene.");
    for d in scenes {
        p.sample(
            "arbor_scene_treelets",
            &[("scene", &d.name)],
            d.treelet_count,
        );
    }
    p.family(
        "arbor_scene_voxels",
        Kind::Gauge,
        "Voxels (node records in use, inner and leaf) of a scene.",
    );
    for d in scenes {
        p.sample("arbor_scene_voxels", &[("scene", &d.name)], d.stats.voxels);
    }
    p.family(
        "arbor_scene_compressed_bytes",
        Kind::Gauge,
        "Compressed bytes of a scene in the pool, by stream (nodes or an attribute channel).",
    );
    for d in scenes {
        for (stream, bytes) in stream_bytes(d) {
            p.sample(
                "arbor_scene_compressed_bytes",
                &[("scene", &d.name), ("stream", stream)],
                bytes,
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn families_are_declared_once_even_without_a_pool() {
        let s = ServiceState::new("ff".into());
        let t = render(
            &s,
            Duration::from_secs(3),
            &Histogram::default(),
            None,
            None,
            None,
            None,
        );
        assert!(t.contains("arbor_pool_readable 0\n"), "{t}");
        for counter in [
            "arbor_scene_checks_total",
            "arbor_pool_copies_total",
            "arbor_pool_copies_skipped_total",
            "arbor_pool_background_read_bytes_total",
            "arbor_pool_background_wait_seconds_total",
        ] {
            assert!(t.contains(&format!("# TYPE {counter} counter\n")), "{t}");
        }
        assert!(
            !t.lines()
                .any(|l| l.starts_with("arbor_pool_copy_last_done_seconds")),
            "a copy's end before any copy: {t}"
        );
        assert!(
            t.contains("# TYPE arbor_pool_background_read_rate_bytes gauge\n")
                && !t
                    .lines()
                    .any(|l| l.starts_with("arbor_pool_background_read_rate_bytes")),
            "a rate sample without a scene manager: {t}"
        );
        for gauge in [
            "arbor_pool_copy_next_scheduled_seconds",
            "arbor_scene_check_next_scheduled_seconds",
            "arbor_pool_copy_period_seconds",
            "arbor_scene_check_period_seconds",
        ] {
            assert!(t.contains(&format!("# TYPE {gauge} gauge\n")), "{t}");
            assert!(
                !t.lines().any(|l| l.starts_with(gauge)),
                "a schedule's next time without a schedule: {t}"
            );
        }
        assert!(!t.contains("arbor_pool_scenes 0"), "{t}");
        let mut names: Vec<_> = t
            .lines()
            .filter_map(|l| l.strip_prefix("# TYPE "))
            .map(|l| l.split(' ').next().unwrap())
            .collect();
        let n = names.len();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), n, "{t}");
    }
}
