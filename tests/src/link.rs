//! A userspace link emulator: a UDP forwarder on loopback with one-way delay, a rate limit, random
//! loss and a drop-tail buffer in each direction, so QUIC over a WAN-like link can be tested and
//! benchmarked on one machine without root (no netem needed).
//!
//! ```text
//!  client ──▶ [listen socket] ──▶ upstream pipe ──▶ [per-client socket] ──▶ upstream server
//!  client ◀── [listen socket] ◀── downstream pipe ◀── [per-client socket] ◀── upstream server
//! ```
//!
//! Each distinct client address gets its own socket towards the upstream server, so the server
//! sees distinct peers, and replies arriving on that socket go back to that client.
//!
//! # Link model (per direction)
//!
//! A datagram of `L` bytes arriving at `now` is handled in this order:
//!
//! 1. **Drop-tail buffer:** if the bytes already held by the direction (waiting for the link or
//!    propagating) plus `L` exceed [`LinkConfig::queue_bytes`], it is dropped
//!    ([`DirectionStats::dropped_queue`]). This also bounds the memory of the direction.
//! 2. **Serialization:** with a rate limit, the packet occupies the link for `L / rate`:
//!    `departure = max(now, link_free_at) + L / rate` and `link_free_at = departure`.
//!    Without one, `departure = now`.
//! 3. **Loss on the wire:** with probability [`LinkConfig::loss`] it is lost
//!    ([`DirectionStats::dropped_loss`]); a lost packet has still used its link time.
//! 4. **Propagation:** it is delivered at `release = departure + delay`.
//!
//! Packets of one direction are released in arrival order (the link never reorders). Each
//! direction has one task that holds a queue of `(release, packet)` and sleeps until the head is
//! due, so all packets share one timer and a long delay never delays unrelated timers.
//!
//! Timer granularity: tokio's timer has a 1 ms resolution and never fires early, so every packet
//! arrives no earlier than the model says and typically up to about 1 ms later.

use arbor_proto::rng::SplitMix64;
use std::collections::{HashMap, VecDeque};
use std::io;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::net::UdpSocket;
use tokio::sync::Notify;
use tokio::task::{JoinHandle, JoinSet};
use tokio::time::Instant;

/// Largest datagram the emulator forwards (the largest UDP payload over IPv4).
pub const MAX_DATAGRAM: usize = 65_507;

/// Most distinct client addresses one emulator serves; datagrams from further clients are dropped
/// and counted in [`LinkStats::unroutable_packets`].
pub const MAX_CLIENTS: usize = 1024;

/// Default size of the drop-tail buffer of each direction.
pub const DEFAULT_QUEUE_BYTES: usize = 1 << 20;

/// Smallest buffer [`LinkConfig::wan`] picks, so short or fast links still absorb small bursts.
pub const MIN_WAN_QUEUE_BYTES: usize = 64 << 10;

/// Parameters of the emulated link; each applies to both directions independently.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkConfig {
    /// One-way propagation delay, added in each direction.
    pub delay: Duration,
    /// Link rate in bytes per second in each direction; `None` is unlimited.
    pub rate_bytes_per_s: Option<u64>,
    /// Probability in `0.0..=1.0` that a packet is lost, drawn independently per packet and per
    /// direction.
    pub loss: f64,
    /// Bytes each direction may hold at once (waiting for the link plus propagating); packets
    /// beyond it are dropped at the tail. Must be at least 1.
    pub queue_bytes: usize,
    /// Seed of the loss generator; the same seed and the same packet sequence give the same
    /// losses.
    pub seed: u64,
}

impl Default for LinkConfig {
    /// A perfect link: no delay, no rate limit, no loss, a [`DEFAULT_QUEUE_BYTES`] buffer.
    fn default() -> Self {
        Self {
            delay: Duration::ZERO,
            rate_bytes_per_s: None,
            loss: 0.0,
            queue_bytes: DEFAULT_QUEUE_BYTES,
            seed: 0,
        }
    }
}

impl LinkConfig {
    /// A WAN-like link with the given one-way delay and rate (bytes/s) and a buffer of twice the
    /// bandwidth-delay product (`2 × rate × 2·delay`, at least [`MIN_WAN_QUEUE_BYTES`]): one
    /// one-way BDP is in flight, the rest absorbs bursts.
    pub fn wan(delay: Duration, rate_bytes_per_s: u64) -> Self {
        let rtt_bdp = (rate_bytes_per_s as f64 * 2.0 * delay.as_secs_f64()) as usize;
        Self {
            delay,
            rate_bytes_per_s: Some(rate_bytes_per_s),
            queue_bytes: rtt_bdp.saturating_mul(2).max(MIN_WAN_QUEUE_BYTES),
            ..Self::default()
        }
    }

