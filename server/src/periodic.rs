//! When the daemon's periodic jobs are due: `serve --check-every/--check-at` (a check of every
//! scene) and `--copy-every/--copy-at` (a copy of the pool).
//!
//! Why two kinds: a period alone (`--copy-every 12h`) counts from the daemon's start, on the
//! monotonic clock, so a restart moves it and a clock step never does. A time of day
//! (`--copy-at 03:00`, `--copy-at "Sun 03:00"`, `--copy-at "03:00 Europe/Berlin"`) pins the
//! jobs to the wall clock, in UTC or in a time zone of the system's database: due at that time
//! and every period before and after it, so a nightly backup lands in the quiet hour whenever
//! the daemon was started, and stays in it across daylight-saving changes.
//!
//! * [`ClockTime`] and [`parse_clock_time`]: `HH:MM[:SS]`, optionally after a weekday and
//!   before `Z`, `UTC` or an IANA time-zone name (read from `/usr/share/zoneinfo` through
//!   `jiff`, so the system's updates of the database apply).
//! * [`Schedule`]: a period, and the clock time it is aligned to. With a clock time the period
//!   divides a day or is whole days (whole weeks with a weekday), so the due times are the same
//!   each day (each week) on that clock and never drift; without a period it is a day (a week
//!   with a weekday).
//! * The due times are a grid on the zone's clock (`Grid`), each mapped to the first instant
//!   the clock reads it: a time the clock skips (02:30 on the night it jumps from 02:00 to 03:00)
//!   is due when it jumps, and a time it reads twice (the hour repeated in autumn) is due the
//!   first time only. So every due time comes once, in order, and a day of 23 or 25 hours loses
//!   or repeats no run of a daily schedule.
//! * [`Timer`] is the arithmetic alone, both clocks passed in (as `quinn-proto` takes time), so
//!   tests step the wall clock back and forward without sleeping: a clock stepped back never
//!   makes a job due twice in its period, one stepped forward (or a process stopped for days)
//!   makes it due once, named by the latest time it was due, not once for every time it missed.
//! * A wall-clock schedule catches up once on start ([`Timer::resume`]): told when the job was
//!   last due (a scheduled copy's name, the checks' record in the data directory), a daemon
//!   that was down at 03:00, or whose restart cut that run short, runs it when it starts, named
//!   by the time it was due; only the latest missed time, never one for each.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use jiff::tz::{AmbiguousOffset, TimeZone};

const DAY: u64 = 86_400;
const WEEK: u64 = 7 * DAY;
/// Days from the Unix epoch (a Thursday) to the first Monday, 1970-01-05.
const FIRST_MONDAY: u64 = 4;
const WEEKDAYS: [&str; 7] = ["Mon", "Tue", "Wed", "Thu", "Fri", "Sat", "Sun"];

/// Why a schedule was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ScheduleError {
    /// Not `[weekday] HH:MM[:SS] [Z|UTC|zone]`, or a field out of range.
    #[error(
        "'{0}': expected a time of day such as 03:00, 23:30:15, \"Sun 03:00\" or \"03:00 \
         Europe/Berlin\" (hours 0-23, minutes and seconds 0-59; UTC unless a time zone follows)"
    )]
    Unreadable(String),
    /// A time zone the system's time-zone database does not have.
    #[error(
        "'{zone}' is not a time zone of this system's database ({reason}); use an IANA name \
         such as Europe/Berlin (the tzdata package provides /usr/share/zoneinfo), or UTC"
    )]
    UnknownZone { zone: String, reason: String },
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

/// A time of day on a clock (UTC or a time zone), and optionally a weekday: when a wall-clock
/// schedule is due.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ClockTime {
    /// Monday 0 to Sunday 6; `None`: every day.
    weekday: Option<u8>,
    /// Seconds after midnight on the clock.
    second_of_day: u32,
    /// The clock's time zone; `None`: UTC.
    zone: Option<TimeZone>,
}

