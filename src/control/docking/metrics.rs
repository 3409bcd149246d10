//! The paper's metric M = (1/T) ∫ ||f_ext|| dt, completion time and peak force.
//!
//! M is reported in newtons as the paper defines it. The paper's plotting code summed a
//! force already scaled by 0.01 at 240 Hz, so its figures are 2.4 x M; [`ForceMetric::paper_code_scale`]
//! gives that number, labelled as such, so the two can be compared.

/// The factor between the paper's published M figures and M in newtons.
pub const PAPER_CODE_SCALE: f64 = 2.4;

/// Running integral of the force norm over time.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct ForceMetric {
    /// ∫ ||f|| dt, N s.
    pub integral: f64,
    /// T, s.
    pub duration: f64,
    /// Largest ||f|| seen, N.
    pub max_force: f64,
    /// Samples added.
    pub samples: u64,
}

impl ForceMetric {
    /// Add a sample of force norm `f` held for `dt` seconds (rectangle rule). Non-finite or
    /// negative inputs are ignored.
    pub fn add(&mut self, f: f64, dt: f64) {
        if !(f.is_finite() && dt.is_finite() && f >= 0.0 && dt > 0.0) {
            return;
        }
        self.integral += f * dt;
        self.duration += dt;
        self.max_force = self.max_force.max(f);
        self.samples += 1;
    }

    /// M = integral / T, N (0 before any sample).
    pub fn mean(&self) -> f64 {
        if self.duration > 0.0 {
            self.integral / self.duration
        } else {
            0.0
        }
    }

    /// 2.4 x M: the scale of the paper's published figures.
    pub fn paper_code_scale(&self) -> f64 {
        PAPER_CODE_SCALE * self.mean()
    }
}

/// Mean and sample standard deviation of `v` (NaN-free input; `(NaN, NaN)` when empty).
pub fn mean_std(v: &[f64]) -> (f64, f64) {
    if v.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = if v.len() > 1 {
        v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    (m, var.sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_force_gives_that_force() {
        let mut m = ForceMetric::default();
        for _ in 0..1000 {
            m.add(3.0, 0.001);
        }
        assert!((m.mean() - 3.0).abs() < 1e-12);
        assert!((m.duration - 1.0).abs() < 1e-9);
        assert!((m.paper_code_scale() - 7.2).abs() < 1e-9);
        m.add(f64::NAN, 0.001);
        m.add(5.0, -1.0);
        assert_eq!(m.samples, 1000);
        assert_eq!(m.max_force, 3.0);
    }

    #[test]
    fn ramp_averages_to_half() {
        let mut m = ForceMetric::default();
        let n = 10000;
        for k in 0..n {
            m.add(10.0 * (k as f64 + 0.5) / n as f64, 1.0 / n as f64);
        }
        assert!((m.mean() - 5.0).abs() < 1e-9);
        assert_eq!(ForceMetric::default().mean(), 0.0);
        let (mu, sd) = mean_std(&[1.0, 2.0, 3.0]);
        assert!((mu - 2.0).abs() < 1e-12 && (sd - 1.0).abs() < 1e-12);
    }
}
