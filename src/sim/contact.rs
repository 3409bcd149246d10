//! Contact between the endoscope shaft and the trocar: a penalty model with damping and
//! regularised Coulomb friction.
//!
//! The shaft (diameter d_s, the last `shaft_length_m` before the tip) is a chain of spheres
//! of radius r_s = d_s / 2 whose centres lie on the optical axis, `sphere_spacing_m` apart;
//! the first centre is r_s behind the tip, so the rounded end reaches the tip exactly.
//! Each sphere is tested against the trocar's axisymmetric solid ([`TrocarParams::profile`]):
//! with d the signed distance of its centre to the solid (negative inside) and n the
//! outward surface normal at the closest surface point Q,
//! ```text
//! depth   delta = r_s - d                      (contact when delta > 0)
//! normal  f_n   = max(0, k delta - c (v_rel . n))
//! tangent f_t   = -mu f_n v_t / sqrt(|v_t|^2 + v_s^2)      v_t = v_rel - (v_rel . n) n
//! ```
//! where v_rel is the velocity of the shaft point minus that of the trocar point at Q, and
//! v_s the slip velocity of the regularisation. The contact's stiffness against the tip's
//! motion (a small twist [dx; dθ] of the shaft changes the wrench on it by -K_c [dx; dθ]) is
//! K_c = sum k g g^T with g = [n; (Q - tip) x n] over the spheres in contact: the deflection
//! of the arm's joints is integrated implicitly in it ([`super::arm`]). The force f = f_n n + f_t acts on the
//! shaft at Q and -f on the trocar. Summed over spheres: the force F on the arm and its
//! moment M about the tip, which make the external joint torques tau = J^T [F; M]
//! (the point Jacobian of Q is J_v - [Q - tip]x J_w, so J_Q^T f = J_v^T f + J_w^T ((Q - tip) x f)).

use nalgebra::{Isometry3, Matrix6, Point3, Vector2, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use super::trocar::{Trocar, TrocarParams};
use super::{check_range, SimError};

/// Parameters of the shaft and the contact law.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct ContactParams {
    /// Penalty stiffness per sphere, N/m.
    pub stiffness_n_per_m: f64,
    /// Penalty damping per sphere, N s/m.
    pub damping_ns_per_m: f64,
    /// Coulomb friction coefficient (steel on polymer).
    pub friction: f64,
    /// Slip velocity of the friction regularisation, m/s.
    pub slip_velocity_m_s: f64,
    /// Shaft diameter, m.
    pub shaft_diameter_m: f64,
    /// Length of shaft behind the tip that can touch the trocar, m.
    pub shaft_length_m: f64,
    /// Spacing of the spheres along the shaft, m.
    pub sphere_spacing_m: f64,
}

crate::shipped_defaults!(ContactParams, crate::sim::SHIPPED, ["sim", "contact"]);

impl ContactParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("contact.stiffness_n_per_m", self.stiffness_n_per_m, 1.0, 1e7)?;
        check_range("contact.damping_ns_per_m", self.damping_ns_per_m, 0.0, 1e4)?;
        check_range("contact.friction", self.friction, 0.0, 2.0)?;
        check_range("contact.slip_velocity_m_s", self.slip_velocity_m_s, 1e-6, 1.0)?;
        check_range("contact.shaft_diameter_m", self.shaft_diameter_m, 1e-4, 0.05)?;
        check_range("contact.shaft_length_m", self.shaft_length_m, 0.0, 1.0)?;
        check_range(
            "contact.sphere_spacing_m",
            self.sphere_spacing_m,
            1e-4,
            self.shaft_diameter_m,
        )
    }
}

/// Motion of the shaft: tip pose and twist (base frame, linear velocity at the tip).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShaftMotion {
    /// Tip pose; its z axis is the shaft axis, pointing out of the tip.
    pub tip: Isometry3<f64>,
    /// Linear velocity of the tip, m/s.
    pub v: Vector3<f64>,
    /// Angular velocity, rad/s.
    pub w: Vector3<f64>,
}

