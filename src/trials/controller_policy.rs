//! The docking controller ([`crate::control::Controller`]) as a trial [`Policy`]: the
//! observation becomes a `ControlInput` (joints and torques stamped now, the trocar pose
//! stamped at capture), its output the commanded joints and the f_ext estimate.

use super::run::{Action, Observation, Policy};
use crate::control::{ControlInput, Controller, ControllerParams, Phase, Stamped};
use crate::kinematics::{JointLimits, Kinematics};

/// The controller driving a simulated trial.
pub struct ControllerPolicy {
    ctrl: Controller,
    torque_filter: f64,
}

impl ControllerPolicy {
    /// A controller with `params` for an arm with `limits`.
    pub fn new(params: &ControllerParams, limits: &JointLimits) -> Result<Self, String> {
        Controller::new(params.clone(), limits.clone())
            .map(|ctrl| Self {
                ctrl,
                torque_filter: params.torque_filter_time_constant,
            })
            .map_err(|e| e.to_string())
    }
}

impl Policy for ControllerPolicy {
    fn torque_filter_time_constant(&self) -> f64 {
        self.torque_filter
    }

    fn start(&mut self, _kin: &dyn Kinematics) {
        self.ctrl.reset();
        // From IDLE, start cannot fail; a failure would show as the phase staying IDLE.
        let _ = self.ctrl.start();
    }

    fn tick(&mut self, kin: &dyn Kinematics, obs: &Observation) -> Action {
        let input = ControlInput {
            scope: None,
            now: obs.t,
            joints: Some(Stamped {
                stamp: obs.t,
                value: obs.q,
            }),
            tau_ext: Some(Stamped {
                stamp: obs.t,
                value: obs.tau_ext,
            }),
            trocar: obs.trocar.map(|m| Stamped {
                stamp: m.stamp,
                value: m.pose,
            }),
        };
        let out = self.ctrl.step(kin, &input);
        Action {
            command: out.command,
            f_ext: Some(out.f_ext),
            phase: out.phase.as_str(),
            hold_code: out.hold.as_ref().map(|h| h.code()),
            aborted: (out.phase == Phase::Aborted).then(|| out.reason_text().unwrap_or_else(|| "aborted".into())),
            latched: self.ctrl.hold_latched(),
        }
    }
}
