//! The arm's external joint torque estimate as an LBR reports it: the true external torque
//! J^T w, plus the error of the LBR's dynamics model, white Gaussian noise, and a dead-band
//! that zeroes small readings:
//! ```text
//! tau_meas_i = db(tau_i + b_i + g_i(q) + n_i),  n_i ~ N(0, sigma^2)
//! b_i ~ U(-bias, bias)                 per trial: a constant offset per joint
//! g(q) = J_c(q)^T (dm g0)              per trial dm ~ U(-m, m): an unmodelled payload
//! db(x) = sign(x) max(0, |x| - deadband)
//! ```
//! g(q) is the gravity torque of a payload mass error dm (wrong load data) at the point
//! c of the tool (tip frame, `payload_com_m` plus U(-s, s) per axis), g0 = (0, 0, -9.81):
//! J_c = J_v - [c - tip]x J_w, so it changes with the configuration as a real load error does.

use nalgebra::{Isometry3, Point3, Vector3, Vector6};
use rand::RngExt;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use super::{check_range, SimError};
use crate::kinematics::{Jacobian, JointVector};

/// Gravity, base frame (z up), m/s^2.
const GRAVITY: Vector3<f64> = Vector3::new(0.0, 0.0, -9.81);

/// Parameters of the torque sensor model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct TorqueSensorParams {
    /// Standard deviation of the white noise per joint, Nm.
    pub noise_sigma_nm: f64,
    /// Half-range of the constant per-trial bias per joint, Nm.
    pub bias_nm: f64,
    /// Dead-band applied to the reading, Nm.
    pub deadband_nm: f64,
    /// Half-range of the per-trial payload mass error, kg (0 = none).
    pub payload_mass_error_kg: f64,
    /// Nominal point of the payload error in the tip frame, m (z: along the optical axis).
    pub payload_com_m: [f64; 3],
    /// Half-range of the per-trial spread of that point, per axis, m.
    pub payload_com_spread_m: f64,
}

crate::shipped_defaults!(TorqueSensorParams, crate::sim::SHIPPED, ["sim", "torque_sensor"]);

impl TorqueSensorParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("torque_sensor.noise_sigma_nm", self.noise_sigma_nm, 0.0, 100.0)?;
        check_range("torque_sensor.bias_nm", self.bias_nm, 0.0, 100.0)?;
        check_range("torque_sensor.deadband_nm", self.deadband_nm, 0.0, 100.0)?;
        check_range(
            "torque_sensor.payload_mass_error_kg",
            self.payload_mass_error_kg,
            0.0,
            10.0,
        )?;
        for c in self.payload_com_m {
            check_range("torque_sensor.payload_com_m", c, -2.0, 2.0)?;
        }
        check_range(
            "torque_sensor.payload_com_spread_m",
            self.payload_com_spread_m,
            0.0,
            1.0,
        )
    }
}

/// Symmetric dead-band: zero inside `[-band, band]`, shifted toward zero outside.
pub use crate::signal::deadband;

/// A torque sensor with its per-trial bias drawn.
#[derive(Debug, Clone)]
pub struct TorqueSensor {
    params: TorqueSensorParams,
    bias: JointVector,
    noise: Option<Normal<f64>>,
    payload_mass: f64,
    payload_com: Point3<f64>,
}

impl TorqueSensor {
    /// A sensor whose bias is drawn from `rng`.
    pub fn new(params: &TorqueSensorParams, rng: &mut impl rand::Rng) -> Result<Self, SimError> {
        params.validate()?;
        let mut u = |h: f64| if h > 0.0 { rng.random_range(-h..=h) } else { 0.0 };
        let bias = JointVector::from_fn(|_, _| u(params.bias_nm));
        let payload_mass = u(params.payload_mass_error_kg);
        let s = params.payload_com_spread_m;
        let [cx, cy, cz] = params.payload_com_m;
        let payload_com = Point3::new(cx + u(s), cy + u(s), cz + u(s));
        let noise = if params.noise_sigma_nm > 0.0 {
            Normal::new(0.0, params.noise_sigma_nm).ok()
        } else {
            None
        };
        Ok(Self {
            params: params.clone(),
            bias,
            noise,
            payload_mass,
            payload_com,
        })
    }

