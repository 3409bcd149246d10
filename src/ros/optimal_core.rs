//! [`DockingCore`] on the optimal controller ([`crate::control::Controller`]: SQP on
//! Clarabel, admittance, safety guard, supervisor). Only type conversion happens here.

use nalgebra::Point3;

use super::core::{DockingCore, StepInput, StepOutput};
use crate::control::{ControlInput, Controller, Stamped};
use crate::kinematics::Kinematics;

/// The optimal controller behind the node's core interface.
#[derive(Debug)]
pub struct OptimalCore {
    controller: Controller,
}

impl OptimalCore {
    /// Wrap a controller.
    pub fn new(controller: Controller) -> Self {
        Self { controller }
    }
}

fn finite_point(p: &Point3<f64>) -> Option<Point3<f64>> {
    p.iter().all(|x| x.is_finite()).then_some(*p)
}

impl DockingCore for OptimalCore {
    fn start(&mut self) -> Result<(), String> {
        self.controller.start()
    }

    fn abort(&mut self, why: &str) {
        self.controller.abort(why);
    }

    fn reset(&mut self) {
        self.controller.reset();
    }

    fn step(&mut self, kin: &dyn Kinematics, input: &StepInput) -> StepOutput {
        let stamped = |s: &super::core::Stamped<_>| Stamped {
            stamp: s.stamp,
            value: s.value,
        };
        let out = self.controller.step(
            kin,
            &ControlInput {
                now: input.now,
                joints: input.joints.as_ref().map(stamped),
                tau_ext: input.tau_ext.as_ref().map(stamped),
                trocar: input.trocar.as_ref().map(|s| Stamped {
                    stamp: s.stamp,
                    value: s.value,
                }),
            },
        );
        let tip_known = input.joints.is_some() && out.tip.translation.vector.iter().all(|x| x.is_finite());
        StepOutput {
            command: out.command,
            phase: out.phase.as_str(),
            reason: out.reason,
            costs: out.costs,
            iterations: u32::try_from(out.iterations).unwrap_or(u32::MAX),
            solve_time_us: out.solve_time_us,
            solver_status: out.solver_status,
            f_ext: out.f_ext,
            reference: finite_point(&out.reference),
            tip: tip_known.then_some(out.tip),
            goal: finite_point(&out.goal),
            metric_m: out.metric_m,
        }
    }
}