    pub fn with_delay(mut self, delay: Duration) -> Self {
        self.delay = delay;
        self
    }

    pub fn with_rate(mut self, rate_bytes_per_s: Option<u64>) -> Self {
        self.rate_bytes_per_s = rate_bytes_per_s;
        self
    }

    pub fn with_loss(mut self, loss: f64) -> Self {
        self.loss = loss;
        self
    }

    pub fn with_queue_bytes(mut self, queue_bytes: usize) -> Self {
        self.queue_bytes = queue_bytes;
        self
    }

    pub fn with_seed(mut self, seed: u64) -> Self {
        self.seed = seed;
        self
    }

    /// Checks that every parameter is in range.
    pub fn validate(&self) -> io::Result<()> {
        let invalid = |msg: String| Err(io::Error::new(io::ErrorKind::InvalidInput, msg));
        if !(0.0..=1.0).contains(&self.loss) {
            return invalid(format!("link loss must be in 0..=1, got {}", self.loss));
        }
        if self.rate_bytes_per_s == Some(0) {
            return invalid("link rate must be positive (use None for unlimited)".into());
        }
        if self.queue_bytes == 0 {
            return invalid("link queue_bytes must be at least 1".into());
        }
        Ok(())
    }
}

/// Counters of one direction.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DirectionStats {
    /// Datagrams that entered the direction (forwarded, dropped, queued or failed).
    pub packets_in: u64,
    pub bytes_in: u64,
    /// Datagrams handed to the outgoing socket successfully.
    pub packets_forwarded: u64,
    pub bytes_forwarded: u64,
    /// Datagrams lost on purpose ([`LinkConfig::loss`]).
    pub dropped_loss: u64,
    /// Datagrams dropped because the buffer was full ([`LinkConfig::queue_bytes`]).
    pub dropped_queue: u64,
    /// Datagrams the outgoing socket refused.
    pub send_errors: u64,
    /// Bytes held right now (waiting for the link or propagating).
    pub queued_bytes: u64,
    /// Most bytes ever held at once; never above the `queue_bytes` in force at the time.
    pub peak_queued_bytes: u64,
}

/// Counters of an emulator.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Client → upstream server.
    pub upstream: DirectionStats,
    /// Upstream server → client.
    pub downstream: DirectionStats,
    /// Distinct client addresses seen (each has its own upstream socket).
    pub clients: u64,
    /// Datagrams not forwarded because they could not be routed: from a client beyond
    /// [`MAX_CLIENTS`], or arriving on a per-client socket from an address other than upstream.
    pub unroutable_packets: u64,
}

/// A packet waiting in a direction.
#[derive(Debug)]
struct Queued {
    release: Instant,
    data: Vec<u8>,
    socket: Arc<UdpSocket>,
    dest: SocketAddr,
}

/// Mutable state of one direction.
#[derive(Debug)]
struct PipeState {
    config: LinkConfig,
    rng: SplitMix64,
    /// When the link finishes serializing the last accepted packet.
    link_free_at: Instant,
    queue: VecDeque<Queued>,
    queued_bytes: usize,
    stats: DirectionStats,
}

/// One direction of the link: admission happens in the receiving task, release in the pipe's own
/// task.
#[derive(Debug)]
struct Pipe {
    /// Distinguishes the two directions' loss streams under one seed.
    salt: u64,
    state: Mutex<PipeState>,
    /// Wakes the release task when a packet arrives in an empty queue.
    wake: Notify,
}

impl Pipe {
    fn new(config: LinkConfig, salt: u64) -> Self {
        Self {
            salt,
            state: Mutex::new(PipeState {
                rng: Self::rng(config.seed, salt),
                config,
                link_free_at: Instant::now(),
                queue: VecDeque::new(),
                queued_bytes: 0,
                stats: DirectionStats::default(),
            }),
            wake: Notify::new(),
        }
    }

    fn rng(seed: u64, salt: u64) -> SplitMix64 {
        // Mix once so that nearby seeds give unrelated streams.
        SplitMix64::new(SplitMix64::new(seed ^ salt).next_u64())
    }

