//! A per-treelet timeline of what the service was asked for and sent, for benchmarks that ask
//! where the time between a view's first request and its last needed treelet went.
//!
//! Off by default: recording costs one relaxed atomic load per event until [`Timeline::start`]
//! is called. When on, every applied request list (its listed and its pushed treelets), every
//! batch handed to a stream and every batch's end is kept, up to [`MAX_RECORDED_IDS`] treelet
//! ids in all; beyond it recording stops and [`Recording::truncated`] says so.
//!
//! [`Breakdown::of`] is the analysis, plain data: given the treelets a view needs and each
//! treelet's bytes, the moment the last needed treelet was acknowledged, when that treelet was
//! first named (by the client's list or by a push) and first sent, and the bytes acknowledged
//! before it, split by who named them and whether the view needed them. Measured with it on
//! the engine over the link emulator: the treelets of a view's tail were named 150–250 ms
//! before they were sent, and half of the pushed bytes before them were not needed.
//! [`progress`] samples the same moments every few milliseconds: how many needed treelets were
//! still unnamed, named and waiting, in flight or acknowledged, and the bytes sent and
//! acknowledged by then (it showed the link idle while needed treelets named by an earlier plan
//! waited in no current list — see `push::PushAnchors`).

use std::collections::{HashMap, HashSet};
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use arbor_proto::TreeletId;

/// Most treelet ids one recording keeps.
pub const MAX_RECORDED_IDS: usize = 1 << 24;

/// Something the service did for connection `session` at `at`.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// A request list replaced the queue: the treelets the client listed, then those the
    /// server added as pushes.
    Listed {
        session: u64,
        at: Instant,
        listed: Vec<TreeletId>,
        pushed: Vec<TreeletId>,
    },
    /// A batch was handed to a stream.
    Dispatched {
        session: u64,
        at: Instant,
        batch: Vec<TreeletId>,
    },
    /// A batch's stream ended: acknowledged in full (`delivered`) or not.
    Ended {
        session: u64,
        at: Instant,
        batch: Vec<TreeletId>,
        delivered: bool,
    },
}

/// What one recording kept.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Recording {
    pub events: Vec<Event>,
    /// Recording stopped at [`MAX_RECORDED_IDS`].
    pub truncated: bool,
}

/// The recorder (see the module docs).
#[derive(Debug, Default)]
pub struct Timeline {
    on: AtomicBool,
    recording: Mutex<(Recording, usize)>,
}

impl Timeline {
    /// Starts a fresh recording (what an earlier one kept is dropped).
    pub fn start(&self) {
        *self.lock() = (Recording::default(), 0);
        self.on.store(true, Ordering::Relaxed);
    }

    /// Stops recording and returns what was kept.
    pub fn take(&self) -> Recording {
        self.on.store(false, Ordering::Relaxed);
        std::mem::take(&mut self.lock().0)
    }

    /// A copy of what the recording has kept so far; it goes on.
    pub fn snapshot(&self) -> Recording {
        self.lock().0.clone()
    }

    /// Whether a recording is on; callers build an event only then.
    pub fn is_on(&self) -> bool {
        self.on.load(Ordering::Relaxed)
    }

    /// Keeps `event` if a recording is on and has room.
    pub fn record(&self, event: impl FnOnce() -> Event) {
        if !self.is_on() {
            return;
        }
        let event = event();
        let ids = match &event {
            Event::Listed { listed, pushed, .. } => listed.len() + pushed.len(),
            Event::Dispatched { batch, .. } | Event::Ended { batch, .. } => batch.len(),
        };
        let mut guard = self.lock();
        let (recording, kept) = &mut *guard;
        if recording.truncated || *kept + ids > MAX_RECORDED_IDS {
            recording.truncated = true;
            return;
        }
        *kept += ids;
        recording.events.push(event);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (Recording, usize)> {
        self.recording.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// Who named a treelet first.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum NamedBy {
    /// The client's list.
    List,
    /// A server push.
    Push,
    /// Nothing the recording saw: named before it started (after a camera jump, what the first
    /// view asked for and is still on its way).
    Earlier,
}

/// One treelet's moments, seconds after the breakdown's start.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TreeletMoments {
    /// First named, and by whom.
    pub named: Option<(f64, NamedBy)>,
    /// Last named before it was first sent (the naming that sent it), and by whom.
    pub named_for_send: Option<(f64, NamedBy)>,
    /// First handed to a stream.
    pub sent: Option<f64>,
    /// First acknowledged.
    pub delivered: Option<f64>,
}

/// Where the time to a view's last needed treelet went (see the module docs).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Breakdown {
    /// The needed treelet acknowledged last, with its moments; `None` if no needed treelet was
    /// acknowledged.
    pub last_needed: Option<(TreeletId, TreeletMoments)>,
    /// Needed treelets never acknowledged.
    pub needed_missing: usize,
    /// Bytes acknowledged up to and including the last needed treelet, by who named them first
    /// and whether the view needs them: `(named by, needed) → (treelets, bytes)`.
    pub before_last: HashMap<(NamedBy, bool), (u64, u64)>,
}

