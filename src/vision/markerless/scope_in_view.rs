//! The endoscope seen in view corrects the hand-eye (pure Rust).
//!
//! The camera and the endoscope ride on the same flange, so the shaft's place in the camera's
//! frame is fixed, and where the hand-eye puts it differs from where the camera sees it by the
//! hand-eye's error. The stereo pair sees the shaft's axis as a line in space (each eye's
//! outline gives the plane through that eye's centre and the axis; the two planes meet in the
//! axis, [`stereo_axis`]). The rigid motion taking the axis where the hand-eye puts it onto
//! the axis seen, [`ScopeInView::camera_t_believed`], is the hand-eye's error in four of its
//! six degrees of freedom: the axis's direction and its place across it. What it cannot tell
//! are the two motions that carry the axis onto itself: a roll about it (which moves nothing
//! on it) and a slide along it, which moves the tip, and so the depth the controller believes,
//! by the error's share along the shaft: that share stays.
//!
//! What it corrects is the port's place across the shaft and the axis's direction as the
//! controller sees them relative to the tip: a hand-eye error of 2 mm and 1 deg puts the port
//! up to about 4 mm beside the shaft's axis at the tip and tilts the axis by up to 1 deg.
//!
//! Robust and bounded: each frame's axis is kept in a window of the last
//! [`SCOPE_WINDOW`] frames and the correction is their median, component by component, once
//! [`SCOPE_MIN_FRAMES`] are in; an axis more than [`SCOPE_MAX_OFFSET_M`] or
//! [`SCOPE_MAX_ANGLE_DEG`] from where the hand-eye puts it is not the shaft (or the hand-eye
//! is too far off to correct: recalibrate) and is left out. No allocation per frame.

use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};

use super::render::ToolCylinder;

/// Frames whose median is the correction.
pub const SCOPE_WINDOW: usize = 15;
/// Frames needed before the correction applies (before: the hand-eye as it is).
pub const SCOPE_MIN_FRAMES: usize = 3;
/// The largest offset of the axis seen from where the hand-eye puts it, at the tip, m.
pub const SCOPE_MAX_OFFSET_M: f64 = 0.006;
/// The largest angle between the axis seen and where the hand-eye puts it, deg.
pub const SCOPE_MAX_ANGLE_DEG: f64 = 3.0;

/// The shaft's axis where two eyes see it: the line where the plane through the left
/// camera's centre (the origin) of unit normal `left` meets the plane through the right
/// camera's centre `right_origin` (left frame) of unit normal `right` (left frame): its point
/// nearest `near` and its direction. `None` when the planes meet at under 5 deg (the line is
/// not well defined).
pub fn stereo_axis(
    left: &Vector3<f64>,
    right: &Vector3<f64>,
    right_origin: &Vector3<f64>,
    near: &Vector3<f64>,
) -> Option<(Vector3<f64>, Unit<Vector3<f64>>)> {
    let d = left.cross(right);
    if d.norm() < 5f64.to_radians().sin() {
        return None;
    }
    let d = Unit::new_normalize(d);
    // x = near + a left + b right on both planes: left . x = 0, right . x = right . o.
    let c = left.dot(right);
    let (r0, r1) = (-left.dot(near), right.dot(right_origin) - right.dot(near));
    let det = 1.0 - c * c;
    let (a, b) = ((r0 - c * r1) / det, (r1 - c * r0) / det);
    let p = near + a * left + b * right;
    p.iter().all(|v| v.is_finite()).then_some((p, d))
}

/// The hand-eye's error as the endoscope in view tells it (see the module doc).
#[derive(Debug, Clone)]
pub struct ScopeInView {
    /// The shaft's tip where the hand-eye puts it (camera frame).
    tip: Vector3<f64>,
    /// The shaft's direction where the hand-eye puts it, from the tip back.
    direction: Unit<Vector3<f64>>,
    /// Per frame: the seen axis's point nearest the predicted tip minus the tip, and the
    /// seen direction.
    window: [[f64; 6]; SCOPE_WINDOW],
    len: usize,
    next: usize,
    camera_t_believed: Isometry3<f64>,
}

