//! Taring the external joint torques, as on the robot.
//!
//! The LBR's external-torque estimate carries an offset per joint (model and payload
//! errors, of the order of 1 Nm) that changes with the pose. Without a tare that offset
//! reads as a phantom tip force, which the admittance yields to and which holds the tip
//! off the axis. Two mechanisms handle it:
//!
//! 1. **Tare before motion**, at every start from IDLE (phase TARE): the arm is held still
//!    for [`TareParams::window_s`] while the torques are averaged. The start is refused
//!    (back to IDLE, with the reason) when the arm moves during the window (someone leans
//!    on it, the driver is not holding) or a torque is implausible: a mean offset above
//!    [`TareParams::max_offset_nm`] (the arm is already in contact, or the load data is
//!    wrong) or a spread above [`TareParams::max_noise_nm`]. The window's spread also sets
//!    a per-joint dead-band of [`TareParams::deadband_sigmas`] standard deviations, so that
//!    the sensor's own noise does not read as force.
//! 2. **Tracking while out of contact**: the offset found at the start pose is not the
//!    offset at the insertion pose. While the tip is more than
//!    [`TareParams::track_clearance_m`] before the trocar's face (no part of the scope can
//!    touch it there), the offset follows the measured torques with the time constant
//!    [`TareParams::track_time_constant_s`]; once the tip is within reach of the trocar it
//!    is frozen. The last update happens close to the stand-off point, a few centimetres
//!    from where the insertion ends, so the pose-dependent part left during the insertion
//!    is the change of the error over those centimetres only.
//!
//! Re-taring on resume from a hold is deliberately not done: a hold may happen in contact
//! (a force stop), and taring there would zero a real force.

use serde::{Deserialize, Serialize};

use nalgebra::UnitQuaternion;

use crate::control::force::payload::PayloadFit;
use crate::control::safety::hold::HoldReason;
use crate::kinematics::{Jacobian, JointVector};
use crate::validate;

/// Parameters of the tare (`tare:` in `config/controller.yaml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct TareParams {
    /// Length of the still window at start, s (0 = no tare: offsets taken as zero).
    pub window_s: f64,
    /// Largest joint motion during the window, rad.
    pub max_motion_rad: f64,
    /// Largest plausible mean offset on a joint, Nm.
    pub max_offset_nm: f64,
    /// Largest plausible standard deviation on a joint during the window, Nm.
    pub max_noise_nm: f64,
    /// Per-joint dead-band, in standard deviations of the window.
    pub deadband_sigmas: f64,
    /// Time constant of the offset tracking out of contact, s (0 = no tracking).
    pub track_time_constant_s: f64,
    /// Tracking runs while the tip is at least this far before the trocar face, m.
    pub track_clearance_m: f64,
    /// Prior standard deviation of a payload's mass error, kg, for the fit of the offset's
    /// pose-dependent part from the tracked samples ([`crate::control::force::payload`]; 0 = no fit: the
    /// offset stays what tracking left).
    pub payload_prior_kg: f64,
}

crate::shipped_defaults!(TareParams, crate::config::CONTROLLER, ["tare"]);

impl TareParams {
    /// Check ranges; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        validate::in_range("tare.window_s", self.window_s, 0.0, 10.0)?;
        validate::positive("tare.max_motion_rad", self.max_motion_rad)?;
        validate::positive("tare.max_offset_nm", self.max_offset_nm)?;
        validate::positive("tare.max_noise_nm", self.max_noise_nm)?;
        validate::non_negative("tare.deadband_sigmas", self.deadband_sigmas)?;
        validate::non_negative("tare.track_time_constant_s", self.track_time_constant_s)?;
        validate::non_negative("tare.track_clearance_m", self.track_clearance_m)?;
        validate::non_negative("tare.payload_prior_kg", self.payload_prior_kg)?;
        Ok(())
    }
}

/// What a step of the tare window says.
#[derive(Debug, Clone, PartialEq)]
pub enum TareStep {
    /// Still collecting.
    Collecting,
    /// Done: the offsets are set.
    Done,
    /// Refused, for the reason.
    Refused(HoldReason),
}

