//! Range checks for configuration values (node parameters, CLI arguments), in one style:
//! each check takes the key as the user wrote it and the value, and returns the value (or
//! the [`Duration`] it stands for) or a [`RangeError`] naming the key, the value and the
//! rule. A node checks its settings once at start-up with these, so a bad value is a clear
//! error there and never a panic later (`Duration::from_secs_f64` panics on a negative or
//! NaN number). A leaf module: the ROS nodes, the CLI and the benchmarks all use it.

use std::fmt;
use std::time::Duration;

/// What a value must satisfy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rule {
    /// Finite and > 0.
    Positive,
    /// Finite and >= 0.
    NonNegative,
    /// Finite and > 0, at most the bound.
    PositiveAtMost(f64),
    /// Within the closed interval.
    Within(f64, f64),
    /// Within the open interval.
    Between(f64, f64),
    /// A period in seconds: 0 (never) or finite and > 0, as a `Duration`.
    PeriodOrNever,
    /// An integer within the closed interval.
    IntegerWithin(i64, i64),
}

impl fmt::Display for Rule {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Positive => write!(f, "a finite number > 0"),
            Self::NonNegative => write!(f, "a finite number >= 0"),
            Self::PositiveAtMost(hi) => write!(f, "in (0, {hi}]"),
            Self::Within(lo, hi) => write!(f, "in [{lo}, {hi}]"),
            Self::Between(lo, hi) => write!(f, "in ({lo}, {hi})"),
            Self::PeriodOrNever => write!(f, "0 (never) or a finite number of seconds > 0"),
            Self::IntegerWithin(lo, hi) => write!(f, "an integer in {lo}..={hi}"),
        }
    }
}

/// A configuration value breaks its rule.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("`{key}` = {value}: must be {rule}")]
pub struct RangeError {
    /// The key, as in the YAML or on the command line (e.g. `report_period_s`).
    pub key: String,
    /// The value given.
    pub value: f64,
    /// The rule it breaks.
    pub rule: Rule,
}

/// The error's text, for the checks that report a `String` (the controller's parameters).
impl From<RangeError> for String {
    fn from(e: RangeError) -> Self {
        e.to_string()
    }
}

fn check(key: &str, value: f64, rule: Rule, ok: bool) -> Result<f64, RangeError> {
    if ok {
        Ok(value)
    } else {
        Err(RangeError {
            key: key.to_string(),
            value,
            rule,
        })
    }
}

/// `value` is finite and > 0 (a rate, a timeout, a size).
pub fn positive(key: &str, value: f64) -> Result<f64, RangeError> {
    check(key, value, Rule::Positive, value.is_finite() && value > 0.0)
}

/// `value` is finite and >= 0.
pub fn non_negative(key: &str, value: f64) -> Result<f64, RangeError> {
    check(key, value, Rule::NonNegative, value.is_finite() && value >= 0.0)
}

/// `value` is finite, > 0 and <= `hi`.
pub fn positive_at_most(key: &str, value: f64, hi: f64) -> Result<f64, RangeError> {
    check(
        key,
        value,
        Rule::PositiveAtMost(hi),
        value.is_finite() && value > 0.0 && value <= hi,
    )
}

/// `value` is in `[lo, hi]` (and so finite).
pub fn in_range(key: &str, value: f64, lo: f64, hi: f64) -> Result<f64, RangeError> {
    check(key, value, Rule::Within(lo, hi), value >= lo && value <= hi)
}

/// `value` is in the open interval `(lo, hi)`.
pub fn between(key: &str, value: f64, lo: f64, hi: f64) -> Result<f64, RangeError> {
    check(key, value, Rule::Between(lo, hi), value > lo && value < hi)
}

/// An integer `value` in `lo..=hi`.
pub fn integer_in_range(key: &str, value: i64, lo: i64, hi: i64) -> Result<i64, RangeError> {
    check(
        key,
        value as f64,
        Rule::IntegerWithin(lo, hi),
        (lo..=hi).contains(&value),
    )
    .map(|_| value)
}

/// A duration of `seconds`, finite and > 0, representable as a [`Duration`].
pub fn duration(key: &str, seconds: f64) -> Result<Duration, RangeError> {
    positive(key, seconds)?;
    Duration::try_from_secs_f64(seconds).map_err(|_| RangeError {
        key: key.to_string(),
        value: seconds,
        rule: Rule::Positive,
    })
}

/// A period of `seconds` where 0 means never: `None` for 0, the [`Duration`] for a finite
/// value > 0; negative, NaN, infinite or too large values are errors.
pub fn period_or_never(key: &str, seconds: f64) -> Result<Option<Duration>, RangeError> {
    if seconds == 0.0 {
        return Ok(None);
    }
    let err = || RangeError {
        key: key.to_string(),
        value: seconds,
        rule: Rule::PeriodOrNever,
    };
    if !(seconds.is_finite() && seconds > 0.0) {
        return Err(err());
    }
    Duration::try_from_secs_f64(seconds).map(Some).map_err(|_| err())
}

/// The period of a rate `hz`, finite and > 0.
pub fn period_of_rate(key: &str, hz: f64) -> Result<Duration, RangeError> {
    positive(key, hz)?;
    duration(key, 1.0 / hz)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_rule_accepts_its_values_and_names_the_key_otherwise() {
        assert_eq!(positive("rate_hz", 100.0), Ok(100.0));
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let e = positive("rate_hz", bad).unwrap_err();
            assert_eq!(e.key, "rate_hz");
            assert!(e.to_string().starts_with("`rate_hz` = "), "{e}");
        }
        assert_eq!(non_negative("x", 0.0), Ok(0.0));
        assert!(non_negative("x", -0.1).is_err());
        assert!(non_negative("x", f64::NAN).is_err());
        assert_eq!(positive_at_most("gap_s", 60.0, 60.0), Ok(60.0));
        assert!(positive_at_most("gap_s", 60.5, 60.0).is_err());
        assert!(positive_at_most("gap_s", 0.0, 60.0).is_err());
        assert_eq!(in_range("p", 0.5, 0.0, 1.0), Ok(0.5));
        assert!(in_range("p", f64::NAN, 0.0, 1.0).is_err());
        assert_eq!(between("size", 0.04, 1e-4, 10.0), Ok(0.04));
        assert!(between("size", 10.0, 1e-4, 10.0).is_err());
        assert!(between("size", f64::NAN, 1e-4, 10.0).is_err());
        assert_eq!(integer_in_range("prio", 0, 0, 99), Ok(0));
        let e = integer_in_range("prio", 100, 0, 99).unwrap_err();
        assert_eq!(e.to_string(), "`prio` = 100: must be an integer in 0..=99");
    }

    #[test]
    fn durations_never_panic() {
        assert_eq!(duration("t", 0.25), Ok(Duration::from_millis(250)));
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, f64::MAX] {
            assert!(duration("t", bad).is_err(), "{bad}");
        }
        assert_eq!(period_or_never("report_period_s", 0.0), Ok(None));
        assert_eq!(
            period_or_never("report_period_s", 10.0),
            Ok(Some(Duration::from_secs(10)))
        );
        for bad in [-1.0, f64::NAN, f64::INFINITY, f64::MAX / 4.0] {
            let e = period_or_never("report_period_s", bad).unwrap_err();
            assert_eq!(e.rule, Rule::PeriodOrNever, "{bad}");
        }
        assert_eq!(period_of_rate("hz", 1000.0), Ok(Duration::from_millis(1)));
        assert!(period_of_rate("hz", 0.0).is_err());
        assert!(period_of_rate("hz", 1e-300).is_err());
    }
}
