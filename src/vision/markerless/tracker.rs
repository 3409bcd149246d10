//! ViSP's model-based tracker (`vpMbGenericTracker`, moving edges, through the cxx bridge)
//! on the trocar model, started and restarted from the per-frame estimate of the opening's
//! ellipse (`MarkerlessEstimator`).
//!
//! The tracker's model is generated from [`TrocarModel`] as ViSP `.cao` text ([`cao`]):
//! polygons of [`TrackerParams::polygon_sides`] sides for the face's rim, the opening and
//! the head's side. The circles of the `.cao` format are not used: the ellipse residual of
//! Debian 12's ViSP 3.5.0 lacks the moments' factor 4 and drives the pose away along the
//! line of sight (fixed upstream in ViSP 3.6.0).
//!
//! A track is lost when the tracker gives up (too few edge sites), when its projection error
//! (the mean angle between the image's gradient and the model's projected edges at the
//! sites) exceeds [`TrackerParams::max_projection_error_deg`], when too few sites are left,
//! or when the robust estimator rejects too many of them.
//! `MarkerlessEstimator::with_tracker` restarts it from every confident per-frame estimate
//! and lets it carry the images that give none.

use cxx::UniquePtr;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use super::geometry::{with_roll_convention, Axis};
use super::model::TrocarModel;
use crate::ffi::model_tracker::{ffi, TRACK_RECORD_LEN};
use crate::vision::{isometry_from_rt, rt_from_isometry, CameraModel, ImageView, VisionError};

/// The tracker's settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerParams {
    /// The moving edges' search range along the edge's normal, px. The face's rim lies
    /// 4.5 mm outside the opening (shipped model): 3.15 px / Z (Z in m) at the ZED Mini's
    /// 700 px focal length, 8 px at 0.4 m; a range over that lets a rim site snap onto the
    /// opening's stronger edge.
    pub range_px: f64,
    /// Spacing of the edge sites along the model's edges, px.
    pub sample_step_px: f64,
    /// ViSP's likelihood threshold for an edge at a site (`vpMe::setThreshold`).
    pub edge_threshold: f64,
    /// How much a site's contrast may change from one image to the next (relative).
    pub contrast_tolerance: f64,
    /// Sides of the polygons standing for the face's rim and the opening.
    pub polygon_sides: usize,
    /// A track whose projection error exceeds this (deg) is lost.
    pub max_projection_error_deg: f64,
    /// A track with fewer edge sites is lost.
    pub min_sites: usize,
    /// A track where the robust estimator keeps a smaller fraction of the sites is lost.
    pub min_kept_fraction: f64,
}

impl Default for TrackerParams {
    fn default() -> Self {
        Self {
            range_px: 5.0,
            sample_step_px: 4.0,
            edge_threshold: 10000.0,
            contrast_tolerance: 0.5,
            polygon_sides: 24,
            max_projection_error_deg: 30.0,
            min_sites: 20,
            min_kept_fraction: 0.5,
        }
    }
}

impl TrackerParams {
    /// Check every setting.
    pub fn validate(&self) -> Result<(), VisionError> {
        let bad = |what: &str| Err(VisionError::InvalidInput(format!("tracker: {what}")));
        if !(self.range_px.is_finite() && (1.0..=50.0).contains(&self.range_px)) {
            return bad("range_px must be 1-50");
        }
        if !(self.sample_step_px.is_finite() && (1.0..=50.0).contains(&self.sample_step_px)) {
            return bad("sample_step_px must be 1-50");
        }
        if !(8..=360).contains(&self.polygon_sides) {
            return bad("polygon_sides must be 8-360");
        }
        if !(self.max_projection_error_deg.is_finite() && self.max_projection_error_deg > 0.0) {
            return bad("max_projection_error_deg must be > 0");
        }
        if !(self.min_kept_fraction.is_finite() && (0.0..=1.0).contains(&self.min_kept_fraction)) {
            return bad("min_kept_fraction must be 0-1");
        }
        Ok(())
    }
}

