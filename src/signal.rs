//! Small signal-processing helpers shared by the controller and the simulated sensors: the
//! dead-band, the two first-order low-pass rules ([`exp_smoothing`] for stamped streams,
//! [`rc_smoothing`] / [`rc_weight`] at a fixed step), the stream low-pass built on the first,
//! and the second-order tracking filter that follows a moving signal without lag
//! ([`TrackingFilter`]).

/// Dead-band: values within ±`band` become 0, others shrink towards 0 by `band`.
pub fn deadband(x: f64, band: f64) -> f64 {
    if x > band {
        x - band
    } else if x < -band {
        x + band
    } else {
        0.0
    }
}

/// The weight of a new sample in a first-order low-pass of time constant `tau` s, `dt` s
/// after the last one: `1 - exp(-dt / tau)`, exact for an input held between samples (a
/// `dt` below 0 counts as 0; `tau` of 0 or less: 1, no filter). The rule of
/// [`StreamLowPass`] and of the trocar estimate's smoothing.
pub fn exp_smoothing(dt: f64, tau: f64) -> f64 {
    if tau > 0.0 {
        1.0 - (-dt.max(0.0) / tau).exp()
    } else {
        1.0
    }
}

/// The weight of a new sample in a first-order low-pass of cut-off `cutoff_hz` Hz stepped at
/// a fixed `dt` s: the discrete RC filter's `dt / (RC + dt)`, `RC = 1 / (2 pi cutoff)` (a
/// cut-off or `dt` of 0 or less: 1, no filter). The rule of the force estimates' filters.
pub fn rc_smoothing(cutoff_hz: f64, dt: f64) -> f64 {
    if cutoff_hz > 0.0 {
        rc_weight(dt, 1.0 / (2.0 * std::f64::consts::PI * cutoff_hz))
    } else {
        1.0
    }
}

/// The discrete RC filter's weight `dt / (rc + dt)` for a time constant `rc` s stepped at a
/// fixed `dt` s (a `dt` of 0 or less, or an `rc` below 0: 1, no filter): the rule of
/// [`rc_smoothing`] given the time constant, as the tare's offset tracking is.
pub fn rc_weight(dt: f64, rc: f64) -> f64 {
    if dt > 0.0 && rc >= 0.0 {
        dt / (rc + dt)
    } else {
        1.0
    }
}

/// A first-order low-pass of a stamped stream, for a signal sampled faster than it is read:
/// the LBR's external torques arrive once per FRI cycle (1-10 ms) and the controller reads
/// them once per control period (10 ms at 100 Hz), so reading the newest sample alone
/// throws the other samples away and keeps all of their white noise. Applied per sample,
/// y += (x - y)(1 - exp(-Δt / τ)), it keeps the noise's variance to about Δt / (2τ) of it
/// (τ = 5 ms at a 1 ms FRI period: a third of the standard deviation) at a lag of τ.
///
/// Irregular stamps are fine (a dropped message only lengthens Δt); a sample with the
/// previous stamp changes nothing; a stamp that goes back (a driver restart) starts the
/// filter again at that sample; τ = 0 passes every sample through. Allocation-free.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamLowPass<const N: usize> {
    time_constant: f64,
    state: Option<(f64, nalgebra::SVector<f64, N>)>,
}

impl<const N: usize> StreamLowPass<N> {
    /// A filter with time constant `time_constant` s (0 or not finite: none).
    pub fn new(time_constant: f64) -> Self {
        Self {
            time_constant: if time_constant.is_finite() {
                time_constant.max(0.0)
            } else {
                0.0
            },
            state: None,
        }
    }

    /// Feed the sample `x` stamped `stamp` (s); returns the filtered value. A sample with a
    /// non-finite stamp or value is passed through and restarts the filter, so that the
    /// reader's own checks see it.
    pub fn update(&mut self, stamp: f64, x: &nalgebra::SVector<f64, N>) -> nalgebra::SVector<f64, N> {
        let fresh = stamp.is_finite() && x.iter().all(|v| v.is_finite());
        let y = match self.state {
            Some((t0, y)) if fresh && self.time_constant > 0.0 && stamp >= t0 => {
                y + (x - y) * exp_smoothing(stamp - t0, self.time_constant)
            }
            _ => *x,
        };
        self.state = fresh.then_some((stamp, y));
        y
    }

    /// Forget the past: the next sample starts the filter again.
    pub fn reset(&mut self) {
        self.state = None;
    }
}

