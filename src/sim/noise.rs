//! The trocar pose measurement: the true port pose, captured at `rate_hz`, delivered after
//! `latency_s`, with noise:
//! - `uniform` (as the paper's public code): each position axis + U(-a, a) and each
//!   quaternion component + U(-b, b), then the quaternion normalised (a = 5 mm,
//!   b = 0.005: at most about 1 deg, typically 0.5 deg);
//! - `gaussian`: each position axis + N(0, s_p^2); the orientation rotated by
//!   exp(N(0, s_r^2 I3));
//! - `none`: the true pose.
//!
//! On top of the noise, an optional per-trial constant calibration bias E (the hand-eye and
//! marker calibration errors of a real setup): a position offset of length U(0, c) in a
//! random direction and a rotation of U(0, c_r) about a random axis, drawn once per trial.
//! `bias_frame: port` applies it in the port frame (T E: the same offset whatever the arm
//! does); `bias_frame: camera` applies it as a hand-eye error does, in the camera frame C
//! (C E C^-1 T, with C the tip pose moved by `camera_in_tip_m`): the estimator maps the
//! marker through a camera pose that is off by E, so a rotation error of theta moves the
//! estimated port by about theta times the camera-to-port distance, and the error changes
//! as the arm moves.

use std::collections::VecDeque;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use rand::RngExt;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use super::{check_range, SimError};

/// Which noise the measurement carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum NoiseModel {
    /// No noise.
    None,
    /// Uniform, as the paper's public code.
    Uniform,
    /// Gaussian, as the paper's text.
    Gaussian,
}

impl std::fmt::Display for NoiseModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::None => "none",
            Self::Uniform => "uniform",
            Self::Gaussian => "gaussian",
        })
    }
}

/// Where the calibration bias acts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BiasFrame {
    /// In the port frame: a constant offset of the trocar pose.
    Port,
    /// In the camera frame: a hand-eye error, seen through the arm's pose.
    Camera,
}

/// Parameters of the trocar pose measurement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct MeasurementParams {
    /// Noise model.
    pub model: NoiseModel,
    /// Capture rate, Hz.
    pub rate_hz: f64,
    /// Delay from capture to delivery, s.
    pub latency_s: f64,
    /// Uniform: half-range per position axis, m.
    pub uniform_position_m: f64,
    /// Uniform: half-range per quaternion component.
    pub uniform_quaternion: f64,
    /// Gaussian: standard deviation per position axis, m.
    pub gaussian_position_m: f64,
    /// Gaussian: standard deviation of the rotation per axis, rad.
    pub gaussian_rotation_rad: f64,
    /// Calibration bias: largest position offset, m (0: none).
    pub bias_position_m: f64,
    /// Calibration bias: largest rotation, rad (0: none).
    pub bias_rotation_rad: f64,
    /// The frame the calibration bias acts in.
    pub bias_frame: BiasFrame,
    /// With `bias_frame: camera`: the camera's position in the tip frame, m (its axes are
    /// taken as the tip's).
    pub camera_in_tip_m: [f64; 3],
}

crate::shipped_defaults!(MeasurementParams, crate::sim::SHIPPED, ["sim", "measurement"]);

impl MeasurementParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("measurement.rate_hz", self.rate_hz, 0.1, 10_000.0)?;
        check_range("measurement.latency_s", self.latency_s, 0.0, 5.0)?;
        check_range("measurement.uniform_position_m", self.uniform_position_m, 0.0, 0.5)?;
        check_range("measurement.uniform_quaternion", self.uniform_quaternion, 0.0, 0.5)?;
        check_range("measurement.gaussian_position_m", self.gaussian_position_m, 0.0, 0.5)?;
        check_range(
            "measurement.gaussian_rotation_rad",
            self.gaussian_rotation_rad,
            0.0,
            1.0,
        )?;
        check_range("measurement.bias_position_m", self.bias_position_m, 0.0, 0.1)?;
        check_range("measurement.bias_rotation_rad", self.bias_rotation_rad, 0.0, 0.5)?;
        for c in self.camera_in_tip_m {
            check_range("measurement.camera_in_tip_m", c, -2.0, 2.0)?;
        }
        Ok(())
    }

    /// Draw the per-trial calibration bias (identity when both ranges are zero).
    pub fn draw_bias(&self, rng: &mut impl rand::Rng) -> Isometry3<f64> {
        let direction = |rng: &mut dyn rand::Rng| {
            let v = Vector3::new(
                rng.random_range(-1.0..=1.0),
                rng.random_range(-1.0..=1.0),
                rng.random_range(-1.0..=1.0),
            );
            nalgebra::Unit::try_new(v, 1e-9).unwrap_or(Vector3::x_axis())
        };
        let length = |rng: &mut dyn rand::Rng, max: f64| if max > 0.0 { rng.random_range(0.0..=max) } else { 0.0 };
        let t = direction(rng).into_inner() * length(rng, self.bias_position_m);
        let axis = direction(rng);
        let rot = UnitQuaternion::from_axis_angle(&axis, length(rng, self.bias_rotation_rad));
        Isometry3::from_parts(Translation3::from(t), rot)
    }
}

