//! [`SimWorld`]: the arm, the trocar, their contact and the sensors, stepped together at the
//! physics rate. A seed fixes everything: the start (scenario) and every noise draw.
//!
//! One physics step of dt: the arm tracks its command over dt; FK and the Jacobian at the
//! new joints give the tip pose and twist (J qd); the trocar and the contact are integrated
//! in `substeps` sub-steps with the tip moving linearly over the step; the sub-step mean of
//! the contact wrench on the arm gives tau_ext = J^T [F; M], read by the torque sensor;
//! the pose sensor captures the trocar when due.

use std::sync::Arc;

use nalgebra::{Isometry3, Point3, Vector3, Vector6};
use rand_chacha::ChaCha8Rng;

use super::arm::Arm;
use super::contact::{ContactModel, ContactWrench, ShaftMotion};
use super::noise::{TrocarMeasurement, TrocarSensor};
use super::scenario::Scenario;
use super::torque::TorqueSensor;
use super::trocar::Trocar;
use super::{stream, SimError, SimParams};
use crate::kinematics::{Jacobian, JointVector, Kinematics};

/// Random stream purposes.
const STREAM_SCENARIO: u64 = 1;
const STREAM_MEASUREMENT: u64 = 2;
const STREAM_TORQUE: u64 = 3;

/// The simulated world: an LBR with an endoscope and a compliant trocar.
pub struct SimWorld {
    params: SimParams,
    kin: Arc<dyn Kinematics>,
    scenario: Scenario,
    t: f64,
    carry: f64,
    arm: Arm,
    trocar: Trocar,
    contact: ContactModel,
    torque: TorqueSensor,
    sensor: TrocarSensor,
    rng_meas: ChaCha8Rng,
    rng_torque: ChaCha8Rng,
    tip: Isometry3<f64>,
    jac: Jacobian,
    wrench: ContactWrench,
    tau_true: JointVector,
    tau_meas: JointVector,
}

impl std::fmt::Debug for SimWorld {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimWorld")
            .field("t", &self.t)
            .field("scenario", &self.scenario)
            .finish()
    }
}

impl SimWorld {
    /// A world whose start (arm configuration, trocar rest pose) is drawn from `seed`.
    pub fn new(params: &SimParams, kin: Arc<dyn Kinematics>, seed: u64) -> Result<Self, SimError> {
        params.validate()?;
        let scenario = Scenario::sample(&params.scenario, kin.as_ref(), &mut stream(seed, STREAM_SCENARIO))?;
        Self::with_scenario(params, kin, &scenario, seed)
    }

    /// A world with a given start; `seed` drives the sensor noise.
    pub fn with_scenario(
        params: &SimParams,
        kin: Arc<dyn Kinematics>,
        scenario: &Scenario,
        seed: u64,
    ) -> Result<Self, SimError> {
        params.validate()?;
        let mut rng_torque = stream(seed, STREAM_TORQUE);
        let mut rng_meas = stream(seed, STREAM_MEASUREMENT);
        let arm = Arm::new(&params.arm, kin.limits(), &scenario.q0())?;
        let (tip, jac) = kin.fk_jacobian(arm.q())?;
        Ok(Self {
            trocar: Trocar::new(&params.trocar, &scenario.trocar_rest)?,
            contact: ContactModel::new(&params.contact, &params.trocar)?,
            torque: TorqueSensor::new(&params.torque_sensor, &mut rng_torque)?,
            sensor: TrocarSensor::new(&params.measurement, &mut rng_meas)?,
            rng_meas,
            rng_torque,
            params: params.clone(),
            kin,
            scenario: scenario.clone(),
            t: 0.0,
            carry: 0.0,
            arm,
            tip,
            jac,
            wrench: ContactWrench::default(),
            tau_true: JointVector::zeros(),
            tau_meas: JointVector::zeros(),
        }
        .primed())
    }

    fn primed(mut self) -> Self {
        let pose = self.trocar.pose();
        self.sensor.update(0.0, &pose, &mut self.rng_meas);
        self
    }

    /// The parameters.
    pub fn params(&self) -> &SimParams {
        &self.params
    }
    /// The kinematics the world uses.
    pub fn kinematics(&self) -> &dyn Kinematics {
        self.kin.as_ref()
    }
    /// The start of this world.
    pub fn scenario(&self) -> &Scenario {
        &self.scenario
    }
    /// Simulated time, s.
    pub fn time(&self) -> f64 {
        self.t
    }

    /// Command joint positions (FRI position mode). Non-finite values are rejected and the
    /// previous command kept.
    pub fn set_command(&mut self, q_cmd: &JointVector) -> Result<(), SimError> {
        self.arm.set_command(q_cmd)
    }