    /// The pose-dependent model error g(q) at the tip pose `tip` with Jacobian `jac`, Nm.
    pub fn model_error(&self, tip: &Isometry3<f64>, jac: &Jacobian) -> JointVector {
        if self.payload_mass == 0.0 {
            return JointVector::zeros();
        }
        let f = GRAVITY * self.payload_mass;
        let lever = tip.rotation * self.payload_com.coords;
        let m = lever.cross(&f);
        jac.transpose() * Vector6::new(f.x, f.y, f.z, m.x, m.y, m.z)
    }

    /// The constant per-joint offset of this trial, Nm.
    pub fn bias(&self) -> &JointVector {
        &self.bias
    }

    /// The reading for the true external torque `tau` at the tip pose `tip` (Jacobian `jac`).
    pub fn measure(
        &self,
        tau: &JointVector,
        tip: &Isometry3<f64>,
        jac: &Jacobian,
        rng: &mut impl rand::Rng,
    ) -> JointVector {
        let g = self.model_error(tip, jac);
        JointVector::from_fn(|i, _| {
            let n = self.noise.map_or(0.0, |d| d.sample(rng));
            deadband(tau[i] + self.bias[i] + g[i] + n, self.params.deadband_nm)
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

    fn at_rest() -> (Isometry3<f64>, Jacobian) {
        (Isometry3::identity(), Jacobian::zeros())
    }

    #[test]
    fn payload_error_depends_on_the_pose() {
        use crate::kinematics::lbr::{LbrModel, ToolParams};
        use crate::kinematics::{Kinematics, LbrKinematics};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let p = TorqueSensorParams {
            noise_sigma_nm: 0.0,
            bias_nm: 0.0,
            deadband_nm: 0.0,
            payload_mass_error_kg: 0.2,
            payload_com_spread_m: 0.02,
            ..Default::default()
        };
        let s = TorqueSensor::new(&p, &mut rng).unwrap();
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let q1 = JointVector::from_column_slice(&[0.0, 0.45, 0.0, -1.15, 0.0, 1.54, 0.0]);
        let q2 = JointVector::from_column_slice(&[0.3, 0.75, -0.2, -1.0, 0.2, 1.2, 0.4]);
        let (t1, j1) = kin.fk_jacobian(&q1).unwrap();
        let (t2, j2) = kin.fk_jacobian(&q2).unwrap();
        let (g1, g2) = (s.model_error(&t1, &j1), s.model_error(&t2, &j2));
        // A few tenths of Nm to about 1 Nm on the shoulder; it changes with q, so a tare
        // taken at one pose leaves an error at another.
        assert!(g1.amax() > 0.05 && g1.amax() < 2.0, "{g1}");
        assert!((g1 - g2).amax() > 0.05, "{g1} vs {g2}");
        // Joint 1 turns about gravity: no gravity torque on it.
        assert!(g1[0].abs() < 1e-9 && g2[0].abs() < 1e-9);
        let m = s.measure(&JointVector::zeros(), &t2, &j2, &mut rng);
        assert!((m - g2).amax() < 1e-12);
    }

    #[test]
    fn noise_statistics_and_bias() {
        let (tip, jac) = at_rest();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let p = TorqueSensorParams {
            noise_sigma_nm: 0.5,
            bias_nm: 0.0,
            deadband_nm: 0.0,
            ..Default::default()
        };
        let s = TorqueSensor::new(&p, &mut rng).unwrap();
        let tau = JointVector::repeat(3.0);
        let n = 20_000;
        let (mut sum, mut sq) = (0.0, 0.0);
        for _ in 0..n {
            let m = s.measure(&tau, &tip, &jac, &mut rng)[2] - 3.0;
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
            ..Default::default()
        };
        let s = TorqueSensor::new(&q, &mut rng).unwrap();
        assert_eq!(
            s.measure(&JointVector::zeros(), &tip, &jac, &mut rng),
            JointVector::zeros()
        );
        let m = s.measure(&JointVector::repeat(5.0), &tip, &jac, &mut rng);
        assert!(m.iter().all(|x| (x - 4.75).abs() <= 0.2 + 1e-12));
    }
}
