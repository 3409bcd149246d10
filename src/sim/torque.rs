//! The arm's external joint torque estimate as an LBR reports it: the true external torque
//! J^T w, plus a per-trial bias (model error of the LBR's dynamics model), white Gaussian
//! noise, and a dead-band that zeroes small readings:
//! ```text
//! tau_meas_i = db(tau_i + b_i + n_i),  b_i ~ U(-bias, bias) per trial,  n_i ~ N(0, sigma^2)
//! db(x) = sign(x) max(0, |x| - deadband)
//! ```

use rand::RngExt;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use super::{check_range, SimError};
use crate::kinematics::JointVector;

/// Parameters of the torque sensor model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TorqueSensorParams {
    /// Standard deviation of the white noise per joint, Nm.
    pub noise_sigma_nm: f64,
    /// Half-range of the constant per-trial bias per joint, Nm.
    pub bias_nm: f64,
    /// Dead-band applied to the reading, Nm.
    pub deadband_nm: f64,
}

impl Default for TorqueSensorParams {
    fn default() -> Self {
        Self {
            noise_sigma_nm: 0.1,
            bias_nm: 0.2,
            deadband_nm: 0.3,
        }
    }
}

impl TorqueSensorParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("torque_sensor.noise_sigma_nm", self.noise_sigma_nm, 0.0, 100.0)?;
        check_range("torque_sensor.bias_nm", self.bias_nm, 0.0, 100.0)?;
        check_range("torque_sensor.deadband_nm", self.deadband_nm, 0.0, 100.0)
    }
}

/// Symmetric dead-band: zero inside `[-band, band]`, shifted toward zero outside.
pub use crate::control::admittance::deadband;

/// A torque sensor with its per-trial bias drawn.
#[derive(Debug, Clone)]
pub struct TorqueSensor {
    params: TorqueSensorParams,
    bias: JointVector,
    noise: Option<Normal<f64>>,
}

impl TorqueSensor {
    /// A sensor whose bias is drawn from `rng`.
    pub fn new(params: &TorqueSensorParams, rng: &mut impl rand::Rng) -> Result<Self, SimError> {
        params.validate()?;
        let b = params.bias_nm;
        let bias = JointVector::from_fn(|_, _| if b > 0.0 { rng.random_range(-b..=b) } else { 0.0 });
        let noise = if params.noise_sigma_nm > 0.0 {
            Normal::new(0.0, params.noise_sigma_nm).ok()
        } else {
            None
        };
        Ok(Self {
            params: params.clone(),
            bias,
            noise,
        })
    }

    /// The reading for the true external torque `tau`.
    pub fn measure(&self, tau: &JointVector, rng: &mut impl rand::Rng) -> JointVector {
        JointVector::from_fn(|i, _| {
            let n = self.noise.map_or(0.0, |d| d.sample(rng));
            deadband(tau[i] + self.bias[i] + n, self.params.deadband_nm)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn deadband_shape() {
        assert_eq!(deadband(0.2, 0.3), 0.0);
        assert_eq!(deadband(-0.3, 0.3), 0.0);
        assert!((deadband(1.0, 0.3) - 0.7).abs() < 1e-15);
        assert!((deadband(-2.0, 0.5) + 1.5).abs() < 1e-15);
    }

    #[test]
    fn noise_statistics_and_bias() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let p = TorqueSensorParams {
            noise_sigma_nm: 0.5,
            bias_nm: 0.0,
            deadband_nm: 0.0,
        };
        let s = TorqueSensor::new(&p, &mut rng).unwrap();
        let tau = JointVector::repeat(3.0);
        let n = 20_000;
        let (mut sum, mut sq) = (0.0, 0.0);
        for _ in 0..n {
            let m = s.measure(&tau, &mut rng)[2] - 3.0;
            sum += m;
            sq += m * m;
        }
        let mean = sum / n as f64;
        let sd = (sq / n as f64 - mean * mean).sqrt();
        assert!(mean.abs() < 0.02, "{mean}");
        assert!((sd - 0.5).abs() < 0.02, "{sd}");
        // A biased, noiseless, dead-banded sensor: zero torque reads zero; bias within range.
        let q = TorqueSensorParams {
            noise_sigma_nm: 0.0,
            bias_nm: 0.2,
            deadband_nm: 0.25,
        };
        let s = TorqueSensor::new(&q, &mut rng).unwrap();
        assert_eq!(s.measure(&JointVector::zeros(), &mut rng), JointVector::zeros());
        let m = s.measure(&JointVector::repeat(5.0), &mut rng);
        assert!(m.iter().all(|x| (x - 4.75).abs() <= 0.2 + 1e-12));
    }
}