    /// Advance by `dt` seconds in whole physics steps (a remainder carries over to the next
    /// call); returns the number of physics steps taken.
    pub fn step(&mut self, dt: f64) -> Result<usize, SimError> {
        if !dt.is_finite() || !(0.0..=60.0).contains(&dt) {
            return Err(SimError::Input(format!("step duration {dt} s")));
        }
        let period = self.params.dt();
        let total = self.carry + dt;
        let n = (total / period + 1e-9).floor() as usize;
        self.carry = (total - n as f64 * period).max(0.0);
        for _ in 0..n {
            self.step_physics()?;
        }
        Ok(n)
    }

    /// One physics step (1 / physics_rate_hz).
    pub fn step_physics(&mut self) -> Result<(), SimError> {
        let dt = self.params.dt();
        self.arm.step(dt);
        let (tip, jac) = self.kin.fk_jacobian(self.arm.q())?;
        let twist: Vector6<f64> = jac * self.arm.qd();
        let v = Vector3::new(twist[0], twist[1], twist[2]);
        let w = Vector3::new(twist[3], twist[4], twist[5]);
        let n = self.params.substeps;
        let h = dt / n as f64;
        let mut force = Vector3::zeros();
        let mut moment = Vector3::zeros();
        let mut last = ContactWrench::default();
        for i in 0..n {
            let back = dt - (i + 1) as f64 * h;
            let mut at = tip;
            at.translation.vector -= v * back;
            let m = ShaftMotion { tip: at, v, w };
            last = self.contact.evaluate(&m, &self.trocar);
            self.trocar.step(h, &last.trocar_force, &last.trocar_torque);
            force += last.force;
            moment += last.moment;
        }
        self.t += dt;
        if !self.trocar.is_finite() {
            return Err(SimError::Diverged {
                t: self.t,
                what: "trocar state",
            });
        }
        let inv = 1.0 / n as f64;
        last.force = force * inv;
        last.moment = moment * inv;
        self.wrench = last;
        let wrench = Vector6::new(
            last.force.x,
            last.force.y,
            last.force.z,
            last.moment.x,
            last.moment.y,
            last.moment.z,
        );
        self.tau_true = jac.transpose() * wrench;
        self.tau_meas = self.torque.measure(&self.tau_true, &mut self.rng_torque);
        self.tip = tip;
        self.jac = jac;
        let pose = self.trocar.pose();
        self.sensor.update(self.t, &pose, &mut self.rng_meas);
        Ok(())
    }

