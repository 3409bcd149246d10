//! [`DockingCore`] on the simulator's baseline policy (`crate::sim::baseline`): resolved
//! rates to a stand-off on the axis, then straight in; no force feedback. It lets the ROS
//! graph run without the optimal controller (`core: baseline`). The supervision here is the
//! node's minimum: nothing before start, HOLD on a missing or stale input, DONE within the
//! tolerance of the goal, ABORTED above the force limit.

use nalgebra::{Point3, Vector3};

use super::core::{DockingCore, StepInput, StepOutput};
use crate::kinematics::Kinematics;
use crate::sim::baseline::Baseline;
use crate::sim::noise::TrocarMeasurement;
use crate::sim::trial::{Observation, Policy};

/// Settings of the baseline core.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BaselineParams {
    /// Goal depth along the axis, m.
    pub goal_depth_m: f64,
    /// Success tolerance on the tip-to-goal distance, m.
    pub tolerance_m: f64,
    /// Abort above this estimated force, N.
    pub abort_force_n: f64,
    /// Oldest accepted trocar pose, s.
    pub trocar_timeout_s: f64,
    /// Oldest accepted joint state and torques, s.
    pub joints_timeout_s: f64,
}

impl Default for BaselineParams {
    fn default() -> Self {
        Self {
            goal_depth_m: 0.03,
            tolerance_m: 0.005,
            abort_force_n: 60.0,
            trocar_timeout_s: 0.5,
            joints_timeout_s: 0.1,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum State {
    Idle,
    Running,
    Done,
    Aborted,
}

/// The baseline policy with start/abort/reset and input checks.
#[derive(Debug)]
pub struct BaselineCore {
    params: BaselineParams,
    policy: Baseline,
    state: State,
    reason: Option<String>,
    started_at: Option<f64>,
    last_t: Option<f64>,
    force_integral: f64,
}

impl BaselineCore {
    /// A core stepping every `period_s`.
    pub fn new(params: BaselineParams, period_s: f64) -> Self {
        Self {
            policy: Baseline::new(params.goal_depth_m, period_s),
            params,
            state: State::Idle,
            reason: None,
            started_at: None,
            last_t: None,
            force_integral: 0.0,
        }
    }

    fn stale(&self, input: &StepInput) -> Option<String> {
        let age = |s: f64| input.now - s;
        match (&input.joints, &input.tau_ext, &input.trocar) {
            (None, _, _) => Some("no valid joint state".into()),
            (_, None, _) => Some("no valid external torques (LBRState)".into()),
            (_, _, None) => Some("no valid trocar pose".into()),
            (Some(j), _, _) if age(j.stamp) > self.params.joints_timeout_s => {
                Some(format!("joint state stale ({:.3} s old)", age(j.stamp)))
            }
            (_, Some(t), _) if age(t.stamp) > self.params.joints_timeout_s => {
                Some(format!("external torques stale ({:.3} s old)", age(t.stamp)))
            }
            (_, _, Some(p)) if age(p.stamp) > self.params.trocar_timeout_s => {
                Some(format!("trocar pose stale ({:.3} s old)", age(p.stamp)))
            }
            _ => None,
        }
    }
}

impl DockingCore for BaselineCore {
    fn start(&mut self) -> Result<(), String> {
        match self.state {
            State::Aborted => Err(format!(
                "aborted ({}): reset first",
                self.reason.clone().unwrap_or_default()
            )),
            State::Done => Err("already docked: reset first".into()),
            _ => {
                self.state = State::Running;
                self.reason = None;
                self.started_at = None;
                self.last_t = None;
                self.force_integral = 0.0;
                Ok(())
            }
        }
    }

    fn abort(&mut self, why: &str) {
        self.state = State::Aborted;
        self.reason = Some(why.to_string());
    }

    fn reset(&mut self) {
        *self = Self::new(self.params.clone(), self.policy.period_s);
    }

    fn step(&mut self, kin: &dyn Kinematics, input: &StepInput) -> StepOutput {
        let tip = input.joints.as_ref().and_then(|j| kin.fk(&j.value).ok());
        let goal = input.trocar.as_ref().map(|t| {
            Point3::from(t.value.translation.vector) + t.value.rotation * Vector3::z() * self.params.goal_depth_m
        });
        let metric = |s: &Self| match (s.started_at, s.last_t) {
            (Some(t0), Some(t)) if t > t0 => s.force_integral / (t - t0),
            _ => 0.0,
        };
        let base = |s: &Self, phase: &'static str| StepOutput {
            tip,
            goal,
            metric_m: metric(s),
            ..StepOutput::idle(phase, s.reason.clone())
        };
        match self.state {
            State::Idle => return base(self, "IDLE"),
            State::Done => return base(self, "DONE"),
            State::Aborted => return base(self, "ABORTED"),
            State::Running => {}
        }
        if let Some(why) = self.stale(input) {
            self.reason = Some(why);
            return base(self, "HOLD");
        }
        let (Some(j), Some(t), Some(p)) = (&input.joints, &input.tau_ext, &input.trocar) else {
            return base(self, "HOLD");
        };
        if self.started_at.is_none() {
            self.policy.start(kin);
            self.started_at = Some(input.now);
        }
        let obs = Observation {
            t: input.now,
            q: j.value,
            tau_ext: t.value,
            trocar: Some(TrocarMeasurement {
                stamp: p.stamp,
                pose: p.value,
            }),
        };
        let action = self.policy.tick(kin, &obs);
        let f_ext = action.f_ext.unwrap_or_else(Vector3::zeros);
        if let Some(last) = self.last_t {
            if input.now > last {
                self.force_integral += f_ext.norm() * (input.now - last);
            }
        }
        self.last_t = Some(input.now);
        self.reason = action.aborted.clone();
        if f_ext.norm() > self.params.abort_force_n {
            self.abort(&format!(
                "force {:.1} N above {:.1} N",
                f_ext.norm(),
                self.params.abort_force_n
            ));
        } else if let (Some(tip), Some(goal)) = (&tip, &goal) {
            if (Point3::from(tip.translation.vector) - goal).norm() <= self.params.tolerance_m {
                self.state = State::Done;
            }
        }
        let phase = match self.state {
            State::Done => "DONE",
            State::Aborted => "ABORTED",
            _ if action.command.is_none() => "HOLD",
            _ => action.phase,
        };
        StepOutput {
            command: if self.state == State::Running {
                action.command
            } else {
                None
            },
            f_ext,
            solver_status: "baseline".into(),
            ..base(self, phase)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::{JointVector, LbrKinematics};
    use crate::robot_model::{LbrModel, ToolParams};
    use crate::ros::core::Stamped;
    use nalgebra::{Isometry3, Translation3};

    fn setup() -> (LbrKinematics, StepInput) {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        let q = JointVector::from_column_slice(&[0.3, 0.6, -0.2, -1.2, 0.4, 0.8, 0.1]);
        let tip = kin.fk(&q).unwrap();
        let trocar = Isometry3::from_parts(
            Translation3::from(tip.translation.vector + tip.rotation * Vector3::new(0.0, 0.0, 0.05)),
            tip.rotation,
        );
        let input = StepInput {
            now: 10.0,
            joints: Some(Stamped { stamp: 10.0, value: q }),
            tau_ext: Some(Stamped {
                stamp: 10.0,
                value: JointVector::zeros(),
            }),
            trocar: Some(Stamped {
                stamp: 10.0,
                value: trocar,
            }),
        };
        (kin, input)
    }

    #[test]
    fn nothing_moves_before_start_and_stale_inputs_hold() {
        let (kin, mut input) = setup();
        let mut core = BaselineCore::new(BaselineParams::default(), 0.01);
        let out = core.step(&kin, &input);
        assert_eq!(out.phase, "IDLE");
        assert!(out.command.is_none());
        core.start().unwrap();
        let out = core.step(&kin, &input);
        assert_eq!(out.phase, "APPROACH");
        assert!(out.command.is_some());
        input.now = 11.0; // trocar pose 1 s old, joints too
        let out = core.step(&kin, &input);
        assert_eq!(out.phase, "HOLD");
        assert!(out.command.is_none());
        assert!(out.reason.unwrap().contains("stale"));
        input.trocar = None;
        assert!(core.step(&kin, &input).reason.unwrap().contains("no valid trocar pose"));
    }

    #[test]
    fn abort_needs_reset() {
        let (kin, input) = setup();
        let mut core = BaselineCore::new(BaselineParams::default(), 0.01);
        core.start().unwrap();
        core.abort("operator");
        assert_eq!(core.step(&kin, &input).phase, "ABORTED");
        assert!(core.start().is_err());
        core.reset();
        assert_eq!(core.step(&kin, &input).phase, "IDLE");
        core.start().unwrap();
    }
}
