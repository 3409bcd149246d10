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
        /// FK and Jacobian; lengths must be n, 12 and 6n.
        fn fk_jacobian(self: &KdlChain, q: &[f64], pose: &mut [f64], jac: &mut [f64]);
        /// FK only; lengths must be n and 12.
        fn fk(self: &KdlChain, q: &[f64], pose: &mut [f64]);
    }
}

// SAFETY: KdlChain is immutable after construction: its methods are const and read only
// the per-segment copies it made at construction (it never calls KDL's Joint::pose, whose
// cache is mutable), so it may be moved to and shared between threads.
unsafe impl Send for ffi::KdlChain {}
// SAFETY: see above.
unsafe impl Sync for ffi::KdlChain {}
