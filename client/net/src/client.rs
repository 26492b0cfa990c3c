//! The caller's handle: [`TreeletClient`].

use std::collections::VecDeque;
use std::sync::Arc;

use arbor_proto::frame::encode;
use arbor_proto::limits::MAX_REQUEST_ITEMS;
use arbor_proto::wire::{Frame, HELLO_VIEW, PROTOCOL_VERSION, ViewHint};
use arbor_proto::{SceneDescription, TreeletId};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;

use super::backoff::Jitter;
use super::config::ClientConfig;
use super::connection::{RequestList, Task, Wishes};
use super::error::ClientError;
use super::event::{ClientEvent, ClientStats};
use super::replicas::Replicas;
use super::shared::{Queued, Shared};
use super::tls::install_crypto_provider;
use super::transport::{CLOSE_TIMEOUT, quinn_client_config};

/// A connection to one scene on a treelet server (or one of its replicas), kept up in the
/// background.
///
/// [`TreeletClient::start`] spawns a task on the current tokio runtime that connects, sends
/// `Hello`, and from then on sends the latest request list whenever it changes, receives
/// treelets, and reconnects with backoff when the connection goes away (unless the server's
/// close code says it cannot help). No method blocks: [`request`](Self::request) replaces a
/// latest-value slot, events queue up for [`try_next_event`](Self::try_next_event) /
/// [`next_event`](Self::next_event), and the queued treelets are bounded by
/// [`ClientConfig::max_buffered_bytes`] (when the caller does not take them, the client stops
/// reading and the server is slowed by QUIC flow control).
///
/// Dropping the handle closes the connection in the background; [`close`](Self::close) does
/// the same and waits for it.
#[derive(Debug)]
pub struct TreeletClient {
    shared: Arc<Shared>,
    lists: watch::Sender<Option<RequestList>>,
    events: mpsc::UnboundedReceiver<Queued>,
    /// The batch being taken from: its events not yet taken, and the budget it holds until
    /// the last one is.
    taking: Queued,
    shutdown: watch::Sender<bool>,
    task: Option<JoinHandle<()>>,
}

impl TreeletClient {
    /// Checks `config` and starts the connection task. Returns at once; the connection is made
    /// in the background and reported as [`ClientEvent::Connected`] (or
    /// [`ClientEvent::Disconnected`]). Must be called inside a tokio runtime.
    pub fn start(config: ClientConfig) -> Result<Self, ClientError> {
        config.validate()?;
        let runtime = tokio::runtime::Handle::try_current().map_err(|_| ClientError::NoRuntime)?;
        install_crypto_provider();
        let quinn_config = quinn_client_config(
            &config.trust,
            config.idle_timeout(),
            config.list_send_window,
        )?;
        let hello = |view: Option<ViewHint>| {
            let flags = config.hello_flags | if view.is_some() { HELLO_VIEW } else { 0 };
            encode(&Frame::Hello {
                version: PROTOCOL_VERSION,
                scene: config.url.scene.clone(),
                channels: config.channels.clone(),
                token: config.token.clone(),
                flags,
                view,
            })
            .map_err(|e| ClientError::InvalidConfig(format!("Hello: {e}")))
        };
        let first_hello = config.hello_view.map(|v| hello(Some(v))).transpose()?;
        let hello = hello(None)?;
        let shared = Arc::new(Shared::new(config.max_buffered_bytes));
        let (lists_tx, lists_rx) = watch::channel(None);
        let (shutdown_tx, shutdown_rx) = watch::channel(false);
        let (events_tx, events_rx) = mpsc::unbounded_channel();
        let task = Task {
            replicas: Replicas::new(config.servers()),
            config,
            quinn_config,
            first_hello,
            hello,
            shared: shared.clone(),
            events: events_tx,
            lists: lists_rx,
            shutdown: shutdown_rx,
            jitter: Jitter::from_entropy(),
            next_addr: 0,
            last_server: None,
        };
        let task = runtime.spawn(task.run());
        Ok(Self {
            shared,
            lists: lists_tx,
            events: events_rx,
            taking: Queued {
                events: VecDeque::new(),
                lease: None,
            },
            shutdown: shutdown_tx,
            task: Some(task),
        })
    }

    /// Replaces the request list: `(treelet, priority)`, higher priority first (see
    /// [`arbor_proto::wire`] for the semantics). The connection sends it as soon as it can with
    /// the next sequence number, and again after every reconnect; a list replaced before it was
    /// sent is never sent. Ids the scene does not have are left out when sending.
    pub fn request(&self, items: Vec<(TreeletId, f32)>) -> Result<(), ClientError> {
        self.check(&items)?;
        self.lists
            .send_replace(Some(Arc::new(Wishes { items, deep: None })));
        Ok(())
    }

