//! [`SimWorld`]: the arm, the trocar, their contact and the sensors, stepped together at the
//! physics rate. A seed fixes everything: the start (scenario) and every noise draw.
//!
//! One physics step of dt: the arm tracks its command over dt; FK and the Jacobian at the
//! link-side joints (motor side plus the joints' elastic deflection) give the tip pose and
//! twist; the trocar (its mount's anchor moving with breathing), the contact, the seal and
//! the joints' deflection are integrated in `substeps` sub-steps, the tip moving linearly
//! over the step and with the deflection (through J); the sub-step mean of the wrench on
//! the arm gives tau_ext = J^T [F; M], read by the torque sensor with the LBR's model
//! error; the pose sensor captures the trocar when due.

use std::sync::Arc;

use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3, Vector6};
use rand_chacha::ChaCha8Rng;

use super::arm::Arm;
use super::contact::{ContactModel, ContactWrench, ShaftMotion};
use super::jam::Jam;
use super::noise::{NoisySensor, PoseSource, SensorInput, TrocarMeasurement};
use super::scenario::Scenario;
use super::seal::Seal;
use super::torque::TorqueSensor;
use super::trocar::{Breathing, Trocar};
use super::{stream, SimError, SimParams};
use crate::kinematics::{Jacobian, JointVector, Kinematics};

/// The random stream of the trocar pose sensor of the world of `seed`: the noise-model
/// sensor draws its calibration bias first from it, then its noise; another pose source
/// that draws its bias first from it by [`super::MeasurementParams::draw_bias`] gets the same
/// bias.
pub fn measurement_stream(seed: u64) -> ChaCha8Rng {
    stream(seed, STREAM_MEASUREMENT)
}

/// Random stream purposes.
const STREAM_SCENARIO: u64 = 1;
const STREAM_MEASUREMENT: u64 = 2;
const STREAM_TORQUE: u64 = 3;
const STREAM_BREATHING: u64 = 4;

/// The simulated world: an LBR with an endoscope and a compliant trocar.
pub struct SimWorld {
    params: SimParams,
    kin: Arc<dyn Kinematics>,
    scenario: Scenario,
    t: f64,
    carry: f64,
    arm: Arm,
    trocar: Trocar,
    breathing: Breathing,
    contact: ContactModel,
    seal: Seal,
    torque: TorqueSensor,
    sensor: Box<dyn PoseSource>,
    rng_torque: ChaCha8Rng,
    tip: Isometry3<f64>,
    jac: Jacobian,
    wrench: ContactWrench,
    tau_meas: JointVector,
    /// A stiff obstacle holding the tip, when one is injected.
    jam: Option<Jam>,
}

impl std::fmt::Debug for SimWorld {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimWorld")
            .field("t", &self.t)
            .field("scenario", &self.scenario)
            .finish()
    }
}

/// `pose` moved by the small joint displacement `dq` through the Jacobian `jac`.
fn moved(pose: &Isometry3<f64>, jac: &Jacobian, dq: &JointVector) -> Isometry3<f64> {
    let d: Vector6<f64> = jac * dq;
    let mut out = *pose;
    out.translation.vector += Vector3::new(d[0], d[1], d[2]);
    out.rotation = UnitQuaternion::from_scaled_axis(Vector3::new(d[3], d[4], d[5])) * out.rotation;
    out
}

impl SimWorld {
    /// A world whose start (arm configuration, trocar rest pose) is drawn from `seed`.
    pub fn new(params: &SimParams, kin: Arc<dyn Kinematics>, seed: u64) -> Result<Self, SimError> {
        params.validate()?;
        let scenario = Scenario::sample(&params.scenario, kin.as_ref(), &mut stream(seed, STREAM_SCENARIO))?;
        Self::with_scenario(params, kin, &scenario, seed)
    }

    /// A world with a given start; `seed` drives the sensor noise and the breathing.
    pub fn with_scenario(
        params: &SimParams,
        kin: Arc<dyn Kinematics>,
        scenario: &Scenario,
        seed: u64,
    ) -> Result<Self, SimError> {
        params.validate()?;
        let mut rng_torque = stream(seed, STREAM_TORQUE);
        let arm = Arm::new(&params.arm, kin.limits(), &scenario.q0())?;
        let (tip, jac) = kin.fk_jacobian(&arm.q_link())?;
        Ok(Self {
            trocar: Trocar::new(&params.trocar, &scenario.trocar_rest)?,
            breathing: Breathing::sample(&params.breathing, &mut stream(seed, STREAM_BREATHING)),
            contact: ContactModel::new(&params.contact, &params.trocar)?,
            seal: Seal::new(&params.seal)?,
            torque: TorqueSensor::new(&params.torque_sensor, &mut rng_torque)?,
            sensor: Box::new(NoisySensor::new(&params.measurement, measurement_stream(seed))?),
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
            tau_meas: JointVector::zeros(),
            jam: None,
        }
        .primed())
    }

