//! A short history of joint positions by time stamp, so that a measurement taken at one
//! instant (a camera frame) is paired with the arm's pose at that same instant rather than
//! with the newest joint state. Pure: no ROS, no C++; its buffer is allocated once.

use crate::kinematics::JointVector;

/// Why no joint positions can be given for a time.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TimelineError {
    /// Nothing was recorded yet.
    #[error("no joint state received yet")]
    Empty,
    /// The time is older than the oldest sample kept.
    #[error("stamp {t:.3} s is {by:.3} s older than the joint history")]
    TooOld {
        /// The time asked for, s.
        t: f64,
        /// How much older than the oldest sample, s.
        by: f64,
    },
    /// The time is later than the newest sample by more than the allowed extrapolation.
    #[error("stamp {t:.3} s is {by:.3} s after the newest joint state")]
    TooNew {
        /// The time asked for, s.
        t: f64,
        /// How much later than the newest sample, s.
        by: f64,
    },
    /// Two samples around the time are farther apart than the allowed gap.
    #[error("joint states around {t:.3} s are {gap:.3} s apart")]
    Gap {
        /// The time asked for, s.
        t: f64,
        /// The gap between the samples around it, s.
        gap: f64,
    },
    /// The time is not finite.
    #[error("stamp is not finite")]
    NonFinite,
}

/// Joint positions over the last `span` seconds, linearly interpolated between samples.
#[derive(Debug, Clone)]
pub struct JointHistory {
    stamps: Vec<f64>,
    values: Vec<JointVector>,
    head: usize,
    len: usize,
    max_gap: f64,
    max_extrapolation: f64,
}

impl JointHistory {
    /// Keep `capacity` samples; refuse to interpolate across a gap longer than `max_gap`
    /// seconds, or to answer more than `max_extrapolation` seconds past the newest sample
    /// (the newest sample is returned there: the arm is assumed still for that long).
    pub fn new(capacity: usize, max_gap: f64, max_extrapolation: f64) -> Self {
        let capacity = capacity.max(2);
        Self {
            stamps: vec![f64::NEG_INFINITY; capacity],
            values: vec![JointVector::zeros(); capacity],
            head: 0,
            len: 0,
            max_gap: max_gap.max(0.0),
            max_extrapolation: max_extrapolation.max(0.0),
        }
    }

    /// Samples kept.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when nothing is kept.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn index(&self, k: usize) -> usize {
        // k-th oldest sample.
        (self.head + self.stamps.len() - self.len + k) % self.stamps.len()
    }

    /// Record a sample. A stamp not after the newest one (time went back: a bag looped, the
    /// simulator restarted) clears the history first; non-finite input is ignored.
    pub fn push(&mut self, stamp: f64, q: JointVector) {
        if !stamp.is_finite() || q.iter().any(|v| !v.is_finite()) {
            return;
        }
        if self.len > 0 && stamp <= self.stamps[self.index(self.len - 1)] {
            self.clear();
        }
        self.stamps[self.head] = stamp;
        self.values[self.head] = q;
        self.head = (self.head + 1) % self.stamps.len();
        self.len = (self.len + 1).min(self.stamps.len());
    }

    /// Forget everything.
    pub fn clear(&mut self) {
        self.len = 0;
    }

    /// Joint positions at time `t`.
    pub fn at(&self, t: f64) -> Result<JointVector, TimelineError> {
        if !t.is_finite() {
            return Err(TimelineError::NonFinite);
        }
        if self.len == 0 {
            return Err(TimelineError::Empty);
        }
        let (oldest, newest) = (self.index(0), self.index(self.len - 1));
        if t >= self.stamps[newest] {
            let by = t - self.stamps[newest];
            return if by <= self.max_extrapolation {
                Ok(self.values[newest])
            } else {
                Err(TimelineError::TooNew { t, by })
            };
        }
        if t < self.stamps[oldest] {
            return Err(TimelineError::TooOld {
                t,
                by: self.stamps[oldest] - t,
            });
        }
        // Newest first: a camera frame is usually recent.
        for k in (0..self.len - 1).rev() {
            let (a, b) = (self.index(k), self.index(k + 1));
            let (ta, tb) = (self.stamps[a], self.stamps[b]);
            if t >= ta {
                let gap = tb - ta;
                if gap > self.max_gap {
                    return Err(TimelineError::Gap { t, gap });
                }
                let s = (t - ta) / gap;
                return Ok(self.values[a].lerp(&self.values[b], s));
            }
        }
        Err(TimelineError::TooOld { t, by: 0.0 })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn q(v: f64) -> JointVector {
        JointVector::from_element(v)
    }

    #[test]
    fn interpolates_between_samples_and_holds_briefly_after_the_newest() {
        let mut h = JointHistory::new(10, 0.05, 0.02);
        assert_eq!(h.at(1.0), Err(TimelineError::Empty));
        for k in 0..5 {
            h.push(1.0 + 0.01 * k as f64, q(k as f64));
        }
        assert!((h.at(1.015).unwrap()[0] - 1.5).abs() < 1e-9);
        assert!((h.at(1.0).unwrap()[3] - 0.0).abs() < 1e-12);
        assert_eq!(h.at(1.05).unwrap(), q(4.0));
        assert!(matches!(h.at(1.2), Err(TimelineError::TooNew { .. })));
        assert!(matches!(h.at(0.9), Err(TimelineError::TooOld { .. })));
        assert_eq!(h.at(f64::NAN), Err(TimelineError::NonFinite));
    }

    #[test]
    fn keeps_only_the_last_samples_and_refuses_gaps() {
        let mut h = JointHistory::new(4, 0.05, 0.0);
        for k in 0..10 {
            h.push(k as f64 * 0.01, q(k as f64));
        }
        assert_eq!(h.len(), 4);
        assert!(matches!(h.at(0.05), Err(TimelineError::TooOld { .. })));
        assert!((h.at(0.075).unwrap()[0] - 7.5).abs() < 1e-9);
        h.push(0.5, q(50.0));
        assert!(matches!(h.at(0.3), Err(TimelineError::Gap { .. })));
    }

    #[test]
    fn time_going_back_restarts_and_bad_samples_are_ignored() {
        let mut h = JointHistory::new(8, 0.05, 0.0);
        h.push(2.0, q(1.0));
        h.push(2.01, q(2.0));
        h.push(1.0, q(3.0));
        assert_eq!(h.len(), 1);
        assert_eq!(h.at(1.0).unwrap(), q(3.0));
        h.push(f64::NAN, q(0.0));
        h.push(1.01, q(f64::INFINITY));
        assert_eq!(h.len(), 1);
    }
}
