//! The projective geometry of the markerless estimator, in undistorted normalised camera
//! coordinates (x/z, y/z): a circle's image conic and the two circle poses an ellipse
//! admits, and the outline (limbs) of a cylinder.

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, SymmetricEigen, Unit, UnitQuaternion, Vector2, Vector3};

/// The trocar's axis in the camera frame: the port centre and the unit direction into the body.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Axis {
    /// Port centre, m.
    pub point: Vector3<f64>,
    /// Unit direction of the axis, into the body (away from the camera that sees the face).
    pub direction: Unit<Vector3<f64>>,
}

impl Axis {
    /// The axis of a port pose: its origin and its z axis.
    pub fn of_pose(pose: &Isometry3<f64>) -> Axis {
        Axis {
            point: pose.translation.vector,
            direction: Unit::new_normalize(pose.rotation * Vector3::z()),
        }
    }

    /// Angle between the two axes' directions, rad.
    pub fn angle_to(&self, other: &Axis) -> f64 {
        self.direction.dot(&other.direction).clamp(-1.0, 1.0).acos()
    }

    /// A point on the axis `t` metres from the port, into the body.
    pub fn at(&self, t: f64) -> Vector3<f64> {
        self.point + t * self.direction.into_inner()
    }

    /// The same axis in another frame: `b_t_a` maps this axis's frame `a` into `b`.
    pub fn transformed(&self, b_t_a: &Isometry3<f64>) -> Axis {
        Axis {
            point: (b_t_a * Point3::from(self.point)).coords,
            direction: b_t_a.rotation * self.direction,
        }
    }
}

/// Two unit vectors completing `n` to a right-handed orthonormal basis (u, v, n).
pub fn basis(n: &Unit<Vector3<f64>>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if n.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let u = n.cross(&helper).normalize();
    let v = n.cross(&u);
    (u, v)
}

/// The image conic (normalised coordinates) of the circle of radius `r` centred at `c`
/// with normal `n`: p^T C p < 0 inside, > 0 outside, for p = (x, y, 1).
pub fn circle_conic(c: &Vector3<f64>, n: &Unit<Vector3<f64>>, r: f64) -> Option<Matrix3<f64>> {
    let (u, v) = basis(n);
    let h = Matrix3::from_columns(&[r * u, r * v, *c]);
    let hi = h.try_inverse()?;
    let d = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0));
    let m = hi.transpose() * d * hi;
    // The sign of p^T C p follows the plane's: keep "inside < 0" for points in front.
    Some(0.5 * (m + m.transpose()))
}

/// First-order (Sampson) distance of the point `p` (normalised) to the conic `c`, signed
/// (> 0 outside), in normalised units.
pub fn conic_distance(c: &Matrix3<f64>, p: &Vector2<f64>) -> f64 {
    let h = Vector3::new(p.x, p.y, 1.0);
    let cp = c * h;
    let e = h.dot(&cp);
    let g = 2.0 * Vector2::new(cp.x, cp.y);
    e / g.norm().max(1e-15)
}

/// The unit outward normal of the conic at `p` (the gradient of p^T C p).
pub fn conic_normal(c: &Matrix3<f64>, p: &Vector2<f64>) -> Vector2<f64> {
    let cp = c * Vector3::new(p.x, p.y, 1.0);
    Vector2::new(cp.x, cp.y).normalize()
}

/// The conic (normalised coordinates) of an ellipse given in undistorted pixels: centre,
/// semi-axes `a`, `b`, angle of `a` (rad), for the intrinsics fx, fy, cx, cy.
pub fn ellipse_conic(centre: [f64; 2], a: f64, b: f64, angle: f64, k: [f64; 4]) -> Matrix3<f64> {
    let (s, co) = angle.sin_cos();
    // Ellipse frame q = R^T (p - centre).
    let t = Matrix3::new(
        co,
        s,
        -(co * centre[0] + s * centre[1]),
        -s,
        co,
        s * centre[0] - co * centre[1],
        0.0,
        0.0,
        1.0,
    );
    let d = Matrix3::from_diagonal(&Vector3::new(1.0 / (a * a), 1.0 / (b * b), -1.0));
    let kmat = Matrix3::new(k[0], 0.0, k[2], 0.0, k[1], k[3], 0.0, 0.0, 1.0);
    let c = kmat.transpose() * t.transpose() * d * t * kmat;
    c / c.norm()
}

