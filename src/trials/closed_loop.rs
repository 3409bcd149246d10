//! The one closed loop every experiment drives (the trials, the pivot benchmark, the soak):
//! a controller at its control rate against a [`SimWorld`] stepped at the physics rate.
//!
//! One control period: [`ClosedLoop::observe`] reads what the controller sees now (the
//! measured joints, the external torques, the newest trocar pose), the experiment steps its
//! controller on it ([`control_input`] turns the observation into the controller's input),
//! and [`ClosedLoop::advance`] sends the command and steps the physics up to the next
//! control tick, keeping the raw external torques of every physics tick on the way: the
//! observation hands all of them to the controller, which low-passes them itself
//! (`torque_filter_time_constant_s`), as the ROS node hands it every FRI cycle's torques.

use std::ops::ControlFlow;

use crate::control::{ControlInput, ScopeCommand, Stamped, TorqueSamples};
use crate::kinematics::JointVector;
use crate::sim::noise::TrocarMeasurement;
use crate::sim::{SimError, SimWorld};

/// What a controller sees at a control tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    /// Simulated time, s.
    pub t: f64,
    /// Measured joint positions, rad.
    pub q: JointVector,
    /// Measured external joint torques, Nm: the newest raw sample.
    pub tau_ext: JointVector,
    /// Every raw torque sample since the last observation (one per physics tick), oldest
    /// first, `tau_ext` the newest.
    pub torque_samples: TorqueSamples,
    /// Newest trocar pose measurement, if any.
    pub trocar: Option<TrocarMeasurement>,
}

/// Why a control period of the plant did not complete.
#[derive(Debug)]
pub enum PlantError {
    /// The world refused the command.
    Command(SimError),
    /// A physics tick failed.
    Physics(SimError),
}

impl PlantError {
    /// The simulator's error, whichever step it came from.
    pub fn into_sim(self) -> SimError {
        match self {
            Self::Command(e) | Self::Physics(e) => e,
        }
    }
}

impl std::fmt::Display for PlantError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Command(e) | Self::Physics(e) => e.fmt(f),
        }
    }
}

/// The plant side of the loop: the physics ticks per control period and the raw torque
/// samples since the last observation, for one run in one world. A control period holds at
/// most [`crate::control::io::TORQUE_SAMPLES`] physics ticks before the oldest samples are
/// dropped (64 at 1 kHz: a control rate of 16 Hz or more).
#[derive(Debug, Clone)]
pub struct ClosedLoop {
    physics_per_tick: usize,
    samples: TorqueSamples,
    tau_ext: JointVector,
}

impl ClosedLoop {
    /// The loop for a controller of control period `period` s in `world` (fresh, or reset
    /// for a new run); the world's torques now are the first sample.
    pub fn new(world: &SimWorld, period: f64) -> Self {
        let tau_ext = world.external_torques();
        let mut samples = TorqueSamples::default();
        samples.push(world.time(), tau_ext);
        Self {
            physics_per_tick: (period * world.params().physics_rate_hz).round().max(1.0) as usize,
            samples,
            tau_ext,
        }
    }

    /// What the controller sees now; the torque samples are handed over (the next
    /// observation carries the ones that come after).
    pub fn observe(&mut self, world: &SimWorld) -> Observation {
        let t = world.time();
        let torque_samples = self.samples;
        self.samples.clear();
        Observation {
            t,
            q: world.joint_positions(),
            tau_ext: self.tau_ext,
            torque_samples,
            trocar: world.measure_trocar(t),
        }
    }

    /// Send `command` (if any), then step the physics to the next control tick, the torques
    /// sampled after each physics tick.
    pub fn advance(&mut self, world: &mut SimWorld, command: Option<&JointVector>) -> Result<(), PlantError> {
        self.advance_until(world, command, |_| ControlFlow::<()>::Continue(()))
            .map(|_| ())
    }

    /// As [`ClosedLoop::advance`]; `after_physics` sees the world after each physics tick
    /// and may end the period early with `Break`, which is returned.
    pub fn advance_until<B>(
        &mut self,
        world: &mut SimWorld,
        command: Option<&JointVector>,
        mut after_physics: impl FnMut(&SimWorld) -> ControlFlow<B>,
    ) -> Result<ControlFlow<B>, PlantError> {
        if let Some(q) = command {
            world.set_command(q).map_err(PlantError::Command)?;
        }
        for _ in 0..self.physics_per_tick {
            world.step_physics().map_err(PlantError::Physics)?;
            self.tau_ext = world.external_torques();
            self.samples.push(world.time(), self.tau_ext);
            if let ControlFlow::Break(b) = after_physics(world) {
                return Ok(ControlFlow::Break(b));
            }
        }
        Ok(ControlFlow::Continue(()))
    }
}

