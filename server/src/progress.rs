//! How far an import has come, readable from another thread while it runs (the daemon's
//! `GET /v1/imports/{id}` and status page): a phase and a done/total count, all atomics, so the
//! build never waits on a reader.

use std::sync::atomic::{AtomicU8, AtomicU64, Ordering};

use serde::Serialize;

/// The steps of an import, in order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// Waiting for an earlier import to finish.
    Queued,
    /// Reading the headers and the points or primitives into scratch columns.
    Reading,
    /// Bounds, the data's resolution and, for points, normals.
    Placing,
    /// Filling treelets (`done` counts treelets; the total is unknown until the end).
    Filling,
    /// Averaging inner attributes, compressing and storing (`done` of `total` treelets: those
    /// whose node and attribute blocks are both stored).
    Packing,
    /// Flushing and publishing the scene.
    Committing,
    /// The scene is published.
    Done,
    /// The import failed; the pool is as it was.
    Failed,
}

const PHASES: [Phase; 8] = [
    Phase::Queued,
    Phase::Reading,
    Phase::Placing,
    Phase::Filling,
    Phase::Packing,
    Phase::Committing,
    Phase::Done,
    Phase::Failed,
];

/// Progress of one import.
#[derive(Debug, Default)]
pub struct ImportProgress {
    phase: AtomicU8,
    done: AtomicU64,
    total: AtomicU64,
}

/// A consistent-enough copy of an [`ImportProgress`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct ProgressSnapshot {
    pub phase: Phase,
    pub done: u64,
    /// 0 when unknown.
    pub total: u64,
}

impl ImportProgress {
    /// Enters `phase` with `total` units of work (0: unknown).
    pub fn enter(&self, phase: Phase, total: u64) {
        self.done.store(0, Ordering::Relaxed);
        self.total.store(total, Ordering::Relaxed);
        self.phase.store(phase as u8, Ordering::Release);
    }

    /// Sets the units of work done in the current phase.
    pub fn set_done(&self, done: u64) {
        self.done.store(done, Ordering::Relaxed);
    }

    pub fn snapshot(&self) -> ProgressSnapshot {
        let phase = PHASES[usize::from(self.phase.load(Ordering::Acquire)).min(PHASES.len() - 1)];
        ProgressSnapshot {
            phase,
            done: self.done.load(Ordering::Relaxed),
            total: self.total.load(Ordering::Relaxed),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phases_round_trip() {
        let p = ImportProgress::default();
        assert_eq!(p.snapshot().phase, Phase::Queued);
        for (i, &phase) in PHASES.iter().enumerate() {
            assert_eq!(phase as usize, i);
            p.enter(phase, 10);
            p.set_done(3);
            assert_eq!(
                p.snapshot(),
                ProgressSnapshot {
                    phase,
                    done: 3,
                    total: 10
                }
            );
        }
    }
}