/// The tare of one run: the window's sums, then the offset and dead-band.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Tare {
    /// When the window began, s (ROS time): its first step's time less that step's `dt`.
    started: Option<f64>,
    n: f64,
    q0: Option<JointVector>,
    sum: JointVector,
    sum_sq: JointVector,
    offset: JointVector,
    band: JointVector,
    done: bool,
    /// The fit of the offset's pose-dependent part, and its change at this step's pose.
    payload: PayloadFit,
    change: JointVector,
}

impl Tare {
    /// Whether the window is complete and the offsets are set.
    pub fn is_done(&self) -> bool {
        self.done
    }

    /// The current offset, Nm.
    pub fn offset(&self) -> &JointVector {
        &self.offset
    }

    /// The per-joint dead-band, Nm.
    pub fn deadband(&self) -> &JointVector {
        &self.band
    }

    /// Take no tare (offsets zero): torques absent and not required, or `window_s` = 0.
    pub fn skip(&mut self) {
        *self = Self {
            done: true,
            ..Self::default()
        };
    }

    /// Feed one sample of the still window (`q` measured, `tau` finite external torques,
    /// `now` this step's time and `dt` its length, s). The window is `window_s` of the
    /// clock, not a count of steps: a loop that runs late (a loaded host) takes fewer
    /// samples but no longer window.
    pub fn collect(&mut self, p: &TareParams, q: &JointVector, tau: &JointVector, now: f64, dt: f64) -> TareStep {
        let q0 = *self.q0.get_or_insert(*q);
        let moved = (q - q0).amax();
        if moved.is_nan() || moved > p.max_motion_rad {
            return TareStep::Refused(HoldReason::TareMotion { moved_rad: moved });
        }
        self.n += 1.0;
        self.sum += tau;
        self.sum_sq += tau.component_mul(tau);
        let started = *self.started.get_or_insert(now - dt);
        if now - started + 1e-9 < p.window_s {
            return TareStep::Collecting;
        }
        let mean = self.sum / self.n;
        let var = (self.sum_sq / self.n - mean.component_mul(&mean)).map(|v| v.max(0.0));
        let sigma = var.map(f64::sqrt);
        for j in 0..mean.len() {
            if mean[j].abs() > p.max_offset_nm || sigma[j] > p.max_noise_nm {
                return TareStep::Refused(HoldReason::TareImplausible {
                    joint: j,
                    offset_nm: mean[j],
                    sigma_nm: sigma[j],
                });
            }
        }
        self.offset = mean;
        self.band = sigma * p.deadband_sigmas;
        self.done = true;
        TareStep::Done
    }

    /// Follow the offset out of contact: `tip_depth` is the tip's depth along the
    /// insertion axis (negative before the face); `jac`, `rot` the tip's Jacobian and
    /// orientation, for the fit of the offset's pose-dependent part.
    pub fn track(
        &mut self,
        p: &TareParams,
        tau: &JointVector,
        tip_depth: f64,
        pose: (&Jacobian, &UnitQuaternion<f64>),
        dt: f64,
    ) {
        let tc = p.track_time_constant_s;
        if !self.done || tc <= 0.0 || tip_depth.is_nan() || tip_depth >= -p.track_clearance_m || dt <= 0.0 {
            return;
        }
        self.offset += (tau - self.offset) * crate::signal::rc_weight(dt, tc);
        self.payload.add(pose.0, pose.1, tau, dt);
    }

    /// Set this step's pose (the measured tip's Jacobian and orientation): the fitted
    /// payload's change of gravity torque since the last tracked sample joins the offset.
    pub fn at_pose(&mut self, p: &TareParams, jac: &Jacobian, rot: &UnitQuaternion<f64>) {
        self.change = self.payload.change(p.payload_prior_kg, jac, rot);
    }

