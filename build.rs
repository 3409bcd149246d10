//! Builds the C++ side of the cxx bridges (KDL kinematics, ViSP/OpenCV vision) and links
//! Debian's libraries. Missing libraries: run `scripts/install-deps`.

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

fn main() {
    let bridges = ["src/ffi/kdl.rs", "src/ffi/vision.rs"];
    let sources = ["cpp/kdl_bridge.cpp", "cpp/vision_bridge.cpp"];
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
}
