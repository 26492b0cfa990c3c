//! `arbor-link`: a userspace UDP link emulator (delay, rate limit, loss) for trying Arbor over a
//! WAN-like link on one machine without root: asymmetric with `--uplink-mbit`, shared by
//! several servers with `--route`. See `arbor_tests::link` for the link model.

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

  # a home line: 50 Mbit/s down, 5 Mbit/s up
  arbor-link --upstream 127.0.0.1:4433 --delay-ms 15 --rate-mbit 50 --uplink-mbit 5

  # two servers behind one bottleneck: clients of :4433 use :5000, clients of :4434 use :5001
  arbor-link --upstream 127.0.0.1:4433 --route 127.0.0.1:5001=127.0.0.1:4434 --delay-ms 20 --rate-mbit 4

Every parameter applies to each direction separately (--uplink-mbit only to clients' packets
towards the servers). Once forwarding, it prints the addresses it listens on to stdout, one line
each (`listen ADDR`, then `route ADDR=UPSTREAM` per route), so port 0 may be given to any of
them. Logs go to stderr (RUST_LOG=debug for more).";

/// Forward UDP between clients and one upstream server through an emulated link.
#[derive(Debug, Parser)]
#[command(name = "arbor-link", version, after_help = EXAMPLES)]
struct Args {
    /// Address clients send to (port 0: any free port, printed on stdout).
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
    /// Rate limit of the client → server direction in Mbit/s; 0 means unlimited [default: the
    /// same as --rate-mbit].
    #[arg(long)]
    uplink_mbit: Option<f64>,
    /// Another address clients send to, LISTEN=UPSTREAM, forwarded to another server through
    /// the same link (its rate and buffer shared); may be given several times (port 0 in LISTEN:
    /// any free port, printed on stdout).
    #[arg(long, value_parser = parse_route)]
    route: Vec<(SocketAddr, SocketAddr)>,
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

/// `LISTEN=UPSTREAM`, two socket addresses.
fn parse_route(text: &str) -> Result<(SocketAddr, SocketAddr), String> {
    let (listen, upstream) = text
        .split_once('=')
        .ok_or_else(|| format!("expected LISTEN=UPSTREAM, got {text:?}"))?;
    let addr = |a: &str| {
        a.trim()
            .parse::<SocketAddr>()
            .map_err(|e| format!("{a:?} is not a socket address (host:port): {e}"))
    };
    Ok((addr(listen)?, addr(upstream)?))
}

/// A rate in Mbit/s as bytes per second, `None` for 0 (unlimited).
fn rate_bytes(flag: &str, mbit: f64) -> Result<Option<u64>> {
    if !(mbit >= 0.0 && mbit.is_finite()) {
        bail!("{flag} must be a non-negative number, got {mbit}");
    }
    let rate = (mbit * 125_000.0).round() as u64;
    Ok((rate > 0).then_some(rate))
}

impl Args {
    /// The uplink's rate when it differs from the downlink's (`--uplink-mbit`).
    fn uplink(&self) -> Result<Option<Option<u64>>> {
        self.uplink_mbit
            .map(|mbit| rate_bytes("--uplink-mbit", mbit))
            .transpose()
    }

    fn config(&self) -> Result<LinkConfig> {
        if !(self.delay_ms >= 0.0 && self.delay_ms.is_finite()) {
            bail!(
                "--delay-ms must be a non-negative number, got {}",
                self.delay_ms
            );
        }
        let delay = Duration::from_secs_f64(self.delay_ms / 1000.0);
        let mut config = match rate_bytes("--rate-mbit", self.rate_mbit)? {
            Some(rate) => LinkConfig::wan(delay, rate),
            None => LinkConfig::default().with_delay(delay),
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
    let uplink = args.uplink()?;
    let mut link = LinkEmulator::start_on(args.listen, args.upstream, config.clone())
        .await
        .with_context(|| format!("starting the link emulator on {}", args.listen))?;
    if let Some(rate) = uplink {
        link.set_upstream_rate(rate)?;
    }
    let mut routes = Vec::new();
    for &(listen, upstream) in &args.route {
        let at = link
            .add_route(listen, upstream)
            .await
            .with_context(|| format!("opening the route {listen}={upstream}"))?;
        tracing::info!(listen = %at, %upstream, "route through the same link");
        routes.push((at, upstream));
    }
    // For scripts and tests that let it pick ports.
    println!("listen {}", link.local_addr());
    for (at, upstream) in routes {
        println!("route {at}={upstream}");
    }
    tracing::info!(
        listen = %link.local_addr(),
        upstream = %link.upstream(),
        delay_ms = config.delay.as_secs_f64() * 1000.0,
        rate_bytes_per_s = ?config.rate_bytes_per_s,
        uplink_bytes_per_s = ?uplink.unwrap_or(config.rate_bytes_per_s),
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