/// One trocar pose measurement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrocarMeasurement {
    /// Capture time, s (simulated clock).
    pub stamp: f64,
    /// Measured port pose in the base frame.
    pub pose: Isometry3<f64>,
}

/// Apply the noise model to `pose`.
pub fn perturb(p: &MeasurementParams, pose: &Isometry3<f64>, rng: &mut impl rand::Rng) -> Isometry3<f64> {
    match p.model {
        NoiseModel::None => *pose,
        NoiseModel::Uniform => {
            let a = p.uniform_position_m;
            let b = p.uniform_quaternion;
            let mut u = |h: f64| if h > 0.0 { rng.random_range(-h..=h) } else { 0.0 };
            let dt = Vector3::new(u(a), u(a), u(a));
            let q = pose.rotation.quaternion();
            let noisy = Quaternion::new(q.w + u(b), q.i + u(b), q.j + u(b), q.k + u(b));
            let rot = UnitQuaternion::try_new(noisy, 1e-9).unwrap_or(pose.rotation);
            Isometry3::from_parts(Translation3::from(pose.translation.vector + dt), rot)
        }
        NoiseModel::Gaussian => {
            let mut g = |s: f64| Normal::new(0.0, s).map_or(0.0, |d| if s > 0.0 { d.sample(rng) } else { 0.0 });
            let dt = Vector3::new(
                g(p.gaussian_position_m),
                g(p.gaussian_position_m),
                g(p.gaussian_position_m),
            );
            let s = p.gaussian_rotation_rad;
            let dr = UnitQuaternion::from_scaled_axis(Vector3::new(g(s), g(s), g(s)));
            Isometry3::from_parts(Translation3::from(pose.translation.vector + dt), dr * pose.rotation)
        }
    }
}

/// What a pose source sees of the world at a physics tick.
#[derive(Debug, Clone, Copy)]
pub struct SensorInput<'a> {
    /// The trocar's true port pose (base frame).
    pub true_pose: &'a Isometry3<f64>,
    /// The true tool tip pose (base frame, link side).
    pub tip: &'a Isometry3<f64>,
    /// The joint positions the arm reports (motor side), rad: what the estimator pairs with
    /// a frame.
    pub q: &'a crate::kinematics::JointVector,
    /// The link-side joint positions (with the joints' elastic deflection), rad: where the
    /// arm, and a camera on it, really is.
    pub q_link: &'a crate::kinematics::JointVector,
}

/// A source of trocar pose measurements, advanced by the world after every physics tick:
/// the noise-model sensor ([`NoisySensor`]) or an implementation outside the simulator (a
/// rendered camera and its estimate). A capture that measures nothing delivers nothing: the
/// newest delivered measurement stays the newest.
pub trait PoseSource: Send {
    /// Advance to time `t` with the world `at`: capture if a capture is due, deliver what is
    /// ready.
    fn update(&mut self, t: f64, at: &SensorInput<'_>);
    /// The newest measurement delivered by time `now`, if any.
    fn latest(&self, now: f64) -> Option<TrocarMeasurement>;
}

/// The timing of a pose sensor: captures on a grid of `1 / rate_hz` from t = 0, each
/// delivered `latency_s` after its capture.
#[derive(Debug, Clone)]
pub struct CaptureSchedule {
    period: f64,
    latency_s: f64,
    next_capture: f64,
    pending: VecDeque<TrocarMeasurement>,
    latest: Option<TrocarMeasurement>,
}

impl CaptureSchedule {
    /// The schedule of `rate_hz` and `latency_s` (checked by [`MeasurementParams::validate`]),
    /// its first capture at t = 0.
    pub fn new(rate_hz: f64, latency_s: f64) -> Self {
        let cap = (latency_s * rate_hz).ceil() as usize + 2;
        Self {
            period: 1.0 / rate_hz,
            latency_s,
            next_capture: 0.0,
            pending: VecDeque::with_capacity(cap),
            latest: None,
        }
    }