    /// Measured joint positions, rad.
    pub fn joint_positions(&self) -> JointVector {
        *self.arm.q()
    }
    /// Joint velocities, rad/s.
    pub fn joint_velocities(&self) -> JointVector {
        *self.arm.qd()
    }
    /// The last accepted joint command.
    pub fn commanded_positions(&self) -> JointVector {
        *self.arm.command()
    }
    /// External joint torques as the LBR reports them (bias, noise, dead-band), Nm.
    pub fn external_torques(&self) -> JointVector {
        self.tau_meas
    }
    /// True external joint torques J^T w of the contact, Nm.
    pub fn external_torques_true(&self) -> JointVector {
        self.tau_true
    }
    /// The contact wrench of the last physics step (force on the arm, moment about the tip).
    pub fn contact(&self) -> &ContactWrench {
        &self.wrench
    }
    /// Tip pose (base frame).
    pub fn tip_pose(&self) -> Isometry3<f64> {
        self.tip
    }
    /// Geometric Jacobian at the current joints.
    pub fn jacobian(&self) -> &Jacobian {
        &self.jac
    }
    /// The trocar's true current port pose (base frame, z into the body).
    pub fn trocar_pose_true(&self) -> Isometry3<f64> {
        self.trocar.pose()
    }
    /// The trocar body (state, parameters, energy).
    pub fn trocar(&self) -> &Trocar {
        &self.trocar
    }
    /// The newest noisy trocar pose measurement delivered by `now`.
    pub fn measure_trocar(&self, now: f64) -> Option<TrocarMeasurement> {
        self.sensor.latest(now)
    }
    /// The tip position in the current port frame (z = depth along the axis).
    pub fn tip_in_port(&self) -> Point3<f64> {
        self.trocar
            .pose()
            .inverse_transform_point(&Point3::from(self.tip.translation.vector))
    }
    /// True when the tip is inside the port, within `tolerance` of the point `depth` along
    /// the axis (the paper's success test).
    pub fn docked(&self, depth: f64, tolerance: f64) -> bool {
        let p = self.tip_in_port();
        let radial = (p.x * p.x + p.y * p.y).sqrt();
        (p - Point3::new(0.0, 0.0, depth)).norm() <= tolerance && radial < self.params.trocar.port_radius()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A two-line kinematics double: the tip is a free point moved by q[0..3] (metres),
    /// pointing along -z, so tests control the shaft directly.
    struct Cartesian {
        names: Vec<String>,
        limits: crate::kinematics::JointLimits,
    }

    impl Cartesian {
        fn new() -> Self {
            let lim = crate::kinematics::JointLimits {
                lower: JointVector::repeat(-2.0),
                upper: JointVector::repeat(2.0),
                velocity: JointVector::repeat(1.0),
                effort: JointVector::repeat(100.0),
            };
            Self {
                names: (1..=7).map(|i| format!("j{i}")).collect(),
                limits: lim,
            }
        }
    }

    impl Kinematics for Cartesian {
        fn joint_names(&self) -> &[String] {
            &self.names
        }
        fn limits(&self) -> &crate::kinematics::JointLimits {
            &self.limits
        }
        fn fk(&self, q: &JointVector) -> Result<Isometry3<f64>, crate::kinematics::KinematicsError> {
            Ok(self.fk_jacobian(q)?.0)
        }
        fn fk_jacobian(
            &self,
            q: &JointVector,
        ) -> Result<(Isometry3<f64>, Jacobian), crate::kinematics::KinematicsError> {
            let rot = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
            let pose = Isometry3::from_parts(nalgebra::Translation3::new(q[0], q[1], q[2]), rot);
            let mut j = Jacobian::zeros();
            j[(0, 0)] = 1.0;
            j[(1, 1)] = 1.0;
            j[(2, 2)] = 1.0;
            Ok((pose, j))
        }
    }

    fn world(tip: [f64; 3]) -> SimWorld {
        let mut p = SimParams::default();
        p.measurement.model = super::super::noise::NoiseModel::None;
        p.torque_sensor = super::super::TorqueSensorParams {
            noise_sigma_nm: 0.0,
            bias_nm: 0.0,
            deadband_nm: 0.0,
        };
        let down = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        let scenario = Scenario {
            q0: [tip[0], tip[1], tip[2], 0.0, 0.0, 0.0, 0.0],
            trocar_rest: Isometry3::from_parts(nalgebra::Translation3::new(0.0, 0.0, 0.0), down),
        };
        SimWorld::with_scenario(&p, Arc::new(Cartesian::new()), &scenario, 1).unwrap()
    }

    #[test]
    fn pushing_the_face_deflects_the_trocar_and_it_returns_to_rest() {
        // Tip 12 mm off axis above the face, pushed 20 mm down (into the body).
        let mut w = world([0.012, 0.0, 0.01]);
        w.set_command(&JointVector::from_column_slice(&[
            0.012, 0.0, -0.01, 0.0, 0.0, 0.0, 0.0,
        ]))
        .unwrap();
        w.step(2.0).unwrap();
        let f = w.contact().force;
        assert!(f.z > 3.0, "the face pushes back up: {f:?}");
        // Joint torques are J^T f: here the first three joints read the force.
        let tau = w.external_torques();
        assert!((tau[2] - f.z).abs() < 1e-9);
        let (dev, _) = w.trocar().deviation();
        assert!(dev > 0.003, "the trocar moved {dev}");
        // Withdraw: the trocar returns to its rest pose.
        w.set_command(&JointVector::from_column_slice(&[0.012, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0]))
            .unwrap();
        w.step(3.0).unwrap();
        assert_eq!(w.contact().contacts, 0);
        let (dev, tilt) = w.trocar().deviation();
        assert!(dev < 1e-4 && tilt < 1e-3, "not back at rest: {dev} m, {tilt} rad");
        assert!(w.trocar().energy() < 1e-6);
    }

    #[test]
    fn same_seed_same_world() {
        let kin: Arc<dyn Kinematics> = Arc::new(Cartesian::new());
        let p = SimParams::default();
        let a = SimWorld::new(&p, kin.clone(), 7).unwrap();
        let b = SimWorld::new(&p, kin.clone(), 7).unwrap();
        let c = SimWorld::new(&p, kin, 8).unwrap();
        assert_eq!(a.scenario(), b.scenario());
        assert_ne!(a.scenario(), c.scenario());
        assert_eq!(a.measure_trocar(0.0), b.measure_trocar(0.0));
    }

    #[test]
    fn rejects_bad_durations_and_commands() {
        let mut w = world([0.0, 0.0, 0.05]);
        assert!(w.step(f64::NAN).is_err());
        assert!(w.step(-1.0).is_err());
        assert!(w.set_command(&JointVector::repeat(f64::INFINITY)).is_err());
        assert_eq!(w.step(0.0105).unwrap(), 10);
        assert_eq!(w.step(0.0005).unwrap(), 1);
    }
}
