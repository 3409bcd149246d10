//! cxx bridge to ViSP and OpenCV aruco (see `cpp/vision_bridge.h`).

/// The raw cxx declarations.
#[cxx::bridge(namespace = "trocar_docking")]
pub mod ffi {
    unsafe extern "C++" {
        include!("trocar_docking/cpp/vision_bridge.h");

        /// The versions of the vision libraries this build links.
        fn vision_backend_versions() -> String;
    }
}
