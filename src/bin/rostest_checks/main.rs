//! rostest test node: `rostest_checks <check>` runs one check against the running graph
//! and writes the JUnit XML to the path rostest passes as `--gtest_output=xml:PATH`; exit
//! code 0 when it passed. The checks: `roundtrip`, `docking`, `stale_hold`
//! ([`docking_checks`]), `replay` and `replay_controller` ([`replay_checks`]), `bad_input` ([`fault_injection`]), `latency` and `bad_images`
//! ([`camera_checks`]), `blocked_arm`, `clock_back`, `clock_forward`, `driver_restart` and
//! `flood` ([`failure_modes`]), `scope_pivot` and `scope_joy` ([`scope_checks`]), `preflight`
//! ([`preflight_checks`]), `dry_run` ([`dry_run_checks`]), `reconfigure` ([`reconfigure_checks`]), `hand_eye` and `hand_eye_dock` ([`hand_eye_checks`]).

mod bag_sync;
mod camera_checks;
mod command_audit;
mod common;
mod docking_checks;
mod dry_run_checks;
mod failure_modes;
mod fault_injection;
mod hand_eye_checks;
mod junit;
mod preflight_checks;
mod reconfigure_checks;
mod replay_checks;
mod replay_faults;
mod scope_checks;
mod starve;
mod tf_checks;

use ::trocar_docking::ros::params;
use common::CheckParams;
use junit::TestReport;

/// Append a line to `$ROS_HOME/rostest_summary.txt`, which scripts/run-rostest prints
/// (rostest keeps a test node's stdout in its logs only).
fn append_summary(line: &str) {
    use std::io::Write as _;
    let Some(home) = std::env::var_os("ROS_HOME") else {
        return;
    };
    let path = std::path::Path::new(&home).join("rostest_summary.txt");
    if let Ok(mut f) = std::fs::OpenOptions::new().create(true).append(true).open(path) {
        let _ = writeln!(f, "{line}");
    }
}

/// Run the check named `name`, write the JUnit XML to `out` if given; true if it passed.
fn run(name: &str, out: Option<&std::path::Path>) -> bool {
    let mut report = TestReport::new(&format!("trocar_docking_{name}"));
    let params = params::load_private::<CheckParams>();
    report.check(name, || {
        let p = params.map_err(|e| e.to_string())?;
        p.validate().map_err(|e| format!("parameter {e}"))?;
        let summary = match name {
            "roundtrip" => docking_checks::roundtrip(&p).map(|()| "round trip ok".to_string()),
            "docking" => docking_checks::docking(&p),
            "stale_hold" => docking_checks::stale_hold(&p),
            "replay" => replay_checks::replay(&p),
            "replay_controller" => replay_checks::replay_controller(&p),
            "replay_fault" => replay_faults::replay_fault(&p),
            "bad_input" => fault_injection::bad_input(&p),
            "latency" => camera_checks::latency(&p),
            "bad_images" => camera_checks::bad_images(&p),
            "blocked_arm" => failure_modes::blocked_arm(&p),
            "clock_back" => failure_modes::clock_jump(&p, -5.0),
            "clock_forward" => failure_modes::clock_jump(&p, 5.0),
            "driver_restart" => failure_modes::driver_restart(&p),
            "flood" => failure_modes::flood(&p),
            "scope_pivot" => scope_checks::scope_pivot(&p),
            "scope_joy" => scope_checks::scope_joy(&p),
            "preflight" => preflight_checks::preflight(&p),
            "dry_run" => dry_run_checks::dry_run(&p),
            "reconfigure" => reconfigure_checks::reconfigure(&p),
            "hand_eye" => hand_eye_checks::hand_eye(&p),
            "camera_tf" => tf_checks::camera_tf(&p),
            "hand_eye_dock" => hand_eye_checks::hand_eye(&p)
                .and_then(|c| docking_checks::docking(&p).map(|d| format!("{c}; then docking: {d}"))),
            other => Err(format!("unknown check {other}")),
        }?;
        rosrust::ros_info!("{name}: {summary}");
        println!("{name}: {summary}");
        append_summary(&format!("{name}: {summary}"));
        Ok(())
    });
    if let Some(c) = report.cases().iter().find(|c| c.failure.is_some()) {
        let why = c.failure.clone().unwrap_or_default();
        eprintln!("{name} FAILED: {why}");
        append_summary(&format!("{name} FAILED: {why}"));
    }
    if let Some(path) = out {
        if let Err(e) = report.write(path) {
            eprintln!("cannot write {}: {e}", path.display());
            return false;
        }
    }
    report.passed()
}

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
    let ok = run(&check, out.as_deref());
    std::process::exit(if ok { 0 } else { 1 });
}