impl Breakdown {
    /// The breakdown of `session` in `recording`, times relative to `start`.
    pub fn of(
        recording: &Recording,
        session: u64,
        start: Instant,
        needed: &HashSet<TreeletId>,
        bytes: impl Fn(TreeletId) -> u64,
    ) -> Breakdown {
        let (moments, delivered_order) = moments(recording, session, start);
        let last_needed = delivered_order
            .iter()
            .filter(|(_, id)| needed.contains(id))
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .map(|&(_, id)| (id, moments[&id]));
        let needed_missing = needed
            .iter()
            .filter(|id| moments.get(id).is_none_or(|m| m.delivered.is_none()))
            .count();
        let mut before_last = HashMap::new();
        if let Some((_, last)) = &last_needed {
            let until = last.delivered.unwrap_or(f64::INFINITY);
            for &(t, id) in &delivered_order {
                if t > until {
                    continue;
                }
                let by = moments[&id].named.map_or(NamedBy::Earlier, |(_, by)| by);
                let e: &mut (u64, u64) = before_last.entry((by, needed.contains(&id))).or_default();
                e.0 += 1;
                e.1 += bytes(id);
            }
        }
        Breakdown {
            last_needed,
            needed_missing,
            before_last,
        }
    }

    /// One line: the last needed treelet's moments and the bytes before it.
    pub fn summary(&self) -> String {
        let Some((id, m)) = &self.last_needed else {
            return "no needed treelet acknowledged".into();
        };
        let at = |t: Option<f64>| t.map_or("-".into(), |t| format!("{t:.3}"));
        let named = |n: Option<(f64, NamedBy)>| {
            n.map_or("-".into(), |(t, by)| {
                let by = match by {
                    NamedBy::List => "list",
                    NamedBy::Push => "push",
                    NamedBy::Earlier => "earlier",
                };
                format!("{t:.3} by {by}")
            })
        };
        let part = |by: NamedBy| {
            let (n_need, b_need) = self
                .before_last
                .get(&(by, true))
                .copied()
                .unwrap_or_default();
            let (n_waste, b_waste) = self
                .before_last
                .get(&(by, false))
                .copied()
                .unwrap_or_default();
            format!(
                "{} needed ({:.2} MB) + {} not ({:.2} MB)",
                n_need,
                b_need as f64 / 1e6,
                n_waste,
                b_waste as f64 / 1e6
            )
        };
        format!(
            "last needed treelet {} named at {} (last before sending at {}), sent {}, acked {}; \
             acked up to then: listed {}, pushed {}{}{}",
            id.0,
            named(m.named),
            named(m.named_for_send),
            at(m.sent),
            at(m.delivered),
            part(NamedBy::List),
            part(NamedBy::Push),
            if self
                .before_last
                .keys()
                .any(|(by, _)| *by == NamedBy::Earlier)
            {
                format!(", named before the recording {}", part(NamedBy::Earlier))
            } else {
                String::new()
            },
            if self.needed_missing > 0 {
                format!("; {} needed never acked", self.needed_missing)
            } else {
                String::new()
            }
        )
    }
}

/// Where a view's needed treelets stood at one moment, and the bytes handed to streams and
/// acknowledged by then, split by whether the view needs them ([`progress`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Progress {
    /// Seconds after the start.
    pub at: f64,
    /// Needed treelets not named yet.
    pub unnamed: usize,
    /// Named (listed or pushed), not handed to a stream yet.
    pub named: usize,
    /// Handed to a stream, not acknowledged yet.
    pub sent: usize,
    /// Acknowledged.
    pub acked: usize,
    /// Bytes handed to streams: `(needed, not needed)`.
    pub sent_bytes: (u64, u64),
    /// Bytes acknowledged: `(needed, not needed)`.
    pub acked_bytes: (u64, u64),
}

