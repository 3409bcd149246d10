//! Builds the C++ side of the cxx bridges (KDL kinematics, ViSP/OpenCV vision) and links
//! Debian's libraries. Missing libraries: run `scripts/install-deps`.
//!
//! It also lays out the ROS message tree rosrust reads (see `ros_message_path`).

use std::process::Command;

/// Flags from `pkg-config` for `lib`, or a clear failure telling how to install it.
fn pkg_config(lib: &str) -> (Vec<String>, Vec<String>, Vec<String>) {
    let out = Command::new("pkg-config").args(["--cflags", "--libs", lib]).output();
    let out = match out {
        Ok(o) if o.status.success() => String::from_utf8_lossy(&o.stdout).into_owned(),
        _ => panic!("pkg-config cannot find `{lib}`: run scripts/install-deps (Debian packages) first"),
    };
    let (mut inc, mut dirs, mut libs) = (vec![], vec![], vec![]);
    for tok in out.split_whitespace() {
        if let Some(p) = tok.strip_prefix("-I") {
            inc.push(p.to_string());
        } else if let Some(p) = tok.strip_prefix("-L") {
            dirs.push(p.to_string());
        } else if let Some(l) = tok.strip_prefix("-l") {
            libs.push(l.to_string());
        }
    }
    (inc, dirs, libs)
}

/// ROS message packages (Debian, under /usr/share) the nodes use.
const ROS_MSG_PACKAGES: [&str; 11] = [
    "std_msgs",
    "std_srvs",
    "geometry_msgs",
    "sensor_msgs",
    "trajectory_msgs",
    "visualization_msgs",
    "tf2_msgs",
    "rosgraph_msgs",
    "actionlib_msgs",
    "diagnostic_msgs",
    "dynamic_reconfigure",
];

/// rosrust's `rosmsg_include!` names a package after the folder holding its `msg/`, and the
/// checkout folder may be called anything. So copy our messages into
/// `$OUT_DIR/ros_msgs/<package>/msg/` (trocar_docking from `msg/`, the vendored driver
/// message from `vendor/lbr_msgs/msg/`), and hand the proc macro that tree plus the Debian
/// message folders through `ROSRUST_MSG_PATH` (set for this crate's compilation only).
fn ros_message_path() {
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    let tree = out.join("ros_msgs");
    for (pkg, src) in [("trocar_docking", "msg"), ("lbr_msgs", "vendor/lbr_msgs/msg")] {
        println!("cargo:rerun-if-changed={src}");
        let dst = tree.join(pkg).join("msg");
        let _ = std::fs::remove_dir_all(&dst);
        std::fs::create_dir_all(&dst).unwrap_or_else(|e| panic!("cannot create {}: {e}", dst.display()));
        let entries = std::fs::read_dir(src).unwrap_or_else(|e| panic!("cannot read {src}: {e}"));
        for entry in entries.flatten() {
            let path = entry.path();
            if path.extension().is_some_and(|x| x == "msg") {
                println!("cargo:rerun-if-changed={}", path.display());
                let target = dst.join(entry.file_name());
                std::fs::copy(&path, &target).unwrap_or_else(|e| panic!("cannot copy {}: {e}", path.display()));
            }
        }
    }
    let mut dirs = vec![tree.display().to_string()];
    for pkg in ROS_MSG_PACKAGES {
        let d = format!("/usr/share/{pkg}");
        if !std::path::Path::new(&d).join("msg").is_dir() && !std::path::Path::new(&d).join("srv").is_dir() {
            panic!("{d} has no messages: run scripts/install-deps (ros-*-msgs Debian packages)");
        }
        dirs.push(d);
    }
    println!("cargo:rustc-env=ROSRUST_MSG_PATH={}", dirs.join(":"));
}

fn main() {
    ros_message_path();
    let bridges = ["src/ffi/kdl.rs", "src/ffi/vision.rs", "src/ffi/markerless.rs"];
    let sources = [
        "cpp/kdl_bridge.cpp",
        "cpp/vision_bridge.cpp",
        "cpp/markerless_bridge.cpp",
    ];
    for f in bridges.iter().chain(sources.iter()) {
        println!("cargo:rerun-if-changed={f}");
    }
    println!("cargo:rerun-if-changed=cpp");

    for h in [
        "/usr/include/kdl/chain.hpp",
        "/usr/include/kdl_parser/kdl_parser.hpp",
        "/usr/include/urdf_parser/urdf_parser.h",
    ] {
        if !std::path::Path::new(h).exists() {
            panic!("{h} is missing: run scripts/install-deps (liborocos-kdl-dev, libkdl-parser-dev, liburdfdom-dev)");
        }
    }
    let (visp_inc, visp_dirs, visp_libs) = pkg_config("visp");

    let mut build = cxx_build::bridges(bridges);
    build
        .files(sources)
        .std("c++17")
        .opt_level(2)
        .include("/usr/include/eigen3")
        .include("/usr/include/opencv4")
        .flag_if_supported("-Wno-deprecated-declarations")
        .flag_if_supported("-Wno-unused-parameter")
        .flag_if_supported("-Wno-deprecated-copy")
        .flag_if_supported("-Wno-ignored-qualifiers");
    for i in &visp_inc {
        build.include(i);
    }
    build.compile("trocar_docking_cpp");

    // pkg-config for kdl_parser/urdf is broken on Debian 12: link by name.
    for lib in [
        "kdl_parser",
        "orocos-kdl",
        "urdfdom_model",
        "tinyxml2",
        "tinyxml",
        "console_bridge",
    ] {
        println!("cargo:rustc-link-lib={lib}");
    }
    for d in &visp_dirs {
        println!("cargo:rustc-link-search=native={d}");
    }
    for l in &visp_libs {
        println!("cargo:rustc-link-lib={l}");
    }
    println!("cargo:rustc-link-lib=opencv_aruco");
    // The official AprilTag library (libapriltag-dev): the tags the renderer draws.
    if !std::path::Path::new("/usr/include/apriltag/apriltag.h").exists() {
        panic!("/usr/include/apriltag/apriltag.h is missing: run scripts/install-deps (libapriltag-dev)");
    }
    println!("cargo:rustc-link-lib=apriltag");
}
