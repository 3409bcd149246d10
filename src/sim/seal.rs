//! The cannula's seal: axial friction on the shaft while it passes the seal, with static
//! friction (stick) and a lower kinetic friction (slip), so that a compliant drive (the
//! abdominal wall holding the trocar, the arm's joints) shows stick–slip.
//!
//! The seal lip is an elastic element of stiffness k between the trocar and the shaft,
//! deflected by z along the trocar axis; v is the axial velocity of the shaft relative to
//! the trocar (positive = inserting). Per sub-step h:
//! ```text
//! stuck:    z <- z + v h;        F = k z + b v;   slip when |k z| > F_s
//! slipping: F = F_k sign(v) + b v;  z = F_k sign(v) / k;  stick when |v| < v_stick
//! ```
//! F is the force the seal exerts on the trocar (along +axis for F > 0); the shaft
//! feels -F. The shaft engages the seal while its tip is deeper than `depth_m` along the
//! axis and it passes through the bore; out of the seal, z = 0 and the lip is stuck.
//! This is a reset-integrator friction model (Haessig & Friedland 1991, J. Dyn. Sys.
//! Meas. Control 113:354): a stiff pre-sliding spring below breakaway, Coulomb friction
//! above it.

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use super::contact::ShaftMotion;
use super::trocar::Trocar;
use super::{check_range, SimError};

/// Parameters of the seal (all zero friction = no seal).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct SealParams {
    /// Depth of the seal along the trocar axis, m.
    pub depth_m: f64,
    /// Breakaway (static) friction, N (0 = no seal).
    pub static_friction_n: f64,
    /// Kinetic friction while slipping, N (<= static).
    pub kinetic_friction_n: f64,
    /// Stiffness of the lip before it slips, N/m.
    pub lip_stiffness_n_per_m: f64,
    /// Viscous friction, N s/m.
    pub viscous_ns_per_m: f64,
    /// Below this relative speed a slipping seal sticks again, m/s.
    pub stick_velocity_m_s: f64,
}

crate::shipped_defaults!(SealParams, crate::sim::SHIPPED, ["sim", "seal"]);

impl SealParams {
    /// Check the values.
    pub fn validate(&self) -> Result<(), SimError> {
        check_range("seal.depth_m", self.depth_m, 0.0, 0.5)?;
        check_range("seal.static_friction_n", self.static_friction_n, 0.0, 100.0)?;
        check_range(
            "seal.kinetic_friction_n",
            self.kinetic_friction_n,
            0.0,
            self.static_friction_n,
        )?;
        check_range("seal.lip_stiffness_n_per_m", self.lip_stiffness_n_per_m, 1.0, 1e7)?;
        check_range("seal.viscous_ns_per_m", self.viscous_ns_per_m, 0.0, 1e4)?;
        check_range("seal.stick_velocity_m_s", self.stick_velocity_m_s, 1e-6, 1.0)
    }

    /// True when the seal exerts any friction.
    pub fn active(&self) -> bool {
        self.static_friction_n > 0.0 || self.viscous_ns_per_m > 0.0
    }
}

/// The seal's state: lip deflection and stick/slip mode.
#[derive(Debug, Clone, PartialEq)]
pub struct Seal {
    params: SealParams,
    z: f64,
    stuck: bool,
    force: f64,
    breakaways: u32,
}

impl Seal {
    /// A relaxed seal (no shaft in it).
    pub fn new(params: &SealParams) -> Result<Self, SimError> {
        params.validate()?;
        Ok(Self {
            params: params.clone(),
            z: 0.0,
            stuck: true,
            force: 0.0,
            breakaways: 0,
        })
    }

    /// Advance the lip by `h` seconds at relative axial shaft velocity `v` (the shaft in
    /// the seal) and return F, the axial force on the trocar (the shaft feels -F).
    pub fn step_axial(&mut self, v: f64, h: f64) -> f64 {
        let p = &self.params;
        let k = p.lip_stiffness_n_per_m;
        if self.stuck {
            self.z += v * h;
            if (k * self.z).abs() > p.static_friction_n {
                self.stuck = false;
                self.breakaways += 1;
            }
        }
        let f = if self.stuck {
            k * self.z + p.viscous_ns_per_m * v
        } else if v.abs() < p.stick_velocity_m_s {
            self.stuck = true;
            self.z = self.z.clamp(-p.kinetic_friction_n / k, p.kinetic_friction_n / k);
            k * self.z + p.viscous_ns_per_m * v
        } else {
            self.z = p.kinetic_friction_n.copysign(v) / k;
            p.kinetic_friction_n.copysign(v) + p.viscous_ns_per_m * v
        };
        self.force = f;
        f
    }

