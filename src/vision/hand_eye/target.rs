//! The calibration target's own motion: a sample's marker pose is not one detection but the
//! detections of a window while the arm is still. A still target gives their mean; a target
//! that moves by itself (the trocar's marker on a breathing abdomen, a plate knocked) is
//! named, and when its motion turns back within the window (periodic: breathing) the sample
//! is the mean of the detections at the same phase at every pose, the motion's extreme along
//! its main direction in the base frame, oriented down: the abdomen's lowest point, the end
//! of expiration (where a ventilator's expiratory pause holds it). The phase is a fixed pose
//! in the base, so every sample sees the same marker; a target that drifts (no turning point
//! in the window) is refused.
//!
//! Why: a hand-eye solver takes each pair as one rigid marker seen from a still arm, every
//! pair the same marker pose in the base (ViSP's `vpHandEyeCalibration`; its app
//! `apps/calibration/hand-eye/visp-compute-eye-in-hand-calibration.cpp` asks, when the solve
//! fails, for poses "covering the half sphere over the chessboard", and ships 8 poses as its
//! eye-in-hand example data). A window too short to see a whole breath takes breathing
//! extremes of both signs at random: 8 mm apart for a 4 mm breath, and the fit spreads them
//! into the mount.

use nalgebra::{Isometry3, Matrix3, Unit, UnitQuaternion, Vector3};

/// How a sample's target is watched.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetRules {
    /// Watch the target at most this long at a pose, s: longer than one breath (a ventilator
    /// at 12-20 breaths a minute: 3-5 s) with a margin at both ends, so that every window
    /// holds a turning point away from its ends.
    pub window_s: f64,
    /// A target within the tolerances this long is still, s: a 1 mm breath at 0.2 Hz stays
    /// within 0.5 mm for at most 1.7 s, so a breathing target is never taken as still.
    pub still_s: f64,
    /// Still: every detection within this of their mean, m.
    pub tolerance_m: f64,
    /// Still: every detection turned less than this from their mean, rad.
    pub tolerance_rad: f64,
    /// A moving target's detections within this of its extreme (along its main direction)
    /// are the same phase, m (at least; 5 % of the motion when that is more).
    pub phase_band_m: f64,
    /// Fewest detections in a still window.
    pub min_detections: usize,
}

impl TargetRules {
    /// The rules with the calibration node's window `window_s` and still period `still_s`
    /// (its parameters, `config/hand_eye_calibration.yaml`) and the rules' own tolerances:
    /// still within 0.5 mm and 0.3 deg; the phase band 0.2 mm; 5 detections at least.
    pub fn new(window_s: f64, still_s: f64) -> Self {
        Self {
            window_s,
            still_s,
            tolerance_m: 0.5e-3,
            tolerance_rad: 0.3_f64.to_radians(),
            phase_band_m: 0.2e-3,
            min_detections: 5,
        }
    }
}

/// One detection: its time (s) and the marker pose in the camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection {
    /// Time, s.
    pub t: f64,
    /// Marker pose in the camera optical frame.
    pub camera_t_marker: Isometry3<f64>,
}

/// The target's motion over a window (the arm still).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    /// Extent of the marker's positions along its main direction, m.
    pub peak_to_peak_m: f64,
    /// Largest rotation of a detection from their mean, rad.
    pub rotation_rad: f64,
    /// The main direction in the base frame (through the hand-eye guess), oriented down.
    pub direction_base: Vector3<f64>,
    /// The period, from the crossings of the mid-level, s (`None`: fewer than three).
    pub period_s: Option<f64>,
    /// The window, s.
    pub window_s: f64,
}

impl std::fmt::Display for Motion {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let d = self.direction_base;
        write!(
            f,
            "the marker moved {:.1} mm (peak to peak, along ({:+.2}, {:+.2}, {:+.2}) in the base) and turned {:.2} deg \
             in {:.1} s while the arm was still",
            self.peak_to_peak_m * 1e3,
            d.x,
            d.y,
            d.z,
            self.rotation_rad.to_degrees(),
            self.window_s
        )?;
        match self.period_s {
            Some(p) => write!(f, ", periodic every {p:.1} s ({:.0} a minute: breathing?)", 60.0 / p),
            None => Ok(()),
        }
    }
}