    /// Whether a capture is due at `t`; when it is, the grid moves past `t` (skipping the
    /// captures a coarse caller missed).
    pub fn capture_due(&mut self, t: f64) -> bool {
        if t + 1e-9 < self.next_capture {
            return false;
        }
        while self.next_capture <= t + 1e-9 {
            self.next_capture += self.period;
        }
        true
    }

    /// Queue a captured measurement for delivery.
    pub fn push(&mut self, m: TrocarMeasurement) {
        self.pending.push_back(m);
    }

    /// Deliver every queued measurement whose latency has passed by `t`.
    pub fn deliver(&mut self, t: f64) {
        while let Some(m) = self.pending.front() {
            if m.stamp + self.latency_s <= t + 1e-9 {
                self.latest = self.pending.pop_front();
            } else {
                break;
            }
        }
    }

    /// The newest measurement delivered by time `now`, if any.
    pub fn latest(&self, now: f64) -> Option<TrocarMeasurement> {
        self.latest.filter(|m| m.stamp + self.latency_s <= now + 1e-9)
    }
}

/// A pose sensor: captures at its rate, delivers after its latency.
#[derive(Debug, Clone)]
pub struct TrocarSensor {
    params: MeasurementParams,
    bias: Isometry3<f64>,
    schedule: CaptureSchedule,
}

impl TrocarSensor {
    /// A sensor whose first capture is at t = 0, its calibration bias drawn from `rng`.
    pub fn new(params: &MeasurementParams, rng: &mut impl rand::Rng) -> Result<Self, SimError> {
        params.validate()?;
        Ok(Self {
            bias: params.draw_bias(rng),
            params: params.clone(),
            schedule: CaptureSchedule::new(params.rate_hz, params.latency_s),
        })
    }

    /// The calibrated pose the sensor sees of `true_pose` with the tool tip at `tip`.
    fn biased(&self, true_pose: &Isometry3<f64>, tip: &Isometry3<f64>) -> Isometry3<f64> {
        match self.params.bias_frame {
            BiasFrame::Port => true_pose * self.bias,
            BiasFrame::Camera => {
                let [x, y, z] = self.params.camera_in_tip_m;
                let camera = tip * Translation3::new(x, y, z);
                camera * self.bias * camera.inverse() * true_pose
            }
        }
    }

    /// Advance to time `t`: capture `true_pose` if a capture is due (the tool tip at `tip`),
    /// deliver what is ready.
    pub fn update(&mut self, t: f64, true_pose: &Isometry3<f64>, tip: &Isometry3<f64>, rng: &mut impl rand::Rng) {
        if self.schedule.capture_due(t) {
            let pose = perturb(&self.params, &self.biased(true_pose, tip), rng);
            self.schedule.push(TrocarMeasurement { stamp: t, pose });
        }
        self.schedule.deliver(t);
    }

    /// The newest measurement delivered by time `now`, if any.
    pub fn latest(&self, now: f64) -> Option<TrocarMeasurement> {
        self.schedule.latest(now)
    }
}

/// The noise-model sensor as the world's [`PoseSource`]: a [`TrocarSensor`] with its own
/// random stream (its calibration bias drawn first from it).
#[derive(Debug, Clone)]
pub struct NoisySensor {
    sensor: TrocarSensor,
    rng: rand_chacha::ChaCha8Rng,
}

impl NoisySensor {
    /// The sensor of `params`, its bias and noise drawn from `rng`.
    pub fn new(params: &MeasurementParams, mut rng: rand_chacha::ChaCha8Rng) -> Result<Self, SimError> {
        Ok(Self {
            sensor: TrocarSensor::new(params, &mut rng)?,
            rng,
        })
    }
}

impl PoseSource for NoisySensor {
    fn update(&mut self, t: f64, at: &SensorInput<'_>) {
        self.sensor.update(t, at.true_pose, at.tip, &mut self.rng);
    }

    fn latest(&self, now: f64) -> Option<TrocarMeasurement> {
        self.sensor.latest(now)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn pose() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(0.6, 0.0, 0.3),
            UnitQuaternion::from_scaled_axis(Vector3::new(3.0, 0.2, 0.0)),
        )
    }