/// A second-order tracking filter of a stamped stream: position and velocity, so that a
/// signal moving at a steady rate is followed without lag.
///
/// The critically damped g-h filter (the fading-memory polynomial filter of degree 1:
/// E. Brookner, *Tracking and Kalman Filtering Made Easy*, Wiley 1998, ch. 1): on a sample
/// `z` stamped Δt after the last, with θ = exp(-Δt / τ),
/// ```text
/// predict:  x- = x + v Δt
/// correct:  x = x- + (1 - θ²)(z - x-),   v = v + (1 - θ)² (z - x-) / Δt
/// ```
/// It follows a ramp with no steady error (a first-order low-pass of time constant τ lags
/// it by τ) and an acceleration `a` with an error of about `a τ²`; at a fixed rate it keeps
/// `(1 - θ)(1 + 4θ + 5θ²) / (1 + θ)³` of white noise's variance.
///
/// The first sample, and the first after a gap longer than `max_gap` s (the velocity of
/// before is then no evidence) or a stamp that goes back, start the filter again at the
/// sample with zero velocity; a sample with the previous stamp changes nothing; a non-finite
/// one restarts it and is passed through. τ = 0 passes every sample through. Allocation-free.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackingFilter<const N: usize> {
    time_constant: f64,
    max_gap: f64,
    /// The stamp, the position and the velocity of the last sample.
    state: Option<(f64, nalgebra::SVector<f64, N>, nalgebra::SVector<f64, N>)>,
}

impl<const N: usize> TrackingFilter<N> {
    /// A filter of time constant `time_constant` s (0 or not finite: none) that restarts
    /// after gaps longer than `max_gap` s.
    pub fn new(time_constant: f64, max_gap: f64) -> Self {
        let finite_or = |v: f64, d: f64| if v.is_finite() { v.max(0.0) } else { d };
        Self {
            time_constant: finite_or(time_constant, 0.0),
            max_gap: finite_or(max_gap, f64::INFINITY),
            state: None,
        }
    }

    /// Feed the sample `z` stamped `stamp` (s); returns the filtered position at `stamp`.
    pub fn update(&mut self, stamp: f64, z: &nalgebra::SVector<f64, N>) -> nalgebra::SVector<f64, N> {
        let fresh = stamp.is_finite() && z.iter().all(|v| v.is_finite());
        let zero = nalgebra::SVector::<f64, N>::zeros();
        let next = match self.state {
            Some((t0, x, v)) if fresh && stamp == t0 => (t0, x, v),
            Some((t0, x, v)) if fresh && self.time_constant > 0.0 && stamp > t0 && stamp - t0 <= self.max_gap => {
                let dt = stamp - t0;
                let theta = (-dt / self.time_constant).exp();
                let predicted = x + v * dt;
                let r = z - predicted;
                let g = 1.0 - theta * theta;
                let h = (1.0 - theta) * (1.0 - theta);
                (stamp, predicted + r * g, v + r * (h / dt))
            }
            _ => (stamp, *z, zero),
        };
        self.state = fresh.then_some(next);
        next.1
    }

    /// Forget the past: the next sample starts the filter again.
    pub fn reset(&mut self) {
        self.state = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector2;

    #[test]
    fn the_low_pass_keeps_a_fraction_of_white_noise_and_follows_a_step() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let noise = Normal::new(0.0, 1.0).unwrap();
        // 1 kHz samples of unit white noise, tau 5 ms: sigma sqrt(1 ms / 10 ms) = 0.32.
        let mut lp = StreamLowPass::<2>::new(0.005);
        let n = 200_000;
        let mut sq = 0.0;
        for k in 0..n {
            let x = Vector2::new(noise.sample(&mut rng), 1.0);
            let y = lp.update(k as f64 * 1e-3, &x);
            assert!((y.y - 1.0).abs() < 1e-12, "a constant passes unchanged");
            sq += y.x * y.x;
        }
        let sigma = (sq / n as f64).sqrt();
        assert!((sigma - 0.312).abs() < 0.02, "sigma {sigma}");
        // A step: 1 - exp(-1) of it after one time constant.
        let mut lp = StreamLowPass::<2>::new(0.005);
        lp.update(0.0, &Vector2::zeros());
        let y = lp.update(0.005, &Vector2::new(1.0, 1.0));
        assert!((y.x - (1.0 - (-1.0f64).exp())).abs() < 1e-12);
    }

    #[test]
    fn the_smoothing_weights_follow_their_rules() {
        assert!((exp_smoothing(0.005, 0.005) - (1.0 - (-1.0f64).exp())).abs() < 1e-15);
        assert_eq!(exp_smoothing(-1.0, 0.005), 0.0);
        assert_eq!(exp_smoothing(0.01, 0.0), 1.0);
        // RC = 1 / (2 pi) s at 1 Hz: after dt = RC, half of the step.
        let rc = 1.0 / (2.0 * std::f64::consts::PI);
        assert!((rc_smoothing(1.0, rc) - 0.5).abs() < 1e-15);
        assert_eq!(rc_smoothing(0.0, 0.01), 1.0);
        assert_eq!(rc_smoothing(5.0, 0.0), 1.0);
        // Given the time constant: dt / (rc + dt), the same weight.
        assert_eq!(rc_weight(0.01, 0.3), 0.01 / 0.31);
        assert!((rc_weight(rc, rc) - 0.5).abs() < 1e-15);
        assert_eq!(
            (rc_weight(0.0, 0.3), rc_weight(0.01, 0.0), rc_weight(0.01, -1.0)),
            (1.0, 1.0, 1.0)
        );
    }