/// The marker pose a window gives.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetSample {
    /// The mean of the detections used.
    pub camera_t_marker: Isometry3<f64>,
    /// Detections averaged.
    pub detections: usize,
    /// `None`: the target was still; else its motion (the sample is at the extreme).
    pub moving: Option<Motion>,
}

/// What a window says so far.
#[derive(Debug, Clone, PartialEq)]
pub enum Assessment {
    /// Keep watching.
    Wait,
    /// A sample.
    Sample(TargetSample),
    /// The target moved and its motion did not turn back: no sample.
    Drifting(Motion),
    /// The window ended with too few detections.
    TooFewDetections(usize),
}

/// The mean of `poses` (translation mean; rotation: the first moved by the mean rotation
/// vector from it) and the largest distance and rotation of a pose from it.
pub fn mean_pose(poses: &[Isometry3<f64>]) -> Option<(Isometry3<f64>, f64, f64)> {
    let first = poses.first()?;
    let n = poses.len() as f64;
    let t = poses.iter().map(|p| p.translation.vector).sum::<Vector3<f64>>() / n;
    let w = poses
        .iter()
        .map(|p| (first.rotation.inverse() * p.rotation).scaled_axis())
        .sum::<Vector3<f64>>()
        / n;
    let r = first.rotation * UnitQuaternion::from_scaled_axis(w);
    let dt = poses
        .iter()
        .map(|p| (p.translation.vector - t).norm())
        .fold(0.0, f64::max);
    let dr = poses.iter().map(|p| p.rotation.angle_to(&r)).fold(0.0, f64::max);
    Some((Isometry3::from_parts(t.into(), r), dt, dr))
}

/// The main direction of the positions (the covariance's largest eigenvector), unit.
fn main_direction(x: &[Vector3<f64>]) -> Vector3<f64> {
    let n = x.len().max(1) as f64;
    let mean = x.iter().sum::<Vector3<f64>>() / n;
    let cov: Matrix3<f64> = x
        .iter()
        .map(|v| (v - mean) * (v - mean).transpose())
        .sum::<Matrix3<f64>>()
        / n;
    let e = cov.symmetric_eigen();
    let k = e.eigenvalues.imax();
    e.eigenvectors.column(k).into_owned()
}

/// The period of `s` over times `t` from its crossings of the mid-level (with hysteresis of
/// a quarter of the extent): two crossings a period.
fn period(t: &[f64], s: &[f64]) -> Option<f64> {
    let (lo, hi) = s
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(*v), b.max(*v)));
    let (mid, h) = ((lo + hi) / 2.0, (hi - lo) / 4.0);
    let mut state = None;
    let mut crossings = Vec::new();
    for (ti, si) in t.iter().zip(s) {
        let now = if *si > mid + h {
            Some(true)
        } else if *si < mid - h {
            Some(false)
        } else {
            continue;
        };
        if state.is_some() && state != now {
            crossings.push(*ti);
        }
        state = now;
    }
    (crossings.len() >= 3).then(|| 2.0 * (crossings[crossings.len() - 1] - crossings[0]) / (crossings.len() - 1) as f64)
}

/// The poses of the runs of detections whose phase `s` is at least `above` and that turn
/// back within the window (neither the first nor the last detection in the run).
fn same_phase(all: &[Isometry3<f64>], s: &[f64], above: f64) -> Vec<Isometry3<f64>> {
    let near: Vec<bool> = s.iter().map(|v| *v >= above).collect();
    let mut used = Vec::new();
    let mut i = 0;
    while i < near.len() {
        if !near[i] {
            i += 1;
            continue;
        }
        let j = (i..near.len()).find(|&k| !near[k]).unwrap_or(near.len());
        if i > 0 && j < near.len() {
            used.extend_from_slice(&all[i..j]);
        }
        i = j;
    }
    used
}