impl ScopeInView {
    /// The correction for the endoscope `shaft` where the hand-eye puts it (the camera's
    /// frame; `start` its tip): none yet.
    pub fn new(shaft: &ToolCylinder) -> Option<Self> {
        let tip = Vector3::from(shaft.start);
        let direction = Unit::try_new(Vector3::from(shaft.end) - tip, 1e-9)?;
        Some(Self {
            tip,
            direction,
            window: [[0.0; 6]; SCOPE_WINDOW],
            len: 0,
            next: 0,
            camera_t_believed: Isometry3::identity(),
        })
    }

    /// Add one frame's axis seen (a point on it and its direction, the camera's frame):
    /// `false` when it is left out (too far from where the hand-eye puts the shaft, or not
    /// finite).
    pub fn add(&mut self, point: &Vector3<f64>, direction: &Unit<Vector3<f64>>) -> bool {
        let d = if direction.dot(&self.direction) < 0.0 {
            -direction.into_inner()
        } else {
            direction.into_inner()
        };
        // The seen axis's point nearest the predicted tip.
        let foot = point + d * (self.tip - point).dot(&d);
        let offset = foot - self.tip;
        let ok = offset.iter().chain(d.iter()).all(|v| v.is_finite())
            && offset.norm() <= SCOPE_MAX_OFFSET_M
            && d.angle(&self.direction) <= SCOPE_MAX_ANGLE_DEG.to_radians();
        if !ok {
            return false;
        }
        self.window[self.next] = [offset.x, offset.y, offset.z, d.x, d.y, d.z];
        self.next = (self.next + 1) % SCOPE_WINDOW;
        self.len = (self.len + 1).min(SCOPE_WINDOW);
        self.update();
        true
    }

    /// Frames in the window.
    pub fn frames(&self) -> usize {
        self.len
    }

    /// The correction: the believed camera frame's points in the true camera's frame (the
    /// rigid motion taking the shaft where the hand-eye puts it onto where it is seen,
    /// rotating about the tip and moving across the axis, not along it); the identity until
    /// [`SCOPE_MIN_FRAMES`] frames are in. The camera's true pose is the believed one times
    /// its inverse.
    pub fn camera_t_believed(&self) -> Isometry3<f64> {
        self.camera_t_believed
    }

    fn update(&mut self) {
        if self.len >= SCOPE_MIN_FRAMES {
            self.camera_t_believed = self.median_correction();
        }
    }

