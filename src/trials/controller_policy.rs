//! The docking controller ([`crate::control::Controller`]) as a trial [`Policy`]: the
//! observation becomes a `ControlInput` (joints and torques stamped now, the trocar pose
//! stamped at capture), its output the commanded joints and the f_ext estimate.

use super::closed_loop::{control_input, Observation};
use super::run::{Action, Policy};
use crate::control::{Controller, ControllerParams, Phase};
use crate::kinematics::{JointLimits, Kinematics};

/// The controller driving a simulated trial.
pub struct ControllerPolicy {
    ctrl: Controller,
}

impl ControllerPolicy {
    /// A controller with `params` for an arm with `limits`.
    pub fn new(params: &ControllerParams, limits: &JointLimits) -> Result<Self, String> {
        Controller::new(params.clone(), limits.clone())
            .map(|ctrl| Self { ctrl })
            .map_err(|e| e.to_string())
    }
}

impl Policy for ControllerPolicy {
    fn start(&mut self, _kin: &dyn Kinematics) {
        self.ctrl.reset();
        // From IDLE, start cannot fail; a failure would show as the phase staying IDLE.
        let _ = self.ctrl.start();
    }

    fn tick(&mut self, kin: &dyn Kinematics, obs: &Observation) -> Action {
        let input = control_input(obs, None);
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

    fn period(&self) -> f64 {
        self.ctrl.params().dt_s
    }
}

#[cfg(test)]
mod tests {
    use std::cell::Cell;
    use std::sync::Arc;

    use nalgebra::Isometry3;

    use super::*;
    use crate::control::docking::depth::DepthBasis;
    use crate::kinematics::lbr::{LbrModel, ToolParams};
    use crate::kinematics::{Jacobian, JointVector, KinematicsError, LbrKinematics};
    use crate::sim::SimWorld;
    use crate::test_alloc::allocations_on_this_thread;
    use crate::trials::config::{load_controller, SimConfig};
    use crate::trials::run::{run_trial, Outcome};

    /// The arm's kinematics, with every call after the first of a poisoned step failing:
    /// the step's own measured pose is right, the SQP's iterations get a NaN Jacobian
    /// (odd poisoned steps) or an error (even ones).
    struct Poisoned<'a> {
        inner: &'a dyn Kinematics,
        calls: Cell<usize>,
        poisoned: Cell<Option<bool>>,
    }

    // SAFETY-free: the cells are only touched from the one test thread.
    unsafe impl Sync for Poisoned<'_> {}

