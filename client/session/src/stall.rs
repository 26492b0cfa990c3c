//! Telling a stalled run from a slow one.
//!
//! A run that has not converged always has something to do: pixels to sample, treelets to
//! ask for, or treelets on their way. When for a while none of that moves — no pixel sampled
//! and no treelet received, cycle after cycle — either the link or the server has stopped
//! delivering what the client asks for, or the client itself has stopped asking (a sampling
//! plan lost with its pass left pixels unknown, and unknown pixels ask for nothing: the
//! viewer's stall that `coverage::LOST_PLAN_CYCLES` ends). From the report's curves alone both
//! look like a slow link. [`StallWatch`] sees the quiet stretch and says which it is, as a
//! [`RunEvent`] in the report, once the stretch has lasted both [`STALL_CYCLES`] and
//! [`STALL_SECONDS`], and again when progress resumes.
//!
//! Plain data, fed one cycle's record at a time with the time in it: tested without a session.

use arbor_client_report::{CycleRecord, RunEvent};

/// Quiet cycles before a stretch counts as a stall: a fast client cycles hundreds of times a
/// second, and waits a few round trips for what it asked for.
pub const STALL_CYCLES: u32 = 32;

/// Seconds a quiet stretch lasts before it counts as a stall: many round trips of any link the
/// client is used over, so a slow cycle rate alone does not make one.
pub const STALL_SECONDS: f64 = 5.0;

/// Watches a run's cycles for stalls: see the module docs.
#[derive(Debug, Default)]
pub struct StallWatch {
    quiet: Option<Quiet>,
}

/// A stretch of quiet cycles.
#[derive(Debug)]
struct Quiet {
    /// Its first cycle and when that cycle ended.
    cycle: u32,
    time_s: f64,
    /// Its quiet cycles so far.
    cycles: u32,
    /// Items requested over the stretch.
    requested: u64,
    /// Reported as a stall.
    reported: bool,
}

impl StallWatch {
    /// Takes the record of the cycle just run and whether its view has converged; returns an
    /// event when a stall is found or, after one, when progress resumes.
    pub fn observe(&mut self, record: &CycleRecord, converged: bool) -> Option<RunEvent> {
        let quiet = !converged && record.sampled == 0 && record.treelets_received == 0;
        if !quiet {
            let q = self.quiet.take()?;
            return q.reported.then(|| RunEvent {
                cycle: record.cycle,
                time_s: record.time_s,
                what: format!(
                    "progress again after {:.1} s without any (cycles {}–{})",
                    record.time_s - q.time_s,
                    q.cycle,
                    q.cycle + q.cycles - 1
                ),
            });
        }
        let q = self.quiet.get_or_insert(Quiet {
            cycle: record.cycle,
            time_s: record.time_s,
            cycles: 0,
            requested: 0,
            reported: false,
        });
        q.cycles += 1;
        q.requested += u64::from(record.requests_sent);
        let lasted = record.time_s - q.time_s;
        if q.reported || q.cycles < STALL_CYCLES || lasted < STALL_SECONDS {
            return None;
        }
        q.reported = true;
        let why = if q.requested > 0 {
            "the client asked for treelets and none came: the server or the link stalled"
        } else {
            "nothing was asked for: the client stalled"
        };
        let what = format!(
            "stalled: no pixel sampled and no treelet received for {lasted:.1} s (cycles {}–{}) \
             with the view not converged ({:.1} % of its pixels known); {why}",
            q.cycle,
            record.cycle,
            record.known_share * 100.0
        );
        tracing::warn!(cycle = record.cycle, "{what}");
        Some(RunEvent {
            cycle: record.cycle,
            time_s: record.time_s,
            what,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cycle's record at `time_s`: `active` ones sample pixels and receive a treelet.
    fn record(cycle: u32, time_s: f64, active: bool, requests: u32) -> CycleRecord {
        CycleRecord {
            cycle,
            time_s,
            sampled: u32::from(active) * 100,
            treelets_received: u32::from(active),
            requests_sent: requests,
            known_share: 0.962,
            ..CycleRecord::default()
        }
    }

    /// Events of `cycles` cycles `step_s` apart, each quiet unless `active(cycle)`.
    fn watch(
        cycles: u32,
        step_s: f64,
        converged: bool,
        requests: u32,
        active: impl Fn(u32) -> bool,
    ) -> Vec<RunEvent> {
        let mut w = StallWatch::default();
        (0..cycles)
            .filter_map(|c| {
                w.observe(
                    &record(c, f64::from(c) * step_s, active(c), requests),
                    converged,
                )
            })
            .collect()
    }

    #[test]
    fn a_quiet_unconverged_stretch_is_a_stall_once_then_progress_is_noted() {
        // Quiet from cycle 10 to 109, 0.1 s apart: 5 s after cycle 10 is cycle 60.
        let events = watch(200, 0.1, false, 0, |c| !(10..110).contains(&c));
        assert_eq!(events.len(), 2, "{events:?}");
        assert_eq!(events[0].cycle, 60);
        assert!(
            events[0].what.contains("cycles 10–60"),
            "{}",
            events[0].what
        );
        assert!(events[0].what.contains("96.2 %"), "{}", events[0].what);
        assert!(
            events[0].what.contains("the client stalled"),
            "{}",
            events[0].what
        );
        assert_eq!(events[1].cycle, 110);
        assert!(
            events[1].what.contains("cycles 10–109"),
            "{}",
            events[1].what
        );
    }

    #[test]
    fn a_stall_with_requests_out_blames_the_server_or_the_link() {
        let events = watch(100, 0.5, false, 40, |c| c < 5);
        assert_eq!(events.len(), 1, "{events:?}");
        assert!(
            events[0].what.contains("the server or the link stalled"),
            "{}",
            events[0].what
        );
    }

    #[test]
    fn short_or_fast_quiet_stretches_and_converged_views_are_no_stall() {
        // Thousands of quiet cycles a second: a few round trips' wait, well under 5 s.
        assert!(watch(4000, 0.001, false, 0, |c| c % 1000 == 0).is_empty());
        // Slow cycles: more than 5 s, but only 20 cycles.
        assert!(watch(200, 0.3, false, 0, |c| c % 20 == 0).is_empty());
        // Converged: nothing left to do.
        assert!(watch(1000, 0.1, true, 0, |_| false).is_empty());
        // Busy every other cycle.
        assert!(watch(1000, 0.1, false, 0, |c| c % 2 == 0).is_empty());
    }
}
