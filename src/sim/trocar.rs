//! The trocar: a rigid, axisymmetric body held by the abdominal wall.
//!
//! **Geometry** (port frame P: origin at the port, the entry point on the face; z along
//! the axis, into the body). In the meridian half-plane (rho = sqrt(x^2 + y^2), z) the
//! solid is
//! ```text
//! { 0 <= z <= length,  wall(z) <= rho <= head_radius }
//! wall(z) = R_f - (R_f - r_p) z / L_f   for z < L_f      (entry funnel)
//!         = r_p                         for z >= L_f     (port bore, r_p = port_diameter / 2)
//! ```
//! so its surfaces are the face (z = 0, R_f <= rho <= head_radius), the funnel cone, the
//! bore, and the outer and bottom faces.
//!
//! **Mount**. The wall holds the trocar at its fulcrum, `pivot_depth_m` along the axis
//! (inside the wall). State: fulcrum position c, velocity v, orientation R (of frame P),
//! angular velocity w (base frame). With e = R0^T (c - c0) and theta = R0^T log(R R0^T) the
//! displacement and rotation from the rest pose (c0, R0), expressed in the rest frame:
//! ```text
//! m dv/dt = R0 ( -K e - C R0^T v ) + F_contact
//! I dw/dt = R0 ( -Kr theta - Cr R0^T w ) + sum (p - c) x F_contact
//! K = diag(k_lat, k_lat, k_ax),  Kr = diag(kr_tilt, kr_tilt, kr_twist)
//! C = 2 zeta sqrt(K m),          Cr = 2 zeta_r sqrt(Kr I)            (per axis)
//! ```
//! m and I are effective (trocar plus the tissue that moves with it; isotropic inertia).
//!
//! **Breathing** ([`Breathing`]) moves the anchor of the mount: c0(t) = c0 + R0 b(t) with
//! b(t) = (a_lat u_x, a_lat u_y, a_ax) sin(2 pi f t + phi), where f, phi and the lateral
//! direction u are drawn once per trial; the trocar follows its anchor through the mount.
//! Integration: semi-implicit Euler (velocities first, then positions; R <- exp(w h) R),
//! which keeps the energy of the undamped oscillator bounded.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::RngExt;
use serde::{Deserialize, Serialize};

use super::{check_range, SimError};

/// Geometry and mount of the trocar.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct TrocarParams {
    /// Inner diameter of the port bore, m.
    pub port_diameter_m: f64,
    /// Diameter of the entry funnel at the face, m.
    pub funnel_diameter_m: f64,
    /// Depth of the entry funnel along the axis, m.
    pub funnel_depth_m: f64,
    /// Radius of the trocar head (outer edge of the face), m.
    pub head_radius_m: f64,
    /// Length of the trocar along its axis, m.
    pub length_m: f64,
    /// Depth of the fulcrum (where the wall holds the trocar) along the axis, m.
    pub pivot_depth_m: f64,
    /// Effective moving mass, kg.
    pub mass_kg: f64,
    /// Effective moment of inertia about the fulcrum, kg m^2.
    pub inertia_kgm2: f64,
    /// Translational stiffness across the axis, N/m.
    pub k_lateral_n_per_m: f64,
    /// Translational stiffness along the axis, N/m.
    pub k_axial_n_per_m: f64,
    /// Rotational stiffness about axes across the trocar axis (tilt), Nm/rad.
    pub k_tilt_nm_per_rad: f64,
    /// Rotational stiffness about the trocar axis (twist), Nm/rad.
    pub k_twist_nm_per_rad: f64,
    /// Damping ratio of the translational modes.
    pub damping_ratio: f64,
    /// Damping ratio of the rotational modes.
    pub rot_damping_ratio: f64,
}

crate::shipped_defaults!(TrocarParams, crate::sim::SHIPPED, ["sim", "trocar"]);

