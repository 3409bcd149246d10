//! DONE over a window: the tip-to-goal error and the alignment angle are averaged over
//! consecutive windows of `goal_window_s` seconds in INSERT, and the goal test is judged on
//! each complete window's mean, so that one lucky sample of a noisy trocar estimate never
//! ends the docking. The means of uniform ±5 mm pose noise at 100 Hz over 0.3 s have a
//! standard deviation of about 0.5 mm per axis, against 2.9 mm for one sample.
//!
//! Sums, not a buffer: nothing allocates, and a window begins afresh when the last one
//! has been judged (so a decision comes at most one window after the goal holds).

use nalgebra::Vector3;

/// The running window.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct GoalWindow {
    sum_error: Vector3<f64>,
    sum_angle: f64,
    samples: u32,
    elapsed: f64,
}

impl GoalWindow {
    /// Add one sample (the tip-to-goal error vector, m, and the alignment angle, rad) taken
    /// `dt` after the last. When the window of `length` s is complete (at once for a
    /// `length` of 0), returns the means (the norm of the mean error vector, and the mean
    /// angle) and starts the next window.
    pub fn add(&mut self, length: f64, error: Vector3<f64>, angle: f64, dt: f64) -> Option<(f64, f64)> {
        if !(error.iter().all(|x| x.is_finite()) && angle.is_finite()) {
            // A sample that cannot be judged breaks the window.
            *self = Self::default();
            return None;
        }
        self.sum_error += error;
        self.sum_angle += angle;
        self.samples += 1;
        self.elapsed += dt.max(0.0);
        if self.elapsed + 1e-9 < length {
            return None;
        }
        let n = f64::from(self.samples);
        let out = ((self.sum_error / n).norm(), self.sum_angle / n);
        *self = Self::default();
        Some(out)
    }

    /// Forget the window (a phase change).
    pub fn reset(&mut self) {
        *self = Self::default();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_window_is_judged_on_its_mean_once_complete() {
        let mut w = GoalWindow::default();
        // 0.3 s at 100 Hz: 29 samples give nothing, the 30th the means.
        for k in 0..29 {
            let s = if k % 2 == 0 { 1.0 } else { -1.0 };
            assert_eq!(w.add(0.3, Vector3::new(0.005 * s, 0.0, 0.0002), 0.001, 0.01), None);
        }
        let (e, a) = w.add(0.3, Vector3::new(-0.005, 0.0, 0.0002), 0.001, 0.01).unwrap();
        // +-5 mm alternating averages to 0; the 0.2 mm along z stays.
        assert!((e - 0.0002).abs() < 1e-12 && (a - 0.001).abs() < 1e-12, "{e} {a}");
        // The next window starts afresh.
        assert_eq!(w.add(0.3, Vector3::new(0.004, 0.0, 0.0), 0.0, 0.01), None);
    }

    #[test]
    fn a_zero_window_judges_each_sample_and_a_nan_breaks_the_window() {
        let mut w = GoalWindow::default();
        assert_eq!(
            w.add(0.0, Vector3::new(0.003, 0.004, 0.0), 0.5, 0.01),
            Some((0.005, 0.5))
        );
        for _ in 0..10 {
            w.add(0.3, Vector3::zeros(), 0.0, 0.01);
        }
        assert_eq!(w.add(0.3, Vector3::new(f64::NAN, 0.0, 0.0), 0.0, 0.01), None);
        // 29 more samples are not enough: the NaN started the window again.
        for _ in 0..29 {
            assert_eq!(w.add(0.3, Vector3::zeros(), 0.0, 0.01), None);
        }
        assert!(w.add(0.3, Vector3::zeros(), 0.0, 0.01).is_some());
    }
}