    #[test]
    fn the_low_pass_restarts_on_a_stamp_back_and_passes_bad_samples() {
        let mut lp = StreamLowPass::<2>::new(0.005);
        lp.update(1.0, &Vector2::zeros());
        // The same stamp again: nothing changes.
        assert_eq!(lp.update(1.0, &Vector2::new(5.0, 5.0)), Vector2::zeros());
        // A stamp back: a restart, the sample as it is.
        assert_eq!(lp.update(0.5, &Vector2::new(5.0, 5.0)), Vector2::new(5.0, 5.0));
        // A NaN passes through (the reader's checks reject it) and restarts the filter.
        assert!(lp.update(0.6, &Vector2::new(f64::NAN, 0.0)).x.is_nan());
        assert_eq!(lp.update(0.601, &Vector2::new(2.0, 2.0)), Vector2::new(2.0, 2.0));
        // Off: every sample as it is.
        let mut off = StreamLowPass::<2>::new(0.0);
        off.update(0.0, &Vector2::zeros());
        assert_eq!(off.update(0.001, &Vector2::new(3.0, 3.0)), Vector2::new(3.0, 3.0));
        assert_eq!(StreamLowPass::<2>::new(f64::NAN), StreamLowPass::<2>::new(0.0));
    }

    #[test]
    fn the_tracking_filter_follows_a_ramp_without_lag_where_the_low_pass_lags() {
        // 15 Hz samples of a ramp at 10 mm/s, tau 0.2 s.
        let mut track = TrackingFilter::<1>::new(0.2, 0.5);
        let mut lp = StreamLowPass::<1>::new(0.2);
        let (mut y, mut l, mut z) = (0.0, 0.0, 0.0);
        for k in 0..60 {
            let t = k as f64 / 15.0;
            z = 0.01 * t;
            y = track.update(t, &nalgebra::Vector1::new(z)).x;
            l = lp.update(t, &nalgebra::Vector1::new(z)).x;
        }
        assert!((y - z).abs() < 1e-5, "tracked: {} m behind", z - y);
        assert!(
            z - l > 0.8 * 0.01 * 0.2,
            "the low-pass lags by about v tau: {} m",
            z - l
        );
        // A constant acceleration a: an error of about a tau^2, far below the low-pass's.
        let mut track = TrackingFilter::<1>::new(0.2, 0.5);
        let a = 0.01;
        for k in 0..150 {
            let t = k as f64 / 100.0;
            z = 0.5 * a * t * t;
            y = track.update(t, &nalgebra::Vector1::new(z)).x;
        }
        assert!((z - y).abs() < 1.2 * a * 0.04, "{} m", z - y);
    }

    #[test]
    fn the_tracking_filter_keeps_the_predicted_share_of_white_noise() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let noise = Normal::new(0.0, 1.0).unwrap();
        let (dt, tau): (f64, f64) = (0.01, 0.2);
        let theta = (-dt / tau).exp();
        let share = (1.0 - theta) * (1.0 + 4.0 * theta + 5.0 * theta * theta) / (1.0 + theta).powi(3);
        let mut f = TrackingFilter::<1>::new(tau, 0.5);
        let n = 200_000;
        let mut sq = 0.0;
        for k in 0..n {
            let y = f
                .update(k as f64 * dt, &nalgebra::Vector1::new(noise.sample(&mut rng)))
                .x;
            if k >= 1000 {
                sq += y * y;
            }
        }
        let var = sq / (n - 1000) as f64;
        assert!((var / share - 1.0).abs() < 0.05, "variance {var}, predicted {share}");
    }

    #[test]
    fn the_tracking_filter_restarts_on_gaps_steps_back_and_bad_samples() {
        let v = |x: f64| nalgebra::Vector1::new(x);
        let mut f = TrackingFilter::<1>::new(0.2, 0.5);
        assert_eq!(f.update(0.0, &v(1.0)).x, 1.0, "the first sample starts it");
        let y = f.update(0.1, &v(2.0)).x;
        assert!(y > 1.0 && y < 2.0);
        assert_eq!(f.update(0.1, &v(9.0)).x, y, "the same stamp changes nothing");
        assert_eq!(f.update(0.7, &v(5.0)).x, 5.0, "after a gap over 0.5 s: starts again");
        assert_eq!(f.update(0.6, &v(4.0)).x, 4.0, "a stamp back: starts again");
        assert!(f.update(0.7, &v(f64::NAN)).x.is_nan(), "passed through");
        assert_eq!(f.update(0.8, &v(3.0)).x, 3.0, "and restarted");
        let mut off = TrackingFilter::<1>::new(0.0, 0.5);
        off.update(0.0, &v(0.0));
        assert_eq!(off.update(0.01, &v(3.0)).x, 3.0, "tau 0 passes through");
    }
}
