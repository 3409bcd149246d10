//! Why the controller holds, as a type: each reason has a stable code (what
//! `/docking/status` carries in `hold_code`, what tests and tools match) and a text for the
//! surgeon (`hold_reason`). Texts may be reworded; codes do not change.

use std::fmt;
use std::sync::Arc;

use crate::control::docking::depth::DepthBasis;

/// Why the controller holds (or stopped). Cloning never allocates (texts are shared).
#[derive(Debug, Clone, PartialEq)]
pub enum HoldReason {
    /// No joint state received yet.
    NoJointState,
    /// The joint state is older than the timeout.
    StaleJointState {
        /// Age, s.
        age: f64,
    },
    /// The joint state contains NaN or infinity.
    NonFiniteJointState,
    /// No trocar pose received yet.
    NoTrocarPose,
    /// The trocar pose is older than the timeout (e.g. the marker is lost).
    StaleTrocarPose {
        /// Age, s.
        age: f64,
    },
    /// The trocar pose is not a finite rigid transform.
    BadTrocarPose,
    /// The external torques are older than the timeout (force feedback is blind).
    StaleTorques {
        /// Age, s.
        age: f64,
    },
    /// The tip force exceeded the stop threshold.
    ForceLimit {
        /// Force, N.
        force: f64,
        /// Threshold, N.
        limit: f64,
    },
    /// The optimiser failed; its solution is not used. The text is the solve's status
    /// ([`crate::control::sqp::SqpStatus::as_text`]), static so that the hold allocates nothing.
    SolverFailed(&'static str),
    /// The command was not finite.
    NonFiniteCommand,
    /// The command would leave the joint limits.
    PositionLimit {
        /// Joint index (0-based).
        joint: usize,
    },
    /// The command would move a joint faster than allowed.
    VelocityLimit {
        /// Joint index (0-based).
        joint: usize,
    },
    /// The command would change a joint's speed faster than its acceleration limit allows.
    AccelerationLimit {
        /// Joint index (0-based).
        joint: usize,
    },
    /// The kinematics failed.
    Kinematics(Arc<str>),
    /// The measured joints are too far from the last command (the arm does not follow:
    /// stopped by its own controller, blocked, or commands not reaching it).
    TrackingError {
        /// Joint index (0-based).
        joint: usize,
        /// |q_measured - q_commanded|, rad.
        error: f64,
    },
    /// The tip reached the stand-off point but could not align with the axis in time (a
    /// joint limit in the way); latched.
    AlignmentStall {
        /// Angle between the optical axis and the insertion axis, deg.
        angle_deg: f64,
        /// How long it tried, s.
        after_s: f64,
    },
    /// The operator asked to stop.
    Operator(Arc<str>),
    /// The start was refused: the arm moved while the torques were tared.
    TareMotion {
        /// Largest joint motion in the window, rad.
        moved_rad: f64,
    },
    /// The start was refused: a torque was implausible while taring.
    TareImplausible {
        /// Joint index (0-based).
        joint: usize,
        /// Its mean over the window, Nm.
        offset_nm: f64,
        /// Its standard deviation over the window, Nm.
        sigma_nm: f64,
    },
    /// The command sat on its lead bound (`guard.max_command_lead_rad` ahead of the measured
    /// joints) for `guard.follow_timeout_s` with the arm not moving on that joint: the arm does
    /// not follow (blocked, stopped by its own controller, or the commands do not reach it). Latched; the hold is where the arm
    /// is, so nothing moves when it frees itself, and a new start begins from there.
    ArmNotFollowing {
        /// Joint index (0-based).
        joint: usize,
        /// q_command - q_measured, rad.
        lead: f64,
    },
    /// The clock (ROS time) went back: a bag that loops, a simulator reset. Latched.
    ClockBack {
        /// How far back, s.
        by_s: f64,
    },
    /// The clock jumped forward by more than `guard.max_clock_jump_s` in one step (or the
    /// loop stalled that long). Latched.
    ClockForward {
        /// How far forward, s.
        by_s: f64,
    },
    /// The joint states restarted: their stamps went back, resumed after an interruption,
    /// or the names arrived in another order (a driver restart). Latched.
    DriverRestart {
        /// Change of the joint-state stamp across the restart, s (negative: back).
        stamp_jump_s: f64,
        /// Whether the joint names arrived in another order.
        names_reordered: bool,
    },
    /// At the goal, but the tip's depth is not known within the docking's tolerance
    /// ([`crate::control::docking::depth`]): held there, latched, instead of DONE; `start`
    /// accepts the depth (DONE).
    DepthUncertain {
        /// The depth's uncertainty, m (about 2 sigma).
        uncertainty_m: f64,
        /// The tolerance it passed, m.
        tolerance_m: f64,
        /// What the depth rests on.
        basis: DepthBasis,
    },
}

impl HoldReason {
    /// The stable code of this reason (upper snake case), as `/docking/status` carries it
    /// in `hold_code`.
    pub fn code(&self) -> &'static str {
        match self {
            HoldReason::NoJointState => "NO_JOINT_STATE",
            HoldReason::StaleJointState { .. } => "STALE_JOINT_STATE",
            HoldReason::NonFiniteJointState => "NON_FINITE_JOINT_STATE",
            HoldReason::NoTrocarPose => "NO_TROCAR_POSE",
            HoldReason::StaleTrocarPose { .. } => "STALE_TROCAR_POSE",
            HoldReason::BadTrocarPose => "BAD_TROCAR_POSE",
            HoldReason::StaleTorques { .. } => "STALE_TORQUES",
            HoldReason::ForceLimit { .. } => "FORCE_LIMIT",
            HoldReason::SolverFailed(_) => "SOLVER_FAILED",
            HoldReason::NonFiniteCommand => "NON_FINITE_COMMAND",
            HoldReason::PositionLimit { .. } => "POSITION_LIMIT",
            HoldReason::VelocityLimit { .. } => "VELOCITY_LIMIT",
            HoldReason::AccelerationLimit { .. } => "ACCELERATION_LIMIT",
            HoldReason::Kinematics(_) => "KINEMATICS",
            HoldReason::TrackingError { .. } => "TRACKING_ERROR",
            HoldReason::AlignmentStall { .. } => "ALIGNMENT_STALL",
            HoldReason::Operator(_) => "OPERATOR",
            HoldReason::TareMotion { .. } => "TARE_MOTION",
            HoldReason::TareImplausible { .. } => "TARE_IMPLAUSIBLE",
            HoldReason::ArmNotFollowing { .. } => "ARM_NOT_FOLLOWING",
            HoldReason::ClockBack { .. } => "CLOCK_BACK",
            HoldReason::ClockForward { .. } => "CLOCK_FORWARD",
            HoldReason::DriverRestart { .. } => "DRIVER_RESTART",
            HoldReason::DepthUncertain { .. } => "DEPTH_UNCERTAIN",
        }
    }