/// The trocar model as ViSP `.cao` text (version 1, m), in the port frame: origin at the
/// opening's centre, z along the axis into the body. Polygons of `sides` sides stand for the
/// circles: the face's rim and the opening (two faces on the face, seen from z < 0, where
/// the camera is), and the head's side as `sides` quads from the face's rim to the bottom
/// rim at `head.height`, facing outwards. ViSP tracks the edges of the faces it sees: the
/// quads' bottom edges give the head's outline against the wall; their edges along the
/// side find no gradient on the smooth shading and drop out. The head is not a `.cao`
/// cylinder: ViSP's cylinder is infinite, and a camera on the trocar's axis line, as in
/// docking, is inside it (its projection fails). The cannula is left out: in the body.
pub fn cao(model: &TrocarModel, sides: usize) -> String {
    let mut s = String::from("V1\n# 3D points\n");
    // The polygon's sides lie inside the circle through its corners; corners this much
    // further out put the sides' mean distance from the centre at the circle's radius (an
    // inscribed 24-gon would look 0.6 % smaller and put the port as much further away).
    let h = std::f64::consts::PI / sides as f64;
    let widen = 1.0 / (h.cos() * (1.0 + h * h / 6.0));
    let circle = |r: f64, z: f64, s: &mut String| {
        let r = r * widen;
        for k in 0..sides {
            // Clockwise about +z seen from +z: counter-clockwise seen from the camera.
            let a = -(k as f64) * std::f64::consts::TAU / sides as f64;
            s.push_str(&format!("{:.9} {:.9} {:.9}\n", r * a.cos(), r * a.sin(), z));
        }
    };
    s.push_str(&format!("{}\n", 3 * sides));
    circle(model.head.radius, 0.0, &mut s);
    circle(model.opening.radius, 0.0, &mut s);
    circle(model.head.radius, model.head.height, &mut s);
    s.push_str("# 3D lines\n0\n# Faces from 3D lines\n0\n# Faces from 3D points\n");
    s.push_str(&format!("{}\n", 2 + sides));
    for first in [0, sides] {
        s.push_str(&sides.to_string());
        for k in 0..sides {
            s.push_str(&format!(" {}", first + k));
        }
        s.push('\n');
    }
    for k in 0..sides {
        let k1 = (k + 1) % sides;
        s.push_str(&format!("4 {} {} {k1} {k}\n", 2 * sides + k, 2 * sides + k1));
    }
    s.push_str("# 3D cylinders\n0\n# 3D circles\n0\n");
    s
}

/// One tracked pose and how well the image holds it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackedPose {
    /// The axis (port centre and direction into the body), camera frame.
    pub axis: Axis,
    /// The mean angle between the image's gradient and the model's projected edges, deg.
    pub projection_error_deg: f64,
    /// Edge sites used.
    pub sites: usize,
    /// Fraction of them the robust estimator kept.
    pub kept_fraction: f64,
    /// Confidence in [0, 1]: (1 - projection error / its limit) x the kept fraction x the
    /// depth's precision (1 - its standard error / [`DEPTH_ERROR_SCALE_M`], at least 0).
    pub confidence: f64,
}

/// The depth error at which a tracked pose's confidence reaches 0, m: half the 10 mm an
/// estimate may be off at high confidence.
pub const DEPTH_ERROR_SCALE_M: f64 = 0.005;

/// ViSP's moving edges find an edge to the pixel: the standard error of one site, px
/// (uniform over a pixel: 1 / sqrt(12), rounded up).
const SITE_ERROR_PX: f64 = 0.5;

/// What one image did to the track.
#[derive(Debug, Clone, PartialEq)]
pub enum TrackStep {
    /// The track holds.
    Tracked(TrackedPose),
    /// The track is lost, and why; the tracker must be started again.
    Lost(String),
}

/// ViSP's model-based tracker on the trocar, for one camera.
pub struct ModelTracker {
    t: UniquePtr<ffi::ModelTrackerCpp>,
    camera: CameraModel,
    params: TrackerParams,
    head_radius: f64,
    tracking: bool,
}

impl ModelTracker {
    /// A tracker for `camera` and `model`.
    pub fn new(camera: &CameraModel, model: &TrocarModel, params: TrackerParams) -> Result<Self, VisionError> {
        model.validate()?;
        params.validate()?;
        let t = ffi::new_model_tracker(
            &[camera.fx, camera.fy, camera.cx, camera.cy],
            &camera.distortion,
            camera.is_equidistant(),
            camera.width as i32,
            camera.height as i32,
            &cao(model, params.polygon_sides),
            &[
                params.range_px,
                params.sample_step_px,
                params.edge_threshold,
                params.contrast_tolerance,
            ],
        )?;
        Ok(Self {
            t,
            camera: camera.clone(),
            params,
            head_radius: model.head.radius,
            tracking: false,
        })
    }

    /// Whether a track is running.
    pub fn is_tracking(&self) -> bool {
        self.tracking
    }