impl TrocarParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("trocar.port_diameter_m", self.port_diameter_m, 1e-3, 0.05)?;
        check_range(
            "trocar.funnel_diameter_m",
            self.funnel_diameter_m,
            self.port_diameter_m,
            0.1,
        )?;
        check_range("trocar.funnel_depth_m", self.funnel_depth_m, 1e-4, 0.05)?;
        check_range(
            "trocar.head_radius_m",
            self.head_radius_m,
            self.funnel_diameter_m / 2.0 + 1e-4,
            0.2,
        )?;
        check_range("trocar.length_m", self.length_m, self.funnel_depth_m + 1e-3, 0.5)?;
        check_range("trocar.pivot_depth_m", self.pivot_depth_m, 0.0, self.length_m)?;
        check_range("trocar.mass_kg", self.mass_kg, 1e-3, 100.0)?;
        check_range("trocar.inertia_kgm2", self.inertia_kgm2, 1e-7, 10.0)?;
        check_range("trocar.k_lateral_n_per_m", self.k_lateral_n_per_m, 0.0, 1e6)?;
        check_range("trocar.k_axial_n_per_m", self.k_axial_n_per_m, 0.0, 1e6)?;
        check_range("trocar.k_tilt_nm_per_rad", self.k_tilt_nm_per_rad, 0.0, 1e4)?;
        check_range("trocar.k_twist_nm_per_rad", self.k_twist_nm_per_rad, 0.0, 1e4)?;
        check_range("trocar.damping_ratio", self.damping_ratio, 0.0, 10.0)?;
        check_range("trocar.rot_damping_ratio", self.rot_damping_ratio, 0.0, 10.0)
    }

    /// Radius of the port bore, m.
    pub fn port_radius(&self) -> f64 {
        self.port_diameter_m / 2.0
    }

    /// Inner wall radius at depth `z` (funnel, then bore).
    pub fn wall_radius(&self, z: f64) -> f64 {
        let rf = self.funnel_diameter_m / 2.0;
        let rp = self.port_radius();
        if z < self.funnel_depth_m {
            rf - (rf - rp) * (z / self.funnel_depth_m).max(0.0)
        } else {
            rp
        }
    }

    /// The corners of the meridian profile (rho, z): face outer edge, funnel mouth, bore
    /// top, bore bottom, bottom outer edge; consecutive corners are the surfaces, and
    /// (head_radius, length) closes the outer face back to the first corner.
    pub fn profile(&self) -> [[f64; 2]; 5] {
        let rf = self.funnel_diameter_m / 2.0;
        let rp = self.port_radius();
        [
            [self.head_radius_m, 0.0],
            [rf, 0.0],
            [rp, self.funnel_depth_m],
            [rp, self.length_m],
            [self.head_radius_m, self.length_m],
        ]
    }
}

/// Breathing: the abdominal wall, and the trocar's mount with it, moves periodically.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct BreathingParams {
    /// Amplitude along the trocar axis, m (0 = no breathing).
    pub amplitude_axial_m: f64,
    /// Amplitude across the axis (in a random direction per trial), m.
    pub amplitude_lateral_m: f64,
    /// Range of the breathing frequency, Hz (drawn uniformly per trial).
    pub frequency_hz: [f64; 2],
}

crate::shipped_defaults!(BreathingParams, crate::sim::SHIPPED, ["sim", "breathing"]);

impl BreathingParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("breathing.amplitude_axial_m", self.amplitude_axial_m, 0.0, 0.05)?;
        check_range("breathing.amplitude_lateral_m", self.amplitude_lateral_m, 0.0, 0.05)?;
        check_range("breathing.frequency_hz[0]", self.frequency_hz[0], 0.01, 5.0)?;
        check_range(
            "breathing.frequency_hz[1]",
            self.frequency_hz[1],
            self.frequency_hz[0],
            5.0,
        )
    }
}

/// One trial's breathing: frequency, phase and lateral direction drawn once.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Breathing {
    /// Frequency, Hz.
    pub frequency_hz: f64,
    /// Phase at t = 0, rad.
    pub phase: f64,
    /// Peak displacement of the anchor in the trocar's rest frame, m.
    pub amplitude: Vector3<f64>,
}

