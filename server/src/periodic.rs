//! When the daemon's periodic jobs are due: `serve --check-every/--check-at` (a check of every
//! scene) and `--copy-every/--copy-at` (a copy of the pool).
//!
//! Why two kinds: a period alone (`--copy-every 12h`) counts from the daemon's start, on the
//! monotonic clock, so a restart moves it and a clock step never does. A time of day
//! (`--copy-at 03:00`, `--copy-at "Sun 03:00"`) pins the jobs to the wall clock in UTC: due at
//! that time and every period before and after it, so a nightly backup lands in the quiet hour
//! whenever the daemon was started.
//!
//! * [`ClockTime`] and [`parse_clock_time`]: `HH:MM[:SS]`, optionally after a weekday and
//!   before `Z` or `UTC`. The daemon has no time-zone database: times are UTC.
//! * [`Schedule`]: a period, and the clock time it is aligned to. With a clock time the period
//!   divides a day or is whole days (whole weeks with a weekday), so the due times are the same
//!   each day (each week) and never drift; without a period it is a day (a week with a weekday).
//! * [`Timer`] is the arithmetic alone, both clocks passed in (as `quinn-proto` takes time), so
//!   tests step the wall clock back and forward without sleeping: a clock stepped back never
//!   makes a job due twice in its period, one stepped forward (or a process stopped for days)
//!   makes it due once, named by the latest time it was due, not once for every time it missed.
//! * A wall-clock schedule catches up once on start ([`Timer::resume`]): told when the job was
//!   last due (a scheduled copy's name, the checks' record in the data directory), a daemon
//!   that was down at 03:00, or whose restart cut that run short, runs it when it starts, named
//!   by the time it was due; only the latest missed time, never one for each.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

const DAY: u64 = 86_400;
const WEEK: u64 = 7 * DAY;
/// Days from the Unix epoch (a Thursday) to the first Monday, 1970-01-05.
const FIRST_MONDAY: u64 = 4;
const WEEKDAYS: [&str; 7] = ["Mon", "Tue", "Wed", "Thu", "Fri", "Sat", "Sun"];

/// Why a schedule was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ScheduleError {
    /// Not `[weekday] HH:MM[:SS] [Z|UTC]`, or a field out of range.
    #[error(
        "'{0}': expected a UTC time of day such as 03:00, 23:30:15 or \"Sun 03:00\" (hours 0-23, \
         minutes and seconds 0-59)"
    )]
    Unreadable(String),
    /// A period of zero.
    #[error("a schedule's period must be longer than zero")]
    ZeroPeriod,
    /// A clock time with a period that neither divides a day nor is whole days, or a weekday
    /// with a period that is not whole weeks: the due times would drift from day to day.
    #[error(
        "a period of {period_seconds} s cannot keep the time {at}: with a time of day the period \
         must divide a day (1h, 6h, 12h) or be whole days, and with a weekday whole weeks (7d)"
    )]
    Misaligned { period_seconds: u64, at: ClockTime },
}

/// A time of day in UTC, and optionally a weekday: when a wall-clock schedule is due.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClockTime {
    /// Monday 0 to Sunday 6; `None`: every day.
    weekday: Option<u8>,
    /// Seconds after midnight UTC.
    second_of_day: u32,
}

impl ClockTime {
    /// The time `hour:minute:second` UTC, on `weekday` (Monday 0 .. Sunday 6) or every day;
    /// `None` when a field is out of range.
    pub fn new(weekday: Option<u8>, hour: u32, minute: u32, second: u32) -> Option<ClockTime> {
        (weekday.is_none_or(|d| d < 7) && hour < 24 && minute < 60 && second < 60).then_some(
            ClockTime {
                weekday,
                second_of_day: hour * 3_600 + minute * 60 + second,
            },
        )
    }

    /// Seconds from the Unix epoch to the first time this is due: that day's time in the
    /// epoch's first day, or in its first week counted from Monday.
    fn anchor(self) -> u64 {
        let day = self
            .weekday
            .map_or(0, |d| (FIRST_MONDAY + u64::from(d)) % 7);
        day * DAY + u64::from(self.second_of_day)
    }
}