    /// Start tracking on `image` from the axis `axis` (camera frame; the roll about it is the
    /// convention's, the model being round).
    pub fn start(&mut self, image: &ImageView, axis: &Axis) -> Result<(), VisionError> {
        self.check(image)?;
        self.tracking = false;
        let pose = with_roll_convention(&pose_of_axis(axis));
        ffi::model_tracker_init(
            self.t.pin_mut(),
            image.data,
            image.width as i32,
            image.height as i32,
            image.channels as i32,
            &rt_from_isometry(&pose),
        )?;
        self.tracking = true;
        Ok(())
    }

    /// Track into `image`. Without a running track, an error.
    pub fn track(&mut self, image: &ImageView) -> Result<TrackStep, VisionError> {
        self.check(image)?;
        if !self.tracking {
            return Err(VisionError::InvalidInput("the tracker has not been started".into()));
        }
        let r = ffi::model_tracker_track(
            self.t.pin_mut(),
            image.data,
            image.width as i32,
            image.height as i32,
            image.channels as i32,
        )?;
        if r.len() != TRACK_RECORD_LEN {
            return Err(VisionError::Backend(format!(
                "the tracker returned {} numbers, not {TRACK_RECORD_LEN}",
                r.len()
            )));
        }
        let (kept, error_deg, sites, kept_fraction) = (r[12] > 0.5, r[13], r[14] as usize, r[15]);
        let lost = if !kept {
            Some("the tracker gave up (too few edge sites)".to_string())
        } else if !(error_deg.is_finite() && error_deg <= self.params.max_projection_error_deg) {
            Some(format!(
                "projection error {error_deg:.1} deg over {:.1} deg",
                self.params.max_projection_error_deg
            ))
        } else if sites < self.params.min_sites {
            Some(format!("{sites} edge sites, fewer than {}", self.params.min_sites))
        } else if kept_fraction < self.params.min_kept_fraction {
            Some(format!(
                "the robust fit kept {:.0} % of the sites, under {:.0} %",
                100.0 * kept_fraction,
                100.0 * self.params.min_kept_fraction
            ))
        } else {
            None
        };
        let axis = axis_of_numbers(&r[..12]);
        let axis = match (lost, axis) {
            (Some(why), _) => {
                self.tracking = false;
                return Ok(TrackStep::Lost(why));
            }
            (None, None) => {
                self.tracking = false;
                return Ok(TrackStep::Lost(
                    "the tracked pose is not finite or behind the camera".into(),
                ));
            }
            (None, Some(a)) => a,
        };
        // The depth comes from the face's rim, f R / z px in radius: one site's pixel-level
        // error moves it by z^2 / (f R) per px (9 mm at 0.4 m for the shipped head).
        let z = axis.point.z;
        let depth_error = z * z * SITE_ERROR_PX / (self.camera.fx * self.head_radius);
        let precision = (1.0 - depth_error / DEPTH_ERROR_SCALE_M).max(0.0);
        let confidence =
            ((1.0 - error_deg / self.params.max_projection_error_deg) * kept_fraction * precision).clamp(0.0, 1.0);
        Ok(TrackStep::Tracked(TrackedPose {
            axis,
            projection_error_deg: error_deg,
            sites,
            kept_fraction,
            confidence,
        }))
    }

    /// Leave out of the edge search where `hidden` (the camera's size, row by row) is
    /// non-zero: a known occluder in view; empty: search everywhere.
    pub fn set_mask(&mut self, hidden: &[u8]) -> Result<(), VisionError> {
        ffi::model_tracker_set_mask(self.t.pin_mut(), hidden)?;
        Ok(())
    }

    /// Stop the track (the next image starts from an estimate).
    pub fn stop(&mut self) {
        self.tracking = false;
    }

    fn check(&self, image: &ImageView) -> Result<(), VisionError> {
        image.validate()?;
        if image.width != self.camera.width || image.height != self.camera.height {
            return Err(VisionError::InvalidInput(format!(
                "image {}x{} does not match the camera {} ({}x{})",
                image.width, image.height, self.camera.name, self.camera.width, self.camera.height
            )));
        }
        Ok(())
    }
}

/// A pose whose origin is the axis's point and whose z axis is its direction.
fn pose_of_axis(axis: &Axis) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(axis.point),
        UnitQuaternion::rotation_between(&Vector3::z(), &axis.direction).unwrap_or_else(|| {
            // Opposite to z: a half turn about x.
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
        }),
    )
}

/// The axis of the bridge's 12 numbers: the origin and the z axis; `None` if not finite, not
/// a rotation, or not in front of the camera.
fn axis_of_numbers(v: &[f64]) -> Option<Axis> {
    isometry_from_rt(v)
        .filter(|p| p.translation.vector.z > 0.0)
        .map(|p| Axis::of_pose(&p))
}