    /// Release the lip (the shaft left the seal).
    pub fn release(&mut self) {
        self.z = 0.0;
        self.stuck = true;
        self.force = 0.0;
    }

    /// True while the lip sticks to the shaft.
    pub fn stuck(&self) -> bool {
        self.stuck
    }

    /// How many times the lip broke away (stick to slip) so far.
    pub fn breakaways(&self) -> u32 {
        self.breakaways
    }

    /// The last axial force on the trocar, N.
    pub fn force(&self) -> f64 {
        self.force
    }

    /// The seal's force on the shaft for the motion `m` over `h` seconds, as (force on the
    /// arm, point of application on the shaft), base frame; None when the shaft is not
    /// in the seal (or there is no seal).
    pub fn evaluate(&mut self, m: &ShaftMotion, trocar: &Trocar, h: f64) -> Option<(Vector3<f64>, Point3<f64>)> {
        if !self.params.active() {
            return None;
        }
        let port = trocar.pose();
        let tip = Point3::from(m.tip.translation.vector);
        let tip_l = port.inverse_transform_point(&tip);
        let bore = trocar.params().wall_radius(self.params.depth_m);
        if tip_l.z <= self.params.depth_m || tip_l.x.hypot(tip_l.y) > bore {
            self.release();
            return None;
        }
        let axis = port.rotation * Vector3::z();
        let shaft = m.tip.rotation * Vector3::z();
        // The shaft point at the seal's depth (the shaft runs along its optical axis).
        let back = (tip_l.z - self.params.depth_m) / shaft.dot(&axis).max(0.1);
        let point = tip - shaft * back;
        let v_rel = m.v + m.w.cross(&(point - tip)) - trocar.point_velocity(&point);
        let f = self.step_axial(v_rel.dot(&axis), h);
        Some((-axis * f, point))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seal() -> Seal {
        Seal::new(&SealParams {
            static_friction_n: 2.5,
            kinetic_friction_n: 1.5,
            ..Default::default()
        })
        .unwrap()
    }

    /// A 0.2 kg shaft in the seal pushed by an axial force ramped to `force` over 0.5 s,
    /// then held for 0.5 s; returns its travel and the largest friction force.
    fn push(s: &mut Seal, force: f64) -> (f64, f64) {
        let (m, h) = (0.2, 1e-4);
        let (mut x, mut v, mut fmax) = (0.0, 0.0, 0.0f64);
        for i in 0..10_000 {
            let push = force * (i as f64 / 5000.0).min(1.0);
            let f = s.step_axial(v, h);
            fmax = fmax.max(f.abs());
            v += (push - f) / m * h;
            x += v * h;
        }
        (x, fmax)
    }

    #[test]
    fn static_friction_holds_below_breakaway_and_slips_above() {
        // 2 N < 2.5 N breakaway: the lip deflects (force / k = 0.4 mm) and holds.
        let mut s = seal();
        let (x, fmax) = push(&mut s, 2.0);
        assert!(s.stuck());
        assert!(x.abs() < 2.0 / 5000.0 * 1.3 + 1e-6, "moved {x}");
        assert!(fmax < 2.5 + 1e-9);
        // 3 N > 2.5 N: breakaway after 0.42 s, then it slides against the 1.5 N kinetic
        // friction, accelerating at (3 - 1.5) / 0.2 = 7.5 m/s^2 once the ramp ends.
        let mut s = seal();
        let (x, fmax) = push(&mut s, 3.0);
        assert!(!s.stuck());
        assert!(x > 0.5, "moved {x}");
        assert!(fmax <= 2.5 + 0.1 && (s.force() - 1.5).abs() < 1e-9);
    }

    #[test]
    fn a_compliant_drive_sticks_and_slips() {
        // A drive at 10 mm/s through a 500 N/m spring (the abdominal wall) on the shaft:
        // the spring force saws between the breakaway and below the kinetic friction.
        let mut s = seal();
        let (m, h, k_drive, v_drive) = (0.2, 1e-4, 500.0, 0.01);
        let (mut x, mut v, mut slips, mut was_stuck) = (0.0, 0.0, 0, true);
        for i in 0..40_000 {
            let drive = k_drive * (v_drive * i as f64 * h - x) - 2.0 * v;
            let f = s.step_axial(v, h);
            v += (drive - f) / m * h;
            x += v * h;
            if was_stuck && !s.stuck() {
                slips += 1;
            }
            was_stuck = s.stuck();
        }
        assert!(slips >= 3, "{slips} slips in 4 s");
    }

    #[test]
    fn bad_parameters_are_rejected() {
        let bad = SealParams {
            static_friction_n: 1.0,
            kinetic_friction_n: 2.0,
            ..Default::default()
        };
        assert!(Seal::new(&bad).is_err());
    }
}
