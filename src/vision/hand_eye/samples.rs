//! The sample set of a live calibration and its acceptance rules: a sample is taken only when
//! the arm has been still for a while, the marker is fully in view, and the flange has turned
//! enough from every sample already taken; its marker pose is what a window of detections
//! gives (`target`: the mean of a still target, a moving one at the same phase).

use nalgebra::{Isometry3, Unit, Vector3};

use super::refine::Sample;
use super::target::Motion;

/// When a sample is accepted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AcceptanceRules {
    /// The arm and the detection must have been still this long, s.
    pub still_for_s: f64,
    /// Still: every joint within this of where it was at the start of the still period, rad.
    pub joint_tolerance_rad: f64,
    /// Still: the marker within this of where it was, m.
    pub marker_tolerance_m: f64,
    /// Still: the marker turned less than this, rad.
    pub marker_tolerance_rad: f64,
    /// Every marker corner at least this far inside the image, px.
    pub border_margin_px: f64,
    /// The flange must have turned at least this much from the nearest sample, rad.
    pub min_rotation_rad: f64,
}

impl AcceptanceRules {
    /// The rules with the calibration node's still period `still_for_s` (s) and border
    /// margin `border_margin_px` (its parameters, `config/hand_eye_calibration.yaml`), and
    /// the rules' own tolerances: still within 0.2 deg a joint, 0.5 mm and 0.3 deg the
    /// marker; at least 3 deg of rotation from the nearest sample.
    pub fn new(still_for_s: f64, border_margin_px: f64) -> Self {
        Self {
            still_for_s,
            joint_tolerance_rad: 0.2_f64.to_radians(),
            marker_tolerance_m: 0.5e-3,
            marker_tolerance_rad: 0.3_f64.to_radians(),
            border_margin_px,
            min_rotation_rad: 3.0_f64.to_radians(),
        }
    }
}

/// How long the arm and the detection have been still. Fed with every joint state and every
/// detection (a lost marker or a motion restarts the period).
#[derive(Debug, Clone, Default)]
pub struct Stillness {
    joints: Option<(f64, Vec<f64>)>,
    marker: Option<(f64, Isometry3<f64>)>,
    last_joint_t: f64,
    last_marker_t: f64,
}

impl Stillness {
    /// A joint state at time `t` (s).
    pub fn joints(&mut self, t: f64, q: &[f64], rules: &AcceptanceRules) {
        self.last_joint_t = t;
        let moved = match &self.joints {
            Some((_, q0)) => {
                q0.len() != q.len() || q0.iter().zip(q).any(|(a, b)| (a - b).abs() > rules.joint_tolerance_rad)
            }
            None => true,
        };
        if moved {
            self.joints = Some((t, q.to_vec()));
        }
    }

    /// A detection at time `t` (s); `None` when the marker was not found.
    pub fn marker(&mut self, t: f64, camera_t_marker: Option<&Isometry3<f64>>, rules: &AcceptanceRules) {
        self.last_marker_t = t;
        let Some(p) = camera_t_marker else {
            self.marker = None;
            return;
        };
        let moved = match &self.marker {
            Some((_, p0)) => {
                (p.translation.vector - p0.translation.vector).norm() > rules.marker_tolerance_m
                    || p.rotation.angle_to(&p0.rotation) > rules.marker_tolerance_rad
            }
            None => true,
        };
        if moved {
            self.marker = Some((t, *p));
        }
    }

    /// How long the arm has been still at time `now`, s (0 when its joint states are missing
    /// or stale: none for `max_gap_s`). The target's own stillness is `target::assess`'s.
    pub fn arm_still_for(&self, now: f64, max_gap_s: f64) -> f64 {
        match &self.joints {
            Some((tj, _)) if now - self.last_joint_t <= max_gap_s => (now - tj).max(0.0),
            _ => 0.0,
        }
    }

    /// How long both have been still at time `now`, s (0 when either is missing or stale:
    /// no message for `max_gap_s`).
    pub fn still_for(&self, now: f64, max_gap_s: f64) -> f64 {
        match (&self.joints, &self.marker) {
            (Some((tj, _)), Some((tm, _)))
                if now - self.last_joint_t <= max_gap_s && now - self.last_marker_t <= max_gap_s =>
            {
                (now - tj.max(*tm)).max(0.0)
            }
            _ => 0.0,
        }
    }
}

/// Why a sample was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Refusal {
    /// Not still long enough.
    #[error("the arm has been still for {still_s:.2} s, {needed_s:.2} s are needed")]
    NotStill {
        /// Still for, s.
        still_s: f64,
        /// Needed, s.
        needed_s: f64,
    },
    /// No detection.
    #[error("no marker detection")]
    NoMarker,
    /// A corner too near the border or outside the image.
    #[error("the marker is not fully in view: a corner {border_px:.1} px from the border, {needed_px:.0} px needed")]
    NotInView {
        /// The nearest corner's distance from the border, px.
        border_px: f64,
        /// Needed, px.
        needed_px: f64,
    },
    /// Too close in rotation to a sample already taken.
    #[error(
        "the flange turned {angle_deg:.1} deg from sample {nearest}: at least {needed_deg:.1} deg are needed (the sample adds no rotation)"
    )]
    NoNewRotation {
        /// The rotation to the nearest sample, deg.
        angle_deg: f64,
        /// Index of the nearest sample.
        nearest: usize,
        /// Needed, deg.
        needed_deg: f64,
    },
    /// A non-finite pose.
    #[error("the flange or marker pose is not finite")]
    NotFinite,
    /// The target moved by itself and did not turn back within the window.
    #[error(
        "target moving: {0}, and did not turn back (drifting, or knocked): hold the target still (clamp the marker \
         to the table) and take the sample again"
    )]
    TargetMoving(Motion),
    /// Too few detections in the window.
    #[error("{detections} marker detections in {window_s:.1} s with the arm still: the marker is lost or the estimator too slow")]
    FewDetections {
        /// Detections.
        detections: usize,
        /// The window, s.
        window_s: f64,
    },
}