/// [`Progress`] of `session` every `step` seconds after `start`, up to `until`: where the time
/// between naming a needed treelet and its arrival went (a needed treelet named but not sent
/// while the bytes sent stand still is one no current list names).
pub fn progress(
    recording: &Recording,
    session: u64,
    start: Instant,
    needed: &HashSet<TreeletId>,
    bytes: impl Fn(TreeletId) -> u64,
    step: f64,
    until: f64,
) -> Vec<Progress> {
    let (moments, _) = moments(recording, session, start);
    let by = |t: Option<f64>, at: f64| t.is_some_and(|t| t <= at);
    let steps = if step > 0.0 && until.is_finite() {
        (until / step).floor().clamp(0.0, 1e6) as usize
    } else {
        0
    };
    (1..=steps)
        .map(|k| {
            let at = k as f64 * step;
            let mut p = Progress {
                at,
                ..Progress::default()
            };
            for id in needed {
                let m = moments.get(id).copied().unwrap_or_default();
                if by(m.delivered, at) {
                    p.acked += 1;
                } else if by(m.sent, at) {
                    p.sent += 1;
                } else if by(m.named.map(|n| n.0), at) {
                    p.named += 1;
                } else {
                    p.unnamed += 1;
                }
            }
            for (id, m) in &moments {
                let b = bytes(*id);
                let side = |pair: &mut (u64, u64)| {
                    if needed.contains(id) {
                        pair.0 += b;
                    } else {
                        pair.1 += b;
                    }
                };
                if by(m.sent, at) {
                    side(&mut p.sent_bytes);
                }
                if by(m.delivered, at) {
                    side(&mut p.acked_bytes);
                }
            }
            p
        })
        .collect()
}