impl std::fmt::Display for ClockTime {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if let Some(d) = self.weekday {
            write!(f, "{} ", WEEKDAYS[usize::from(d)])?;
        }
        let s = self.second_of_day;
        write!(f, "{:02}:{:02}", s / 3_600, s / 60 % 60)?;
        if !s.is_multiple_of(60) {
            write!(f, ":{:02}", s % 60)?;
        }
        f.write_str(" UTC")
    }
}

/// Reads a time as the command line writes it: `HH:MM` or `HH:MM:SS` (hours may have one
/// digit), after an optional weekday (`Sun`, `sunday`, any case) and before an optional `Z`
/// or `UTC`.
pub fn parse_clock_time(s: &str) -> Result<ClockTime, ScheduleError> {
    let bad = || ScheduleError::Unreadable(s.to_owned());
    let mut words: Vec<&str> = s.split_whitespace().collect();
    if words
        .last()
        .is_some_and(|w| w.eq_ignore_ascii_case("utc") || w.eq_ignore_ascii_case("z"))
    {
        words.pop();
    }
    let (weekday, time) = match words[..] {
        [time] => (None, time),
        [day, time] => (Some(weekday_of(day).ok_or_else(bad)?), time),
        _ => return Err(bad()),
    };
    let time = time
        .strip_suffix('Z')
        .or_else(|| time.strip_suffix('z'))
        .unwrap_or(time);
    let fields: Vec<&str> = time.split(':').collect();
    let number = |f: &str, max_digits: usize| -> Result<u32, ScheduleError> {
        if f.is_empty() || f.len() > max_digits || !f.bytes().all(|b| b.is_ascii_digit()) {
            return Err(bad());
        }
        f.parse().map_err(|_| bad())
    };
    let (hour, minute, second) = match fields[..] {
        [h, m] if m.len() == 2 => (number(h, 2)?, number(m, 2)?, 0),
        [h, m, sec] if m.len() == 2 && sec.len() == 2 => {
            (number(h, 2)?, number(m, 2)?, number(sec, 2)?)
        }
        _ => return Err(bad()),
    };
    ClockTime::new(weekday, hour, minute, second).ok_or_else(bad)
}

/// Monday 0 .. Sunday 6 from a weekday's name or its first three letters, any case.
fn weekday_of(word: &str) -> Option<u8> {
    const NAMES: [&str; 7] = [
        "monday",
        "tuesday",
        "wednesday",
        "thursday",
        "friday",
        "saturday",
        "sunday",
    ];
    let word = word.to_ascii_lowercase();
    NAMES
        .iter()
        .position(|n| word.len() >= 3 && n.starts_with(&word))
        .map(|d| d as u8)
}

/// When a periodic job is due: every `period`, counted from the start or kept to a clock time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Schedule {
    period: Duration,
    at: Option<ClockTime>,
}

impl Schedule {
    /// The schedule of `--X-every period --X-at at`: `None` when neither is given. A clock time
    /// alone is due once a day (once a week with a weekday).
    pub fn new(
        period: Option<Duration>,
        at: Option<ClockTime>,
    ) -> Result<Option<Schedule>, ScheduleError> {
        let period = match (period, at) {
            (None, None) => return Ok(None),
            (Some(p), _) => p,
            (None, Some(at)) => Duration::from_secs(if at.weekday.is_some() { WEEK } else { DAY }),
        };
        if period.is_zero() {
            return Err(ScheduleError::ZeroPeriod);
        }
        if let Some(at) = at {
            let seconds = period.as_secs();
            let whole = period.subsec_nanos() == 0;
            let aligned = match at.weekday {
                Some(_) => whole && seconds % WEEK == 0,
                None => whole && (DAY.is_multiple_of(seconds) || seconds % DAY == 0),
            };
            if !aligned {
                return Err(ScheduleError::Misaligned {
                    period_seconds: seconds,
                    at,
                });
            }
        }
        Ok(Some(Schedule { period, at }))
    }

    /// How often.
    pub fn period(&self) -> Duration {
        self.period
    }

    /// The clock time it keeps, if any.
    pub fn at(&self) -> Option<ClockTime> {
        self.at
    }

    /// For logs and the status page: `every 1d`, `every 1d at 03:00 UTC`.
    pub fn describe(&self) -> String {
        let s = self.period.as_secs();
        let every = match s {
            _ if self.period.subsec_nanos() != 0 => format!("{:?}", self.period),
            _ if s.is_multiple_of(DAY) => format!("{}d", s / DAY),
            _ if s.is_multiple_of(3_600) => format!("{}h", s / 3_600),
            _ if s.is_multiple_of(60) => format!("{}m", s / 60),
            _ => format!("{s}s"),
        };
        match self.at {
            Some(at) => format!("every {every} at {at}"),
            None => format!("every {every}"),
        }
    }

