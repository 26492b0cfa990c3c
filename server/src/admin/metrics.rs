//! `/metrics`: the service's own metrics ([`ServiceState::render_prometheus`]) followed by the
//! admin API's gauges of the process and the pool. Every family here is new (none of the
//! service's names), each declared once with HELP and TYPE before its samples.

use std::fmt::Write as _;
use std::time::Duration;

use arbor_proto::SceneDescription;

use crate::pool::{Pool, PoolError};
use crate::service::state::ServiceState;

/// Prometheus text exposition format 0.0.4.
pub(super) const CONTENT_TYPE: &str = "text/plain; version=0.0.4; charset=utf-8";

/// What the admin API reads from the pool for one answer.
#[derive(Debug)]
pub(super) struct PoolFigures {
    pub scenes: Vec<SceneDescription>,
    pub disk_bytes: u64,
}

impl PoolFigures {
    /// Blocking: decodes the catalogue and sizes the database directory.
    pub(super) fn read(pool: &Pool) -> Result<Self, PoolError> {
        Ok(Self {
            scenes: pool.scenes()?,
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

/// A label value escaped as the text format asks (`\`, `"`, newline).
fn label(v: &str) -> String {
    let mut out = String::with_capacity(v.len());
    for c in v.chars() {
        match c {
            '\\' => out.push_str("\\\\"),
            '"' => out.push_str("\\\""),
            '\n' => out.push_str("\\n"),
            c => out.push(c),
        }
    }
    out
}

fn family(out: &mut String, name: &str, kind: &str, help: &str) {
    let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} {kind}");
}

/// The whole `/metrics` body. `pool` is `None` when the pool could not be read: its families are
/// still declared, without samples, and `arbor_pool_readable` is 0.
pub(super) fn render(state: &ServiceState, uptime: Duration, pool: Option<&PoolFigures>) -> String {
    let mut out = state.render_prometheus();
    if !out.is_empty() && !out.ends_with('\n') {
        out.push('\n');
    }
    family(
        &mut out,
        "arbor_build_info",
        "gauge",
        "Always 1; the server's version in a label.",
    );
    let _ = writeln!(
        out,
        "arbor_build_info{{version=\"{}\"}} 1",
        label(env!("CARGO_PKG_VERSION"))
    );
    family(
        &mut out,
        "arbor_ready",
        "gauge",
        "1 when the service is ready (pool open, endpoint bound, not shutting down), else 0.",
    );
    let _ = writeln!(out, "arbor_ready {}", u8::from(state.is_ready()));
    family(
        &mut out,
        "arbor_shutting_down",
        "gauge",
        "1 once graceful shutdown has begun, else 0.",
    );
    let _ = writeln!(
        out,
        "arbor_shutting_down {}",
        u8::from(state.is_shutting_down())
    );
    family(
        &mut out,
        "arbor_uptime_seconds",
        "gauge",
        "Seconds since the service started its admin API.",
    );
    let _ = writeln!(out, "arbor_uptime_seconds {}", uptime.as_secs_f64());
    family(
        &mut out,
        "arbor_pool_readable",
        "gauge",
        "1 when the pool's catalogue could be read for this scrape, else 0.",
    );
    let _ = writeln!(out, "arbor_pool_readable {}", u8::from(pool.is_some()));
    family(
        &mut out,
        "arbor_pool_scenes",
        "gauge",
        "Scenes in the pool.",
    );
    if let Some(p) = pool {
        let _ = writeln!(out, "arbor_pool_scenes {}", p.scenes.len());
    }
    family(
        &mut out,
        "arbor_pool_disk_bytes",
        "gauge",
        "Bytes the pool database occupies on disk.",
    );
    if let Some(p) = pool {
        let _ = writeln!(out, "arbor_pool_disk_bytes {}", p.disk_bytes);
    }
    let scenes = pool.map_or(&[][..], |p| &p.scenes[..]);
    family(
        &mut out,
        "arbor_scene_treelets",
        "gauge",
        "Treelets of a scene.",
    );
    for d in scenes {
        let _ = writeln!(
            out,
            "arbor_scene_treelets{{scene=\"{}\"}} {}",
            label(&d.name),
            d.treelet_count
        );
    }
    family(
        &mut out,
        "arbor_scene_voxels",
        "gauge",
        "Voxels (node records in use, inner and leaf) of a scene.",
    );
    for d in scenes {
        let _ = writeln!(
            out,
            "arbor_scene_voxels{{scene=\"{}\"}} {}",
            label(&d.name),
            d.stats.voxels
        );
    }
    family(
        &mut out,
        "arbor_scene_compressed_bytes",
        "gauge",
        "Compressed bytes of a scene in the pool, by stream (nodes or an attribute channel).",
    );
    for d in scenes {
        for (stream, bytes) in stream_bytes(d) {
            let _ = writeln!(
                out,
                "arbor_scene_compressed_bytes{{scene=\"{}\",stream=\"{stream}\"}} {bytes}",
                label(&d.name)
            );
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_are_escaped() {
        assert_eq!(label("a\"b\\c\nd"), "a\\\"b\\\\c\\nd");
    }

    #[test]
    fn families_are_declared_once_even_without_a_pool() {
        let s = ServiceState::new("ff".into());
        let t = render(&s, Duration::from_secs(3), None);
        assert!(t.contains("arbor_pool_readable 0\n"), "{t}");
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