/// The two poses of a circle of radius `r` whose image is the conic `c` (the classic
/// two-fold ambiguity), each with its normal pointing away from the camera. `None` when
/// the conic is not the image of a circle in front of the camera (not an ellipse).
pub fn circle_poses(c: &Matrix3<f64>, r: f64) -> Option<[Axis; 2]> {
    let q = 0.5 * (c + c.transpose());
    let mut eig = SymmetricEigen::new(q);
    if eig.eigenvalues.iter().filter(|l| **l > 0.0).count() == 1 {
        eig.eigenvalues = -eig.eigenvalues;
    }
    if eig.eigenvalues.iter().filter(|l| **l > 0.0).count() != 2 {
        return None;
    }
    // Order l1 >= l2 > 0 > l3.
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]));
    let l: Vec<f64> = idx.iter().map(|&i| eig.eigenvalues[i]).collect();
    let e: Vec<Vector3<f64>> = idx.iter().map(|&i| eig.eigenvectors.column(i).into_owned()).collect();
    let (l1, l2, l3) = (l[0], l[1], l[2]);
    if !(l2 > 0.0 && l3 < 0.0) {
        return None;
    }
    // Q - l2 I factors into two planes; their normals cut the cone in circles.
    let a = ((l1 - l2) / (l1 - l3)).max(0.0).sqrt();
    let b = ((l2 - l3) / (l1 - l3)).max(0.0).sqrt();
    let mut out = [Axis {
        point: Vector3::zeros(),
        direction: Vector3::z_axis(),
    }; 2];
    for (k, sign) in [1.0, -1.0].into_iter().enumerate() {
        let n = Unit::new_normalize(a * e[0] + sign * b * e[2]);
        out[k] = section_circle(&q, n, r)?;
    }
    Some(out)
}

/// The circle where the plane with normal `n` cuts the cone `q`, scaled to radius `r`,
/// its normal turned away from the camera.
fn section_circle(q: &Matrix3<f64>, n: Unit<Vector3<f64>>, r: f64) -> Option<Axis> {
    let (u, v) = basis(&n);
    let h = Matrix3::from_columns(&[u, v, n.into_inner()]);
    let m = h.transpose() * q * h;
    let alpha = 0.5 * (m[(0, 0)] + m[(1, 1)]);
    if alpha.abs() < 1e-300 {
        return None;
    }
    let bvec = Vector2::new(m[(0, 2)], m[(1, 2)]);
    let st = -bvec / alpha;
    let r1sq = (bvec.norm_squared() / alpha - m[(2, 2)]) / alpha;
    if !(r1sq > 0.0 && r1sq.is_finite()) {
        return None;
    }
    let x0 = n.into_inner() + st.x * u + st.y * v;
    let k = r / r1sq.sqrt();
    // The plane n.X = 1 may lie behind the camera: the cone is symmetric, take -X.
    let (centre, normal) = if x0.z >= 0.0 { (k * x0, n) } else { (-k * x0, -n) };
    if centre.z.is_nan() || centre.z <= 0.0 {
        return None;
    }
    Some(Axis {
        point: centre,
        direction: normal,
    })
}

/// The two limb lines (outline) of the cylinder of radius `radius` about `axis`, between
/// `t0` and `t1` along it: each as its two end points. `None` when the camera is inside
/// the cylinder's radius.
pub fn cylinder_limbs(axis: &Axis, radius: f64, t0: f64, t1: f64) -> Option<[[Vector3<f64>; 2]; 2]> {
    let n = axis.direction.into_inner();
    let c = axis.point;
    let w0 = -c + c.dot(&n) * n;
    let rho = w0.norm();
    if rho.is_nan() || rho <= radius * 1.0001 {
        return None;
    }
    let w0 = w0 / rho;
    let side = n.cross(&w0);
    let (ca, sa) = (radius / rho, (1.0 - (radius / rho).powi(2)).sqrt());
    let mut out = [[Vector3::zeros(); 2]; 2];
    for (k, s) in [1.0, -1.0].into_iter().enumerate() {
        let w = ca * w0 + s * sa * side;
        out[k] = [c + t0 * n + radius * w, c + t1 * n + radius * w];
    }
    Some(out)
}

/// The normalised image point of a camera-frame point (`None` behind the camera).
pub fn project(p: &Vector3<f64>) -> Option<Vector2<f64>> {
    (p.z > 1e-9).then(|| Vector2::new(p.x / p.z, p.y / p.z))
}

/// `pose` with its origin and z axis kept and its roll about z set by the convention of
/// the markerless estimator (x = base x projected normal to z; base y when z is within 25 deg of base x).
pub fn with_roll_convention(pose: &Isometry3<f64>) -> Isometry3<f64> {
    let z = pose.rotation * Vector3::z();
    Isometry3::from_parts(pose.translation, rotation_of_axis(&Unit::new_normalize(z)))
}