/// Summed contact forces of one evaluation (base frame).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ContactWrench {
    /// Force on the arm, N.
    pub force: Vector3<f64>,
    /// Moment on the arm about the tip, Nm.
    pub moment: Vector3<f64>,
    /// Force on the trocar, N.
    pub trocar_force: Vector3<f64>,
    /// Torque on the trocar about its fulcrum, Nm.
    pub trocar_torque: Vector3<f64>,
    /// Spheres in contact.
    pub contacts: usize,
    /// Deepest penetration, m.
    pub max_depth: f64,
    /// The normal stiffness against the tip's motion (module doc), [N/m, N/rad; N, Nm/rad].
    pub stiffness: Matrix6<f64>,
}

impl ContactWrench {
    /// Add the force `f` on the arm acting at the point `q` (base frame): its moment about
    /// the arm's `tip`, and the reaction -f on the trocar with its torque about `pivot`.
    pub fn add_point_force(&mut self, f: &Vector3<f64>, q: &Point3<f64>, tip: &Point3<f64>, pivot: &Point3<f64>) {
        self.force += f;
        self.moment += (q - tip).cross(f);
        self.trocar_force -= f;
        self.trocar_torque -= (q - pivot).cross(f);
    }
}

/// A sphere-vs-trocar contact in the port frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalContact {
    /// Penetration depth, m (> 0).
    pub depth: f64,
    /// Outward normal of the trocar surface (port frame).
    pub normal: Vector3<f64>,
    /// Closest surface point (port frame).
    pub point: Point3<f64>,
}

/// The contact model: shaft spheres and the trocar profile, built once.
#[derive(Debug, Clone)]
pub struct ContactModel {
    params: ContactParams,
    radius: f64,
    /// Distances of the sphere centres behind the tip.
    offsets: Vec<f64>,
    /// Profile segments (a, b, outward normal) in the meridian plane (rho, z).
    segments: [(Vector2<f64>, Vector2<f64>, Vector2<f64>); 5],
    trocar: TrocarParams,
}

impl ContactModel {
    /// Build the model for a shaft and a trocar.
    pub fn new(params: &ContactParams, trocar: &TrocarParams) -> Result<Self, SimError> {
        params.validate()?;
        trocar.validate()?;
        let radius = params.shaft_diameter_m / 2.0;
        let n = (params.shaft_length_m / params.sphere_spacing_m).floor() as usize + 1;
        let offsets = (0..n).map(|i| radius + i as f64 * params.sphere_spacing_m).collect();
        let c = trocar.profile().map(|[r, z]| Vector2::new(r, z));
        // Walking the corners in order, the solid lies on the right: the outward normal is
        // the left normal (-dz, drho) of each directed segment.
        let seg = |i: usize, j: usize| {
            let d = c[j] - c[i];
            (c[i], c[j], Vector2::new(-d.y, d.x).normalize())
        };
        let segments = [seg(0, 1), seg(1, 2), seg(2, 3), seg(3, 4), seg(4, 0)];
        Ok(Self {
            params: params.clone(),
            radius,
            offsets,
            segments,
            trocar: trocar.clone(),
        })
    }

    fn inside(&self, rho: f64, z: f64) -> bool {
        z >= 0.0 && z <= self.trocar.length_m && rho >= self.trocar.wall_radius(z) && rho <= self.trocar.head_radius_m
    }