    impl Kinematics for Poisoned<'_> {
        fn joint_names(&self) -> &[String] {
            self.inner.joint_names()
        }
        fn limits(&self) -> &crate::kinematics::JointLimits {
            self.inner.limits()
        }
        fn fk(&self, q: &JointVector) -> Result<Isometry3<f64>, KinematicsError> {
            self.inner.fk(q)
        }
        fn fk_jacobian(&self, q: &JointVector) -> Result<(Isometry3<f64>, Jacobian), KinematicsError> {
            let call = self.calls.get();
            self.calls.set(call + 1);
            match self.poisoned.get() {
                Some(nan) if call > 0 => {
                    if nan {
                        let (pose, _) = self.inner.fk_jacobian(q)?;
                        Ok((pose, Jacobian::repeat(f64::NAN)))
                    } else {
                        Err(KinematicsError::NonFinite {
                            index: 0,
                            value: f64::NAN,
                        })
                    }
                }
                _ => self.inner.fk_jacobian(q),
            }
        }
    }

    /// The DONE gate in the realistic world (2 mm / 1 deg hand-eye error): with the cannula's
    /// seal the controller refines the depth there and docks at DONE; with the seal's friction
    /// taken away it cannot know the depth within the 2 mm tolerance, and holds at the goal,
    /// DEPTH_UNCERTAIN, never DONE.
    #[test]
    fn the_seal_makes_the_depth_known_and_without_it_done_is_withheld() {
        let cfg = SimConfig::load_default().unwrap().with_protocol("realistic").unwrap();
        let mut no_seal = cfg.clone();
        no_seal.sim.seal.static_friction_n = 0.0;
        no_seal.sim.seal.kinetic_friction_n = 0.0;
        no_seal.sim.seal.viscous_ns_per_m = 0.0;
        let kin: Arc<dyn Kinematics> =
            Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap());
        let p = crate::trials::policy::controller_params(&load_controller(None).unwrap(), &cfg, true);
        assert_eq!(
            (p.depth.hand_eye_error_m, p.depth.hand_eye_error_deg.round()),
            (0.002, 1.0)
        );
        for seed in [15, 16] {
            for (c, want) in [(&cfg, Outcome::Docked), (&no_seal, Outcome::DepthUncertain)] {
                let mut policy = ControllerPolicy::new(&p, kin.limits()).unwrap();
                let mut world = SimWorld::new(&c.sim, kin.clone(), seed).unwrap();
                let r = run_trial(&mut world, &mut policy, &c.trial, seed);
                let what = format!("seed {seed}: {:?} ({}), {}", r.outcome, r.reason, r.final_hold);
                assert_eq!(r.outcome, want, "{what}");
                let depth = policy.ctrl.depth().unwrap();
                if want == Outcome::Docked {
                    assert!(matches!(depth.basis, DepthBasis::Seal { .. }), "{what}: {depth:?}");
                    assert!(depth.uncertainty <= p.depth.tolerance_m, "{what}: {depth:?}");
                } else {
                    assert_eq!(depth.basis, DepthBasis::Estimate, "{what}");
                    assert!(depth.uncertainty > p.depth.tolerance_m, "{what}: {depth:?}");
                    assert_eq!(r.final_hold, "DEPTH_UNCERTAIN", "{what}");
                }
            }
        }
    }

    /// Steps in which the kinematics may be poisoned (3 s at 100 Hz).
    const POISONED_STEPS: usize = 300;

    /// The controller as a policy, counting the allocations of each `Controller::step`.
    struct Counted {
        inner: ControllerPolicy,
        poison_every: usize,
        steps: usize,
        allocating_steps: usize,
        clarabel_allocations: usize,
        solver_failures: usize,
    }

    impl Policy for Counted {
        fn period(&self) -> f64 {
            self.inner.period()
        }
        fn start(&mut self, kin: &dyn Kinematics) {
            self.inner.start(kin);
        }
        fn tick(&mut self, kin: &dyn Kinematics, obs: &Observation) -> Action {
            self.steps += 1;
            // Poisoned through APPROACH and INSERT (the first 3 s), then clean: DONE needs
            // 0.3 s windows without a hold, which a failure every 70 ms never leaves.
            let poison =
                (self.poison_every > 0 && self.steps <= POISONED_STEPS && self.steps.is_multiple_of(self.poison_every))
                    .then_some(self.steps / self.poison_every % 2 == 1);
            let kin = Poisoned {
                inner: kin,
                calls: Cell::new(0),
                poisoned: Cell::new(poison),
            };
            let input = control_input(obs, None);
            let before = allocations_on_this_thread();
            let out = self.inner.ctrl.step(&kin, &input);
            let allocated = allocations_on_this_thread() > before;
            let failed = out.reason_code() == "SOLVER_FAILED";
            self.solver_failures += usize::from(failed);
            // Clarabel's own timer map grows in a first solve of some of its paths (a
            // successful one): counted apart, and the only allocation allowed.
            let in_clarabel = out
                .solve
                .as_ref()
                .is_some_and(|r| r.clarabel_qps > 0 && r.status.is_usable());
            if allocated && (failed || !in_clarabel) {
                self.allocating_steps += 1;
            }
            self.clarabel_allocations += usize::from(allocated && !failed && in_clarabel);
            Action {
                command: out.command,
                f_ext: Some(out.f_ext),
                phase: out.phase.as_str(),
                hold_code: out.hold.as_ref().map(|h| h.code()),
                aborted: None,
                latched: self.inner.ctrl.hold_latched(),
            }
        }
    }

    /// A whole docking in the simulator (realistic world), with the SQP failing in some
    /// steps: its kinematics poisoned every 7th step (NaN Jacobian: a QP failure; an
    /// error: a kinematics failure). The failures hold for a step and the docking goes on; no step of the
    /// controller allocates, failed ones included, except in a successful Clarabel solve:
    /// Clarabel's timer map grows there (two steps per docking, measured), which is
    /// counted apart and not yet removed.
    #[test]
    fn a_docking_with_solver_failures_allocates_nothing_per_step() {
        let cfg = SimConfig::load_default().unwrap().with_protocol("realistic").unwrap();
        let kin: Arc<dyn Kinematics> =
            Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap());
        let shipped = load_controller(None).unwrap();
        for (params, poison_every) in [(&shipped, 7)] {
            let p = params.clone();
            let mut policy = Counted {
                inner: ControllerPolicy::new(&p, kin.limits()).unwrap(),
                poison_every,
                steps: 0,
                allocating_steps: 0,
                clarabel_allocations: 0,
                solver_failures: 0,
            };
            for seed in [1, 2] {
                policy.steps = 0;
                policy.solver_failures = 0;
                let mut world = SimWorld::new(&cfg.sim, kin.clone(), seed).unwrap();
                let r = run_trial(&mut world, &mut policy, &cfg.trial, seed);
                let what = format!(
                    "seed {seed}, poison every {poison_every}, qp_max_iterations {}: {:?} ({}; in {} {}) after {} \
                     steps, {} solver failures, {} steps allocated ({} in a successful Clarabel solve)",
                    p.sqp.qp_max_iterations,
                    r.outcome,
                    r.reason,
                    r.final_phase,
                    r.final_hold,
                    policy.steps,
                    policy.solver_failures,
                    policy.allocating_steps,
                    policy.clarabel_allocations
                );
                eprintln!("{what}");
                // It goes on to the goal: DONE, or held there on the depth's uncertainty (the
                // depth gate's own business: control::docking::depth).
                assert!(matches!(r.outcome, Outcome::Docked | Outcome::DepthUncertain), "{what}");
                assert!(policy.solver_failures >= 10, "{what}");
                assert_eq!(policy.allocating_steps, 0, "{what}");
            }
        }
    }
}