/// Assess the detections `dets` (in time order) of a window that began at `start` (the arm
/// still since), at time `now`; `base_r_camera` turns camera directions into the base
/// (through the hand-eye guess), `reference` is the phase direction of the samples already
/// taken (the extreme kept the same at every pose), else down (base -z).
pub fn assess(
    dets: &[Detection],
    start: f64,
    now: f64,
    rules: &TargetRules,
    base_r_camera: &UnitQuaternion<f64>,
    reference: Option<&Unit<Vector3<f64>>>,
) -> Assessment {
    let dets: Vec<&Detection> = dets.iter().filter(|d| d.t >= start && d.t <= now).collect();
    // Still: the last `still_s` within the tolerances.
    if now - start >= rules.still_s {
        let tail: Vec<Isometry3<f64>> = dets
            .iter()
            .filter(|d| d.t >= now - rules.still_s)
            .map(|d| d.camera_t_marker)
            .collect();
        if tail.len() >= rules.min_detections {
            if let Some((mean, dt, dr)) = mean_pose(&tail) {
                if dt <= rules.tolerance_m && dr <= rules.tolerance_rad {
                    return Assessment::Sample(TargetSample {
                        camera_t_marker: mean,
                        detections: tail.len(),
                        moving: None,
                    });
                }
            }
        }
    }
    if now - start < rules.window_s {
        return Assessment::Wait;
    }
    if dets.len() < 2 * rules.min_detections {
        return Assessment::TooFewDetections(dets.len());
    }
    let x: Vec<Vector3<f64>> = dets.iter().map(|d| d.camera_t_marker.translation.vector).collect();
    let dir_c = main_direction(&x);
    let mut dir_b = base_r_camera * dir_c;
    let down = reference.map_or(-Vector3::z(), |r| r.into_inner());
    let sign = if dir_b.dot(&down) < 0.0 { -1.0 } else { 1.0 };
    dir_b *= sign;
    let s: Vec<f64> = x.iter().map(|v| sign * dir_c.dot(v)).collect();
    let t: Vec<f64> = dets.iter().map(|d| d.t).collect();
    let (lo, hi) = s
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(*v), b.max(*v)));
    let all: Vec<Isometry3<f64>> = dets.iter().map(|d| d.camera_t_marker).collect();
    let rotation_rad = mean_pose(&all).map_or(0.0, |m| m.2);
    let motion = Motion {
        peak_to_peak_m: hi - lo,
        rotation_rad,
        direction_base: dir_b,
        period_s: period(&t, &s),
        window_s: now - start,
    };
    let band = rules.phase_band_m.max(0.05 * (hi - lo));
    let used = same_phase(&all, &s, hi - band);
    match mean_pose(&used) {
        Some((mean, _, _)) => Assessment::Sample(TargetSample {
            camera_t_marker: mean,
            detections: used.len(),
            moving: Some(motion),
        }),
        None => Assessment::Drifting(motion),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A marker 0.3 m ahead moving by `offset(t)` (camera frame), seen at 15 Hz from `t0`.
    fn window(t0: f64, secs: f64, offset: impl Fn(f64) -> Vector3<f64>) -> Vec<Detection> {
        (0..(secs * 15.0) as usize)
            .map(|k| {
                let t = t0 + k as f64 / 15.0;
                Detection {
                    t,
                    camera_t_marker: Isometry3::translation(0.0, 0.0, 0.3)
                        * Isometry3::translation(offset(t).x, offset(t).y, offset(t).z),
                }
            })
            .collect()
    }

    /// The camera looking down: its z is the base's -z.
    fn looking_down() -> UnitQuaternion<f64> {
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
    }

    fn rules() -> TargetRules {
        TargetRules::new(6.0, 2.0)
    }

    #[test]
    fn a_still_target_is_the_mean_of_the_last_still_period() {
        let d = window(0.0, 2.5, |t| Vector3::new(0.0, 0.0, 1e-5 * (t * 40.0).sin()));
        assert_eq!(assess(&d, 0.0, 1.9, &rules(), &looking_down(), None), Assessment::Wait);
        let Assessment::Sample(s) = assess(&d, 0.0, 2.5, &rules(), &looking_down(), None) else {
            panic!("still target not sampled");
        };
        assert!(s.moving.is_none());
        assert!((s.camera_t_marker.translation.z - 0.3).abs() < 2e-5, "{s:?}");
        assert!(s.detections >= 29, "{s:?}");
    }

    #[test]
    fn a_breathing_target_is_named_and_sampled_at_its_lowest_point_whatever_the_phase() {
        // 4 mm along the line of sight (base -z), 0.25 Hz: still for 0.5 s at each extreme,
        // never for 2 s.
        let (mut lowest, mut periods) = (Vec::new(), 0);
        for phase in [0.0, 1.0, 2.0, 3.0, 4.0, 5.0] {
            let breath = move |t: f64| Vector3::new(0.0, 0.0, 0.004 * (std::f64::consts::TAU * 0.25 * t + phase).sin());
            let d = window(10.0, 6.2, breath);
            assert_eq!(
                assess(&d, 10.0, 15.9, &rules(), &looking_down(), None),
                Assessment::Wait
            );
            let Assessment::Sample(s) = assess(&d, 10.0, 16.2, &rules(), &looking_down(), None) else {
                panic!("phase {phase}: no sample");
            };
            let m = s.moving.expect("the breathing is named");
            assert!((m.peak_to_peak_m - 0.008).abs() < 1e-4, "{m}");
            assert!((m.direction_base.z + 1.0).abs() < 1e-6, "{m}");
            if let Some(p) = m.period_s {
                assert!((p - 4.0).abs() < 0.3, "{m}");
                periods += 1;
            }
            assert!(m.to_string().contains("moved 8.0 mm"), "{m}");
            // The lowest point in the base is the farthest from the camera looking down.
            lowest.push(s.camera_t_marker.translation.z);
            assert!(s.detections >= 2, "{s:?}");
        }
        // The same pose at every phase (the band's mean sits a third of the band, 0.13 mm,
        // inside the extreme).
        let (lo, hi) = lowest
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), z| (a.min(*z), b.max(*z)));
        assert!(hi - lo < 0.05e-3, "{lowest:?}");
        assert!((lo - 0.304).abs() < 0.2e-3, "{lowest:?}");
        assert!(periods >= 3, "the period found in {periods} of 6 windows");
        // With a reference pointing up, the other extreme.
        let up = Unit::new_normalize(Vector3::z());
        let d = window(0.0, 6.2, |t| {
            Vector3::new(0.0, 0.0, 0.004 * (std::f64::consts::TAU * 0.25 * t).sin())
        });
        let Assessment::Sample(s) = assess(&d, 0.0, 6.2, &rules(), &looking_down(), Some(&up)) else {
            panic!("no sample");
        };
        assert!((s.camera_t_marker.translation.z - 0.296).abs() < 0.2e-3, "{s:?}");
    }

    #[test]
    fn a_drifting_target_is_refused_and_a_dark_window_is_named() {
        // 1 mm/s: never within 0.5 mm for 2 s, and no turning point.
        let d = window(0.0, 6.2, |t| Vector3::new(0.0, 0.0, 0.001 * t));
        match assess(&d, 0.0, 6.2, &rules(), &looking_down(), None) {
            Assessment::Drifting(m) => {
                assert!((m.peak_to_peak_m - 0.0061).abs() < 1e-4, "{m}");
                assert!(m.period_s.is_none(), "{m}");
            }
            a => panic!("{a:?}"),
        }
        // Detections before the window (the arm moving) do not count.
        let d = window(0.0, 6.2, |_| Vector3::zeros());
        assert_eq!(
            assess(&d[..4], 0.0, 6.2, &rules(), &looking_down(), None),
            Assessment::TooFewDetections(4)
        );
        assert_eq!(assess(&d, 5.0, 6.2, &rules(), &looking_down(), None), Assessment::Wait);
    }
}
