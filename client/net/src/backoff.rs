//! Reconnect delays: exponential backoff with a little jitter.

use arbor_proto::rng::SplitMix64;
use std::collections::hash_map::RandomState;
use std::hash::{BuildHasher, Hasher};
use std::time::Duration;

use super::error::ClientError;

/// How long to wait before reconnect attempt `n` (counted from 0 after the last successful
/// connection): `initial × factor^n`, capped at `max`, then shortened by up to
/// [`Backoff::JITTER`] of itself so that many clients dropped at once by the same server do not
/// all come back in the same instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Backoff {
    /// Delay before the first reconnect attempt.
    pub initial: Duration,
    /// Longest delay.
    pub max: Duration,
    /// Growth per failed attempt, at least 1.
    pub factor: f64,
}

impl Default for Backoff {
    /// 250 ms, doubling, at most 30 s.
    fn default() -> Self {
        Self {
            initial: Duration::from_millis(250),
            max: Duration::from_secs(30),
            factor: 2.0,
        }
    }
}

impl Backoff {
    /// Largest fraction of a delay that jitter removes.
    pub const JITTER: f64 = 0.1;

    /// Checks the fields: `initial > 0`, `max >= initial`, `factor` finite and `>= 1`.
    pub fn validate(&self) -> Result<(), ClientError> {
        if self.initial.is_zero() {
            return Err(ClientError::InvalidConfig(
                "backoff: initial delay must be positive".into(),
            ));
        }
        if self.max < self.initial {
            return Err(ClientError::InvalidConfig(format!(
                "backoff: max delay {:?} is shorter than the initial delay {:?}",
                self.max, self.initial
            )));
        }
        if !(self.factor.is_finite() && self.factor >= 1.0) {
            return Err(ClientError::InvalidConfig(format!(
                "backoff: factor {} must be finite and at least 1",
                self.factor
            )));
        }
        Ok(())
    }

    /// The delay before attempt `attempt` without jitter: `initial × factor^attempt`, at most
    /// `max`.
    pub fn base_delay(&self, attempt: u32) -> Duration {
        let exp = i32::try_from(attempt).unwrap_or(i32::MAX);
        let secs = self.initial.as_secs_f64() * self.factor.powi(exp);
        if secs.is_finite() && secs < self.max.as_secs_f64() {
            Duration::from_secs_f64(secs)
        } else {
            self.max
        }
    }

    /// The delay before attempt `attempt`: [`Self::base_delay`] shortened by a fraction in
    /// `[0, JITTER)` drawn from `jitter`. Never longer than `max`.
    pub fn delay(&self, attempt: u32, jitter: &mut Jitter) -> Duration {
        self.base_delay(attempt)
            .mul_f64(1.0 - Self::JITTER * jitter.next_unit())
    }
}

/// A small deterministic random source for jitter ([`SplitMix64`]). Seeded explicitly for
/// reproducible delays, or from the process's hash randomness.
#[derive(Clone, Debug)]
pub struct Jitter(SplitMix64);

impl Jitter {
    /// A generator whose delays are fixed by `seed`.
    pub fn new(seed: u64) -> Self {
        Self(SplitMix64::new(seed))
    }

    /// A generator seeded differently in every process and call.
    pub fn from_entropy() -> Self {
        let mut h = RandomState::new().build_hasher();
        h.write_u128(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_nanos())
                .unwrap_or(0),
        );
        Self::new(h.finish())
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0.next_u64()
    }

    /// Uniform in `[0, 1)`.
    pub fn next_unit(&mut self) -> f64 {
        self.0.next_f64()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(v: u64) -> Duration {
        Duration::from_millis(v)
    }

    #[test]
    fn base_sequence_grows_and_caps() {
        let b = Backoff {
            initial: ms(100),
            max: ms(1000),
            factor: 2.0,
        };
        let seq: Vec<Duration> = (0..7).map(|n| b.base_delay(n)).collect();
        assert_eq!(
            seq,
            [
                ms(100),
                ms(200),
                ms(400),
                ms(800),
                ms(1000),
                ms(1000),
                ms(1000)
            ]
        );
        assert_eq!(b.base_delay(u32::MAX), ms(1000));
        let flat = Backoff {
            initial: ms(50),
            max: ms(50),
            factor: 1.0,
        };
        assert!((0..10).all(|n| flat.base_delay(n) == ms(50)));
    }

    #[test]
    fn jitter_only_shortens_and_is_deterministic() {
        let b = Backoff::default();
        let mut j1 = Jitter::new(7);
        let mut j2 = Jitter::new(7);
        let mut distinct = std::collections::BTreeSet::new();
        for n in 0..40 {
            let d = b.delay(n, &mut j1);
            assert_eq!(d, b.delay(n, &mut j2));
            let base = b.base_delay(n);
            assert!(d <= base && d <= b.max, "{n}: {d:?} > {base:?}");
            assert!(d.as_secs_f64() >= base.as_secs_f64() * (1.0 - Backoff::JITTER) - 1e-9);
            distinct.insert(d);
        }
        // Jitter actually varies the delays at the cap.
        assert!(distinct.len() > 20);
        let mut j = Jitter::new(1);
        assert!(
            (0..1000)
                .map(|_| j.next_unit())
                .all(|u| (0.0..1.0).contains(&u))
        );
        assert_ne!(
            Jitter::from_entropy().next_u64(),
            Jitter::from_entropy().next_u64()
        );
    }

    #[test]
    fn validation() {
        assert!(Backoff::default().validate().is_ok());
        for b in [
            Backoff {
                initial: Duration::ZERO,
                ..Backoff::default()
            },
            Backoff {
                max: ms(1),
                ..Backoff::default()
            },
            Backoff {
                factor: 0.5,
                ..Backoff::default()
            },
            Backoff {
                factor: f64::NAN,
                ..Backoff::default()
            },
        ] {
            assert!(
                matches!(b.validate(), Err(ClientError::InvalidConfig(_))),
                "{b:?}"
            );
        }
    }
}
