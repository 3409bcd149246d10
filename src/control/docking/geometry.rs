//! Task geometry of docking: the insertion axis and the points along it.
//!
//! The trocar pose (in the robot base frame) has its origin at the port, the entry point on
//! the trocar's face, and its z axis along the insertion direction, pointing into the body.
//! Along that axis lie the stand-off point (outside the body, where the tip lines up before
//! it enters) and the goal (past the port, at the insertion depth).

use nalgebra::{Isometry3, Point3, Unit, Vector3};

/// The insertion axis of a trocar and the points of the docking task on it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InsertionAxis {
    /// The port: entry point on the trocar's face, base frame, m.
    pub port: Point3<f64>,
    /// Unit insertion direction, into the body.
    pub direction: Unit<Vector3<f64>>,
}

impl InsertionAxis {
    /// The axis of a trocar pose (origin = port, z = insertion direction).
    pub fn from_pose(pose: &Isometry3<f64>) -> Self {
        Self {
            port: Point3::from(pose.translation.vector),
            direction: Unit::new_unchecked(pose.rotation * Vector3::z()),
        }
    }

    /// The point at signed distance `s` along the axis from the port (positive: into the body).
    pub fn point_at(&self, s: f64) -> Point3<f64> {
        self.port + self.direction.into_inner() * s
    }

    /// Signed distance of the projection of `p` on the axis from the port (insertion depth).
    pub fn depth_of(&self, p: &Point3<f64>) -> f64 {
        (p - self.port).dot(&self.direction)
    }

    /// The point of the axis nearest to `p` (the paper's n(g_a)).
    pub fn nearest_point(&self, p: &Point3<f64>) -> Point3<f64> {
        self.point_at(self.depth_of(p))
    }

    /// The component of `p - port` across the axis (zero on the axis).
    pub fn lateral_offset(&self, p: &Point3<f64>) -> Vector3<f64> {
        across(&self.direction, &(p - self.port))
    }

    /// Distance from `p` to the axis line, m.
    pub fn distance_to_axis(&self, p: &Point3<f64>) -> f64 {
        self.lateral_offset(p).norm()
    }

    /// Angle between an optical axis `a` and the insertion direction, rad (0 = aligned).
    pub fn alignment_error(&self, a: &Vector3<f64>) -> f64 {
        let n = a.norm();
        if !(n.is_finite() && n > 0.0) {
            return f64::NAN;
        }
        (a.dot(&self.direction) / n).clamp(-1.0, 1.0).acos()
    }

    /// Project `v` across the axis (remove its component along the axis).
    pub fn across(&self, v: &Vector3<f64>) -> Vector3<f64> {
        across(&self.direction, v)
    }

    /// Whether the axis is usable: finite port and a unit direction.
    pub fn is_finite(&self) -> bool {
        self.port.coords.iter().all(|x| x.is_finite()) && (self.direction.norm() - 1.0).abs() < 1e-6
    }
}

/// The component of `v` across the unit direction `a`: `v - a (a . v)`, the projection on
/// the plane normal to `a` (zero for `v` along `a`).
pub fn across(a: &Vector3<f64>, v: &Vector3<f64>) -> Vector3<f64> {
    v - a * v.dot(a)
}

/// Distance of `p` from the line through `origin` along the unit direction `a`, m: the one
/// point-to-line distance (the shaft's from the port, the axis's from the tip).
pub fn distance_to_line(p: &Point3<f64>, origin: &Point3<f64>, a: &Vector3<f64>) -> f64 {
    across(a, &(p - origin)).norm()
}

/// Whether a pose has only finite entries and a unit quaternion.
pub fn pose_is_finite(p: &Isometry3<f64>) -> bool {
    p.translation.vector.iter().all(|x| x.is_finite())
        && p.rotation.coords.iter().all(|x| x.is_finite())
        && (p.rotation.coords.norm() - 1.0).abs() < 1e-6
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn tilted() -> InsertionAxis {
        let pose = Isometry3::from_parts(
            Translation3::new(0.6, 0.1, 0.3),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI + 0.3),
        );
        InsertionAxis::from_pose(&pose)
    }

    #[test]
    fn points_and_distances() {
        let ax = tilted();
        // Pointing mostly down, tilted by 0.3 rad.
        assert!((ax.direction.z + 0.3f64.cos()).abs() < 1e-12);
        let g = ax.point_at(0.03);
        assert!((ax.depth_of(&g) - 0.03).abs() < 1e-12);
        assert!(ax.distance_to_axis(&g) < 1e-12);
        let side = g + ax.direction.cross(&Vector3::x()).normalize() * 0.004;
        assert!((ax.distance_to_axis(&side) - 0.004).abs() < 1e-12);
        assert!((ax.nearest_point(&side) - g).norm() < 1e-12);
        assert!(ax.lateral_offset(&side).dot(&ax.direction).abs() < 1e-12);
        assert!(ax.alignment_error(&ax.direction.into_inner()) < 1e-7);
        assert!((ax.alignment_error(&-ax.direction.into_inner()) - std::f64::consts::PI).abs() < 1e-7);
        assert!(ax.alignment_error(&Vector3::zeros()).is_nan());
        assert!(ax.is_finite());
    }
}
