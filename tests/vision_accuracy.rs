//! Fixed-seed accuracy over a small grid of synthetic 1280x720 frames (the full sweep is
//! `trocar_docking bench --suite vision`).

use trocar_docking::bench::vision::{evaluate, synthetic_frames, SweepConfig, SweepResult};
use trocar_docking::vision::MarkerFamily;

fn sweep(family: &str, frames: usize, noise: f64, seed: u64) -> SweepResult {
    let family: MarkerFamily = family.parse().unwrap();
    let cfg = SweepConfig {
        family,
        frames,
        noise_sigma: noise,
        blur_sigma: 0.0,
        seed,
    };
    report(evaluate(&synthetic_frames(&cfg).unwrap()).unwrap())
}

/// Print the errors (the figures the bounds below sit on).
fn report(r: SweepResult) -> SweepResult {
    let ((tm, tx), (rm, rx)) = (r.translation_median_max(), r.rotation_median_max());
    eprintln!(
        "translation median {:.4} mm max {:.4} mm; rotation median {:.4} deg max {:.4} deg",
        tm * 1e3,
        tx * 1e3,
        rm.to_degrees(),
        rx.to_degrees()
    );
    r
}

#[test]
fn aruco_clean_frames_meet_the_accuracy_target() {
    let r = sweep("DICT_4X4_50", 12, 0.0, 3);
    assert_eq!(r.detected, r.frames, "every marker in view must be found");
    let (tm, _) = r.translation_median_max();
    let (rm, _) = r.rotation_median_max();
    assert!(tm <= 1e-3, "median translation error {tm} m");
    assert!(rm.to_degrees() <= 0.2, "median rotation error {} deg", rm.to_degrees());
}

#[test]
fn aruco_noisy_frames_stay_within_3mm() {
    let r = sweep("DICT_ARUCO_ORIGINAL", 8, 3.0, 5);
    assert_eq!(r.detected, r.frames);
    let (tm, tx) = r.translation_median_max();
    assert!(tm <= 1e-3, "median translation error {tm} m");
    assert!(tx <= 3e-3, "max translation error {tx} m");
}

#[test]
fn apriltag_frames_are_accurate() {
    let r = sweep("tag36h11", 6, 3.0, 9);
    assert_eq!(r.detected, r.frames);
    let (tm, _) = r.translation_median_max();
    let (rm, _) = r.rotation_median_max();
    assert!(tm <= 1e-3, "median translation error {tm} m");
    assert!(rm.to_degrees() <= 0.2, "median rotation error {} deg", rm.to_degrees());
}

#[test]
fn blurred_noisy_frames_stay_accurate() {
    let cfg = SweepConfig {
        family: "DICT_5X5_100".parse().unwrap(),
        frames: 6,
        noise_sigma: 2.0,
        blur_sigma: 1.0,
        seed: 21,
    };
    let r = report(evaluate(&synthetic_frames(&cfg).unwrap()).unwrap());
    assert_eq!(r.detected, r.frames);
    let (tm, tx) = r.translation_median_max();
    assert!(tm <= 1e-3 && tx <= 3e-3, "median {tm} m, max {tx} m");
}