/// Every treelet's moments in `session`'s events, seconds after `start`, and the deliveries in
/// the order they happened.
fn moments(
    recording: &Recording,
    session: u64,
    start: Instant,
) -> (HashMap<TreeletId, TreeletMoments>, Vec<(f64, TreeletId)>) {
    let secs = |at: &Instant| at.saturating_duration_since(start).as_secs_f64();
    let mut moments: HashMap<TreeletId, TreeletMoments> = HashMap::new();
    let mut delivered_order: Vec<(f64, TreeletId)> = Vec::new();
    for event in &recording.events {
        match event {
            Event::Listed {
                session: s,
                at,
                listed,
                pushed,
            } if *s == session => {
                let t = secs(at);
                let named = listed
                    .iter()
                    .map(|&id| (id, NamedBy::List))
                    .chain(pushed.iter().map(|&id| (id, NamedBy::Push)));
                for (id, by) in named {
                    let m = moments.entry(id).or_default();
                    m.named.get_or_insert((t, by));
                    if m.sent.is_none() {
                        m.named_for_send = Some((t, by));
                    }
                }
            }
            Event::Dispatched {
                session: s,
                at,
                batch,
            } if *s == session => {
                for &id in batch {
                    moments.entry(id).or_default().sent.get_or_insert(secs(at));
                }
            }
            Event::Ended {
                session: s,
                at,
                batch,
                delivered: true,
            } if *s == session => {
                for &id in batch {
                    let m = moments.entry(id).or_default();
                    if m.delivered.is_none() {
                        m.delivered = Some(secs(at));
                        delivered_order.push((secs(at), id));
                    }
                }
            }
            _ => {}
        }
    }
    (moments, delivered_order)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn ids(v: &[u32]) -> Vec<TreeletId> {
        v.iter().map(|&i| TreeletId(i)).collect()
    }

    #[test]
    fn off_records_nothing_and_start_clears() {
        let t = Timeline::default();
        let now = Instant::now();
        let ev = || Event::Dispatched {
            session: 1,
            at: now,
            batch: ids(&[1]),
        };
        t.record(ev);
        assert!(t.take().events.is_empty());
        t.start();
        t.record(ev);
        t.start();
        t.record(ev);
        assert_eq!(
            t.snapshot().events.len(),
            1,
            "a snapshot leaves the recording on"
        );
        let r = t.take();
        assert_eq!(r.events.len(), 1);
        assert!(!r.truncated);
        t.record(ev);
        assert!(t.take().events.is_empty(), "take stops the recording");
    }

    #[test]
    fn a_recording_stops_at_its_limit() {
        let t = Timeline::default();
        t.start();
        let now = Instant::now();
        let big = vec![TreeletId(0); MAX_RECORDED_IDS / 2 + 1];
        for _ in 0..3 {
            t.record(|| Event::Dispatched {
                session: 1,
                at: now,
                batch: big.clone(),
            });
        }
        let r = t.take();
        assert_eq!(r.events.len(), 1);
        assert!(r.truncated);
    }

    #[test]
    fn breakdown_finds_the_last_needed_and_what_went_before() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let events = vec![
            Event::Listed {
                session: 7,
                at: at(10),
                listed: ids(&[1, 2]),
                pushed: ids(&[3, 4]),
            },
            // Another connection's events are ignored.
            Event::Dispatched {
                session: 8,
                at: at(11),
                batch: ids(&[2]),
            },
            // 9 was named before the recording started.
            Event::Ended {
                session: 7,
                at: at(15),
                batch: ids(&[9]),
                delivered: true,
            },
            Event::Dispatched {
                session: 7,
                at: at(20),
                batch: ids(&[1, 3]),
            },
            Event::Ended {
                session: 7,
                at: at(70),
                batch: ids(&[1, 3]),
                delivered: true,
            },
            // 5 is named later by a push; 2 by the first list, listed again here.
            Event::Listed {
                session: 7,
                at: at(80),
                listed: ids(&[2]),
                pushed: ids(&[5]),
            },
            Event::Dispatched {
                session: 7,
                at: at(90),
                batch: ids(&[4, 2]),
            },
            Event::Ended {
                session: 7,
                at: at(150),
                batch: ids(&[4, 2]),
                delivered: true,
            },
            // Reset, not delivered: 5 never arrives.
            Event::Dispatched {
                session: 7,
                at: at(160),
                batch: ids(&[5]),
            },
            Event::Ended {
                session: 7,
                at: at(170),
                batch: ids(&[5]),
                delivered: false,
            },
        ];
        let recording = Recording {
            events,
            truncated: false,
        };
        let needed: HashSet<TreeletId> = ids(&[1, 2, 5]).into_iter().collect();
        let b = Breakdown::of(&recording, 7, t0, &needed, |id| 100 * u64::from(id.0));
        let (last, m) = b.last_needed.unwrap();
        assert_eq!(last, TreeletId(2));
        assert_eq!(m.named, Some((0.010, NamedBy::List)));
        assert_eq!(m.named_for_send, Some((0.080, NamedBy::List)));
        assert_eq!(m.sent, Some(0.090));
        assert_eq!(m.delivered, Some(0.150));
        assert_eq!(b.needed_missing, 1);
        assert_eq!(b.before_last[&(NamedBy::List, true)], (2, 300));
        assert_eq!(b.before_last[&(NamedBy::Push, false)], (2, 700));
        assert!(!b.before_last.contains_key(&(NamedBy::Push, true)));
        assert_eq!(b.before_last[&(NamedBy::Earlier, false)], (1, 900));
        let s = b.summary();
        assert!(
            s.contains("last needed treelet 2 named at 0.010 by list (last before sending at 0.080 by list)"),
            "{s}"
        );
        assert!(s.contains("1 needed never acked"), "{s}");
        assert!(
            s.contains("named before the recording 0 needed (0.00 MB) + 1 not (0.00 MB)"),
            "{s}"
        );

        let p = progress(
            &recording,
            7,
            t0,
            &needed,
            |id| 100 * u64::from(id.0),
            0.05,
            0.2,
        );
        assert_eq!(p.len(), 4);
        for (k, p) in p.iter().enumerate() {
            assert!((p.at - 0.05 * (k + 1) as f64).abs() < 1e-12, "{p:?}");
        }
        let counts = |p: &Progress| (p.unnamed, p.named, p.sent, p.acked);
        assert_eq!(counts(&p[0]), (1, 1, 1, 0));
        assert_eq!((p[0].sent_bytes, p[0].acked_bytes), ((100, 300), (0, 900)));
        assert_eq!(counts(&p[1]), (0, 1, 1, 1));
        assert_eq!(
            (p[1].sent_bytes, p[1].acked_bytes),
            ((300, 700), (100, 1200))
        );
        assert_eq!(
            counts(&p[3]),
            (0, 0, 1, 2),
            "5 was reset, never acknowledged"
        );
        assert_eq!(
            (p[3].sent_bytes, p[3].acked_bytes),
            ((800, 700), (300, 1600))
        );
        assert!(progress(&recording, 7, t0, &needed, |_| 1, 0.0, 1.0).is_empty());
        assert!(progress(&recording, 7, t0, &needed, |_| 1, 0.1, f64::INFINITY).is_empty());
    }
}
