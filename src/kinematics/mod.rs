//! Robot kinematics: the [`Kinematics`] trait the controller and simulator use, and its
//! implementation on orocos KDL ([`KdlChain`], [`LbrKinematics`]) through the cxx bridge.
//!
//! Conventions: poses are `nalgebra::Isometry3<f64>` of the tip in the base frame; the
//! geometric Jacobian is 6 x n with rows (vx, vy, vz, wx, wy, wz) in the base frame, its
//! linear part taken at the tip. The chain is built once; FK and Jacobian calls allocate
//! nothing. Every bad input is an `Err`, never a panic.

use std::path::Path;
use std::sync::Arc;

use nalgebra::{Isometry3, Matrix3, Rotation3, SMatrix, SVector, Translation3, UnitQuaternion};

use crate::ffi::kdl::ffi as kdl;
pub mod lbr;

use lbr::{LbrModel, ToolParams};

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

/// A KDL chain of any length, built once from a URDF.
#[derive(Clone)]
pub struct KdlChain {
    chain: Arc<cxx::UniquePtr<kdl::KdlChain>>,
    names: Vec<String>,
    lower: Vec<f64>,
    upper: Vec<f64>,
    velocity: Vec<f64>,
    effort: Vec<f64>,
}

impl std::fmt::Debug for KdlChain {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("KdlChain").field("joints", &self.names).finish()
    }
}

/// An error the C++ side raised (its own checks of the slice lengths).
fn bridge_err(e: cxx::Exception) -> KinematicsError {
    KinematicsError::Bridge(e.what().to_string())
}

fn pose_from_raw(p: &[f64; 12]) -> Isometry3<f64> {
    let m = Matrix3::new(p[3], p[4], p[5], p[6], p[7], p[8], p[9], p[10], p[11]);
    let r = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m));
    Isometry3::from_parts(Translation3::new(p[0], p[1], p[2]), r)
}

impl KdlChain {
    /// Build the chain from `base` to `tip` of the URDF in `urdf_xml`.
    pub fn from_urdf_str(urdf_xml: &str, base: &str, tip: &str) -> Result<Self, KinematicsError> {
        let chain =
            kdl::kdl_chain_from_urdf(urdf_xml, base, tip).map_err(|e| KinematicsError::Urdf(e.what().to_string()))?;
        if chain.is_null() {
            return Err(KinematicsError::Urdf("KDL returned no chain".into()));
        }
        let names = chain.joint_names();
        if names.len() != chain.n_joints() {
            return Err(KinematicsError::Urdf(format!(
                "KDL chain has {} joints but {} joint names",
                chain.n_joints(),
                names.len()
            )));
        }
        Ok(Self {
            names,
            lower: chain.lower(),
            upper: chain.upper(),
            velocity: chain.velocity(),
            effort: chain.effort(),
            chain: Arc::new(chain),
        })
    }

    /// Build the chain from a URDF file.
    pub fn from_urdf_file(path: &Path, base: &str, tip: &str) -> Result<Self, KinematicsError> {
        let xml = std::fs::read_to_string(path).map_err(|source| KinematicsError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_urdf_str(&xml, base, tip)
    }

    /// Number of movable joints.
    pub fn n_joints(&self) -> usize {
        self.names.len()
    }
    /// Joint names, base to tip.
    pub fn joint_names(&self) -> &[String] {
        &self.names
    }
    /// Lower position limits, rad (-inf for continuous joints).
    pub fn lower(&self) -> &[f64] {
        &self.lower
    }
    /// Upper position limits, rad (+inf for continuous joints).
    pub fn upper(&self) -> &[f64] {
        &self.upper
    }
    /// Velocity limits, rad/s (+inf where the URDF gives none).
    pub fn velocity(&self) -> &[f64] {
        &self.velocity
    }
    /// Effort limits, Nm (+inf where the URDF gives none).
    pub fn effort(&self) -> &[f64] {
        &self.effort
    }

    fn check(&self, q: &[f64]) -> Result<(), KinematicsError> {
        if q.len() != self.names.len() {
            return Err(KinematicsError::WrongJointCount {
                expected: self.names.len(),
                got: q.len(),
            });
        }
        if let Some((index, &value)) = q.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(KinematicsError::NonFinite { index, value });
        }
        Ok(())
    }