    fn lock(&self) -> MutexGuard<'_, PipeState> {
        // The state stays consistent even if a holder panicked: every update is a few plain stores.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn set_config(&self, config: LinkConfig) {
        let mut st = self.lock();
        if st.config.seed != config.seed {
            st.rng = Self::rng(config.seed, self.salt);
        }
        st.config = config;
    }

    /// Applies the link model to one arriving datagram (see the module docs).
    fn admit(&self, data: &[u8], socket: &Arc<UdpSocket>, dest: SocketAddr) {
        let now = Instant::now();
        let len = data.len();
        let mut st = self.lock();
        let st = &mut *st;
        st.stats.packets_in += 1;
        st.stats.bytes_in += len as u64;
        if st.queued_bytes + len > st.config.queue_bytes {
            st.stats.dropped_queue += 1;
            return;
        }
        let departure = match st.config.rate_bytes_per_s {
            Some(rate) => {
                let nanos = (len as u128 * 1_000_000_000).div_ceil(u128::from(rate));
                let start = st.link_free_at.max(now);
                st.link_free_at = start + Duration::from_nanos(nanos.min(u64::MAX as u128) as u64);
                st.link_free_at
            }
            None => now,
        };
        if st.config.loss > 0.0 && st.rng.next_f64() < st.config.loss {
            st.stats.dropped_loss += 1;
            return;
        }
        let was_empty = st.queue.is_empty();
        st.queue.push_back(Queued {
            release: departure + st.config.delay,
            data: data.to_vec(),
            socket: Arc::clone(socket),
            dest,
        });
        st.queued_bytes += len;
        st.stats.queued_bytes = st.queued_bytes as u64;
        st.stats.peak_queued_bytes = st.stats.peak_queued_bytes.max(st.stats.queued_bytes);
        if was_empty {
            self.wake.notify_one();
        }
    }

    /// The release task: sends every packet when it is due, in order.
    async fn run(self: Arc<Self>) {
        let mut due = Vec::new();
        loop {
            let next = {
                let mut st = self.lock();
                let now = Instant::now();
                while st.queue.front().is_some_and(|q| q.release <= now) {
                    let q = st.queue.pop_front().expect("front checked");
                    st.queued_bytes -= q.data.len();
                    due.push(q);
                }
                st.stats.queued_bytes = st.queued_bytes as u64;
                st.queue.front().map(|q| q.release)
            };
            if !due.is_empty() {
                let (mut packets, mut bytes, mut errors) = (0, 0, 0);
                for q in due.drain(..) {
                    match q.socket.send_to(&q.data, q.dest).await {
                        Ok(_) => {
                            packets += 1;
                            bytes += q.data.len() as u64;
                        }
                        Err(e) => {
                            errors += 1;
                            tracing::debug!(dest = %q.dest, error = %e, "link: send failed");
                        }
                    }
                }
                let mut st = self.lock();
                st.stats.packets_forwarded += packets;
                st.stats.bytes_forwarded += bytes;
                st.stats.send_errors += errors;
                // Sending took time: look at the queue again before sleeping.
                continue;
            }
            match next {
                Some(release) => {
                    tokio::select! {
                        () = tokio::time::sleep_until(release) => {}
                        () = self.wake.notified() => {}
                    }
                }
                None => self.wake.notified().await,
            }
        }
    }
}

/// Shared between the emulator handle and its tasks.
#[derive(Debug)]
struct Shared {
    up: Arc<Pipe>,
    down: Arc<Pipe>,
    clients: AtomicU64,
    unroutable: AtomicU64,
}

impl Shared {
    fn bump(counter: &AtomicU64) {
        counter.fetch_add(1, Ordering::Relaxed);
    }

    fn read(counter: &AtomicU64) -> u64 {
        counter.load(Ordering::Relaxed)
    }
}

/// A running link emulator. Dropping it (or [`LinkEmulator::shutdown`]) stops its tasks and
/// closes its sockets.
#[derive(Debug)]
pub struct LinkEmulator {
    local_addr: SocketAddr,
    upstream: SocketAddr,
    shared: Arc<Shared>,
    tasks: Vec<JoinHandle<()>>,
}

impl LinkEmulator {
    /// Starts an emulator listening on `127.0.0.1:0` that forwards to `upstream`. Must be called
    /// inside a tokio runtime with the time and I/O drivers enabled.
    pub async fn start(upstream: SocketAddr, config: LinkConfig) -> io::Result<Self> {
        Self::start_on(SocketAddr::from((Ipv4Addr::LOCALHOST, 0)), upstream, config).await
    }

