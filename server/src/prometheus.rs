//! The Prometheus text exposition format (0.0.4), written in one place: families declared once
//! with `# HELP` and `# TYPE` before their samples, label values escaped. The service's counters
//! ([`crate::service::state`]) and the admin API's gauges ([`crate::admin`]) both write through
//! [`PromText`], and both keep their histograms in a [`Histogram`].

use std::fmt::{Display, Write as _};
use std::marker::PhantomData;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// A metrics text being written.
#[derive(Debug, Default)]
pub struct PromText {
    out: String,
}

/// What kind of metric a family is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// Only ever increases.
    Counter,
    /// Goes up and down.
    Gauge,
    /// Cumulative buckets with `_bucket`, `_sum` and `_count` samples.
    Histogram,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Counter => "counter",
            Kind::Gauge => "gauge",
            Kind::Histogram => "histogram",
        }
    }
}

impl PromText {
    /// Declares a family: `# HELP` and `# TYPE` lines.
    pub fn family(&mut self, name: &str, kind: Kind, help: &str) -> &mut Self {
        let _ = writeln!(
            self.out,
            "# HELP {name} {help}\n# TYPE {name} {}",
            kind.name()
        );
        self
    }

    /// One sample of the family declared last (or of its `_bucket`/`_sum`/`_count` series),
    /// with `labels` as `name="value"` pairs, values escaped.
    pub fn sample(
        &mut self,
        name: &str,
        labels: &[(&str, &str)],
        value: impl Display,
    ) -> &mut Self {
        self.out.push_str(name);
        if !labels.is_empty() {
            self.out.push('{');
            for (i, (k, v)) in labels.iter().enumerate() {
                if i > 0 {
                    self.out.push(',');
                }
                let _ = write!(self.out, "{k}=\"{}\"", escape_label(v));
            }
            self.out.push('}');
        }
        let _ = writeln!(self.out, " {value}");
        self
    }

    /// A family with exactly one unlabelled sample.
    pub fn single(&mut self, name: &str, kind: Kind, help: &str, value: impl Display) -> &mut Self {
        self.family(name, kind, help).sample(name, &[], value)
    }

    /// The text written so far.
    pub fn finish(self) -> String {
        self.out
    }
}

/// A label value escaped as the text format asks (`\`, `"`, newline).
pub fn escape_label(v: &str) -> String {
    let mut out = String::with_capacity(v.len());
    for c in v.chars() {
        match c {
            '\\' => out.push_str("\\\\"),
            '"' => out.push_str("\\\""),
            '\n' => out.push_str("\\n"),
            c => out.push(c),
        }
    }
    out
}

/// Most buckets a [`Histogram`] has (its observations are counted on the stack first).
pub const MAX_BUCKETS: usize = 32;

/// The bucket bounds of one kind of [`Histogram`].
pub trait Buckets {
    /// Upper bounds in seconds, ascending; `+Inf` is implied.
    const BOUNDS: &'static [f64];
}

/// A Prometheus histogram of durations with the fixed buckets of `B`.
///
/// Each bucket counts the observations that fall in it alone (above the bucket before), and
/// the cumulative counts Prometheus expects are summed when rendered: an observation is one
/// atomic add to its bucket, not one to every bucket at or above it (with 14 buckets and one
/// observation per treelet sent, the cumulative adds had been most of the metrics' cost).
pub struct Histogram<B: Buckets> {
    buckets: Box<[AtomicU64]>,
    count: AtomicU64,
    /// Sum in nanoseconds (atomics hold integers; the pool's reads take microseconds).
    sum_nanos: AtomicU64,
    bounds: PhantomData<B>,
}

impl<B: Buckets> std::fmt::Debug for Histogram<B> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Histogram")
            .field("count", &self.count())
            .finish_non_exhaustive()
    }
}

impl<B: Buckets> Default for Histogram<B> {
    fn default() -> Self {
        Self {
            buckets: B::BOUNDS.iter().map(|_| AtomicU64::new(0)).collect(),
            count: AtomicU64::new(0),
            sum_nanos: AtomicU64::new(0),
            bounds: PhantomData,
        }
    }
}