    #[test]
    fn uniform_noise_is_bounded_like_the_paper_code() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let p = MeasurementParams::default();
        let mut max_dp: f64 = 0.0;
        let mut max_ang: f64 = 0.0;
        for _ in 0..5000 {
            let m = perturb(&p, &pose(), &mut rng);
            let d = m.translation.vector - pose().translation.vector;
            max_dp = max_dp.max(d.amax());
            max_ang = max_ang.max(m.rotation.angle_to(&pose().rotation));
        }
        assert!(max_dp <= 0.005 + 1e-12 && max_dp > 0.0045, "{max_dp}");
        assert!(max_ang < 0.018 && max_ang > 0.008, "{max_ang}");
    }

    #[test]
    fn gaussian_noise_has_its_sigma() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let p = MeasurementParams {
            model: NoiseModel::Gaussian,
            ..Default::default()
        };
        let n = 20_000;
        let sq: f64 = (0..n)
            .map(|_| (perturb(&p, &pose(), &mut rng).translation.x - 0.6).powi(2))
            .sum();
        let sd = (sq / n as f64).sqrt();
        assert!((sd - 0.003).abs() < 0.0001, "{sd}");
    }

    #[test]
    fn calibration_bias_is_constant_and_bounded() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        let p = MeasurementParams {
            model: NoiseModel::None,
            bias_position_m: 0.003,
            bias_rotation_rad: 0.02,
            ..Default::default()
        };
        let mut s = TrocarSensor::new(&p, &mut rng).unwrap();
        s.update(0.0, &pose(), &Isometry3::identity(), &mut rng);
        let a = s.latest(0.0).unwrap().pose;
        s.update(0.5, &pose(), &Isometry3::identity(), &mut rng);
        let b = s.latest(0.5).unwrap().pose;
        assert_eq!(a, b);
        let d = pose().inverse() * a;
        assert!(d.translation.vector.amax() <= 0.003 && d.translation.vector.norm() > 0.0);
        assert!(d.rotation.angle() <= 0.02 + 1e-12);
    }

    #[test]
    fn a_hand_eye_rotation_error_grows_with_the_camera_distance() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let p = MeasurementParams {
            model: NoiseModel::None,
            bias_position_m: 0.0,
            bias_rotation_rad: 0.0175,
            bias_frame: BiasFrame::Camera,
            camera_in_tip_m: [0.0, 0.0, 0.0],
            ..Default::default()
        };
        let s = TrocarSensor::new(&p, &mut rng).unwrap();
        let angle = s.bias.rotation.angle();
        assert!(angle > 0.0);
        // The port 0.1 m and 0.3 m in front of the camera: the error scales with the
        // distance (up to theta d, less the part along the rotation axis).
        let at = |d: f64| {
            let tip = pose() * Translation3::new(0.0, 0.0, -d);
            (s.biased(&pose(), &tip).translation.vector - pose().translation.vector).norm()
        };
        let (near, far) = (at(0.1), at(0.3));
        assert!(
            far <= angle * 0.3 + 1e-12 && (far / near - 3.0).abs() < 1e-6,
            "{near} {far}"
        );
        // In the port frame it does not depend on the arm.
        let q = MeasurementParams {
            bias_frame: BiasFrame::Port,
            ..p
        };
        let s = TrocarSensor::new(&q, &mut rng).unwrap();
        let tip = pose() * Translation3::new(0.0, 0.0, -0.3);
        assert_eq!(s.biased(&pose(), &tip), s.biased(&pose(), &Isometry3::identity()));
    }

    #[test]
    fn rate_and_latency() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let p = MeasurementParams {
            model: NoiseModel::None,
            rate_hz: 50.0,
            latency_s: 0.03,
            bias_position_m: 0.0,
            bias_rotation_rad: 0.0,
            ..Default::default()
        };
        let mut s = TrocarSensor::new(&p, &mut rng).unwrap();
        let mut stamps = vec![];
        for k in 0..=100 {
            let t = k as f64 * 1e-3;
            s.update(t, &pose(), &Isometry3::identity(), &mut rng);
            if let Some(m) = s.latest(t) {
                assert!(t - m.stamp >= 0.03 - 1e-9 && t - m.stamp < 0.03 + 0.02 + 1e-9);
                if stamps.last() != Some(&m.stamp) {
                    stamps.push(m.stamp);
                }
            } else {
                assert!(t < 0.03 - 1e-9);
            }
        }
        assert_eq!(stamps.len(), 4, "{stamps:?}");
        assert_eq!(s.latest(1.0).map(|m| m.pose), Some(pose()));
        assert!((stamps[1] - stamps[0] - 0.02).abs() < 1e-9);
    }
}