    /// Tip pose for joint positions `q`.
    pub fn fk_slice(&self, q: &[f64]) -> Result<Isometry3<f64>, KinematicsError> {
        self.check(q)?;
        let mut raw = [0.0; 12];
        self.chain.fk(q, &mut raw).map_err(bridge_err)?;
        Ok(pose_from_raw(&raw))
    }

    /// Tip pose and Jacobian; `jac` receives the 6 x n Jacobian column-major and must
    /// hold 6n values.
    pub fn fk_jacobian_slice(&self, q: &[f64], jac: &mut [f64]) -> Result<Isometry3<f64>, KinematicsError> {
        self.check(q)?;
        if jac.len() != 6 * q.len() {
            return Err(KinematicsError::WrongJointCount {
                expected: 6 * q.len(),
                got: jac.len(),
            });
        }
        let mut raw = [0.0; 12];
        self.chain.fk_jacobian(q, &mut raw, jac).map_err(bridge_err)?;
        Ok(pose_from_raw(&raw))
    }
}

/// The 7-joint LBR Med chain from `lbr_link_0` to a tool frame, on KDL.
#[derive(Debug, Clone)]
pub struct LbrKinematics {
    chain: KdlChain,
    limits: JointLimits,
}

impl LbrKinematics {
    /// Wrap a KDL chain, which must have exactly 7 joints with finite limits.
    pub fn from_chain(chain: KdlChain) -> Result<Self, KinematicsError> {
        if chain.n_joints() != N_JOINTS {
            return Err(KinematicsError::WrongJointCount {
                expected: N_JOINTS,
                got: chain.n_joints(),
            });
        }
        let v = |s: &[f64]| JointVector::from_column_slice(s);
        let limits = JointLimits {
            lower: v(chain.lower()),
            upper: v(chain.upper()),
            velocity: v(chain.velocity()),
            effort: v(chain.effort()),
        };
        if !(limits
            .lower
            .iter()
            .chain(limits.upper.iter())
            .chain(limits.velocity.iter())
            .all(|x| x.is_finite()))
        {
            return Err(KinematicsError::Urdf(
                "every arm joint needs finite position and velocity limits".into(),
            ));
        }
        Ok(Self { chain, limits })
    }

    /// The chain `lbr_link_0` -> `tip` of a URDF string.
    pub fn from_urdf_str(urdf_xml: &str, tip: &str) -> Result<Self, KinematicsError> {
        Self::from_chain(KdlChain::from_urdf_str(urdf_xml, BASE_LINK, tip)?)
    }

    /// The chain `lbr_link_0` -> `tip` of a URDF file.
    pub fn from_urdf_file(path: &Path, tip: &str) -> Result<Self, KinematicsError> {
        Self::from_chain(KdlChain::from_urdf_file(path, BASE_LINK, tip)?)
    }

    /// The built-in model with an endoscope, chain to `endoscope_tip`.
    pub fn from_model(model: LbrModel, tool: &ToolParams) -> Result<Self, KinematicsError> {
        Self::from_urdf_str(&lbr::urdf(model, tool)?, TIP_LINK)
    }

    /// The chain `lbr_link_0` -> `tip` of `urdf_file`, or of the built-in `model` (default
    /// endoscope) when `urdf_file` is empty: how the nodes build their chains.
    pub fn from_model_or_file(model: LbrModel, urdf_file: &str, tip: &str) -> Result<Self, KinematicsError> {
        if urdf_file.is_empty() {
            Self::from_urdf_str(&lbr::urdf(model, &ToolParams::default())?, tip)
        } else {
            Self::from_urdf_file(Path::new(urdf_file), tip)
        }
    }

    /// The underlying chain.
    pub fn chain(&self) -> &KdlChain {
        &self.chain
    }
}

impl Kinematics for LbrKinematics {
    fn joint_names(&self) -> &[String] {
        self.chain.joint_names()
    }
    fn limits(&self) -> &JointLimits {
        &self.limits
    }
    fn fk(&self, q: &JointVector) -> Result<Isometry3<f64>, KinematicsError> {
        self.chain.fk_slice(q.as_slice())
    }
    fn fk_jacobian(&self, q: &JointVector) -> Result<(Isometry3<f64>, Jacobian), KinematicsError> {
        let mut jac = Jacobian::zeros();
        let pose = self.chain.fk_jacobian_slice(q.as_slice(), jac.as_mut_slice())?;
        Ok((pose, jac))
    }
}