    /// Contact of a sphere of the shaft radius centred at `c` (port frame), if any.
    pub fn sphere_contact(&self, c: &Point3<f64>) -> Option<LocalContact> {
        let r = self.radius;
        let t = &self.trocar;
        let rho = (c.x * c.x + c.y * c.y).sqrt();
        if c.z < -r || c.z > t.length_m + r || rho > t.head_radius_m + r {
            return None;
        }
        let p = Vector2::new(rho, c.z);
        let mut best = (f64::INFINITY, Vector2::zeros(), Vector2::zeros());
        for (a, b, n) in &self.segments {
            let ab = b - a;
            let s = ((p - a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0);
            let q = a + ab * s;
            let d = (p - q).norm();
            if d < best.0 {
                best = (d, q, *n);
            }
        }
        let (d, q, seg_n) = best;
        let inside = self.inside(rho, c.z);
        let signed = if inside { -d } else { d };
        let depth = r - signed;
        if depth <= 0.0 {
            return None;
        }
        let n2 = if d > 1e-12 {
            let u = (p - q) / d;
            if inside {
                -u
            } else {
                u
            }
        } else {
            seg_n
        };
        let (ux, uy) = if rho > 1e-12 {
            (c.x / rho, c.y / rho)
        } else {
            (1.0, 0.0)
        };
        Some(LocalContact {
            depth,
            normal: Vector3::new(n2.x * ux, n2.x * uy, n2.y),
            point: Point3::new(q.x * ux, q.x * uy, q.y),
        })
    }

    /// Contact forces for the shaft motion `m` against the trocar in its current state.
    pub fn evaluate(&self, m: &ShaftMotion, trocar: &Trocar) -> ContactWrench {
        let mut out = ContactWrench::default();
        let port = trocar.pose();
        let tip_l = port.inverse_transform_point(&Point3::from(m.tip.translation.vector));
        let axis = m.tip.rotation * Vector3::z();
        let axis_l = port.inverse_transform_vector(&axis);
        // Quick reject: the whole shaft segment is away from the trocar's bounding box.
        let r = self.radius;
        let far = self.offsets.last().copied().unwrap_or(0.0);
        let back_l = tip_l - axis_l * far;
        let t = &self.trocar;
        let lim = t.head_radius_m + r;
        if (tip_l.z < -r && back_l.z < -r)
            || (tip_l.z > t.length_m + r && back_l.z > t.length_m + r)
            || (tip_l.x > lim && back_l.x > lim)
            || (tip_l.x < -lim && back_l.x < -lim)
            || (tip_l.y > lim && back_l.y > lim)
            || (tip_l.y < -lim && back_l.y < -lim)
        {
            return out;
        }
        let tip = Point3::from(m.tip.translation.vector);
        let pivot = trocar.pivot();
        let p = &self.params;
        for &s in &self.offsets {
            let c = tip_l - axis_l * s;
            let Some(lc) = self.sphere_contact(&c) else {
                continue;
            };
            let q = port * lc.point;
            let n = port * lc.normal;
            let v_rel = m.v + m.w.cross(&(q - tip)) - trocar.point_velocity(&q);
            let vn = v_rel.dot(&n);
            let fn_ = (p.stiffness_n_per_m * lc.depth - p.damping_ns_per_m * vn).max(0.0);
            let vt = v_rel - n * vn;
            let ft = vt * (-p.friction * fn_ / (vt.norm_squared() + p.slip_velocity_m_s * p.slip_velocity_m_s).sqrt());
            out.add_point_force(&(n * fn_ + ft), &q, &tip, &pivot);
            let rn = (q - tip).cross(&n);
            let g = Vector6::new(n.x, n.y, n.z, rn.x, rn.y, rn.z);
            out.stiffness += g * g.transpose() * p.stiffness_n_per_m;
            out.contacts += 1;
            out.max_depth = out.max_depth.max(lc.depth);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn model() -> ContactModel {
        ContactModel::new(&ContactParams::default(), &TrocarParams::default()).unwrap()
    }

    fn trocar() -> Trocar {
        Trocar::new(&TrocarParams::default(), &Isometry3::identity()).unwrap()
    }

    /// Tip at `p` (port frame = base frame here), shaft along `axis`.
    fn motion(p: Vector3<f64>, axis: Vector3<f64>, v: Vector3<f64>) -> ShaftMotion {
        let rot = UnitQuaternion::rotation_between(&Vector3::z(), &axis).unwrap_or_else(UnitQuaternion::identity);
        ShaftMotion {
            tip: Isometry3::from_parts(Translation3::from(p), rot),
            v,
            w: Vector3::zeros(),
        }
    }

    #[test]
    fn pressing_into_the_face_gives_stiffness_times_depth() {
        let m = model();
        let k = ContactParams::default().stiffness_n_per_m;
        for depth in [0.0005, 0.001, 0.002] {
            // Tip 12 mm off axis (on the face, outside the 8 mm funnel), pushed `depth` past it.
            let w = m.evaluate(
                &motion(Vector3::new(0.012, 0.0, depth), Vector3::z(), Vector3::zeros()),
                &trocar(),
            );
            assert_eq!(w.contacts, 1);
            assert!(
                (w.force - Vector3::new(0.0, 0.0, -k * depth)).norm() < 1e-9 * k,
                "{:?}",
                w.force
            );
            assert!((w.trocar_force + w.force).norm() < 1e-12);
            assert!((w.max_depth - depth).abs() < 1e-12);
        }
        // Just short of the face: no contact.
        let w = m.evaluate(
            &motion(Vector3::new(0.012, 0.0, -1e-4), Vector3::z(), Vector3::zeros()),
            &trocar(),
        );
        assert_eq!(w.contacts, 0);
        assert_eq!(w.force, Vector3::zeros());
    }

    #[test]
    fn centred_shaft_in_the_bore_is_free_and_off_centre_is_pushed_back() {
        let m = model();
        let w = m.evaluate(
            &motion(Vector3::new(0.0, 0.0, 0.03), Vector3::z(), Vector3::zeros()),
            &trocar(),
        );
        assert_eq!(w.contacts, 0);
        // 1.5 mm off centre in a 3.5 mm bore with a 2.5 mm shaft: 0.5 mm into the wall.
        let w = m.evaluate(
            &motion(Vector3::new(0.0015, 0.0, 0.03), Vector3::z(), Vector3::zeros()),
            &trocar(),
        );
        assert!(w.contacts > 1);
        assert!(w.force.x < 0.0 && w.force.y.abs() < 1e-9 && w.force.z.abs() < 1e-9);
        assert!((w.max_depth - 0.0005).abs() < 1e-9);
    }

    #[test]
    fn funnel_pushes_outward_and_back() {
        let m = model();
        // Tip in the funnel, off-axis in +x: the cone pushes it toward the axis and back out.
        let w = m.evaluate(
            &motion(Vector3::new(0.006, 0.0, 0.004), Vector3::z(), Vector3::zeros()),
            &trocar(),
        );
        assert!(w.contacts >= 1);
        assert!(w.force.x < 0.0 && w.force.z < 0.0, "{:?}", w.force);
    }

    #[test]
    fn friction_opposes_sliding_and_is_bounded_by_mu() {
        let m = model();
        let p = ContactParams::default();
        let v = Vector3::new(0.02, -0.01, 0.0);
        let w = m.evaluate(&motion(Vector3::new(0.012, 0.0, 0.001), Vector3::z(), v), &trocar());
        let ft = Vector3::new(w.force.x, w.force.y, 0.0);
        let fnrm = -w.force.z;
        assert!(ft.dot(&v) < 0.0, "friction {ft:?} does not oppose sliding {v:?}");
        assert!((ft.normalize() + v.normalize()).norm() < 1e-9);
        assert!(ft.norm() <= p.friction * fnrm + 1e-12);
        assert!(ft.norm() > 0.9 * p.friction * fnrm);
    }

    #[test]
    fn moment_about_the_tip_matches_point_of_application() {
        let m = model();
        // Shaft across the bore top, tilted: contacts behind the tip create a moment.
        let axis = Vector3::new(0.3, 0.0, 1.0).normalize();
        let w = m.evaluate(&motion(Vector3::new(0.0, 0.0, 0.03), axis, Vector3::zeros()), &trocar());
        assert!(w.contacts > 0);
        // The force on the arm and on the trocar balance; the moment is non-trivial.
        assert!((w.force + w.trocar_force).norm() < 1e-12);
        assert!(w.moment.norm() > 1e-4);
    }

    /// The realistic world's 5.5 mm cannula (0.25 mm of clearance for the 5 mm shaft) at
    /// the origin, with the default contact.
    fn cannula_5_5_mm() -> (ContactModel, Trocar) {
        let tp = TrocarParams {
            port_diameter_m: 0.0055,
            ..Default::default()
        };
        let m = ContactModel::new(&ContactParams::default(), &tp).unwrap();
        (m, Trocar::new(&tp, &Isometry3::identity()).unwrap())
    }

    /// K_c is the wrench's derivative: a small twist of a shaft pressed into the bore's side
    /// (at rest, so no damping or friction) changes the wrench on it by -K_c
    /// times the twist, within the surface's curvature (second order at micrometre depths).
    #[test]
    fn the_contact_stiffness_is_the_wrench_derivative() {
        let (m, t) = cannula_5_5_mm();
        // 30 mm deep, 5 um into the bore's side (0.25 mm clearance) along its length.
        let axis = Vector3::z();
        let tip = Vector3::new(0.000255, 0.0, 0.03);
        let w0 = m.evaluate(&motion(tip, axis, Vector3::zeros()), &t);
        assert!(
            w0.contacts >= 2 && w0.max_depth < 2e-5,
            "{} {}",
            w0.contacts,
            w0.max_depth
        );
        let wrench =
            |w: &ContactWrench| Vector6::new(w.force.x, w.force.y, w.force.z, w.moment.x, w.moment.y, w.moment.z);
        for twist in [
            Vector6::new(1e-6, 0.0, 0.0, 0.0, 0.0, 0.0),
            Vector6::new(0.0, 0.0, 0.0, 0.0, 2e-5, 0.0),
            Vector6::new(-5e-7, 3e-7, 0.0, 1e-5, -1e-5, 0.0),
        ] {
            let dx = Vector3::new(twist[0], twist[1], twist[2]);
            let rot = UnitQuaternion::from_scaled_axis(Vector3::new(twist[3], twist[4], twist[5]));
            let w1 = m.evaluate(&motion(tip + dx, rot * axis, Vector3::zeros()), &t);
            assert_eq!(w1.contacts, w0.contacts);
            let got = wrench(&w1) - wrench(&w0);
            let want = -w0.stiffness * twist;
            assert!((got - want).norm() < 0.05 * want.norm(), "{got} vs {want}");
        }
        // Out of contact: no stiffness.
        let free = m.evaluate(
            &motion(Vector3::new(0.0, 0.0, 0.03), Vector3::z(), Vector3::zeros()),
            &t,
        );
        assert_eq!(free.stiffness, Matrix6::zeros());
    }

    /// The mount answers the shaft's lever: a shaft tilted in the bore about a point above
    /// the trocar's fulcrum presses the bore as a couple, which turns the trocar (force and
    /// moment both reach the body) the way the shaft leans, against its tilt spring.
    #[test]
    fn a_shaft_levered_in_the_bore_turns_the_trocar_with_it() {
        let (m, mut t) = cannula_5_5_mm();
        // Tip 30 mm deep, the shaft turned 3 deg about y through the point 20 mm deep: it
        // presses the bore at its top (10 mm) and at the tip.
        let deg = 3f64.to_radians();
        let lean = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), deg);
        let axis = lean * Vector3::z();
        let tip = Vector3::new(0.0, 0.0, 0.02) + axis * 0.01;
        let w = m.evaluate(&motion(tip, axis, Vector3::zeros()), &t);
        assert!(w.contacts >= 2, "{}", w.contacts);
        assert!((w.force + w.trocar_force).norm() < 1e-12);
        // A moment about the fulcrum, the way the shaft leans (about +y), besides the force.
        assert!(w.trocar_torque.y > 0.05, "{:?}", w.trocar_torque);
        // Held there, the trocar turns the way the shaft leans (and slides) until the bore
        // is free.
        for _ in 0..20_000 {
            let w = m.evaluate(&motion(tip, axis, Vector3::zeros()), &t);
            t.step(1e-4, &w.trocar_force, &w.trocar_torque);
        }
        let trocar_axis = t.pose().rotation * Vector3::z();
        let turned = trocar_axis.angle(&Vector3::z());
        assert!(trocar_axis.x > 0.0 && turned > 0.2 * deg, "{turned} rad");
        assert!(turned < deg, "{turned} rad");
    }
}