    /// The first due time at or after `t` (seconds since the epoch) of a clock-time schedule.
    fn due_at_or_after(period: u64, anchor: u64, t: u64) -> u64 {
        match t.checked_sub(anchor) {
            None => anchor,
            Some(since) => anchor + since.div_ceil(period) * period,
        }
    }
}

/// What `/metrics` and the status page say of a running schedule.
#[derive(Clone, Debug, PartialEq)]
pub struct ScheduleFigures {
    /// [`Schedule::describe`].
    pub schedule: String,
    /// When the job is next due, seconds since the Unix epoch.
    pub next_due_unix: f64,
}

/// Counts a [`Schedule`] down: told the time on both clocks, it says whether the job is due
/// and when it next will be.
#[derive(Debug, Clone)]
pub struct Timer {
    period: Duration,
    next: Next,
}

#[derive(Debug, Clone, Copy)]
enum Next {
    /// One period after the start, then one period after each time it fired.
    Monotonic(Instant),
    /// Seconds since the epoch of the next clock time, of the anchor of the clock time, and of
    /// the last time it fired.
    Wall {
        due: u64,
        anchor: u64,
        last: Option<u64>,
    },
}

impl Timer {
    /// A timer started at `wall` / `mono`: due one period later, or at the next clock time
    /// strictly after the start.
    pub fn start(schedule: Schedule, wall: SystemTime, mono: Instant) -> Timer {
        let next = match schedule.at {
            None => Next::Monotonic(mono + schedule.period),
            Some(at) => {
                let anchor = at.anchor();
                let due =
                    Schedule::due_at_or_after(schedule.period.as_secs(), anchor, seconds(wall) + 1);
                Next::Wall {
                    due,
                    anchor,
                    last: None,
                }
            }
        };
        Timer {
            period: schedule.period,
            next,
        }
    }

    /// [`Timer::start`], for a job whose last run was due at `last` (`None`: never, or not
    /// known): when a clock-time schedule's latest due time at or before the start is later
    /// than that, the job is due at once, named by that time — the run the daemon was down
    /// for, or one a restart cut short. A period from the start has nothing to catch up.
    pub fn resume(
        schedule: Schedule,
        wall: SystemTime,
        mono: Instant,
        last: Option<SystemTime>,
    ) -> Timer {
        let mut timer = Timer::start(schedule, wall, mono);
        let period = schedule.period.as_secs();
        if let (Next::Wall { due, anchor, .. }, Some(last)) = (&mut timer.next, last) {
            let now = seconds(wall);
            if let Some(since) = now.checked_sub(*anchor) {
                let latest = now - since % period;
                if seconds(last) < latest {
                    *due = latest;
                }
            }
        }
        timer
    }

    /// Whether the job is due at `wall` / `mono`: `Some(when it was due)` once per time it
    /// comes (the wall time of a period counted from the start), and the next due time is set.
    pub fn poll(&mut self, wall: SystemTime, mono: Instant) -> Option<SystemTime> {
        match &mut self.next {
            Next::Monotonic(due) => {
                if mono < *due {
                    return None;
                }
                // From now, not from when it was due: a process stopped for a while asks once,
                // not once for every period it missed.
                *due = mono + self.period;
                Some(wall)
            }
            Next::Wall { due, anchor, last } => {
                let now = seconds(wall);
                let period = self.period.as_secs();
                if now < *due {
                    if *due - now > period {
                        // The clock was stepped back: the next time is the next one from the
                        // clock's new now, and after the last time it fired unless the clock
                        // went back beyond that by a whole period (then that one is forgotten).
                        let after = match *last {
                            Some(l) if now + period >= l => l.max(now),
                            _ => now,
                        };
                        *due = Schedule::due_at_or_after(period, *anchor, after + 1);
                    }
                    return None;
                }
                let latest = now - (now - *anchor) % period;
                *due = latest + period;
                *last = Some(latest);
                Some(UNIX_EPOCH + Duration::from_secs(latest))
            }
        }
    }