impl Breathing {
    /// Draw a trial's breathing.
    pub fn sample(p: &BreathingParams, rng: &mut impl rand::Rng) -> Self {
        let [f0, f1] = p.frequency_hz;
        let frequency_hz = if f1 > f0 { rng.random_range(f0..=f1) } else { f0 };
        let phase = rng.random_range(0.0..std::f64::consts::TAU);
        let dir = rng.random_range(0.0..std::f64::consts::TAU);
        let lat = p.amplitude_lateral_m;
        Self {
            frequency_hz,
            phase,
            amplitude: Vector3::new(lat * dir.cos(), lat * dir.sin(), p.amplitude_axial_m),
        }
    }

    /// The anchor's displacement at time `t`, in the trocar's rest frame, m.
    pub fn offset(&self, t: f64) -> Vector3<f64> {
        self.amplitude * (std::f64::consts::TAU * self.frequency_hz * t + self.phase).sin()
    }
}

/// How far the trocar is from its rest pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Deviation {
    /// Distance of the fulcrum from its anchor, m.
    pub shift_m: f64,
    /// Tilt angle from rest, rad.
    pub tilt_rad: f64,
}

/// State of the compliantly mounted trocar.
#[derive(Debug, Clone, PartialEq)]
pub struct Trocar {
    params: TrocarParams,
    rest: Isometry3<f64>,
    k_lin: Vector3<f64>,
    c_lin: Vector3<f64>,
    k_rot: Vector3<f64>,
    c_rot: Vector3<f64>,
    c: Point3<f64>,
    v: Vector3<f64>,
    r: UnitQuaternion<f64>,
    w: Vector3<f64>,
    /// Displacement of the mount's anchor (breathing), rest frame.
    anchor: Vector3<f64>,
}

impl Trocar {
    /// A trocar at rest with its port at `rest` (base frame; z into the body).
    pub fn new(params: &TrocarParams, rest: &Isometry3<f64>) -> Result<Self, SimError> {
        params.validate()?;
        if !(rest.translation.vector.iter().all(|x| x.is_finite())
            && rest.rotation.coords.iter().all(|x| x.is_finite()))
        {
            return Err(SimError::Input("trocar rest pose is not finite".into()));
        }
        let p = params;
        let k_lin = Vector3::new(p.k_lateral_n_per_m, p.k_lateral_n_per_m, p.k_axial_n_per_m);
        let k_rot = Vector3::new(p.k_tilt_nm_per_rad, p.k_tilt_nm_per_rad, p.k_twist_nm_per_rad);
        let c_lin = k_lin.map(|k| 2.0 * p.damping_ratio * (k * p.mass_kg).sqrt());
        let c_rot = k_rot.map(|k| 2.0 * p.rot_damping_ratio * (k * p.inertia_kgm2).sqrt());
        let c = rest * Point3::new(0.0, 0.0, p.pivot_depth_m);
        Ok(Self {
            params: p.clone(),
            rest: *rest,
            k_lin,
            c_lin,
            k_rot,
            c_rot,
            c,
            v: Vector3::zeros(),
            r: rest.rotation,
            w: Vector3::zeros(),
            anchor: Vector3::zeros(),
        })
    }

    /// The parameters.
    pub fn params(&self) -> &TrocarParams {
        &self.params
    }

    /// Move the mount's anchor by `d` from its rest (rest frame): breathing.
    pub fn set_anchor_offset(&mut self, d: &Vector3<f64>) {
        self.anchor = *d;
    }

    /// The current pose of the port (frame P) in the base frame.
    pub fn pose(&self) -> Isometry3<f64> {
        let origin = self.c - self.r * Vector3::new(0.0, 0.0, self.params.pivot_depth_m);
        Isometry3::from_parts(Translation3::from(origin.coords), self.r)
    }

    /// The fulcrum position (base frame).
    pub fn pivot(&self) -> Point3<f64> {
        self.c
    }

    /// Where the wall holds the fulcrum at rest: the mount's anchor, moving with the
    /// breathing (base frame). The trocar's fulcrum sits here when nothing pushes it.
    pub fn anchor(&self) -> Point3<f64> {
        self.rest * Point3::new(0.0, 0.0, self.params.pivot_depth_m) + self.rest.rotation * self.anchor
    }

    /// Velocity of the body point `p` (base frame).
    pub fn point_velocity(&self, p: &Point3<f64>) -> Vector3<f64> {
        self.v + self.w.cross(&(p - self.c))
    }