    /// Every code, for documentation and tests.
    pub const CODES: [&'static str; 24] = [
        "NO_JOINT_STATE",
        "STALE_JOINT_STATE",
        "NON_FINITE_JOINT_STATE",
        "NO_TROCAR_POSE",
        "STALE_TROCAR_POSE",
        "BAD_TROCAR_POSE",
        "STALE_TORQUES",
        "FORCE_LIMIT",
        "SOLVER_FAILED",
        "NON_FINITE_COMMAND",
        "POSITION_LIMIT",
        "VELOCITY_LIMIT",
        "ACCELERATION_LIMIT",
        "KINEMATICS",
        "TRACKING_ERROR",
        "ALIGNMENT_STALL",
        "OPERATOR",
        "TARE_MOTION",
        "TARE_IMPLAUSIBLE",
        "ARM_NOT_FOLLOWING",
        "CLOCK_BACK",
        "CLOCK_FORWARD",
        "DRIVER_RESTART",
        "DEPTH_UNCERTAIN",
    ];
}

impl fmt::Display for HoldReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            HoldReason::NoJointState => write!(f, "no joint state received"),
            HoldReason::StaleJointState { age } => write!(f, "joint state stale ({age:.3} s old)"),
            HoldReason::NonFiniteJointState => write!(f, "joint state has NaN or infinite values"),
            HoldReason::NoTrocarPose => write!(f, "no trocar pose received"),
            HoldReason::StaleTrocarPose { age } => write!(f, "trocar pose stale ({age:.3} s old): marker lost?"),
            HoldReason::BadTrocarPose => write!(f, "trocar pose is not a finite rigid transform"),
            HoldReason::StaleTorques { age } => write!(f, "external torques stale ({age:.3} s old)"),
            HoldReason::ForceLimit { force, limit } => write!(f, "tip force {force:.1} N over the {limit:.1} N limit"),
            HoldReason::SolverFailed(s) => write!(f, "optimiser failed ({s}); holding"),
            HoldReason::NonFiniteCommand => write!(f, "command has NaN or infinite values"),
            HoldReason::PositionLimit { joint } => {
                write!(f, "command would pass the position limit of joint {}", joint + 1)
            }
            HoldReason::VelocityLimit { joint } => {
                write!(f, "command would exceed the velocity limit of joint {}", joint + 1)
            }
            HoldReason::AccelerationLimit { joint } => {
                write!(f, "command would exceed the acceleration limit of joint {}", joint + 1)
            }
            HoldReason::Kinematics(s) => write!(f, "kinematics: {s}"),
            HoldReason::TrackingError { joint, error } => write!(
                f,
                "joint {} is {error:.3} rad from its command: the arm does not follow",
                joint + 1
            ),
            HoldReason::AlignmentStall { angle_deg, after_s } => write!(
                f,
                "cannot align at the stand-off point: {angle_deg:.1} deg off after {after_s:.1} s (a joint limit in the way? reposition the arm or the trocar)"
            ),
            HoldReason::Operator(s) => write!(f, "operator: {s}"),
            HoldReason::TareMotion { moved_rad } => write!(
                f,
                "start refused: the arm moved {:.2} deg while the torques were tared (keep it still and start again)",
                moved_rad.to_degrees()
            ),
            HoldReason::TareImplausible {
                joint,
                offset_nm,
                sigma_nm,
            } => write!(
                f,
                "start refused: joint {} reads {offset_nm:.1} Nm (spread {sigma_nm:.2} Nm) with the arm still: in contact, or wrong load data?",
                joint + 1
            ),
            HoldReason::ArmNotFollowing { joint, lead } => write!(
                f,
                "the arm does not follow: joint {} stays {:.2} deg behind its command; holding where the arm is (free it, then start again)",
                joint + 1,
                lead.abs().to_degrees()
            ),
            HoldReason::ClockBack { by_s } => write!(
                f,
                "the clock went back by {by_s:.3} s (a looping bag or a simulator reset?); start again"
            ),
            HoldReason::ClockForward { by_s } => write!(
                f,
                "the clock jumped forward by {by_s:.3} s in one step (or the control loop stalled); start again"
            ),
            HoldReason::DriverRestart {
                stamp_jump_s,
                names_reordered,
            } => write!(
                f,
                "the joint states restarted (stamps {stamp_jump_s:+.3} s{}): driver restarted? start again",
                if *names_reordered { ", names in another order" } else { "" }
            ),
            HoldReason::DepthUncertain {
                uncertainty_m,
                tolerance_m,
                basis,
            } => write!(
                f,
                "at the goal, but the tip's depth is known only to +-{:.1} mm (over the {:.1} mm tolerance): {basis}; check the depth in the endoscope's view, then start to accept it (DONE), or abort",
                uncertainty_m * 1e3,
                tolerance_m * 1e3
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all() -> Vec<HoldReason> {
        vec![
            HoldReason::NoJointState,
            HoldReason::StaleJointState { age: 1.0 },
            HoldReason::NonFiniteJointState,
            HoldReason::NoTrocarPose,
            HoldReason::StaleTrocarPose { age: 1.0 },
            HoldReason::BadTrocarPose,
            HoldReason::StaleTorques { age: 1.0 },
            HoldReason::ForceLimit {
                force: 30.0,
                limit: 20.0,
            },
            HoldReason::SolverFailed("x"),
            HoldReason::NonFiniteCommand,
            HoldReason::PositionLimit { joint: 0 },
            HoldReason::VelocityLimit { joint: 0 },
            HoldReason::AccelerationLimit { joint: 0 },
            HoldReason::Kinematics("x".into()),
            HoldReason::TrackingError { joint: 0, error: 0.2 },
            HoldReason::AlignmentStall {
                angle_deg: 3.0,
                after_s: 3.0,
            },
            HoldReason::Operator("x".into()),
            HoldReason::TareMotion { moved_rad: 0.01 },
            HoldReason::TareImplausible {
                joint: 3,
                offset_nm: 7.0,
                sigma_nm: 0.1,
            },
            HoldReason::ArmNotFollowing { joint: 1, lead: 0.035 },
            HoldReason::ClockBack { by_s: 5.0 },
            HoldReason::ClockForward { by_s: 5.0 },
            HoldReason::DriverRestart {
                stamp_jump_s: -3.0,
                names_reordered: true,
            },
            HoldReason::DepthUncertain {
                uncertainty_m: 0.0056,
                tolerance_m: 0.002,
                basis: DepthBasis::Estimate,
            },
        ]
    }

    #[test]
    fn every_reason_has_its_own_listed_code_and_a_text() {
        let reasons = all();
        let codes: Vec<_> = reasons.iter().map(HoldReason::code).collect();
        assert_eq!(codes, HoldReason::CODES.to_vec());
        let mut unique = codes.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len(), codes.len(), "codes are unique");
        assert!(reasons.iter().all(|r| !r.to_string().is_empty()));
    }
}
