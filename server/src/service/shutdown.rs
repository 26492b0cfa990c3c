//! Graceful shutdown plumbing, in the style of mini-redis: a broadcast that every task listens
//! to, and a drop-to-finish channel that tells the server when the last connection task is gone.
//!
//! * [`ShutdownTrigger::trigger`] starts shutdown once, fixing its **deadline** (now + grace):
//!   in-flight treelet streams may finish until then.
//! * Every task holds a `Shutdown` and selects on `Shutdown::recv`, which yields the
//!   deadline.
//! * Every connection task holds a clone of the `Done` sender; the server drops its own and
//!   waits for the receiver to see all senders gone.

use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::{mpsc, watch};

/// Starts the server's graceful shutdown. Cheap to clone.
#[derive(Clone, Debug)]
pub struct ShutdownTrigger {
    tx: Arc<watch::Sender<Option<Instant>>>,
    grace: Duration,
}

impl ShutdownTrigger {
    /// Begins shutdown (idempotent: the first call fixes the deadline).
    pub fn trigger(&self) {
        let deadline = Instant::now() + self.grace;
        self.tx.send_if_modified(|d| {
            if d.is_none() {
                *d = Some(deadline);
                true
            } else {
                false
            }
        });
    }

    /// Whether shutdown has begun.
    pub fn is_triggered(&self) -> bool {
        self.tx.borrow().is_some()
    }
}

/// Listens for the shutdown broadcast.
#[derive(Clone, Debug)]
pub(crate) struct Shutdown {
    rx: watch::Receiver<Option<Instant>>,
}

impl Shutdown {
    /// The deadline, if shutdown has begun.
    pub(crate) fn deadline(&self) -> Option<Instant> {
        *self.rx.borrow()
    }

    /// Waits until shutdown begins and returns its deadline. Cancel-safe.
    pub(crate) async fn recv(&mut self) -> Instant {
        loop {
            if let Some(d) = *self.rx.borrow_and_update() {
                return d;
            }
            if self.rx.changed().await.is_err() {
                // The trigger is gone: nobody can stop us gracefully any more; stop now.
                return Instant::now();
            }
        }
    }
}

/// A new trigger/listener pair with the given grace.
pub(crate) fn channel(grace: Duration) -> (ShutdownTrigger, Shutdown) {
    let (tx, rx) = watch::channel(None);
    (
        ShutdownTrigger {
            tx: Arc::new(tx),
            grace,
        },
        Shutdown { rx },
    )
}

/// Held by every connection task; dropped when it ends.
pub(crate) type Done = mpsc::Sender<()>;

/// The drop-to-finish pair.
pub(crate) fn done_channel() -> (Done, mpsc::Receiver<()>) {
    mpsc::channel(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn trigger_fixes_the_deadline_once() {
        let (t, mut s) = channel(Duration::from_secs(5));
        assert_eq!(s.deadline(), None);
        assert!(!t.is_triggered());
        let waiter = tokio::spawn({
            let mut s = s.clone();
            async move { s.recv().await }
        });
        t.trigger();
        let d = s.recv().await;
        t.trigger();
        assert_eq!(s.deadline(), Some(d));
        assert_eq!(waiter.await.unwrap(), d);
        assert!(d > Instant::now() + Duration::from_secs(4));
        let (done, mut rx) = done_channel();
        let a = done.clone();
        drop(done);
        tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(10)).await;
            drop(a);
        });
        assert!(rx.recv().await.is_none());
    }
}