    /// Displacement of the fulcrum from its (breathing) anchor and rotation vector from the
    /// rest pose, in the rest frame.
    fn deflection(&self) -> (Vector3<f64>, Vector3<f64>) {
        let r0 = self.rest.rotation;
        let c0 = self.rest * Point3::new(0.0, 0.0, self.params.pivot_depth_m);
        let e = r0.inverse_transform_vector(&(self.c - c0)) - self.anchor;
        let th = r0.inverse_transform_vector(&(self.r * r0.inverse()).scaled_axis());
        (e, th)
    }

    /// Spring-damper force and torque of the mount (base frame).
    fn mount_wrench(&self) -> (Vector3<f64>, Vector3<f64>) {
        let r0 = self.rest.rotation;
        let (e, th) = self.deflection();
        let vl = r0.inverse_transform_vector(&self.v);
        let wl = r0.inverse_transform_vector(&self.w);
        let f = -self.k_lin.component_mul(&e) - self.c_lin.component_mul(&vl);
        let t = -self.k_rot.component_mul(&th) - self.c_rot.component_mul(&wl);
        (r0 * f, r0 * t)
    }

    /// Advance by `h` seconds under an external force `f` and torque `tau` about the
    /// fulcrum (base frame).
    pub fn step(&mut self, h: f64, f: &Vector3<f64>, tau: &Vector3<f64>) {
        let (fm, tm) = self.mount_wrench();
        self.v += (fm + f) * (h / self.params.mass_kg);
        self.w += (tm + tau) * (h / self.params.inertia_kgm2);
        self.c += self.v * h;
        self.r = UnitQuaternion::from_scaled_axis(self.w * h) * self.r;
    }

    /// Mechanical energy (kinetic + spring), J.
    pub fn energy(&self) -> f64 {
        let (e, th) = self.deflection();
        let ke =
            0.5 * self.params.mass_kg * self.v.norm_squared() + 0.5 * self.params.inertia_kgm2 * self.w.norm_squared();
        let pe = 0.5 * e.dot(&self.k_lin.component_mul(&e)) + 0.5 * th.dot(&self.k_rot.component_mul(&th));
        ke + pe
    }

    /// How far the trocar is from its rest pose.
    pub fn deviation(&self) -> Deviation {
        let (e, _) = self.deflection();
        Deviation {
            shift_m: e.norm(),
            tilt_rad: self.r.angle_to(&self.rest.rotation),
        }
    }

    /// Place the trocar at a displaced state (tests).
    #[cfg(test)]
    pub fn set_state(&mut self, dc: &Vector3<f64>, drot: &Vector3<f64>, v: &Vector3<f64>, w: &Vector3<f64>) {
        self.c = self.rest * Point3::new(0.0, 0.0, self.params.pivot_depth_m) + dc;
        self.r = UnitQuaternion::from_scaled_axis(*drot) * self.rest.rotation;
        self.v = *v;
        self.w = *w;
    }