    /// The correction the medians make.
    fn median_correction(&self) -> Isometry3<f64> {
        let mut m = [0.0; 6];
        for (k, out) in m.iter_mut().enumerate() {
            let mut col = [0.0; SCOPE_WINDOW];
            for (c, w) in col.iter_mut().zip(&self.window[..self.len]) {
                *c = w[k];
            }
            *out = crate::stats::upper_median_in_place(&mut col[..self.len]);
        }
        let (offset, seen) = (Vector3::new(m[0], m[1], m[2]), Vector3::new(m[3], m[4], m[5]));
        let seen = seen.try_normalize(1e-12).unwrap_or(self.direction.into_inner());
        // The camera turned about its centre by the least rotation that gives the shaft the
        // seen direction, then moved across the seen axis (not along it) onto it.
        let rot = UnitQuaternion::rotation_between(&self.direction, &seen).unwrap_or_else(UnitQuaternion::identity);
        let (foot, turned) = (self.tip + offset, rot * self.tip);
        let onto = foot + seen * (turned - foot).dot(&seen);
        Translation3::from(onto - turned) * rot
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shaft() -> ToolCylinder {
        ToolCylinder {
            start: [0.0, 0.06, 0.22],
            end: [0.0, -0.0, -0.02],
            radius: 0.0025,
        }
    }

    /// The plane through `origin` and the line (point, direction): its unit normal.
    fn plane(origin: &Vector3<f64>, p: &Vector3<f64>, d: &Vector3<f64>) -> Vector3<f64> {
        (p - origin).cross(d).normalize()
    }

    #[test]
    fn two_eyes_planes_meet_in_the_axis_and_parallel_planes_give_none() {
        let (p, d) = (
            Vector3::new(0.003, 0.06, 0.2),
            Vector3::new(0.01, -0.1, -1.0).normalize(),
        );
        let o = Vector3::new(0.063, 0.0, 0.0);
        let (l, r) = (plane(&Vector3::zeros(), &p, &d), plane(&o, &p, &d));
        let near = Vector3::new(0.0, 0.06, 0.22);
        let (q, e) = stereo_axis(&l, &r, &o, &near).unwrap();
        // On the axis, and its point nearest `near`.
        assert!((q - p).cross(&d).norm() < 1e-9);
        assert!((q - near).dot(&d).abs() < 1e-9);
        assert!(e.cross(&d).norm() < 1e-9);
        assert!(stereo_axis(&l, &l, &o, &near).is_none());
    }

    #[test]
    fn the_correction_carries_the_believed_shaft_onto_the_seen_one_turning_about_the_camera_centre() {
        let s = shaft();
        let (tip, back) = (Vector3::from(s.start), Vector3::from(s.end));
        // A hand-eye error: the true camera sees the believed frame's points moved by this.
        let err = Isometry3::new(
            Vector3::new(0.0012, -0.0008, 0.0015),
            Vector3::new(0.012, -0.006, 0.004),
        );
        let (t, b) = (err * nalgebra::Point3::from(tip), err * nalgebra::Point3::from(back));
        let dir = Unit::new_normalize(b - t);
        let mut scope = ScopeInView::new(&s).unwrap();
        assert!(scope.add(&t.coords, &dir));
        assert!(scope.add(&t.coords, &dir));
        // Not yet: the hand-eye as it is.
        assert_eq!(scope.camera_t_believed(), Isometry3::identity());
        // A wrong line (another edge) is left out; the median stands on the rest.
        assert!(!scope.add(&(t.coords + Vector3::new(0.02, 0.0, 0.0)), &dir));
        assert!(!scope.add(&(t.coords + Vector3::new(f64::NAN, 0.0, 0.0)), &dir));
        assert!(scope.add(&t.coords, &dir));
        assert_eq!(scope.frames(), 3);
        let c = scope.camera_t_believed();
        // The corrected shaft lies on the seen axis, parallel to it.
        let (ct, cb) = (c * nalgebra::Point3::from(tip), c * nalgebra::Point3::from(back));
        assert!((ct - t).cross(&dir).norm() < 1e-9, "{}", (ct - t).cross(&dir).norm());
        assert!((cb - ct).normalize().cross(&dir).norm() < 1e-9);
        // Along the axis, the tip moved by the turn's share only (the camera turned about its
        // centre): what the centre's own error along the shaft slid it by stays.
        let turn = err.rotation * nalgebra::Point3::from(tip) - nalgebra::Point3::from(tip);
        let moved = (ct - nalgebra::Point3::from(tip)).dot(&dir);
        assert!((moved - turn.dot(&dir)).abs() < 1e-6, "{moved} vs {}", turn.dot(&dir));
        let unseen = err.translation.vector.dot(&dir);
        assert!(
            unseen.abs() > 1e-4,
            "the test's error slides the centre along the shaft"
        );
        assert!(((t - nalgebra::Point3::from(tip)).dot(&dir) - moved - unseen).abs() < 1e-6);
    }

    #[test]
    fn the_median_stands_on_the_shaft_when_a_few_frames_are_off() {
        let s = shaft();
        let tip = Vector3::from(s.start);
        let dir = Unit::new_normalize(Vector3::from(s.end) - tip);
        let mut scope = ScopeInView::new(&s).unwrap();
        let seen = tip + Vector3::new(0.001, 0.0, 0.0);
        for k in 0..SCOPE_WINDOW {
            // Every fifth frame on a wrong edge 4 mm off (inside the gate).
            let p = if k % 5 == 0 {
                seen + Vector3::new(0.004, 0.0, 0.0)
            } else {
                seen
            };
            assert!(scope.add(&p, &dir));
        }
        let c = scope.camera_t_believed();
        assert!(((c * nalgebra::Point3::from(tip)).coords - seen).norm() < 1e-9);
    }
}
