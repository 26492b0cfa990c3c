//! The screen-space error of one cycle's feedback, summarised: what the cycle reports and what
//! run reports and charts plot against time.

/// Summary of the screen-space error over one cycle's feedback samples.
///
/// Each sample is the screen-space error, in octree levels, of the treelet a feedback ray hit:
/// how many more levels of refinement that pixel would still show. 0 means nothing there is
/// refinable any more.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ErrorSummary {
    /// Mean error over the samples (levels).
    pub mean: f32,
    /// 95th percentile, nearest rank: the `⌈0.95·n⌉`-th smallest sample (levels).
    pub p95: f32,
    /// Largest sample (levels).
    pub max: f32,
    /// Error-weighted pixel count: Σ error × pixels per sample (levels × pixels).
    pub error_pixels: f64,
}

impl ErrorSummary {
    /// Summarises one cycle's feedback samples; `pixels_per_sample` is how many screen pixels one
    /// feedback sample stands for (the feedback ratio squared, typically).
    ///
    /// Values that are not a positive finite number — negative, zero, NaN or infinite — count as
    /// an error of 0 (a sample with nothing left to refine): they still count as samples, so they
    /// pull the mean and the percentile down rather than vanish. A `pixels_per_sample` that is
    /// not a non-negative finite number counts as 0. With no samples every field is 0.
    pub fn from_samples(errors: &[f32], pixels_per_sample: f64) -> Self {
        if errors.is_empty() {
            return Self::default();
        }
        let mut clean: Vec<f32> = errors
            .iter()
            .map(|&e| if e > 0.0 && e.is_finite() { e } else { 0.0 })
            .collect();
        clean.sort_unstable_by(f32::total_cmp);
        let n = clean.len();
        let sum: f64 = clean.iter().map(|&e| f64::from(e)).sum();
        // Nearest rank: the smallest value with at least 95 % of the samples at or below it.
        // Integer arithmetic, so that e.g. n = 20 gives rank 19 exactly.
        let rank = (n * 95).div_ceil(100).max(1);
        let pps = if pixels_per_sample >= 0.0 && pixels_per_sample.is_finite() {
            pixels_per_sample
        } else {
            0.0
        };
        Self {
            mean: (sum / n as f64) as f32,
            p95: clean[rank - 1],
            max: clean[n - 1],
            error_pixels: sum * pps,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_summary_exact_values() {
        assert_eq!(
            ErrorSummary::from_samples(&[], 64.0),
            ErrorSummary::default()
        );
        assert_eq!(
            ErrorSummary::from_samples(&[0.0, 0.0, 0.0], 64.0),
            ErrorSummary {
                mean: 0.0,
                p95: 0.0,
                max: 0.0,
                error_pixels: 0.0
            }
        );
        assert_eq!(
            ErrorSummary::from_samples(&[2.0], 4.0),
            ErrorSummary {
                mean: 2.0,
                p95: 2.0,
                max: 2.0,
                error_pixels: 8.0
            }
        );
        // Unsorted input; n = 4: rank ⌈3.8⌉ = 4, the largest.
        assert_eq!(
            ErrorSummary::from_samples(&[3.0, 1.0, 4.0, 0.0], 2.0),
            ErrorSummary {
                mean: 2.0,
                p95: 4.0,
                max: 4.0,
                error_pixels: 16.0
            }
        );
        // n = 20: rank exactly 19, so the single outlier at the top is not the p95.
        let mut v: Vec<f32> = (1..=19).map(|i| i as f32).collect();
        v.push(100.0);
        let s = ErrorSummary::from_samples(&v, 1.0);
        assert_eq!((s.p95, s.max, s.error_pixels), (19.0, 100.0, 290.0));
        assert_eq!(s.mean, 14.5);
        // n = 21: rank ⌈19.95⌉ = 20.
        v.push(50.0);
        assert_eq!(ErrorSummary::from_samples(&v, 1.0).p95, 50.0);
        // NaN, negatives and infinities count as 0 but still count as samples.
        assert_eq!(
            ErrorSummary::from_samples(&[f32::NAN, -3.0, 4.0, f32::INFINITY], 0.5),
            ErrorSummary {
                mean: 1.0,
                p95: 4.0,
                max: 4.0,
                error_pixels: 2.0
            }
        );
        assert_eq!(
            ErrorSummary::from_samples(&[f32::NAN, -1.0, f32::NEG_INFINITY], 1.0),
            ErrorSummary::default()
        );
        // A bad pixels-per-sample gives 0 error-pixels, not NaN.
        assert_eq!(
            ErrorSummary::from_samples(&[1.0], f64::NAN).error_pixels,
            0.0
        );
        assert_eq!(ErrorSummary::from_samples(&[1.0], -4.0).error_pixels, 0.0);
    }
}