    fn primed(mut self) -> Self {
        self.trocar.set_anchor_offset(&self.breathing.offset(0.0));
        self.update_sensor();
        self.tau_meas = self
            .torque
            .measure(&JointVector::zeros(), &self.tip, &self.jac, &mut self.rng_torque);
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
    /// This trial's breathing (frequency, phase, amplitude).
    pub fn breathing(&self) -> &Breathing {
        &self.breathing
    }
    /// The cannula's seal (stick or slip, its force).
    pub fn seal(&self) -> &Seal {
        &self.seal
    }
    /// The torque sensor (its bias and model error).
    pub fn torque_sensor(&self) -> &TorqueSensor {
        &self.torque
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

    /// Catch the tip with a stiff obstacle (`None`: free it); see [`super::jam`].
    pub fn set_jam(&mut self, jam: Option<Jam>) {
        self.jam = jam;
    }

    /// The injected jam, if any.
    pub fn jam(&self) -> Option<&Jam> {
        self.jam.as_ref()
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
        let (tip, jac) = self.kin.fk_jacobian(&self.arm.q_link())?;
        let v_track: Vector6<f64> = jac * self.arm.qd();
        let d0 = *self.arm.deflection();
        let n = self.params.substeps;
        let h = dt / n as f64;
        let mut sum = ContactWrench::default();
        let mut last = ContactWrench::default();
        for i in 0..n {
            let back = dt - (i + 1) as f64 * h;
            let mut at = moved(&tip, &jac, &(self.arm.deflection() - d0));
            at.translation.vector -= Vector3::new(v_track[0], v_track[1], v_track[2]) * back;
            // The deflection moves the tip but is not fed to the contact as a velocity: as a
            // velocity it would meet the friction's steep regularisation in an explicit
            // loop and chatter at the sub-step rate.
            let m = ShaftMotion {
                tip: at,
                v: Vector3::new(v_track[0], v_track[1], v_track[2]),
                w: Vector3::new(v_track[3], v_track[4], v_track[5]),
            };
            last = self.substep(&m, &jac, h, self.t + (i + 1) as f64 * h);
            sum.force += last.force;
            sum.moment += last.moment;
        }
        self.t += dt;
        if !self.trocar.is_finite() {
            return Err(SimError::Diverged {
                t: self.t,
                what: "trocar state",
            });
        }
        let inv = 1.0 / n as f64;
        last.force = sum.force * inv;
        last.moment = sum.moment * inv;
        self.wrench = last;
        self.tip = moved(&tip, &jac, &(self.arm.deflection() - d0));
        self.jac = jac;
        let tau_true = self.tau_of(&last);
        self.tau_meas = self.torque.measure(&tau_true, &self.tip, &jac, &mut self.rng_torque);
        self.update_sensor();
        Ok(())
    }

    /// Advance the pose source to now.
    fn update_sensor(&mut self) {
        let pose = self.trocar.pose();
        let at = SensorInput {
            true_pose: &pose,
            tip: &self.tip,
            q: self.arm.q(),
            q_link: &self.arm.q_link(),
        };
        self.sensor.update(self.t, &at);
    }

    /// Replace the trocar pose source (the noise model of `measurement` by default), from
    /// now on: it is advanced to the current time at once (a capture at t = 0 in a fresh
    /// world).
    pub fn set_pose_source(&mut self, source: Box<dyn PoseSource>) {
        self.sensor = source;
        self.update_sensor();
    }

    /// J^T [F; M] of a wrench on the arm, at the current Jacobian.
    fn tau_of(&self, w: &ContactWrench) -> JointVector {
        let wrench = Vector6::new(w.force.x, w.force.y, w.force.z, w.moment.x, w.moment.y, w.moment.z);
        self.jac.transpose() * wrench
    }

    /// One sub-step of `h` ending at time `t`: breathing, contact, seal, trocar, deflection.
    fn substep(&mut self, m: &ShaftMotion, jac: &Jacobian, h: f64, t: f64) -> ContactWrench {
        self.trocar.set_anchor_offset(&self.breathing.offset(t));
        let mut w = self.contact.evaluate(m, &self.trocar);
        let tip = Point3::from(m.tip.translation.vector);
        if let Some((f, q)) = self.seal.evaluate(m, &self.trocar, h) {
            w.add_point_force(&f, &q, &tip, &self.trocar.pivot());
        }
        // The jam acts on the arm alone: the trocar's own wrench is taken before it.
        self.trocar.step(h, &w.trocar_force, &w.trocar_torque);
        if let Some(jam) = &self.jam {
            jam.add_to(&mut w, &tip, &m.v);
        }
        let wrench = Vector6::new(w.force.x, w.force.y, w.force.z, w.moment.x, w.moment.y, w.moment.z);
        let kq = jac.transpose() * w.stiffness * jac;
        self.arm.relax(&(jac.transpose() * wrench), &kq, h);
        w
    }

    /// Measured joint positions (motor side, as the LBR reports them), rad.
    pub fn joint_positions(&self) -> JointVector {
        *self.arm.q()
    }
    /// Link-side joint positions (with the joints' elastic deflection), rad.
    pub fn joint_positions_link(&self) -> JointVector {
        self.arm.q_link()
    }
    /// External joint torques as the LBR reports them (bias, model error, noise,
    /// dead-band), Nm.
    pub fn external_torques(&self) -> JointVector {
        self.tau_meas
    }
    /// The contact wrench of the last physics step (force on the arm, moment about the tip).
    pub fn contact(&self) -> &ContactWrench {
        &self.wrench
    }
    /// The true tip pose (base frame, link side).
    pub fn tip_pose(&self) -> Isometry3<f64> {
        self.tip
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
        world_with(tip, SimParams::default())
    }

    fn world_with(tip: [f64; 3], mut p: SimParams) -> SimWorld {
        p.measurement.model = super::super::noise::NoiseModel::None;
        p.torque_sensor = super::super::TorqueSensorParams {
            noise_sigma_nm: 0.0,
            bias_nm: 0.0,
            deadband_nm: 0.0,
            ..Default::default()
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
        let dev = w.trocar().deviation().shift_m;
        assert!(dev > 0.003, "the trocar moved {dev}");
        // Withdraw: the trocar returns to its rest pose.
        w.set_command(&JointVector::from_column_slice(&[0.012, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0]))
            .unwrap();
        w.step(3.0).unwrap();
        assert_eq!(w.contact().contacts, 0);
        let deviation = w.trocar().deviation();
        let (dev, tilt) = (deviation.shift_m, deviation.tilt_rad);
        assert!(dev < 1e-4 && tilt < 1e-3, "not back at rest: {dev} m, {tilt} rad");
        assert!(w.trocar().energy() < 1e-6);
    }

    #[test]
    fn elastic_joints_deflect_by_j_kinv_jt_f() {
        // The double's J is the identity on joints 1-3, so J K^-1 J^T f = f / k there.
        let k = 5000.0;
        let mut p = SimParams::default();
        p.arm.joint_stiffness_nm_per_rad = [k; 7];
        // A trocar that does not tilt or slide: the face's normal stays the axis.
        p.trocar.k_tilt_nm_per_rad = 1e4;
        p.trocar.k_lateral_n_per_m = 1e6;
        let mut w = world_with([0.012, 0.0, 0.01], p);
        let q_cmd = JointVector::from_column_slice(&[0.012, 0.0, -0.01, 0.0, 0.0, 0.0, 0.0]);
        w.set_command(&q_cmd).unwrap();
        w.step(3.0).unwrap();
        let f = w.contact().force;
        assert!(f.z > 3.0, "{f:?}");
        let deflection = w.tip_pose().translation.vector - Vector3::new(q_cmd[0], q_cmd[1], q_cmd[2]);
        assert!(
            (deflection - f / k).norm() < 0.02 * f.norm() / k,
            "{deflection:?} vs {:?}",
            f / k
        );
        // The arm reports its motor side: the command, not the deflected link.
        assert!((w.joint_positions() - q_cmd).amax() < 1e-9);
        assert!((w.joint_positions_link() - w.joint_positions()).amax() > 1e-4);
    }

    #[test]
    fn same_seed_same_world() {
        let kin: Arc<dyn Kinematics> = Arc::new(Cartesian::new());
        let mut p = SimParams::default();
        // The Cartesian stand-in has no wrist to keep in range.
        p.scenario.reach_margin_deg = 0.0;
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

    /// A pose source that counts its updates and delivers the true pose at each one.
    struct Counting {
        updates: std::sync::Arc<std::sync::atomic::AtomicUsize>,
        last: Option<TrocarMeasurement>,
    }

    impl PoseSource for Counting {
        fn update(&mut self, t: f64, at: &SensorInput<'_>) {
            self.updates.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            self.last = Some(TrocarMeasurement {
                stamp: t,
                pose: *at.true_pose,
            });
        }

        fn latest(&self, _now: f64) -> Option<TrocarMeasurement> {
            self.last
        }
    }

    #[test]
    fn a_pose_source_set_on_the_world_is_advanced_every_physics_tick_and_read() {
        let mut w = world([0.0, 0.0, 0.05]);
        let updates = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        w.set_pose_source(Box::new(Counting {
            updates: updates.clone(),
            last: None,
        }));
        assert_eq!(
            updates.load(std::sync::atomic::Ordering::Relaxed),
            1,
            "advanced to now at once"
        );
        let n = w.step(0.02).unwrap();
        assert_eq!(updates.load(std::sync::atomic::Ordering::Relaxed), n + 1);
        let m = w.measure_trocar(w.time()).unwrap();
        assert_eq!((m.stamp, m.pose), (w.time(), w.trocar_pose_true()));
    }
}