    /// When the job is next due, on the wall clock (a period counted from the start is
    /// projected from `wall` / `mono`).
    pub fn next_due(&self, wall: SystemTime, mono: Instant) -> SystemTime {
        match self.next {
            Next::Monotonic(due) => wall + due.saturating_duration_since(mono),
            Next::Wall { due, .. } => UNIX_EPOCH + Duration::from_secs(due),
        }
    }
}

/// Year, month, day, hour, minute and second of `t` in UTC (a time before the epoch reads as the
/// epoch).
pub fn utc_fields(t: SystemTime) -> (u64, u64, u64, u64, u64, u64) {
    let secs = seconds(t);
    let (days, rest) = (secs / DAY, secs % DAY);
    let (year, month, day) = civil_from_days(days);
    (year, month, day, rest / 3_600, rest / 60 % 60, rest % 60)
}

/// The time of a UTC civil date and time; `None` when a field is out of range (the 30th of
/// February, hour 24) or the time is before the epoch.
pub fn utc_time(
    year: u64,
    month: u64,
    day: u64,
    hour: u64,
    minute: u64,
    second: u64,
) -> Option<SystemTime> {
    if !(1970..=9999).contains(&year) || !(1..=12).contains(&month) || !(1..=31).contains(&day) {
        return None;
    }
    // Howard Hinnant's `days_from_civil`, in a year counted from March.
    let y = if month <= 2 { year - 1 } else { year };
    let (era, yoe) = (y / 400, y % 400);
    let doy = (153 * ((month + 9) % 12) + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = (era * 146_097 + doe).checked_sub(719_468)?;
    let t = UNIX_EPOCH + Duration::from_secs(days * DAY + hour * 3_600 + minute * 60 + second);
    // Out-of-range days and times come back as other fields.
    (utc_fields(t) == (year, month, day, hour, minute, second)).then_some(t)
}

/// `t` as people read it: `2026-12-03 03:00:00 UTC`.
pub fn utc_text(t: SystemTime) -> String {
    let (y, mo, d, h, mi, s) = utc_fields(t);
    format!("{y:04}-{mo:02}-{d:02} {h:02}:{mi:02}:{s:02} UTC")
}

/// The proleptic Gregorian date `days` after 1970-01-01 (Howard Hinnant's `civil_from_days`).
fn civil_from_days(days: u64) -> (u64, u64, u64) {
    let z = days + 719_468;
    let era = z / 146_097;
    let doe = z % 146_097;
    let yoe = (doe - doe / 1_460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + u64::from(month <= 2);
    (year, month, day)
}

/// Whole seconds since the epoch (a clock before it reads as the epoch).
pub(crate) fn seconds(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(s: &str) -> ClockTime {
        parse_clock_time(s).unwrap()
    }

    /// Seconds since the epoch of a UTC civil time, by counting days from the epoch one by one
    /// (the brute-force reference for the timer's arithmetic).
    fn utc(y: u64, mo: u64, d: u64, h: u64, mi: u64, s: u64) -> u64 {
        let leap =
            |y: u64| (y.is_multiple_of(4) && !y.is_multiple_of(100)) || y.is_multiple_of(400);
        let mut days = 0;
        for year in 1970..y {
            days += if leap(year) { 366 } else { 365 };
        }
        let months = [31, 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31];
        for (m, len) in months.iter().enumerate().take(mo as usize - 1) {
            days += len + u64::from(m == 1 && leap(y));
        }
        ((days + d - 1) * 24 + h) * 3_600 + mi * 60 + s
    }

    fn wall(secs: u64) -> SystemTime {
        UNIX_EPOCH + Duration::from_secs(secs)
    }

    fn wall_timer(period: Option<u64>, clock: &str, start: u64) -> (Timer, Instant) {
        let schedule = Schedule::new(period.map(Duration::from_secs), Some(at(clock)))
            .unwrap()
            .unwrap();
        let mono = Instant::now();
        (Timer::start(schedule, wall(start), mono), mono)
    }

    #[test]
    fn clock_times_are_read_in_their_forms_and_bad_ones_named() {
        assert_eq!(at("03:00"), ClockTime::new(None, 3, 0, 0).unwrap());
        assert_eq!(at("3:00"), at("03:00"));
        assert_eq!(at("03:00Z"), at("03:00"));
        assert_eq!(at(" 03:00 UTC "), at("03:00"));
        assert_eq!(at("23:59:59"), ClockTime::new(None, 23, 59, 59).unwrap());
        assert_eq!(at("Sun 03:00"), ClockTime::new(Some(6), 3, 0, 0).unwrap());
        assert_eq!(at("sunday 03:00 utc"), at("SUN 03:00"));
        assert_eq!(at("mon 00:00"), ClockTime::new(Some(0), 0, 0, 0).unwrap());
        assert_eq!(at("Sun 03:00").to_string(), "Sun 03:00 UTC");
        assert_eq!(at("23:59:59").to_string(), "23:59:59 UTC");
        for bad in [
            "",
            "3",
            "24:00",
            "03:60",
            "03:00:60",
            "03:0",
            "003:00",
            "-1:00",
            "+3:00",
            "03:00:00:00",
            "su 03:00",
            "someday 03:00",
            "Sun",
            "Sun Mon 03:00",
            "03:00 CET",
            "03h00",
            "٣:00",
        ] {
            let e = parse_clock_time(bad).unwrap_err();
            assert!(
                e.to_string().contains(&format!("'{bad}'")) && e.to_string().contains("UTC"),
                "{bad:?}: {e}"
            );
        }
    }

    #[test]
    fn periods_that_would_drift_from_the_clock_time_are_refused() {
        let day = Duration::from_secs(DAY);
        assert_eq!(Schedule::new(None, None), Ok(None));
        let daily = Schedule::new(None, Some(at("03:00"))).unwrap().unwrap();
        assert_eq!(daily.period(), day);
        assert_eq!(daily.describe(), "every 1d at 03:00 UTC");
        let weekly = Schedule::new(None, Some(at("Sun 03:00"))).unwrap().unwrap();
        assert_eq!(weekly.period(), 7 * day);
        for ok in [
            1,
            2,
            60,
            900,
            3_600,
            6 * 3_600,
            12 * 3_600,
            DAY,
            2 * DAY,
            30 * DAY,
        ] {
            assert!(
                Schedule::new(Some(Duration::from_secs(ok)), Some(at("03:00"))).is_ok(),
                "{ok}"
            );
        }
        for bad in [7, 7 * 3_600, 36 * 3_600, DAY + 1] {
            let e = Schedule::new(Some(Duration::from_secs(bad)), Some(at("03:00"))).unwrap_err();
            assert!(matches!(e, ScheduleError::Misaligned { .. }), "{bad}: {e}");
            assert!(e.to_string().contains("03:00 UTC"), "{e}");
        }
        for bad in [DAY, 3 * DAY, 10 * DAY] {
            let e =
                Schedule::new(Some(Duration::from_secs(bad)), Some(at("Sun 03:00"))).unwrap_err();
            assert!(e.to_string().contains("whole weeks"), "{bad}: {e}");
        }
        assert!(Schedule::new(Some(Duration::from_secs(14 * DAY)), Some(at("Sun 03:00"))).is_ok());
        assert!(Schedule::new(Some(Duration::from_millis(1500)), Some(at("03:00"))).is_err());
        assert_eq!(
            Schedule::new(Some(Duration::ZERO), None),
            Err(ScheduleError::ZeroPeriod)
        );
        let plain = Schedule::new(Some(Duration::from_secs(90)), None)
            .unwrap()
            .unwrap();
        assert_eq!(plain.describe(), "every 90s");
        assert_eq!(plain.at(), None);
    }

    #[test]
    fn clock_times_fall_on_the_day_and_weekday_the_calendar_says() {
        let now = utc(2026, 12, 2, 7, 55, 47);
        let (t, mono) = wall_timer(None, "03:00", now);
        assert_eq!(t.next_due(wall(now), mono), wall(utc(2026, 12, 3, 3, 0, 0)));
        let (t, mono) = wall_timer(None, "Sun 03:00", now);
        assert_eq!(t.next_due(wall(now), mono), wall(utc(2026, 12, 6, 3, 0, 0)));
        let (t, mono) = wall_timer(None, "Wed 07:55:48", now);
        assert_eq!(
            t.next_due(wall(now), mono),
            wall(utc(2026, 12, 2, 7, 55, 48))
        );
        let (t, mono) = wall_timer(Some(6 * 3_600), "00:30", now);
        assert_eq!(
            t.next_due(wall(now), mono),
            wall(utc(2026, 12, 2, 12, 30, 0))
        );
        // Started exactly when due: the next one, not at once.
        let (t, mono) = wall_timer(None, "03:00", utc(2028, 2, 29, 3, 0, 0));
        assert_eq!(
            t.next_due(wall(utc(2028, 2, 29, 3, 0, 0)), mono),
            wall(utc(2028, 3, 1, 3, 0, 0))
        );
        let (t, mono) = wall_timer(None, "Mon 00:00", utc(2100, 2, 28, 12, 0, 0));
        assert_eq!(
            t.next_due(wall(0), mono),
            wall(utc(2100, 3, 1, 0, 0, 0)),
            "2100 is not a leap year; 2100-03-01 is a Monday"
        );
    }

    #[test]
    fn the_next_time_matches_a_brute_force_walk_over_the_calendar() {
        // Every 7919 s over four centuries (leap days, 2100, huge second counts), against
        // a walk from the anchor one period at a time.
        let mut rng = 0x2545_f491_4f6c_dd1d_u64;
        for (period, clock) in [
            (DAY, "03:00"),
            (3_600, "00:17:05"),
            (7 * DAY, "Sun 23:59:59"),
            (14 * DAY, "Thu 00:00"),
            (5 * DAY, "12:00"),
        ] {
            let anchor = at(clock).anchor();
            for _ in 0..300 {
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                let now = rng % utc(2400, 1, 1, 0, 0, 0);
                let mut due = anchor;
                if now >= anchor {
                    let skip = (now - anchor) / period;
                    due += skip.saturating_sub(1) * period;
                    while due <= now {
                        due += period;
                    }
                }
                let (t, mono) = wall_timer(Some(period), clock, now);
                assert_eq!(
                    t.next_due(wall(now), mono),
                    wall(due),
                    "{clock} every {period} s from {now}"
                );
                assert_eq!((due - anchor) % period, 0);
                assert!(due > now && due - now <= period);
            }
        }
    }

    #[test]
    fn utc_fields_agree_with_counting_days() {
        for (y, mo, d, h, mi, sec) in [
            (1970, 1, 1, 0, 0, 0),
            (2000, 2, 29, 23, 59, 59),
            (2026, 12, 2, 7, 55, 47),
            (2100, 3, 1, 0, 0, 0),
            (2399, 12, 31, 12, 0, 1),
        ] {
            let t = wall(utc(y, mo, d, h, mi, sec));
            assert_eq!(utc_fields(t), (y, mo, d, h, mi, sec));
        }
        assert_eq!(
            utc_text(wall(utc(2026, 12, 3, 3, 0, 0))),
            "2026-12-03 03:00:00 UTC"
        );
        // And back, over four centuries against the brute-force count.
        let mut rng = 0x9e37_79b9_7f4a_7c15_u64;
        for _ in 0..2_000 {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            let secs = rng % utc(2400, 1, 1, 0, 0, 0);
            let (y, mo, d, h, mi, s) = utc_fields(wall(secs));
            assert_eq!(utc(y, mo, d, h, mi, s), secs);
            assert_eq!(utc_time(y, mo, d, h, mi, s), Some(wall(secs)));
        }
        for bad in [
            (2026, 2, 29, 0, 0, 0),
            (2100, 2, 29, 0, 0, 0),
            (2026, 4, 31, 0, 0, 0),
            (2026, 13, 1, 0, 0, 0),
            (2026, 0, 1, 0, 0, 0),
            (2026, 1, 0, 0, 0, 0),
            (2026, 1, 1, 24, 0, 0),
            (2026, 1, 1, 0, 60, 0),
            (2026, 1, 1, 0, 0, 60),
            (1969, 12, 31, 23, 59, 59),
            (10_000, 1, 1, 0, 0, 0),
        ] {
            let (y, mo, d, h, mi, s) = bad;
            assert_eq!(utc_time(y, mo, d, h, mi, s), None, "{bad:?}");
        }
        assert_eq!(
            utc_time(2000, 2, 29, 0, 0, 0),
            Some(wall(utc(2000, 2, 29, 0, 0, 0)))
        );
    }

    #[test]
    fn a_time_missed_while_down_is_due_at_once_and_only_the_latest() {
        let schedule = Schedule::new(None, Some(at("03:00"))).unwrap().unwrap();
        let mono = Instant::now();
        let start = utc(2026, 12, 2, 7, 55, 47);
        let today = utc(2026, 12, 2, 3, 0, 0);
        // The last copy was due yesterday (or days ago): today's is made at once, named so.
        for last in [today - DAY, today - 10 * DAY, 0] {
            let mut t = Timer::resume(schedule, wall(start), mono, Some(wall(last)));
            assert_eq!(t.next_due(wall(start), mono), wall(today));
            assert_eq!(t.poll(wall(start), mono), Some(wall(today)));
            assert_eq!(t.poll(wall(start + 1), mono), None);
            assert_eq!(t.next_due(wall(start), mono), wall(today + DAY));
        }
        // Today's was made (or nothing is known): the next one, as a plain start.
        for last in [Some(today), Some(today + 5), None] {
            let t = Timer::resume(schedule, wall(start), mono, last.map(wall));
            assert_eq!(t.next_due(wall(start), mono), wall(today + DAY), "{last:?}");
        }
        // Started in the very second it is due, after yesterday's: due now.
        let mut t = Timer::resume(schedule, wall(today), mono, Some(wall(today - DAY)));
        assert_eq!(t.poll(wall(today), mono), Some(wall(today)));
        // A period from the start has nothing to catch up.
        let plain = Schedule::new(Some(Duration::from_secs(60)), None)
            .unwrap()
            .unwrap();
        let t = Timer::resume(plain, wall(start), mono, Some(wall(0)));
        assert_eq!(t.next_due(wall(start), mono), wall(start + 60));
    }

    #[test]
    fn a_wall_clock_timer_fires_once_a_period_whatever_the_clock_does() {
        let start = utc(2026, 12, 2, 7, 55, 47);
        let (mut t, mono) = wall_timer(None, "03:00", start);
        let tonight = utc(2026, 12, 3, 3, 0, 0);
        assert_eq!(t.poll(wall(tonight - 1), mono), None);
        assert_eq!(t.poll(wall(tonight), mono), Some(wall(tonight)));
        assert_eq!(t.poll(wall(tonight), mono), None, "due twice in one second");
        assert_eq!(t.poll(wall(tonight + 5), mono), None);
        assert_eq!(t.next_due(wall(0), mono), wall(tonight + DAY));
        // Stepped back an hour: not due again tonight.
        assert_eq!(t.poll(wall(tonight - 3_600), mono), None);
        assert_eq!(t.poll(wall(tonight + 60), mono), None);
        assert_eq!(t.next_due(wall(0), mono), wall(tonight + DAY));
        // Stepped back three days: due at the next 03:00 from there, not in four days.
        assert_eq!(t.poll(wall(tonight - 3 * DAY + 60), mono), None);
        assert_eq!(t.next_due(wall(0), mono), wall(tonight - 2 * DAY));
        assert_eq!(
            t.poll(wall(tonight - 2 * DAY), mono),
            Some(wall(tonight - 2 * DAY))
        );
        // Stepped forward ten days (or stopped for them): due once, named by the latest time.
        let later = tonight + 10 * DAY + 7_200;
        assert_eq!(t.poll(wall(later), mono), Some(wall(tonight + 10 * DAY)));
        assert_eq!(t.poll(wall(later + 60), mono), None);
        assert_eq!(t.next_due(wall(0), mono), wall(tonight + 11 * DAY));
    }

    #[test]
    fn a_period_from_the_start_follows_the_monotonic_clock_only() {
        let schedule = Schedule::new(Some(Duration::from_secs(60)), None)
            .unwrap()
            .unwrap();
        let mono = Instant::now();
        let mut t = Timer::start(schedule, wall(1_000), mono);
        assert_eq!(
            t.next_due(wall(1_000), mono),
            wall(1_060),
            "projected on the wall clock"
        );
        // The wall clock jumping changes nothing.
        assert_eq!(
            t.poll(wall(1_000_000), mono + Duration::from_secs(59)),
            None
        );
        assert_eq!(
            t.poll(wall(5), mono + Duration::from_secs(60)),
            Some(wall(5))
        );
        assert_eq!(t.poll(wall(6), mono + Duration::from_secs(61)), None);
        // Late by far (a stopped process): once, then a period from then.
        let late = mono + Duration::from_secs(1_000);
        assert!(t.poll(wall(2_000), late).is_some());
        assert_eq!(t.poll(wall(2_001), late + Duration::from_secs(59)), None);
        assert!(
            t.poll(wall(2_002), late + Duration::from_secs(60))
                .is_some()
        );
    }
}