    /// The offset at this step's pose: the tracked one plus the payload's change, Nm.
    pub fn offset_here(&self) -> JointVector {
        self.offset + self.change
    }

    /// The torques less the offset, without the dead-band: for a consumer that filters
    /// them and bands its own estimate (the fulcrum's, [`crate::control::scope::fulcrum`]).
    pub fn remove_offset(&self, tau: &JointVector) -> JointVector {
        tau - self.offset_here()
    }

    /// The torques less the offset, with the dead-band applied per joint.
    pub fn correct(&self, tau: &JointVector) -> JointVector {
        (tau - self.offset_here()).zip_map(&self.band, crate::control::force::admittance::deadband)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The window is the clock's: a loop running late (steps 25 ms apart, each `dt` capped
    /// at the 10 ms period) ends it after 0.3 s, in 13 steps, not after 30 steps (0.75 s).
    #[test]
    fn the_window_is_clock_time_not_a_count_of_steps() {
        let p = TareParams::default();
        let q = JointVector::repeat(0.3);
        let mut t = Tare::default();
        let mut steps = 0;
        while t.collect(&p, &q, &JointVector::zeros(), 5.0 + f64::from(steps) * 0.025, 0.01) == TareStep::Collecting {
            steps += 1;
            assert!(steps < 100);
        }
        // ends at the first step whose time is 0.3 s past the window's start (5.0 - 0.01)
        assert_eq!(steps, 12, "{steps} steps");
        assert!(t.is_done());
    }

    fn still(tare: &mut Tare, p: &TareParams, tau: impl Fn(usize) -> JointVector, steps: usize) -> TareStep {
        let q = JointVector::repeat(0.3);
        let mut last = TareStep::Collecting;
        for k in 0..steps {
            // one step of 10 ms after the window's samples so far
            let now = tare.n * 0.01;
            last = tare.collect(p, &q, &tau(k), now, 0.01);
            if last != TareStep::Collecting {
                break;
            }
        }
        last
    }

    #[test]
    fn a_still_window_measures_the_offset_and_the_noise() {
        let p = TareParams::default();
        let mut t = Tare::default();
        let offset = JointVector::from_column_slice(&[0.8, -0.6, 0.2, 1.0, -0.3, 0.1, 0.05]);
        // ±0.3 Nm alternating: sigma 0.3.
        let r = still(
            &mut t,
            &p,
            |k| offset.add_scalar(if k % 2 == 0 { 0.3 } else { -0.3 }),
            100,
        );
        assert_eq!(r, TareStep::Done);
        assert!((t.offset() - offset).amax() < 0.02, "{}", t.offset());
        assert!((t.deadband() - JointVector::repeat(0.6)).amax() < 0.05);
        // The offset is gone and the noise is inside the dead-band.
        assert_eq!(t.correct(&(offset.add_scalar(0.3))), JointVector::zeros());
        let push = offset + JointVector::repeat(2.0);
        assert!((t.correct(&push) - JointVector::repeat(2.0 - 0.6)).amax() < 0.05);
    }

    #[test]
    fn the_window_is_at_least_its_length() {
        let p = TareParams::default();
        let mut t = Tare::default();
        assert_eq!(still(&mut t, &p, |_| JointVector::zeros(), 29), TareStep::Collecting);
        assert!(!t.is_done());
        assert_eq!(still(&mut t, &p, |_| JointVector::zeros(), 2), TareStep::Done);
    }

    #[test]
    fn motion_or_implausible_torques_refuse() {
        let p = TareParams::default();
        let mut t = Tare::default();
        t.collect(&p, &JointVector::zeros(), &JointVector::zeros(), 0.0, 0.01);
        let r = t.collect(&p, &JointVector::repeat(0.01), &JointVector::zeros(), 0.01, 0.01);
        assert!(matches!(r, TareStep::Refused(HoldReason::TareMotion { .. })), "{r:?}");
        let mut t = Tare::default();
        let big = JointVector::from_column_slice(&[0.0, 0.0, 0.0, 7.0, 0.0, 0.0, 0.0]);
        let r = still(&mut t, &p, |_| big, 100);
        assert!(
            matches!(r, TareStep::Refused(HoldReason::TareImplausible { joint: 3, .. })),
            "{r:?}"
        );
        let mut t = Tare::default();
        let r = still(
            &mut t,
            &p,
            |k| JointVector::repeat(if k % 2 == 0 { 2.0 } else { -2.0 }),
            100,
        );
        assert!(
            matches!(r, TareStep::Refused(HoldReason::TareImplausible { .. })),
            "{r:?}"
        );
        let mut t = Tare::default();
        let r = t.collect(&p, &JointVector::repeat(f64::NAN), &JointVector::zeros(), 0.0, 0.01);
        assert!(matches!(r, TareStep::Refused(_)), "NaN joints never pass: {r:?}");
    }

    #[test]
    fn tracking_follows_the_offset_only_out_of_contact() {
        let p = TareParams::default();
        let mut t = Tare::default();
        still(&mut t, &p, |_| JointVector::zeros(), 100);
        let drifted = JointVector::repeat(0.5);
        let (jac, rot) = (Jacobian::identity(), UnitQuaternion::identity());
        for _ in 0..300 {
            t.track(&p, &drifted, -0.05, (&jac, &rot), 0.01);
        }
        assert!((t.offset() - drifted).amax() < 1e-3, "out of contact: follows");
        let pushed = JointVector::repeat(3.0);
        for _ in 0..300 {
            t.track(&p, &pushed, -0.005, (&jac, &rot), 0.01);
        }
        assert!(
            (t.offset() - drifted).amax() < 1e-3,
            "within reach of the trocar: frozen"
        );
    }

    /// A payload's gravity torque (the sim's load-data error): tracked over an approach, then
    /// the scope pivots within reach, where tracking is frozen. The fitted change keeps the
    /// corrected torques near zero; without the fit they read the change.
    #[test]
    fn the_payloads_change_of_gravity_is_removed_after_tracking() {
        use crate::kinematics::lbr::{LbrModel, ToolParams};
        use crate::kinematics::{Kinematics, LbrKinematics};
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let q0 = JointVector::from_column_slice(&[0.3, 0.6, -0.2, -1.2, 0.4, 0.8, 0.1]);
        let tau_at = |q: &JointVector| {
            let (tip, jac) = kin.fk_jacobian(q).unwrap();
            let r = nalgebra::Vector3::new(0.0, 0.0, -0.2);
            let tau = crate::control::force::payload::tests::payload_torque(&jac, &tip.rotation, 0.15, &r);
            (tau.add_scalar(0.4), jac, tip.rotation)
        };
        let run = |p: &TareParams| {
            let mut t = Tare::default();
            still(&mut t, p, |_| tau_at(&q0).0, 100);
            for k in 0..300 {
                let s = k as f64 / 300.0;
                let q = q0 + JointVector::from_column_slice(&[0.0, 0.1 * s, 0.0, 0.2 * s, 0.3 * s, -0.3 * s, 0.2 * s]);
                let (tau, jac, rot) = tau_at(&q);
                t.at_pose(p, &jac, &rot);
                t.track(p, &tau, -0.05, (&jac, &rot), 0.01);
            }
            // Pivoted within reach.
            let q = q0 + JointVector::from_column_slice(&[0.0, 0.1, 0.0, 0.2, 0.7, 0.0, 0.2]);
            let (tau, jac, rot) = tau_at(&q);
            t.at_pose(p, &jac, &rot);
            t.remove_offset(&tau).amax()
        };
        let fitted = run(&TareParams::default());
        let frozen = run(&TareParams {
            payload_prior_kg: 0.0,
            ..TareParams::default()
        });
        assert!(frozen > 0.05, "the pivot changes the payload's torque: {frozen}");
        // Measured 0.24 x: the prior (0.5 kg) shrinks what the approach's poses leave open.
        assert!(fitted < 0.35 * frozen, "fitted {fitted} vs frozen {frozen}");
    }
}