    /// Checks a list against the protocol's limits before it is queued.
    fn check(&self, items: &[(TreeletId, f32)]) -> Result<(), ClientError> {
        if items.len() > MAX_REQUEST_ITEMS {
            return Err(ClientError::InvalidRequest(format!(
                "{} items, at most {MAX_REQUEST_ITEMS}",
                items.len()
            )));
        }
        if let Some((i, (id, p))) = items
            .iter()
            .enumerate()
            .find(|(_, (id, p))| id.is_none() || !p.is_finite())
        {
            return Err(ClientError::InvalidRequest(format!(
                "item {i}: treelet {id} with priority {p}: ids must not be NONE and priorities \
                 must be finite"
            )));
        }
        Ok(())
    }

    /// Replaces the request list with a deep one ([`arbor_proto::wire::Frame::DeepRequestList`]):
    /// `(treelet, priority, error in levels)` and the view the errors were measured in, so the
    /// server may also send the descendants that view would refine. Items from `prefetch_from`
    /// on are prefetch (the frame's `prefetch_from`; `items.len()` or more: none). Errors are
    /// clamped to ±[`ViewHint::MAX_ERROR`].
    pub fn request_deep(
        &self,
        items: Vec<(TreeletId, f32, f32)>,
        view: ViewHint,
        prefetch_from: usize,
    ) -> Result<(), ClientError> {
        let prefetch_from = prefetch_from.min(items.len());
        view.check()
            .map_err(|e| ClientError::InvalidRequest(format!("view: {e}")))?;
        if let Some((i, (id, _, e))) = items.iter().enumerate().find(|(_, (_, _, e))| e.is_nan()) {
            return Err(ClientError::InvalidRequest(format!(
                "item {i}: treelet {id} with error {e}: errors must be numbers"
            )));
        }
        let (plain, errors): (Vec<(TreeletId, f32)>, Vec<f32>) = items
            .into_iter()
            .map(|(id, p, e)| ((id, p), e.clamp(-ViewHint::MAX_ERROR, ViewHint::MAX_ERROR)))
            .unzip();
        self.check(&plain)?;
        self.lists.send_replace(Some(Arc::new(Wishes {
            items: plain,
            deep: Some((view, errors, prefetch_from)),
        })));
        Ok(())
    }

    /// The next event if one is queued.
    pub fn try_next_event(&mut self) -> Option<ClientEvent> {
        loop {
            if let Some(e) = self.take_queued() {
                return Some(e);
            }
            self.taking = self.events.try_recv().ok()?;
        }
    }

    /// Waits for the next event; `None` once the client has given up (after a final
    /// [`ClientEvent::Disconnected`]) or was closed, and every event was taken.
    pub async fn next_event(&mut self) -> Option<ClientEvent> {
        loop {
            if let Some(e) = self.take_queued() {
                return Some(e);
            }
            self.taking = self.events.recv().await?;
        }
    }

    /// The next event of the batch being taken; the batch's budget is given back with its
    /// last event.
    fn take_queued(&mut self) -> Option<ClientEvent> {
        let event = self.taking.events.pop_front();
        if self.taking.events.is_empty() {
            self.taking.lease = None;
        }
        event
    }

    /// The scene of the current (or last) connection. With replicas it is the same on every
    /// server: one that describes it differently is refused.
    pub fn scene(&self) -> Option<Arc<SceneDescription>> {
        self.shared.scene()
    }

    pub fn stats(&self) -> ClientStats {
        self.shared.stats().clone()
    }

    /// Whether the connection task has ended (gave up for good, or closed).
    pub fn is_finished(&self) -> bool {
        self.task.as_ref().is_none_or(|t| t.is_finished())
    }

    /// Closes gracefully: `Goodbye` on the control stream, QUIC close with
    /// [`ErrorCode::NoError`](arbor_proto::wire::ErrorCode::NoError), and waits (a few seconds
    /// at most) until that is sent.
    pub async fn close(mut self) {
        let _ = self.shutdown.send(true);
        if let Some(task) = self.task.take() {
            let _ = tokio::time::timeout(3 * CLOSE_TIMEOUT, task).await;
        }
    }
}

impl Drop for TreeletClient {
    fn drop(&mut self) {
        let _ = self.shutdown.send(true);
    }
}