/// The samples taken so far.
#[derive(Debug, Clone)]
pub struct SampleSet {
    /// The rules.
    pub rules: AcceptanceRules,
    samples: Vec<Sample>,
    /// Each sample's target motion (`None`: the target was still).
    motions: Vec<Option<Motion>>,
}

impl SampleSet {
    /// An empty set with `rules`.
    pub fn new(rules: AcceptanceRules) -> Self {
        Self {
            rules,
            samples: Vec::new(),
            motions: Vec::new(),
        }
    }

    /// The samples.
    pub fn samples(&self) -> &[Sample] {
        &self.samples
    }

    /// Take a sample if the rules allow: `still_s` from `Stillness::still_for`, `border_px`
    /// the detection's nearest corner distance from the image border. Returns its index.
    pub fn try_add(&mut self, sample: Sample, still_s: f64, border_px: f64) -> Result<usize, Refusal> {
        let finite = |p: &Isometry3<f64>| {
            p.translation.vector.iter().all(|v| v.is_finite()) && p.rotation.coords.iter().all(|v| v.is_finite())
        };
        if !finite(&sample.base_t_flange) || !finite(&sample.camera_t_marker) {
            return Err(Refusal::NotFinite);
        }
        if still_s.is_nan() || still_s < self.rules.still_for_s {
            return Err(Refusal::NotStill {
                still_s,
                needed_s: self.rules.still_for_s,
            });
        }
        if border_px.is_nan() || border_px < self.rules.border_margin_px {
            return Err(Refusal::NotInView {
                border_px,
                needed_px: self.rules.border_margin_px,
            });
        }
        if let Some((nearest, angle)) = self.nearest_rotation(&sample.base_t_flange) {
            if angle < self.rules.min_rotation_rad {
                return Err(Refusal::NoNewRotation {
                    angle_deg: angle.to_degrees(),
                    nearest,
                    needed_deg: self.rules.min_rotation_rad.to_degrees(),
                });
            }
        }
        self.samples.push(sample);
        self.motions.push(None);
        Ok(self.samples.len() - 1)
    }

    /// `try_add` for a sample whose target moved by `motion` (taken at its phase).
    pub fn try_add_moving(
        &mut self,
        sample: Sample,
        still_s: f64,
        border_px: f64,
        motion: Option<Motion>,
    ) -> Result<usize, Refusal> {
        let i = self.try_add(sample, still_s, border_px)?;
        self.motions[i] = motion;
        Ok(i)
    }

    /// The phase direction of the samples taken at a moving target's extreme (the first
    /// one's, in the base): the next ones take the same extreme.
    pub fn phase_reference(&self) -> Option<Unit<Vector3<f64>>> {
        self.motions
            .iter()
            .flatten()
            .next()
            .and_then(|m| Unit::try_new(m.direction_base, 1e-9))
    }

    /// The target's motion in words when it moved at some sample (the largest), with what
    /// was done and the fix; `None` when it was still at every sample.
    pub fn target_note(&self) -> Option<String> {
        let moving: Vec<&Motion> = self.motions.iter().flatten().collect();
        let largest = moving
            .iter()
            .max_by(|a, b| a.peak_to_peak_m.total_cmp(&b.peak_to_peak_m))?;
        Some(format!(
            "target moving at {} of {} samples: {largest}; those samples were taken at the same phase (the marker's \
             lowest point, the end of expiration) so that the marker is the same pose at each; for a still target \
             pause the ventilator (or hold the breath) or clamp the marker to the table",
            moving.len(),
            self.samples.len()
        ))
    }

    /// The nearest sample in flange rotation and the angle to it, rad.
    pub fn nearest_rotation(&self, base_t_flange: &Isometry3<f64>) -> Option<(usize, f64)> {
        self.samples
            .iter()
            .map(|s| s.base_t_flange.rotation.angle_to(&base_t_flange.rotation))
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1))
    }

    /// Remove the last sample; `None` when empty.
    pub fn remove_last(&mut self) -> Option<Sample> {
        self.motions.pop();
        self.samples.pop()
    }

    /// Remove every sample.
    pub fn clear(&mut self) {
        self.samples.clear();
        self.motions.clear();
    }

    /// The largest rotation between two samples' flanges, rad.
    pub fn rotation_spread_rad(&self) -> f64 {
        let poses: Vec<Isometry3<f64>> = self.samples.iter().map(|s| s.base_t_flange).collect();
        super::quality::conditioning(&poses).spread_deg.to_radians()
    }
}