/// The docking controller's input from an observation: joints and the newest torques stamped
/// now with every raw torque sample since the last, the trocar pose stamped at capture, and
/// the surgeon's `scope` command if any.
pub fn control_input(obs: &Observation, scope: Option<Stamped<ScopeCommand>>) -> ControlInput {
    ControlInput {
        scope,
        now: obs.t,
        joints: Some(Stamped {
            stamp: obs.t,
            value: obs.q,
        }),
        tau_ext: Some(Stamped {
            stamp: obs.t,
            value: obs.tau_ext,
        }),
        torque_samples: obs.torque_samples,
        trocar: obs.trocar.map(|m| Stamped {
            stamp: m.stamp,
            value: m.pose,
        }),
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::kinematics::lbr::{LbrModel, ToolParams};
    use crate::kinematics::{Kinematics, LbrKinematics};
    use crate::sim::SimParams;

    fn world() -> SimWorld {
        let kin: Arc<dyn Kinematics> =
            Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap());
        SimWorld::new(&SimParams::default(), kin, 1).unwrap()
    }

    /// One period of a loop run in a fresh world.
    struct Period {
        result: Result<ControlFlow<usize>, PlantError>,
        /// The physics ticks run.
        ticks: usize,
        world: SimWorld,
    }

    /// One period of a loop at `rate_hz` in a fresh world, stopped after `stop_at` physics
    /// ticks (if ever).
    fn period(rate_hz: f64, stop_at: usize) -> Period {
        let mut w = world();
        let mut lp = ClosedLoop::new(&w, 1.0 / rate_hz);
        let mut ticks = 0;
        let r = lp.advance_until(&mut w, None, |_| {
            ticks += 1;
            if ticks == stop_at {
                ControlFlow::Break(ticks)
            } else {
                ControlFlow::Continue(())
            }
        });
        Period {
            result: r,
            ticks,
            world: w,
        }
    }

    #[test]
    fn a_period_steps_the_physics_to_the_next_control_tick() {
        let Period {
            result: r,
            ticks,
            world: w,
        } = period(100.0, usize::MAX);
        assert!(matches!(r, Ok(ControlFlow::Continue(()))));
        assert_eq!(ticks, (w.params().physics_rate_hz / 100.0).round() as usize);
        assert!((w.time() - 0.01).abs() < 1e-9, "{}", w.time());
        let obs = ClosedLoop::new(&w, 0.01).observe(&w);
        assert_eq!(obs.t, w.time());
        assert_eq!(obs.q, w.joint_positions());
    }

    #[test]
    fn an_observation_hands_over_every_physics_ticks_raw_torques_once() {
        let mut w = world();
        let mut lp = ClosedLoop::new(&w, 0.01);
        let first = lp.observe(&w);
        assert_eq!(first.torque_samples.len(), 1, "the torques at the start");
        assert_eq!(first.torque_samples.last(), Some(&(w.time(), first.tau_ext)));
        lp.advance(&mut w, None).unwrap();
        let obs = lp.observe(&w);
        let stamps: Vec<f64> = obs.torque_samples.iter().map(|(t, _)| *t).collect();
        assert_eq!(stamps.len(), lp.physics_per_tick);
        assert!(stamps.windows(2).all(|p| p[1] > p[0]) && stamps[0] > first.t);
        assert_eq!(obs.torque_samples.last(), Some(&(obs.t, w.external_torques())));
        assert_eq!(obs.tau_ext, w.external_torques(), "the newest sample, raw");
        assert!(lp.observe(&w).torque_samples.is_empty(), "handed over once");
    }

    #[test]
    fn a_break_ends_the_period_early() {
        let Period { result: r, ticks, .. } = period(10.0, 3);
        assert!(matches!(r, Ok(ControlFlow::Break(3))));
        assert_eq!(ticks, 3);
    }

    #[test]
    fn a_bad_command_is_the_commands_error() {
        let mut w = world();
        let mut lp = ClosedLoop::new(&w, 0.01);
        let bad = JointVector::from_element(f64::NAN);
        let r = lp.advance(&mut w, Some(&bad));
        assert!(matches!(r, Err(PlantError::Command(_))), "{r:?}");
        assert_eq!(w.time(), 0.0);
    }

    #[test]
    fn the_input_stamps_joints_and_torques_now_and_the_pose_at_capture() {
        let w = world();
        let obs = ClosedLoop::new(&w, 0.01).observe(&w);
        let input = control_input(&obs, None);
        assert_eq!(input.now, obs.t);
        assert_eq!(input.joints.unwrap().value, obs.q);
        assert_eq!(input.tau_ext.unwrap().stamp, obs.t);
        assert_eq!(input.trocar.map(|s| s.stamp), obs.trocar.map(|m| m.stamp));
        assert!(input.scope.is_none());
    }
}