impl ClockTime {
    /// The time `hour:minute:second` UTC, on `weekday` (Monday 0 .. Sunday 6) or every day;
    /// `None` when a field is out of range.
    pub fn new(weekday: Option<u8>, hour: u32, minute: u32, second: u32) -> Option<ClockTime> {
        (weekday.is_none_or(|d| d < 7) && hour < 24 && minute < 60 && second < 60).then_some(
            ClockTime {
                weekday,
                second_of_day: hour * 3_600 + minute * 60 + second,
                zone: None,
            },
        )
    }

    /// The same time of day on the clock of `zone` (IANA name, from the system's database).
    pub fn in_zone(self, zone: &str) -> Result<ClockTime, ScheduleError> {
        let tz = TimeZone::get(zone).map_err(|e| ScheduleError::UnknownZone {
            zone: zone.to_owned(),
            reason: e.to_string(),
        })?;
        Ok(ClockTime {
            zone: Some(tz),
            ..self
        })
    }

    /// The clock's time since the Unix epoch on that clock (civil seconds) of the first time
    /// this is due: that day's time in the epoch's first day, or in its first week counted
    /// from Monday.
    fn anchor(&self) -> i64 {
        let day = self
            .weekday
            .map_or(0, |d| (FIRST_MONDAY + u64::from(d)) % 7);
        (day * DAY) as i64 + i64::from(self.second_of_day)
    }

    /// The zone's name as the database gives it, or `UTC`.
    fn zone_name(&self) -> &str {
        self.zone
            .as_ref()
            .map_or("UTC", |z| z.iana_name().unwrap_or("(unnamed zone)"))
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
        write!(f, " {}", self.zone_name())
    }
}

