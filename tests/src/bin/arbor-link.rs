//! `arbor-link`: a userspace UDP link emulator (delay, rate limit, loss) for trying Arbor over a
//! WAN-like link on one machine without root. See `arbor_tests::link` for the link model.

use std::io::IsTerminal;
use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use arbor_tests::link::{LinkConfig, LinkEmulator, LinkStats};
use clap::Parser;

const EXAMPLES: &str = "\
Examples:
  # 25 ms each way (50 ms RTT), 100 Mbit/s each way, no loss, in front of a server on :4433;
  # point the client at 127.0.0.1:5000
  arbor-link --listen 127.0.0.1:5000 --upstream 127.0.0.1:4433 --delay-ms 25 --rate-mbit 100 --loss 0.0

  # a lossy mobile-like link: 40 ms each way, 10 Mbit/s, 1 % loss, reproducible losses
  arbor-link --listen 127.0.0.1:5000 --upstream 127.0.0.1:4433 --delay-ms 40 --rate-mbit 10 --loss 0.01 --seed 7

  # only delay, unlimited rate, a 256 KiB buffer, counters every second
  arbor-link --upstream 127.0.0.1:4433 --delay-ms 100 --queue-bytes 262144 --stats-every-s 1

Every parameter applies to each direction separately. Logs go to stderr (RUST_LOG=debug for more).";

/// Forward UDP between clients and one upstream server through an emulated link.
#[derive(Debug, Parser)]
#[command(name = "arbor-link", version, after_help = EXAMPLES)]
struct Args {
    /// Address clients send to.
    #[arg(long, default_value = "127.0.0.1:5000")]
    listen: SocketAddr,
    /// Address of the server everything is forwarded to.
    #[arg(long)]
    upstream: SocketAddr,
    /// One-way delay in milliseconds (each direction).
    #[arg(long, default_value_t = 0.0)]
    delay_ms: f64,
    /// Rate limit in Mbit/s (10^6 bits) each direction; 0 means unlimited.
    #[arg(long, default_value_t = 0.0)]
    rate_mbit: f64,
    /// Loss probability in 0..=1 (each direction, independently per packet).
    #[arg(long, default_value_t = 0.0)]
    loss: f64,
    /// Drop-tail buffer per direction in bytes [default: twice the round-trip bandwidth-delay
    /// product when rate-limited (at least 64 KiB), else 1 MiB].
    #[arg(long)]
    queue_bytes: Option<usize>,
    /// Seed of the loss generator.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Log the counters this often (seconds); 0 turns it off.
    #[arg(long, default_value_t = 10)]
    stats_every_s: u64,
}

impl Args {
    fn config(&self) -> Result<LinkConfig> {
        if !(self.delay_ms >= 0.0 && self.delay_ms.is_finite()) {
            bail!(
                "--delay-ms must be a non-negative number, got {}",
                self.delay_ms
            );
        }
        if !(self.rate_mbit >= 0.0 && self.rate_mbit.is_finite()) {
            bail!(
                "--rate-mbit must be a non-negative number, got {}",
                self.rate_mbit
            );
        }
        let delay = Duration::from_secs_f64(self.delay_ms / 1000.0);
        let rate = (self.rate_mbit * 125_000.0).round() as u64;
        let mut config = if rate > 0 {
            LinkConfig::wan(delay, rate)
        } else {
            LinkConfig::default().with_delay(delay)
        };
        config.loss = self.loss;
        config.seed = self.seed;
        if let Some(q) = self.queue_bytes {
            config.queue_bytes = q;
        }
        config.validate()?;
        Ok(config)
    }
}

fn log_stats(s: &LinkStats) {
    for (dir, d) in [("up", &s.upstream), ("down", &s.downstream)] {
        tracing::info!(
            dir,
            packets_in = d.packets_in,
            forwarded = d.packets_forwarded,
            bytes_forwarded = d.bytes_forwarded,
            dropped_loss = d.dropped_loss,
            dropped_queue = d.dropped_queue,
            send_errors = d.send_errors,
            queued_bytes = d.queued_bytes,
            peak_queued_bytes = d.peak_queued_bytes,
            "link counters"
        );
    }
    tracing::info!(
        clients = s.clients,
        unroutable = s.unroutable_packets,
        "link clients"
    );
}

/// Resolves on Ctrl-C (SIGINT) or, on Unix, SIGTERM.
async fn stop_signal() -> Result<()> {
    #[cfg(unix)]
    {
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
            .context("installing the SIGTERM handler")?;
        tokio::select! {
            r = tokio::signal::ctrl_c() => r.context("waiting for Ctrl-C"),
            _ = term.recv() => Ok(()),
        }
    }
    #[cfg(not(unix))]
    {
        tokio::signal::ctrl_c().await.context("waiting for Ctrl-C")
    }
}

#[tokio::main]
async fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
    let args = Args::parse();
    let config = args.config()?;
    let link = LinkEmulator::start_on(args.listen, args.upstream, config.clone())
        .await
        .with_context(|| format!("starting the link emulator on {}", args.listen))?;
    tracing::info!(
        listen = %link.local_addr(),
        upstream = %link.upstream(),
        delay_ms = config.delay.as_secs_f64() * 1000.0,
        rate_bytes_per_s = ?config.rate_bytes_per_s,
        loss = config.loss,
        queue_bytes = config.queue_bytes,
        seed = config.seed,
        "arbor-link forwarding; Ctrl-C to stop"
    );
    let every = Duration::from_secs(args.stats_every_s.max(1));
    let mut ticker = tokio::time::interval_at(tokio::time::Instant::now() + every, every);
    let stop = stop_signal();
    tokio::pin!(stop);
    loop {
        tokio::select! {
            r = &mut stop => {
                r?;
                break;
            }
            _ = ticker.tick(), if args.stats_every_s > 0 => log_stats(&link.stats()),
        }
    }
    log_stats(&link.stats());
    link.shutdown().await;
    Ok(())
}