/// The rotation whose z axis is `z`, with the roll of the convention.
pub(super) fn rotation_of_axis(z: &Unit<Vector3<f64>>) -> UnitQuaternion<f64> {
    let helper = if z.x.abs() < 25f64.to_radians().cos() {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let x = (helper - z.dot(&helper) * z.into_inner()).normalize();
    let y = z.cross(&x);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[
        x,
        y,
        z.into_inner(),
    ])))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn circle_points(axis: &Axis, r: f64, n: usize) -> Vec<Vector2<f64>> {
        let (u, v) = basis(&axis.direction);
        (0..n)
            .map(|k| {
                let phi = std::f64::consts::TAU * k as f64 / n as f64;
                project(&(axis.point + r * (phi.cos() * u + phi.sin() * v))).unwrap()
            })
            .collect()
    }

    #[test]
    fn a_circle_is_recovered_from_its_conic_up_to_the_two_fold_ambiguity() {
        let truth = Axis {
            point: Vector3::new(0.03, -0.02, 0.25),
            direction: Unit::new_normalize(Vector3::new(0.2, 0.35, 1.0)),
        };
        let r = 0.008;
        let c = circle_conic(&truth.point, &truth.direction, r).unwrap();
        for p in circle_points(&truth, r, 12) {
            assert!(conic_distance(&c, &p).abs() < 1e-12);
        }
        assert!(conic_distance(&c, &project(&truth.point).unwrap()) < 0.0);
        let sols = circle_poses(&c, r).unwrap();
        let best = sols
            .iter()
            .min_by(|a, b| a.angle_to(&truth).total_cmp(&b.angle_to(&truth)))
            .unwrap();
        assert!((best.point - truth.point).norm() < 1e-9, "{best:?}");
        assert!(best.angle_to(&truth) < 1e-7);
        // The other solution images to the same conic, its normal also away from the camera.
        for s in &sols {
            assert!(s.direction.dot(&s.point) > 0.0);
            for p in circle_points(s, r, 8) {
                assert!(conic_distance(&c, &p).abs() < 1e-9);
            }
        }
        assert!(sols[0].angle_to(&sols[1]) > 0.1);
    }

    #[test]
    fn the_pixel_ellipse_conic_matches_the_circle_conic() {
        let k = [700.0, 700.0, 640.0, 360.0];
        let c = ellipse_conic([700.0, 300.0], 30.0, 20.0, 0.4, k);
        let (s, co) = 0.4f64.sin_cos();
        for phi in [0.0, 1.0, 2.5, 4.0] {
            let (x, y) = (30.0 * f64::cos(phi), 20.0 * f64::sin(phi));
            let px = [700.0 + co * x - s * y, 300.0 + s * x + co * y];
            let p = Vector2::new((px[0] - k[2]) / k[0], (px[1] - k[3]) / k[1]);
            assert!(conic_distance(&c, &p).abs() * 700.0 < 1e-9);
        }
        assert!(circle_poses(&c, 0.008).is_some());
        // A frontal circle: both solutions along the optical axis, at r / (r/d).
        let frontal = circle_poses(&Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -0.01)), 0.01).unwrap();
        assert!((frontal[0].point - Vector3::new(0.0, 0.0, 0.1)).norm() < 1e-12);
        assert!((frontal[1].direction.z - 1.0).abs() < 1e-12);
        // A cone about the x axis images no circle in front of the camera.
        assert!(circle_poses(&Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0)), 0.01).is_none());
        assert!(circle_poses(&Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, 1.0)), 0.01).is_none());
    }

    #[test]
    fn limbs_touch_the_cylinder_tangentially() {
        let axis = Axis {
            point: Vector3::new(0.01, 0.02, 0.3),
            direction: Unit::new_normalize(Vector3::new(0.0, 0.4, 1.0)),
        };
        let limbs = cylinder_limbs(&axis, 0.0125, 0.0, 0.025).unwrap();
        for l in &limbs {
            for p in l {
                let off = p - axis.point;
                let radial = off - off.dot(&axis.direction) * axis.direction.into_inner();
                assert!((radial.norm() - 0.0125).abs() < 1e-12);
                // The ray to the point is tangent: perpendicular to the radial direction.
                assert!(p.dot(&radial).abs() < 1e-12);
            }
        }
        let inside = Axis {
            point: Vector3::new(0.0, 0.0, 0.3),
            direction: Vector3::z_axis(),
        };
        assert!(cylinder_limbs(&inside, 0.01, 0.0, 0.02).is_none());
    }
}