/// Reads a time as the command line writes it: `HH:MM` or `HH:MM:SS` (hours may have one
/// digit), after an optional weekday (`Sun`, `sunday`, any case) and before an optional `Z`,
/// `UTC` or IANA time-zone name (`Europe/Berlin`).
pub fn parse_clock_time(s: &str) -> Result<ClockTime, ScheduleError> {
    let bad = || ScheduleError::Unreadable(s.to_owned());
    let mut words: Vec<&str> = s.split_whitespace().collect();
    // A last word that is not the time (it has no colon) names the clock.
    let zone = match words[..] {
        [.., w] if words.len() >= 2 && !w.contains(':') => {
            words.pop();
            (!w.eq_ignore_ascii_case("utc") && !w.eq_ignore_ascii_case("z")).then_some(w)
        }
        _ => None,
    };
    let (weekday, time) = match words[..] {
        [time] => (None, time),
        [day, time] => (Some(weekday_of(day).ok_or_else(bad)?), time),
        _ => return Err(bad()),
    };
    let time = match time.strip_suffix('Z').or_else(|| time.strip_suffix('z')) {
        // `03:00Z Europe/Berlin` says two clocks.
        Some(_) if zone.is_some() => return Err(bad()),
        Some(utc) => utc,
        None => time,
    };
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
    let time = ClockTime::new(weekday, hour, minute, second).ok_or_else(bad)?;
    match zone {
        Some(zone) => time.in_zone(zone),
        None => Ok(time),
    }
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
#[derive(Debug, Clone, PartialEq, Eq)]
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
        let period = match (period, &at) {
            (None, None) => return Ok(None),
            (Some(p), _) => p,
            (None, Some(at)) => Duration::from_secs(if at.weekday.is_some() { WEEK } else { DAY }),
        };
        if period.is_zero() {
            return Err(ScheduleError::ZeroPeriod);
        }
        if let Some(at) = &at {
            let seconds = period.as_secs();
            let whole = period.subsec_nanos() == 0;
            let aligned = match at.weekday {
                Some(_) => whole && seconds % WEEK == 0,
                None => whole && (DAY.is_multiple_of(seconds) || seconds % DAY == 0),
            };
            if !aligned {
                return Err(ScheduleError::Misaligned {
                    period_seconds: seconds,
                    at: at.clone(),
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
    pub fn at(&self) -> Option<&ClockTime> {
        self.at.as_ref()
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
        match &self.at {
            Some(at) => format!("every {every} at {at}"),
            None => format!("every {every}"),
        }
    }
}

/// The due times of a clock-time schedule: every `period` from `anchor` on the zone's clock
/// (civil seconds, the clock's reading counted from 1970-01-01 00:00 on that clock), each due at
/// the first instant the clock reads it (seconds since the Unix epoch). That map never goes
/// back, so the grid's instants are in order; two grid times the clock skips over share the
/// instant it jumps at.
#[derive(Debug, Clone)]
struct Grid {
    anchor: i64,
    period: i64,
    zone: Option<TimeZone>,
}

impl Grid {
    fn new(at: &ClockTime, period: Duration) -> Grid {
        Grid {
            anchor: at.anchor(),
            period: period.as_secs().max(1) as i64,
            zone: at.zone.clone(),
        }
    }

    /// The clock's reading at the instant `t`.
    fn civil(&self, t: u64) -> i64 {
        let t = t as i64;
        match &self.zone {
            None => t,
            Some(zone) => match jiff::Timestamp::from_second(t) {
                Ok(ts) => t + i64::from(zone.to_offset(ts).seconds()),
                Err(_) => t,
            },
        }
    }

    /// The first instant the clock reads `c` or later.
    fn instant(&self, c: i64) -> u64 {
        let Some(zone) = &self.zone else {
            return c.max(0) as u64;
        };
        let Some(datetime) = civil_datetime(c) else {
            return c.max(0) as u64;
        };
        let at = |offset: jiff::tz::Offset| (c - i64::from(offset.seconds())).max(0) as u64;
        match zone.to_ambiguous_timestamp(datetime).offset() {
            AmbiguousOffset::Unambiguous { offset } => at(offset),
            // Read twice: the first time.
            AmbiguousOffset::Fold { before, .. } => at(before),
            // Skipped: when the clock jumps past it, between the reading with the offset after
            // the jump (too early) and the one with the offset before it (too late).
            AmbiguousOffset::Gap { before, after } => {
                let (mut lo, mut hi) = (at(after), at(before));
                while lo < hi {
                    let mid = lo + (hi - lo) / 2;
                    if self.civil(mid) >= c {
                        hi = mid;
                    } else {
                        lo = mid + 1;
                    }
                }
                lo
            }
        }
    }

    /// The instant of the `k`th due time.
    fn due(&self, k: i64) -> u64 {
        self.instant(self.anchor + k * self.period)
    }

    /// The smallest `k` whose due time is at or after `t` (none before the anchor).
    fn first_index_at_or_after(&self, t: u64) -> i64 {
        // A clock is within 26 hours of UTC, and the map from clock to instant never goes back:
        // the index lies in this bracket, found by halving it.
        let c = self.civil(t) - self.anchor;
        let mut lo = (c - 3 * DAY as i64).div_euclid(self.period).max(0);
        let mut hi = (c + 3 * DAY as i64).div_euclid(self.period).max(0) + 1;
        if self.due(lo) >= t {
            return lo;
        }
        while lo + 1 < hi {
            let mid = lo + (hi - lo) / 2;
            if self.due(mid) >= t {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        hi
    }

    /// The first due time at or after `t`.
    fn first_at_or_after(&self, t: u64) -> u64 {
        self.due(self.first_index_at_or_after(t))
    }

    /// The latest due time at or before `t`; `None` before the first.
    fn latest_at_or_before(&self, t: u64) -> Option<u64> {
        let k = self.first_index_at_or_after(t + 1);
        (k > 0).then(|| self.due(k - 1))
    }
}

/// The civil date and time `c` seconds after 1970-01-01 00:00; `None` outside jiff's years.
fn civil_datetime(c: i64) -> Option<jiff::civil::DateTime> {
    let c = u64::try_from(c).ok()?;
    let (year, month, day) = civil_from_days(c / DAY);
    let rest = c % DAY;
    jiff::civil::DateTime::new(
        i16::try_from(year).ok()?,
        month as i8,
        day as i8,
        (rest / 3_600) as i8,
        (rest / 60 % 60) as i8,
        (rest % 60) as i8,
        0,
    )
    .ok()
}

/// What `/metrics` and the status page say of a running schedule.
#[derive(Clone, Debug, PartialEq)]
pub struct ScheduleFigures {
    /// [`Schedule::describe`].
    pub schedule: String,
    /// When the job is next due, seconds since the Unix epoch.
    pub next_due_unix: f64,
    /// Its period in seconds (alerts compare the age of the last run with it).
    pub period_seconds: f64,
}

/// Counts a [`Schedule`] down: told the time on both clocks, it says whether the job is due
/// and when it next will be.
#[derive(Debug, Clone)]
pub struct Timer {
    period: Duration,
    next: Next,
}

#[derive(Debug, Clone)]
enum Next {
    /// One period after the start, then one period after each time it fired.
    Monotonic(Instant),
    /// Seconds since the epoch of the next due time of the grid and of the last time it fired.
    Wall {
        grid: Grid,
        due: u64,
        last: Option<u64>,
    },
}

impl Timer {
    /// A timer started at `wall` / `mono`: due one period later, or at the next clock time
    /// strictly after the start.
    pub fn start(schedule: &Schedule, wall: SystemTime, mono: Instant) -> Timer {
        let next = match &schedule.at {
            None => Next::Monotonic(mono + schedule.period),
            Some(at) => {
                let grid = Grid::new(at, schedule.period);
                let due = grid.first_at_or_after(seconds(wall) + 1);
                Next::Wall {
                    grid,
                    due,
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
        schedule: &Schedule,
        wall: SystemTime,
        mono: Instant,
        last: Option<SystemTime>,
    ) -> Timer {
        let mut timer = Timer::start(schedule, wall, mono);
        if let (Next::Wall { grid, due, .. }, Some(last)) = (&mut timer.next, last)
            && let Some(latest) = grid.latest_at_or_before(seconds(wall))
            && seconds(last) < latest
        {
            *due = latest;
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
            Next::Wall { grid, due, last } => {
                let now = seconds(wall);
                if now < *due {
                    if grid.first_at_or_after(now + 1) < *due {
                        // The clock was stepped back past a due time: the next time is the next
                        // one from the clock's new now, and after the last time it fired unless
                        // the clock went back beyond that by a whole period (then that one is
                        // forgotten).
                        let after = match *last {
                            Some(l) if now + self.period.as_secs() >= l => l.max(now),
                            _ => now,
                        };
                        *due = grid.first_at_or_after(after + 1);
                    }
                    return None;
                }
                let latest = grid.latest_at_or_before(now).unwrap_or(*due);
                *due = grid.first_at_or_after(latest + 1);
                *last = Some(latest);
                Some(UNIX_EPOCH + Duration::from_secs(latest))
            }
        }
    }

    /// When the job is next due, on the wall clock (a period counted from the start is
    /// projected from `wall` / `mono`).
    pub fn next_due(&self, wall: SystemTime, mono: Instant) -> SystemTime {
        match &self.next {
            Next::Monotonic(due) => wall + due.saturating_duration_since(mono),
            Next::Wall { due, .. } => UNIX_EPOCH + Duration::from_secs(*due),
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
        (Timer::start(&schedule, wall(start), mono), mono)
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
            let anchor = at(clock).anchor() as u64;
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
            let mut t = Timer::resume(&schedule, wall(start), mono, Some(wall(last)));
            assert_eq!(t.next_due(wall(start), mono), wall(today));
            assert_eq!(t.poll(wall(start), mono), Some(wall(today)));
            assert_eq!(t.poll(wall(start + 1), mono), None);
            assert_eq!(t.next_due(wall(start), mono), wall(today + DAY));
        }
        // Today's was made (or nothing is known): the next one, as a plain start.
        for last in [Some(today), Some(today + 5), None] {
            let t = Timer::resume(&schedule, wall(start), mono, last.map(wall));
            assert_eq!(t.next_due(wall(start), mono), wall(today + DAY), "{last:?}");
        }
        // Started in the very second it is due, after yesterday's: due now.
        let mut t = Timer::resume(&schedule, wall(today), mono, Some(wall(today - DAY)));
        assert_eq!(t.poll(wall(today), mono), Some(wall(today)));
        // A period from the start has nothing to catch up.
        let plain = Schedule::new(Some(Duration::from_secs(60)), None)
            .unwrap()
            .unwrap();
        let t = Timer::resume(&plain, wall(start), mono, Some(wall(0)));
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
        let mut t = Timer::start(&schedule, wall(1_000), mono);
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

    #[test]
    fn clock_times_in_a_time_zone_are_read_and_unknown_zones_named() {
        let berlin = at("03:00 Europe/Berlin");
        assert_eq!(berlin.to_string(), "03:00 Europe/Berlin");
        assert_ne!(berlin, at("03:00"));
        assert_eq!(
            at("sun 23:30:15 America/New_York").to_string(),
            "Sun 23:30:15 America/New_York"
        );
        assert_eq!(at("03:00 utc"), at("03:00"));
        let daily = Schedule::new(Some(Duration::from_secs(6 * 3_600)), Some(berlin))
            .unwrap()
            .unwrap();
        assert_eq!(daily.describe(), "every 6h at 03:00 Europe/Berlin");
        assert!(matches!(
            parse_clock_time("03:00Z Europe/Berlin"),
            Err(ScheduleError::Unreadable(_))
        ));
        for (bad, zone) in [
            ("03:00 Mars/Olympus", "Mars/Olympus"),
            ("Sun 03:00 Europe/Atlantis", "Europe/Atlantis"),
            ("03:00 sunday", "sunday"),
        ] {
            let e = parse_clock_time(bad).unwrap_err();
            assert!(
                matches!(&e, ScheduleError::UnknownZone { zone: z, .. } if z == zone),
                "{bad}: {e:?}"
            );
            assert!(e.to_string().contains(&format!("'{zone}'")), "{e}");
        }
        // A time zone does not excuse a period that drifts from it.
        let e = Schedule::new(
            Some(Duration::from_secs(7 * 3_600)),
            Some(at("03:00 Europe/Berlin")),
        )
        .unwrap_err();
        assert!(e.to_string().contains("03:00 Europe/Berlin"), "{e}");
    }

    /// Polls `timer` at each due time from `from` to `until` (and the second before it), and
    /// returns the times it fired.
    fn fired(timer: &mut Timer, until: u64) -> Vec<u64> {
        let mono = Instant::now();
        let mut out = Vec::new();
        loop {
            let due = seconds(timer.next_due(wall(0), mono));
            if due > until {
                return out;
            }
            assert_eq!(timer.poll(wall(due - 1), mono), None, "early at {due}");
            assert_eq!(timer.poll(wall(due), mono), Some(wall(due)));
            assert_eq!(timer.poll(wall(due), mono), None, "twice at {due}");
            out.push(due);
        }
    }

    #[test]
    fn a_daily_time_in_a_zone_is_due_once_a_day_across_daylight_saving_changes() {
        // Berlin, 2026: clocks jump from 02:00 to 03:00 on 29 March and fall back from 03:00
        // to 02:00 on 25 October; 02:30 is skipped on the first and read twice on the second.
        let (mut t, _) = wall_timer(None, "02:30 Europe/Berlin", utc(2026, 3, 27, 12, 0, 0));
        let times = fired(&mut t, utc(2026, 3, 31, 0, 0, 0));
        assert_eq!(
            times,
            [
                utc(2026, 3, 28, 1, 30, 0), // 02:30 CET
                utc(2026, 3, 29, 1, 0, 0),  // the jump: 03:00 CEST
                utc(2026, 3, 30, 0, 30, 0), // 02:30 CEST
            ]
        );
        let (mut t, _) = wall_timer(None, "02:30 Europe/Berlin", utc(2026, 10, 23, 12, 0, 0));
        let times = fired(&mut t, utc(2026, 10, 27, 0, 0, 0));
        assert_eq!(
            times,
            [
                utc(2026, 10, 24, 0, 30, 0), // 02:30 CEST
                utc(2026, 10, 25, 0, 30, 0), // the first 02:30, still CEST
                utc(2026, 10, 26, 1, 30, 0), // 02:30 CET
            ]
        );
        // A daemon started between the two readings of 02:30 does not run it again.
        let (t, mono) = wall_timer(None, "02:30 Europe/Berlin", utc(2026, 10, 25, 1, 0, 0));
        assert_eq!(t.next_due(wall(0), mono), wall(utc(2026, 10, 26, 1, 30, 0)));
        // Nor does a catch-up name a time the clock skipped later than when it jumped.
        let schedule = Schedule::new(None, Some(at("02:30 Europe/Berlin")))
            .unwrap()
            .unwrap();
        let jump = utc(2026, 3, 29, 1, 0, 0);
        let t = Timer::resume(
            &schedule,
            wall(jump + 600),
            Instant::now(),
            Some(wall(utc(2026, 3, 28, 1, 30, 0))),
        );
        assert_eq!(t.next_due(wall(0), Instant::now()), wall(jump));
    }

    #[test]
    fn zoned_due_times_match_a_minute_by_minute_walk_of_the_clock() {
        // Each zone over a year with its clock changes: Berlin and New York (an hour, at
        // 02:00 and 03:00), Lord Howe (half an hour), Sao Paulo in 2018 (midnight skipped:
        // the day starts at 01:00), Apia in 2011 (30 December skipped whole), Kolkata (no
        // change, +05:30).
        let zones = [
            ("Europe/Berlin", 2026),
            ("America/New_York", 2026),
            ("Australia/Lord_Howe", 2026),
            ("America/Sao_Paulo", 2018),
            ("Pacific/Apia", 2011),
            ("Asia/Kolkata", 2026),
        ];
        let schedules = [
            ("02:30", DAY),
            ("00:00", DAY),
            ("00:00", 3_600),
            ("00:15", 6 * 3_600),
            ("Sun 02:00", WEEK),
        ];
        for (zone, year) in zones {
            let tz = TimeZone::get(zone).unwrap();
            let (from, until) = (utc(year, 1, 1, 0, 0, 0), utc(year + 1, 1, 1, 0, 0, 0));
            // The clock's reading each minute, straight from the database's offsets.
            let civil: Vec<(u64, i64)> = (from..until)
                .step_by(60)
                .map(|t| {
                    let ts = jiff::Timestamp::from_second(t as i64).unwrap();
                    (t, t as i64 + i64::from(tz.to_offset(ts).seconds()))
                })
                .collect();
            for (clock, period) in schedules {
                let time = at(&format!("{clock} {zone}"));
                let (anchor, p) = (time.anchor(), period as i64);
                // A grid time is due at the first minute the clock reads it or later.
                let mut reference = Vec::new();
                let mut seen = civil[0].1;
                for &(t, c) in &civil[1..] {
                    if c > seen {
                        let first = (seen - anchor).div_euclid(p) + 1;
                        if anchor + first * p <= c {
                            reference.push(t);
                        }
                        seen = c;
                    }
                }
                let what = format!("{clock} {zone} every {period} s in {year}");
                let (mut timer, _) = wall_timer(Some(period), &format!("{clock} {zone}"), from);
                assert_eq!(fired(&mut timer, until - 60), reference, "{what}");
                // Started anywhere, the next time is the reference's next.
                for (i, &t) in reference.iter().enumerate().step_by(7) {
                    let start = t - 1 - (i as u64 * 7_919) % 3_000;
                    let start = start.max(reference.get(i.wrapping_sub(1)).map_or(from, |&r| r));
                    let (timer, mono) = wall_timer(Some(period), &format!("{clock} {zone}"), start);
                    assert_eq!(
                        seconds(timer.next_due(wall(0), mono)),
                        t,
                        "{what}, started at {start}"
                    );
                }
            }
        }
    }
}