impl<B: Buckets> Histogram<B> {
    pub fn observe(&self, d: Duration) {
        self.observe_all([d]);
    }

    /// Observes every duration of `ds` (a batch of treelets), with one atomic add per bucket
    /// they fall in, plus the count and the sum.
    pub fn observe_all(&self, ds: impl IntoIterator<Item = Duration>) {
        const { assert!(B::BOUNDS.len() <= MAX_BUCKETS) };
        let mut in_bucket = [0u64; MAX_BUCKETS];
        let (mut count, mut sum_nanos) = (0u64, 0u64);
        for d in ds {
            let s = d.as_secs_f64();
            // Above the last bound: counted only in `+Inf` (the total).
            if let Some(i) = B::BOUNDS.iter().position(|&le| s <= le) {
                in_bucket[i] += 1;
            }
            count += 1;
            sum_nanos = sum_nanos.saturating_add(d.as_nanos().min(u128::from(u64::MAX)) as u64);
        }
        for (b, n) in self.buckets.iter().zip(in_bucket) {
            if n > 0 {
                b.fetch_add(n, Ordering::Relaxed);
            }
        }
        if count > 0 {
            self.count.fetch_add(count, Ordering::Relaxed);
            self.sum_nanos.fetch_add(sum_nanos, Ordering::Relaxed);
        }
    }

    /// Observations so far.
    pub fn count(&self) -> u64 {
        self.count.load(Ordering::Relaxed)
    }

    /// Observations at or below each bound so far, in the order of `B::BOUNDS`.
    pub fn cumulative(&self) -> Vec<u64> {
        self.buckets
            .iter()
            .scan(0, |sum, b| {
                *sum += b.load(Ordering::Relaxed);
                Some(*sum)
            })
            .collect()
    }

    /// Writes the family `name`: declaration, cumulative buckets, `+Inf`, sum (seconds) and
    /// count.
    pub fn write(&self, p: &mut PromText, name: &str, help: &str) {
        p.family(name, Kind::Histogram, help);
        let bucket = format!("{name}_bucket");
        for (n, le) in self.cumulative().into_iter().zip(B::BOUNDS) {
            p.sample(&bucket, &[("le", &le.to_string())], n);
        }
        let count = self.count();
        p.sample(&bucket, &[("le", "+Inf")], count)
            .sample(
                &format!("{name}_sum"),
                &[],
                self.sum_nanos.load(Ordering::Relaxed) as f64 / 1e9,
            )
            .sample(&format!("{name}_count"), &[], count);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn families_samples_and_escaped_labels() {
        let mut p = PromText::default();
        p.single("a_total", Kind::Counter, "A.", 3)
            .family("b", Kind::Gauge, "B.")
            .sample("b", &[("k", "x\"y\\z\nw"), ("s", "n")], 1.5);
        assert_eq!(
            p.finish(),
            "# HELP a_total A.\n# TYPE a_total counter\na_total 3\n\
             # HELP b B.\n# TYPE b gauge\nb{k=\"x\\\"y\\\\z\\nw\",s=\"n\"} 1.5\n"
        );
        assert_eq!(escape_label("a\"b\\c\nd"), "a\\\"b\\\\c\\nd");
    }
    struct Micro;

    impl Buckets for Micro {
        const BOUNDS: &'static [f64] = &[0.000_001, 0.000_01];
    }

    #[test]
    fn a_histogram_of_microseconds_keeps_its_sum_to_the_nanosecond() {
        let h = Histogram::<Micro>::default();
        h.observe(Duration::from_nanos(700));
        h.observe_all([Duration::from_nanos(1_000), Duration::from_nanos(2_500)]);
        h.observe(Duration::from_millis(1));
        assert_eq!(h.cumulative(), [2, 3]);
        let mut p = PromText::default();
        h.write(&mut p, "t_seconds", "T.");
        assert_eq!(
            p.finish(),
            "# HELP t_seconds T.\n# TYPE t_seconds histogram\n\
             t_seconds_bucket{le=\"0.000001\"} 2\nt_seconds_bucket{le=\"0.00001\"} 3\n\
             t_seconds_bucket{le=\"+Inf\"} 4\nt_seconds_sum 0.0010042\nt_seconds_count 4\n"
        );
    }
}
