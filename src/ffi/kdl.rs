//! cxx bridge to orocos KDL + kdl_parser + urdfdom (see `cpp/kdl_bridge.h`).

/// The raw cxx declarations.
#[cxx::bridge(namespace = "trocar_docking")]
pub mod ffi {
    unsafe extern "C++" {
        include!("trocar_docking/cpp/kdl_bridge.h");

        /// A KDL chain with its joint limits, built once from a URDF.
        type KdlChain;

        /// Parse a URDF and build the chain from `base` to `tip`.
        fn kdl_chain_from_urdf(urdf_xml: &str, base: &str, tip: &str) -> Result<UniquePtr<KdlChain>>;
        /// Number of movable joints.
        fn n_joints(self: &KdlChain) -> usize;
        /// Joint names, base to tip.
        fn joint_names(self: &KdlChain) -> Vec<String>;
        /// Lower position limits, rad.
        fn lower(self: &KdlChain) -> Vec<f64>;
        /// Upper position limits, rad.
        fn upper(self: &KdlChain) -> Vec<f64>;
        /// Velocity limits, rad/s.
        fn velocity(self: &KdlChain) -> Vec<f64>;
        /// Effort limits, Nm.
        fn effort(self: &KdlChain) -> Vec<f64>;
        /// FK and Jacobian; lengths must be n, 12 and 6n (checked on both sides: a wrong
        /// length is an `Err`, never an out-of-bounds access).
        fn fk_jacobian(self: &KdlChain, q: &[f64], pose: &mut [f64], jac: &mut [f64]) -> Result<()>;
        /// FK only; lengths must be n and 12 (checked on both sides).
        fn fk(self: &KdlChain, q: &[f64], pose: &mut [f64]) -> Result<()>;
    }
}

// SAFETY: KdlChain is immutable after construction: its methods are const and read only
// the per-segment copies it made at construction (it never calls KDL's Joint::pose, whose
// cache is mutable), so it may be moved to and shared between threads.
unsafe impl Send for ffi::KdlChain {}
// SAFETY: see above.
unsafe impl Sync for ffi::KdlChain {}

#[cfg(test)]
mod tests {
    use super::ffi;
    use crate::kinematics::lbr::{urdf, LbrModel, ToolParams};
    use crate::kinematics::{BASE_LINK, TIP_LINK};

    fn chain() -> cxx::UniquePtr<ffi::KdlChain> {
        let xml = urdf(LbrModel::Med7, &ToolParams::default()).unwrap();
        ffi::kdl_chain_from_urdf(&xml, BASE_LINK, TIP_LINK).unwrap()
    }

    #[test]
    fn the_cpp_side_rejects_wrong_lengths_itself() {
        // Called past the Rust wrappers' own checks: the C++ checks must hold on their own.
        let c = chain();
        let n = c.n_joints();
        let (q, mut pose, mut jac) = (vec![0.1; n], [0.0; 12], vec![0.0; 6 * n]);
        c.fk(&q, &mut pose).unwrap();
        c.fk_jacobian(&q, &mut pose, &mut jac).unwrap();
        let short_q = vec![0.1; n - 1];
        let long_q = vec![0.1; n + 1];
        for (q, what) in [(&short_q, "joint"), (&long_q, "joint")] {
            let e = c.fk(q, &mut pose).unwrap_err();
            assert!(e.what().contains(what), "{}", e.what());
            assert!(c.fk_jacobian(q, &mut pose, &mut jac).is_err());
        }
        assert!(c.fk(&q, &mut [0.0; 11]).is_err());
        assert!(c.fk_jacobian(&q, &mut [0.0; 11], &mut jac).is_err());
        let e = c.fk_jacobian(&q, &mut pose, &mut vec![0.0; 6 * n - 1]).unwrap_err();
        assert!(e.what().contains("Jacobian"), "{}", e.what());
        assert!(c.fk_jacobian(&q, &mut pose, &mut []).is_err());
    }
}