    /// True when the state is finite.
    pub fn is_finite(&self) -> bool {
        self.c
            .coords
            .iter()
            .chain(self.v.iter())
            .chain(self.w.iter())
            .all(|x| x.is_finite())
            && self.r.coords.iter().all(|x| x.is_finite())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tilted() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(0.6, 0.05, 0.25),
            UnitQuaternion::from_scaled_axis(Vector3::new(std::f64::consts::PI - 0.3, 0.1, 0.0)),
        )
    }

    #[test]
    fn wall_radius_profile() {
        let p = TrocarParams::default();
        assert!((p.wall_radius(0.0) - 0.008).abs() < 1e-12);
        assert!((p.wall_radius(0.005) - 0.00575).abs() < 1e-12);
        assert!((p.wall_radius(0.05) - 0.0035).abs() < 1e-12);
    }

    #[test]
    fn free_swing_energy_does_not_grow() {
        let p = TrocarParams {
            damping_ratio: 0.0,
            rot_damping_ratio: 0.0,
            ..Default::default()
        };
        let mut t = Trocar::new(&p, &tilted()).unwrap();
        t.set_state(
            &Vector3::new(0.004, -0.002, 0.003),
            &Vector3::new(0.05, -0.03, 0.02),
            &Vector3::new(0.0, 0.02, 0.0),
            &Vector3::new(0.3, 0.0, -0.2),
        );
        let e0 = t.energy();
        let mut emax: f64 = 0.0;
        for _ in 0..50_000 {
            t.step(2e-4, &Vector3::zeros(), &Vector3::zeros());
            emax = emax.max(t.energy());
        }
        assert!(emax <= e0 * 1.02, "energy grew from {e0} to {emax}");
        assert!(
            t.energy() > 0.9 * e0,
            "undamped swing lost energy: {} of {e0}",
            t.energy()
        );

        // With damping, the energy only decays.
        let mut d = Trocar::new(&TrocarParams::default(), &tilted()).unwrap();
        d.set_state(
            &Vector3::new(0.004, 0.0, 0.0),
            &Vector3::new(0.05, 0.0, 0.0),
            &Vector3::zeros(),
            &Vector3::zeros(),
        );
        // The discrete energy wiggles within a step; its peak over each 50 ms window falls.
        let e0 = d.energy();
        let mut prev_peak = e0;
        for _ in 0..20 {
            let mut peak: f64 = 0.0;
            for _ in 0..250 {
                d.step(2e-4, &Vector3::zeros(), &Vector3::zeros());
                peak = peak.max(d.energy());
            }
            assert!(peak <= prev_peak * 1.01 + 1e-15, "{peak} > {prev_peak}");
            prev_peak = peak;
        }
        assert!(d.energy() < 1e-3 * e0);
    }

    #[test]
    fn breathing_moves_the_port_with_its_amplitude_and_frequency() {
        use rand::SeedableRng;
        let p = BreathingParams {
            amplitude_axial_m: 0.005,
            amplitude_lateral_m: 0.001,
            frequency_hz: [0.2, 0.3],
        };
        let b = Breathing::sample(&p, &mut rand_chacha::ChaCha8Rng::seed_from_u64(2));
        assert!((0.2..=0.3).contains(&b.frequency_hz));
        let rest = tilted();
        let mut t = Trocar::new(&TrocarParams::default(), &rest).unwrap();
        let axis = rest.rotation * Vector3::z();
        let (h, n) = (1e-3, 20_000);
        let mut along = Vec::with_capacity(n);
        for k in 0..n {
            t.set_anchor_offset(&b.offset(k as f64 * h));
            t.step(h, &Vector3::zeros(), &Vector3::zeros());
            along.push((t.pose().translation.vector - rest.translation.vector).dot(&axis));
        }
        // After the first breath, the port swings by the axial amplitude along the axis
        // (the mount's 9 Hz mode follows a 0.25 Hz anchor within a fraction of a percent).
        let tail = &along[5000..];
        let (lo, hi) = tail
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
        assert!(((hi - lo) / 2.0 - 0.005).abs() < 1e-4, "amplitude {}", (hi - lo) / 2.0);
        // Rising zero crossings are one period apart.
        let ups: Vec<usize> = (1..tail.len())
            .filter(|&i| tail[i - 1] < 0.0 && tail[i] >= 0.0)
            .collect();
        assert!(ups.len() >= 2, "{ups:?}");
        let period = (ups[1] - ups[0]) as f64 * h;
        assert!((period * b.frequency_hz - 1.0).abs() < 0.01, "period {period} s");
    }

    #[test]
    fn static_force_deflects_by_force_over_stiffness() {
        let p = TrocarParams::default();
        let rest = tilted();
        let mut t = Trocar::new(&p, &rest).unwrap();
        // 2 N along the axis at the fulcrum (no torque): deflection 2 / k_axial.
        let f = rest.rotation * Vector3::new(0.0, 0.0, 2.0);
        for _ in 0..20_000 {
            t.step(2e-4, &f, &Vector3::zeros());
        }
        let Deviation {
            shift_m: d,
            tilt_rad: tilt,
        } = t.deviation();
        assert!((d - 2.0 / p.k_axial_n_per_m).abs() < 1e-5, "{d}");
        assert!(tilt < 1e-9);
        let port = t.pose().translation.vector - rest.translation.vector;
        assert!((port - f / p.k_axial_n_per_m).norm() < 1e-5);
    }
}
