//! Robot kinematics: the [`Kinematics`] trait the controller and simulator use (pure Rust,
//! this file), and its implementation on orocos KDL ([`KdlChain`], [`LbrKinematics`]) through
//! the cxx bridge, in `kdl.rs`.
//!
//! Conventions: poses are `nalgebra::Isometry3<f64>` of the tip in the base frame; the
//! geometric Jacobian is 6 x n with rows (vx, vy, vz, wx, wy, wz) in the base frame, its
//! linear part taken at the tip. The chain is built once; FK and Jacobian calls allocate
//! nothing. Every bad input is an `Err`, never a panic.

use nalgebra::{Isometry3, SMatrix, SVector};

mod kdl;
pub mod lbr;

pub use kdl::{fixed_transform, KdlChain, LbrKinematics};
use lbr::LbrModel;

/// Number of joints of an LBR Med arm.
pub const N_JOINTS: usize = 7;
/// A joint-space vector of the arm (positions, velocities, torques), rad or Nm.
pub type JointVector = SVector<f64, N_JOINTS>;
/// The arm's 6 x 7 geometric Jacobian.
pub type Jacobian = SMatrix<f64, 6, N_JOINTS>;

/// The joints of the LBR chain are named this prefix and 1..=7 (`lbr_joint_1`), as the
/// lbr_fri_ros driver names them.
pub const JOINT_NAME_PREFIX: &str = "lbr_joint_";

/// The name of joint `i` (1-based, base to tip): `lbr_joint_{i}`.
pub fn joint_name(i: usize) -> String {
    format!("{JOINT_NAME_PREFIX}{i}")
}

/// The seven joint names in chain order, `lbr_joint_1` .. `lbr_joint_7`.
pub fn joint_names() -> Vec<String> {
    (1..=N_JOINTS).map(joint_name).collect()
}

/// The base link of the LBR chain.
pub const BASE_LINK: &str = "lbr_link_0";
/// The tool tip link: its z axis is the endoscope's optical axis.
pub const TIP_LINK: &str = "endoscope_tip";
/// The flange link (the hand-eye calibration's "hand").
pub const FLANGE_LINK: &str = "lbr_link_ee";

/// Errors of the kinematics layer.
#[derive(Debug, thiserror::Error)]
pub enum KinematicsError {
    /// The URDF could not be read from disk.
    #[error("cannot read URDF {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The cause.
        source: std::io::Error,
    },
    /// The URDF is malformed, or the base/tip links are unknown or not a chain.
    #[error("URDF: {0}")]
    Urdf(String),
    /// The joint vector has the wrong length.
    #[error("wrong joint count: the chain has {expected} joints, got {got}")]
    WrongJointCount {
        /// Joints in the chain.
        expected: usize,
        /// Values given.
        got: usize,
    },
    /// A joint value is NaN or infinite.
    #[error("joint {index} is not finite ({value})")]
    NonFinite {
        /// Index of the joint.
        index: usize,
        /// Its value.
        value: f64,
    },
    /// The C++ side refused a call (it checks every slice length itself).
    #[error("KDL bridge: {0}")]
    Bridge(String),
    /// A tool parameter is invalid.
    #[error(transparent)]
    Model(#[from] lbr::ModelError),
}

/// Joint limits of a 7-joint arm.
#[derive(Debug, Clone, PartialEq)]
pub struct JointLimits {
    /// Lower position limits, rad.
    pub lower: JointVector,
    /// Upper position limits, rad.
    pub upper: JointVector,
    /// Velocity limits, rad/s.
    pub velocity: JointVector,
    /// Torque limits, Nm.
    pub effort: JointVector,
}

impl JointLimits {
    /// The limits of an LBR Med model, from its kinematic facts.
    pub fn of_model(model: LbrModel) -> Self {
        let s = model.spec();
        let pos = JointVector::from_fn(|i, _| s.limit_deg[i].to_radians());
        Self {
            lower: -pos,
            upper: pos,
            velocity: JointVector::from_fn(|i, _| s.velocity_deg[i].to_radians()),
            effort: JointVector::from_fn(|i, _| s.effort[i]),
        }
    }
}

/// Forward kinematics and Jacobian of a 7-joint arm. Implemented on KDL by
/// [`LbrKinematics`]; tests may implement it with a double.
pub trait Kinematics: Send + Sync {
    /// Joint names, base to tip.
    fn joint_names(&self) -> &[String];
    /// Joint limits.
    fn limits(&self) -> &JointLimits;
    /// Pose of the tip in the base frame.
    fn fk(&self, q: &JointVector) -> Result<Isometry3<f64>, KinematicsError>;
    /// Pose of the tip and the geometric Jacobian at `q`.
    fn fk_jacobian(&self, q: &JointVector) -> Result<(Isometry3<f64>, Jacobian), KinematicsError>;
}