    /// Starts an emulator listening on `listen` that forwards to `upstream`.
    pub async fn start_on(
        listen: SocketAddr,
        upstream: SocketAddr,
        config: LinkConfig,
    ) -> io::Result<Self> {
        config.validate()?;
        let front = Arc::new(UdpSocket::bind(listen).await?);
        let local_addr = front.local_addr()?;
        let shared = Arc::new(Shared {
            up: Arc::new(Pipe::new(config.clone(), 0x5550_5354_5245_414D)),
            down: Arc::new(Pipe::new(config, 0x444F_574E_5354_524D)),
            clients: AtomicU64::new(0),
            unroutable: AtomicU64::new(0),
        });
        let tasks = vec![
            tokio::spawn(Arc::clone(&shared.up).run()),
            tokio::spawn(Arc::clone(&shared.down).run()),
            tokio::spawn(front_task(front, upstream, Arc::clone(&shared))),
        ];
        tracing::debug!(%local_addr, %upstream, "link emulator started");
        Ok(Self {
            local_addr,
            upstream,
            shared,
            tasks,
        })
    }

    /// Opens another listening socket on `listen` that forwards to `upstream` through the same
    /// two directions, and returns its address: a second server behind the same bottleneck, so
    /// flows to different servers compete for one link's rate and buffer.
    pub async fn add_route(
        &mut self,
        listen: SocketAddr,
        upstream: SocketAddr,
    ) -> io::Result<SocketAddr> {
        let front = Arc::new(UdpSocket::bind(listen).await?);
        let addr = front.local_addr()?;
        self.tasks.push(tokio::spawn(front_task(
            front,
            upstream,
            Arc::clone(&self.shared),
        )));
        tracing::debug!(%addr, %upstream, "link emulator: route added");
        Ok(addr)
    }

    /// The address clients send to.
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The address everything is forwarded to.
    pub fn upstream(&self) -> SocketAddr {
        self.upstream
    }

    /// The parameters in force (the server → client direction's, when
    /// [`set_upstream_rate`](Self::set_upstream_rate) made the two differ).
    pub fn config(&self) -> LinkConfig {
        self.shared.down.lock().config.clone()
    }

    /// Changes the parameters of both directions for packets arriving from now on; packets
    /// already queued keep their release times (and later packets never overtake them). The loss
    /// generator restarts only when the seed changes.
    pub fn set_config(&self, config: LinkConfig) -> io::Result<()> {
        config.validate()?;
        self.shared.up.set_config(config.clone());
        self.shared.down.set_config(config);
        Ok(())
    }

    /// Changes the rate of the client → server direction only (bytes/s, `None` unlimited), for
    /// packets arriving from now on: an asymmetric link such as a home line or a mobile one,
    /// whose uplink is a fraction of its downlink. [`set_config`](Self::set_config) sets both
    /// directions again.
    pub fn set_upstream_rate(&self, rate_bytes_per_s: Option<u64>) -> io::Result<()> {
        let config = LinkConfig {
            rate_bytes_per_s,
            ..self.shared.up.lock().config.clone()
        };
        config.validate()?;
        self.shared.up.set_config(config);
        Ok(())
    }

    /// A snapshot of the counters.
    pub fn stats(&self) -> LinkStats {
        LinkStats {
            upstream: self.shared.up.lock().stats,
            downstream: self.shared.down.lock().stats,
            clients: Shared::read(&self.shared.clients),
            unroutable_packets: Shared::read(&self.shared.unroutable),
        }
    }

    /// Stops all tasks and waits until they are gone, so every socket is closed on return.
    pub async fn shutdown(mut self) {
        let tasks = std::mem::take(&mut self.tasks);
        for t in &tasks {
            t.abort();
        }
        for t in tasks {
            let _ = t.await;
        }
    }
}

impl Drop for LinkEmulator {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

/// Whether a receive error is worth retrying at once (ICMP errors reported on the socket).
fn transient(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::Interrupted
            | io::ErrorKind::WouldBlock
    )
}

