//! The [`Kinematics`] implementation on orocos KDL through the cxx bridge: [`KdlChain`] (any
//! chain of a URDF) and [`LbrKinematics`] (an LBR Med with its endoscope). The only file of
//! `kinematics` that reaches C++: the controller and the simulator use the trait alone.

use std::path::Path;
use std::sync::Arc;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};

use super::lbr::{self, LbrModel, ToolParams};
use super::{
    Jacobian, JointLimits, JointVector, Kinematics, KinematicsError, BASE_LINK, FLANGE_LINK, N_JOINTS, TIP_LINK,
};
use crate::ffi::kdl::ffi as kdl;

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

/// The pose of link `frame` in link `of` of the URDF in `urdf_xml`, where the two are joined
/// by fixed joints only (a tool frame and the flange, `lbr_link_7` and `lbr_link_ee`): both
/// chains from `lbr_link_0` (KDL, through kdl_parser's tree) must share their moving joints,
/// so the pose is the same at every joint position. Refused, naming the link: a link the URDF
/// lacks, one a moving joint separates from `of`.
pub fn fixed_transform(urdf_xml: &str, of: &str, frame: &str) -> Result<Isometry3<f64>, KinematicsError> {
    let chain = |link: &str| {
        KdlChain::from_urdf_str(urdf_xml, BASE_LINK, link).map_err(|e| match e {
            KinematicsError::Urdf(m) if m.contains("unknown tip link") => {
                KinematicsError::Urdf(format!("the URDF has no link `{link}`"))
            }
            e => e,
        })
    };
    let (a, b) = (chain(of)?, chain(frame)?);
    if a.joint_names() != b.joint_names() {
        return Err(KinematicsError::Urdf(format!(
            "`{frame}` is not joined to `{of}` by fixed joints (moving joints to `{frame}`: [{}], to `{of}`: [{}])",
            b.joint_names().join(", "),
            a.joint_names().join(", ")
        )));
    }
    let q = vec![0.0; a.n_joints()];
    Ok(a.fk_slice(&q)?.inverse() * b.fk_slice(&q)?)
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

    /// The distance from the flange to the tool's tip (`FLANGE_LINK` to `TIP_LINK`) of
    /// `urdf_file`, or of the built-in `model` when it is empty, m: the endoscope's length.
    pub fn flange_to_tip_m(model: LbrModel, urdf_file: &str) -> Result<f64, KinematicsError> {
        let q = JointVector::zeros();
        let flange = Self::from_model_or_file(model, urdf_file, FLANGE_LINK)?.fk(&q)?;
        let tip = Self::from_model_or_file(model, urdf_file, TIP_LINK)?.fk(&q)?;
        Ok((flange.inverse() * tip).translation.vector.norm())
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
