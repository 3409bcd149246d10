//! rostest test node: `rostest_checks <check>` runs one check of `trocar_docking::ros::checks`
//! (roundtrip, docking, stale_hold, replay) against the running graph and writes the JUnit
//! XML to the path rostest passes as `--gtest_output=xml:PATH`. Exit code 0 when it passed.

use trocar_docking::ros::{checks, junit};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let out = junit::gtest_output_path(&args);
    let check = args
        .iter()
        .skip(1)
        .find(|a| !a.starts_with("--") && !a.contains(":="))
        .cloned()
        .unwrap_or_default();
    if let Err(e) = rosrust::try_init("rostest_checks") {
        eprintln!("rostest_checks: cannot reach the ROS master: {e}");
        std::process::exit(2);
    }
    let ok = checks::run(&check, out.as_deref());
    std::process::exit(if ok { 0 } else { 1 });
}
