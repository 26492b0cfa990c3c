//! How the server's binaries write their log lines (stderr, filtered by `RUST_LOG`, `info` by
//! default).
//!
//! Text lines carry ANSI colour only when stderr is a terminal and `NO_COLOR` is unset, so a log
//! written to a file or a pipe (the main job's `serve.log`, journald, a container runtime) holds
//! no escape sequences. `json` writes one JSON object per line with the event's fields at the
//! top level (`timestamp`, `level`, `target`, `message`, …), which is what log shippers expect.

use std::io::IsTerminal as _;

/// The shape of the log lines.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines, coloured only on a terminal.
    #[default]
    Text,
    /// One JSON object per line.
    Json,
}

/// Whether text logs should be coloured: stderr is a terminal and `NO_COLOR` is not set.
pub fn colour_on_stderr() -> bool {
    std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty())
}

/// Installs the global subscriber writing to stderr in `format`. Call once, first thing.
pub fn init(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    match format {
        LogFormat::Text => builder.with_ansi(colour_on_stderr()).init(),
        LogFormat::Json => builder
            .json()
            .flatten_event(true)
            .with_current_span(false)
            .with_span_list(false)
            .init(),
    }
}