/// Backs off briefly after an unexpected receive error so a persistent one cannot spin.
async fn after_recv_error(what: &str, e: &io::Error) {
    if !transient(e) {
        tracing::warn!(error = %e, "link: receive on {what} failed");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// The address a per-client socket binds: loopback when upstream is on loopback, else any.
fn upstream_bind_addr(upstream: SocketAddr) -> SocketAddr {
    let ip = match (upstream.ip(), upstream.ip().is_loopback()) {
        (IpAddr::V4(_), true) => IpAddr::V4(Ipv4Addr::LOCALHOST),
        (IpAddr::V4(_), false) => IpAddr::V4(Ipv4Addr::UNSPECIFIED),
        (IpAddr::V6(_), true) => IpAddr::V6(Ipv6Addr::LOCALHOST),
        (IpAddr::V6(_), false) => IpAddr::V6(Ipv6Addr::UNSPECIFIED),
    };
    SocketAddr::new(ip, 0)
}

/// Receives from clients, opens one upstream socket per client, feeds the upstream pipe. Owns the
/// per-client reader tasks: they stop when this task does.
async fn front_task(front: Arc<UdpSocket>, upstream: SocketAddr, shared: Arc<Shared>) {
    let mut clients: HashMap<SocketAddr, Arc<UdpSocket>> = HashMap::new();
    let mut readers = JoinSet::new();
    let mut buf = vec![0u8; MAX_DATAGRAM + 1];
    loop {
        let (n, client) = match front.recv_from(&mut buf).await {
            Ok(r) => r,
            Err(e) => {
                after_recv_error("listen socket", &e).await;
                continue;
            }
        };
        let sock = match clients.get(&client) {
            Some(s) => Arc::clone(s),
            None => {
                if clients.len() >= MAX_CLIENTS {
                    Shared::bump(&shared.unroutable);
                    continue;
                }
                let sock = match UdpSocket::bind(upstream_bind_addr(upstream)).await {
                    Ok(s) => Arc::new(s),
                    Err(e) => {
                        tracing::warn!(%client, error = %e, "link: cannot open upstream socket");
                        Shared::bump(&shared.unroutable);
                        continue;
                    }
                };
                tracing::debug!(%client, via = ?sock.local_addr().ok(), "link: new client");
                clients.insert(client, Arc::clone(&sock));
                Shared::bump(&shared.clients);
                readers.spawn(reader_task(
                    Arc::clone(&sock),
                    upstream,
                    client,
                    Arc::clone(&front),
                    Arc::clone(&shared),
                ));
                sock
            }
        };
        shared.up.admit(&buf[..n], &sock, upstream);
        // Reap finished readers (they only end on panic) without waiting.
        while readers.try_join_next().is_some() {}
    }
}

/// Receives the upstream server's replies for one client and feeds the downstream pipe.
async fn reader_task(
    sock: Arc<UdpSocket>,
    upstream: SocketAddr,
    client: SocketAddr,
    front: Arc<UdpSocket>,
    shared: Arc<Shared>,
) {
    let mut buf = vec![0u8; MAX_DATAGRAM + 1];
    loop {
        let (n, from) = match sock.recv_from(&mut buf).await {
            Ok(r) => r,
            Err(e) => {
                after_recv_error("upstream socket", &e).await;
                continue;
            }
        };
        if from != upstream {
            Shared::bump(&shared.unroutable);
            continue;
        }
        shared.down.admit(&buf[..n], &front, client);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splitmix_is_uniform_enough() {
        let mut r = SplitMix64::new(42);
        let n = 100_000;
        let below = (0..n).filter(|_| r.next_f64() < 0.3).count();
        let frac = below as f64 / n as f64;
        assert!((0.29..0.31).contains(&frac), "{frac}");
    }

    #[test]
    fn config_validation() {
        assert!(LinkConfig::default().validate().is_ok());
        assert!(LinkConfig::default().with_loss(1.5).validate().is_err());
        assert!(
            LinkConfig::default()
                .with_loss(f64::NAN)
                .validate()
                .is_err()
        );
        assert!(LinkConfig::default().with_rate(Some(0)).validate().is_err());
        assert!(
            LinkConfig::default()
                .with_queue_bytes(0)
                .validate()
                .is_err()
        );
    }

    #[test]
    fn wan_queue_is_twice_the_rtt_bdp() {
        let c = LinkConfig::wan(Duration::from_millis(25), 12_500_000);
        assert_eq!(c.queue_bytes, 2 * 12_500_000 / 20);
        let small = LinkConfig::wan(Duration::from_millis(1), 1000);
        assert_eq!(small.queue_bytes, MIN_WAN_QUEUE_BYTES);
    }
}
