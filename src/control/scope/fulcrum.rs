//! The fulcrum's adaptation after docking: where the wall pushes, the port is.
//!
//! The remote centre of motion starts on the shaft line at the estimated port plus a prior
//! depth along the shaft (the abdominal wall holds the trocar some centimetres below its
//! face). Two laws move it from the force across the shaft, f_⊥ (the controller's filtered
//! tip-force estimate with its component along the shaft removed, then a dead-band):
//!
//! - **across the shaft**, a first-order admittance of the fulcrum point,
//!   D ẋ + K x = f_⊥, |x| <= x_max: a wall that pushes the shaft sideways (the port moved
//!   with breathing, or the scope pivots about a point beside the port) moves the fulcrum,
//!   and with it the scope, the way it pushes. K (shipped 0: the wall is the spring) pulls x
//!   back to zero; without it a force estimate's bias moves the fulcrum until the wall
//!   pushes back as hard (bias / the wall's stiffness), within x_max. While no command comes the
//!   scope holds still: the law is then D ẋ = f_⊥ with a larger dead-band, so that only a
//!   wall pushing harder than the estimate's drift (or the wall settling after a motion)
//!   moves it;
//! - **along the shaft**, the fulcrum's depth s (past the port) by a gradient law on the
//!   lever: pivoting by an angle θ about a point δ short of the true fulcrum moves the
//!   shaft there by δ θ x a and the wall pushes back, f_⊥ = -k δ (θ x a). So with the
//!   commanded angular velocity ω of the pan and tilt (known exactly) and
//!   u = (ω x a) / |ω|: ṡ = -γ f_⊥ · u, which is zero when the scope pivots about the
//!   point where the wall holds it, and does nothing while the scope does not pivot (a
//!   force then says nothing about the depth). s stays between 0 (the port) and the tip's
//!   depth (the wall can only push where there is shaft).
//!
//! **The rate bound.** Both the lateral admittance and the depth's yield along the shaft
//! ([`FulcrumParams::axial_yield`]) are integrators of a force that reaches them late: the
//! arm follows its command about 20 ms behind (a position-mode joint servo), the torques
//! are low-passed (5 ms), the force again at 5 Hz (32 ms), and the law acts a control
//! period later. Against a contact of stiffness k such a loop has the gain k / D per
//! second; with D = 50 N s/m it crosses over near 70 rad/s against k = 8000 N/m, where
//! those lags take more than the 90 deg of phase the integrator leaves (the 5 Hz low-pass
//! alone 66 deg, the servo about 70, the period 40): it rings and grows (measured: a pan with the tip
//! caught at 8000 N/m, the force oscillating at about 16 Hz, 8 -> 28 N in 0.4 s, the
//! fulcrum swinging 1-8 mm across and 23-31 mm in depth with it). No damping serves both
//! the wall (1500 N/m, which the fulcrum must follow) and a caught tip (10^4-10^5 N/m).
//! What bounds the damage is the speed: the laws exist to follow the port, and the port
//! moves slowly: across the shaft at most about 5 mm/s (breathing 3 mm across at 0.25 Hz,
//! p95 in the realistic world: 4.7 mm/s) plus what pivoting about a wrong depth needs
//! (10 mm off at the benchmark's 10 deg/s: 1.7 mm/s), so the lateral motion is bounded
//! at `max_lateral_speed_m_s` 10 mm/s; along the shaft the yield must undo the fastest zoom's
//! drag on a wedged trocar (`scope.max_zoom_speed_m_s` 20 mm/s), so `axial_max_speed_m_s` is 20 mm/s.
//! The force a caught tip then gains from the laws in one step is at most k v dt (50 000
//! N/m x 20 mm/s x 10 ms = 10 N), which the controller's force stop, acting on the force
//! predicted past its lags, catches (`tests/force_stop.rs`); on a compliant wall the laws
//! run below their bounds and are unchanged.
//!
//! **The force** is the shaft's whole wrench at the tip from the external joint torques,
//! [f; m] = (J J^T + λ² I)^{-1} J tau over all six rows of the Jacobian
//! ([`shaft_wrench`](crate::control::force::wrench::shaft_wrench)),
//! low-passed: a moment on the shaft (the trocar's tilt spring, transmitted as a couple
//! across its bore) is then not read as a force, as it is by the docking's estimate from
//! the linear rows alone, which would bias both laws in proportion to the tilt.
//!
//! Nothing here allocates.

use nalgebra::{Unit, Vector3};

use serde::{Deserialize, Serialize};

use crate::control::docking::geometry::across;
use crate::signal::deadband;

/// Parameters of the fulcrum's adaptation (`scope.fulcrum` in `config/controller.yaml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct FulcrumParams {
    /// Prior depth of the fulcrum past the port (the trocar's face) along the shaft, m.
    pub prior_depth_m: f64,
    /// Stiffness K of the fulcrum's admittance across the shaft, N/m.
    pub stiffness_n_per_m: f64,
    /// Damping D of the same, N s/m.
    pub damping_ns_per_m: f64,
    /// Forces across the shaft below this are ignored while the surgeon steers, N.
    pub force_deadband_n: f64,
    /// ... and below this while no command comes, N: the scope then holds still against
    /// the small forces (the estimate's drift, the wall settling after a motion) and
    /// yields only to a wall that pushes harder.
    pub still_force_deadband_n: f64,
    /// Largest displacement of the fulcrum across the shaft, m.
    pub max_displacement_m: f64,
    /// Largest speed of the fulcrum across the shaft, m/s (module doc: the rate bound).
    pub max_lateral_speed_m_s: f64,
    /// Gain γ of the depth's adaptation, m/(N s) (0 = the depth stays at the prior).
    pub depth_gain_m_per_ns: f64,
    /// The depth adapts only while the scope pivots faster than this, rad/s.
    pub min_pivot_speed_rad_s: f64,
    /// Cut-off of the force's first-order low-pass, Hz (0: none).
    pub filter_cutoff_hz: f64,
    /// Damping of the tip's target depth against the force along the shaft, N s/m (0: the
    /// depth does not yield): the scope gives way along the shaft to a trocar that pushes
    /// or drags it (breathing, or a shaft wedged in the bore), as the fulcrum does across.
    pub axial_damping_ns_per_m: f64,
    /// Forces along the shaft below this are ignored while the surgeon steers, N: the
    /// seal's sliding friction while zooming is not a reason to move ...
    pub axial_deadband_n: f64,
    /// ... and below this while no command comes, N: the scope then holds still against
    /// the breathing trocar's pull through the seal, and yields only to more.
    pub axial_still_deadband_n: f64,
    /// Largest speed of that yield, m/s (module doc: the rate bound).
    pub axial_max_speed_m_s: f64,
}

crate::shipped_defaults!(FulcrumParams, crate::config::CONTROLLER, ["scope", "fulcrum"]);

impl FulcrumParams {
    /// Check every range; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        let check = |n: &str, v: f64, lo: f64, hi: f64| {
            if v.is_finite() && (lo..=hi).contains(&v) {
                Ok(())
            } else {
                Err(format!("scope.fulcrum.{n} must be in [{lo}, {hi}], got {v}"))
            }
        };
        check("prior_depth_m", self.prior_depth_m, 0.0, 0.2)?;
        check("stiffness_n_per_m", self.stiffness_n_per_m, 0.0, 1e5)?;
        check("damping_ns_per_m", self.damping_ns_per_m, 1e-3, 1e5)?;
        check("force_deadband_n", self.force_deadband_n, 0.0, 50.0)?;
        check("still_force_deadband_n", self.still_force_deadband_n, 0.0, 50.0)?;
        check("max_displacement_m", self.max_displacement_m, 0.0, 0.05)?;
        check("max_lateral_speed_m_s", self.max_lateral_speed_m_s, 1e-4, 1.0)?;
        check("depth_gain_m_per_ns", self.depth_gain_m_per_ns, 0.0, 1.0)?;
        check("min_pivot_speed_rad_s", self.min_pivot_speed_rad_s, 0.0, 10.0)?;
        check("filter_cutoff_hz", self.filter_cutoff_hz, 0.0, 1000.0)?;
        check("axial_damping_ns_per_m", self.axial_damping_ns_per_m, 0.0, 1e5)?;
        check("axial_deadband_n", self.axial_deadband_n, 0.0, 50.0)?;
        check("axial_still_deadband_n", self.axial_still_deadband_n, 0.0, 50.0)?;
        check("axial_max_speed_m_s", self.axial_max_speed_m_s, 1e-4, 1.0)
    }

    /// How far the tip's target depth yields in a step of `dt` to `along`, the force on the
    /// shaft along its direction (into the body; negative pushes the scope out), m: past
    /// the dead-band (`axial_deadband_n` while `steering`, else `axial_still_deadband_n`), at
    /// 1 / `axial_damping_ns_per_m` m/s per N; zero when off or not finite.
    pub fn axial_yield(&self, along: f64, steering: bool, dt: f64) -> f64 {
        let band = if steering {
            self.axial_deadband_n
        } else {
            self.axial_still_deadband_n
        };
        if self.axial_damping_ns_per_m > 0.0 && along.is_finite() && dt.is_finite() && dt > 0.0 {
            let most = self.axial_max_speed_m_s * dt;
            (deadband(along, band) / self.axial_damping_ns_per_m * dt).clamp(-most, most)
        } else {
            0.0
        }
    }
}

/// The adapted fulcrum, relative to where it started: its depth along the shaft past the
/// port and its displacement across the shaft.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fulcrum {
    /// Depth past the port along the shaft, m.
    pub depth: f64,
    /// Displacement across the shaft from the initial fulcrum, base frame, m.
    pub lateral: Vector3<f64>,
}

/// How the scope moves in a step, for [`Fulcrum::step`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    /// The commanded angular velocity of the pan and tilt, base frame, rad/s.
    pub omega: Vector3<f64>,
    /// The tip's depth past the port (the fulcrum depth's upper bound), m.
    pub tip_depth: f64,
    /// Whether a command moves the scope (the dead-band is then `force_deadband_n`, else
    /// `still_force_deadband_n`).
    pub steering: bool,
}

impl Fulcrum {
    /// At the prior depth, not displaced.
    pub fn new(p: &FulcrumParams) -> Self {
        Self {
            depth: p.prior_depth_m,
            lateral: Vector3::zeros(),
        }
    }

    /// One step of `dt`: `force` is the force on the shaft (base frame, N), `shaft` its
    /// direction (into the body), `m` how the scope moves. Returns the change of depth, m.
    pub fn step(
        &mut self,
        p: &FulcrumParams,
        force: &Vector3<f64>,
        shaft: &Unit<Vector3<f64>>,
        m: &Motion,
        dt: f64,
    ) -> f64 {
        let (omega, tip_depth, steering) = (&m.omega, m.tip_depth, m.steering);
        let f_across = across(shaft, force);
        let n = f_across.norm();
        if !(n.is_finite() && dt > 0.0 && dt.is_finite()) {
            return 0.0;
        }
        let f = if n > 0.0 {
            let band = if steering {
                p.force_deadband_n
            } else {
                p.still_force_deadband_n
            };
            f_across * (deadband(n, band) / n)
        } else {
            f_across
        };
        // Across: first-order admittance, exact for a constant force over the step; while
        // no command comes, damping only (the spring would pull the scope back to where the
        // fulcrum began: a motion nobody asked for).
        let lateral = across(shaft, &self.lateral);
        let x = if p.stiffness_n_per_m > 0.0 && steering {
            let rest = f / p.stiffness_n_per_m;
            rest + (lateral - rest) * (-p.stiffness_n_per_m / p.damping_ns_per_m * dt).exp()
        } else {
            lateral + f * (dt / p.damping_ns_per_m)
        };
        // The rate bound (module doc).
        let step = x - lateral;
        let most = p.max_lateral_speed_m_s * dt;
        let x = if step.norm() > most {
            lateral + step * (most / step.norm())
        } else {
            x
        };
        let xn = x.norm();
        self.lateral = if xn > p.max_displacement_m {
            x * (p.max_displacement_m / xn)
        } else {
            x
        };
        // Along: the lever's gradient, only while pivoting.
        let w = omega.norm();
        let before = self.depth;
        if w > p.min_pivot_speed_rad_s && w.is_finite() {
            let u = omega.cross(shaft) / w;
            self.depth = (self.depth - p.depth_gain_m_per_ns * f.dot(&u) * dt).clamp(0.0, tip_depth.max(0.0));
        }
        self.depth - before
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn steer(omega: Vector3<f64>, tip_depth: f64) -> Motion {
        Motion {
            omega,
            tip_depth,
            steering: true,
        }
    }

    fn silent() -> Motion {
        Motion {
            omega: Vector3::zeros(),
            tip_depth: 0.03,
            steering: false,
        }
    }

    /// The true fulcrum `delta` deeper than the estimate: pivoting about the estimate by θ
    /// moves the shaft there by delta θ x a and the wall (stiffness k) pushes it back.
    #[test]
    fn the_depth_converges_on_the_wall_from_either_side_and_only_while_pivoting() {
        let p = FulcrumParams {
            stiffness_n_per_m: 1e4, // keep the lateral part out of the way
            ..Default::default()
        };
        let a = Unit::new_normalize(Vector3::new(0.1, 0.0, -1.0));
        let omega = Vector3::new(0.17, 0.0, 0.0);
        for truth in [0.005, 0.03] {
            let mut fc = Fulcrum::new(&p);
            let (k, dt) = (1500.0, 0.01);
            let mut theta = 0.0;
            for _ in 0..300 {
                theta += 0.17 * dt;
                let delta = truth - fc.depth;
                let force = -(omega.normalize() * theta).cross(&a) * (k * delta);
                fc.step(&p, &force, &a, &steer(omega, 0.04), dt);
            }
            assert!((fc.depth - truth).abs() < 0.002, "truth {truth}: depth {}", fc.depth);
            // Still, the same force changes nothing along the shaft.
            let before = fc.depth;
            let d = fc.step(&p, &Vector3::new(3.0, 0.0, 0.0), &a, &steer(Vector3::zeros(), 0.04), dt);
            assert_eq!((d, fc.depth), (0.0, before));
        }
    }

    #[test]
    fn the_lateral_part_yields_to_the_force_within_its_bounds_and_ignores_the_axial_force() {
        // With a spring (the shipped 0 leaves the wall to place it).
        let p = FulcrumParams {
            stiffness_n_per_m: 100.0,
            force_deadband_n: 0.3,
            ..FulcrumParams::default()
        };
        let a = Unit::new_normalize(Vector3::new(0.0, 0.0, -1.0));
        let m = steer(Vector3::zeros(), 0.03);
        let mut fc = Fulcrum::new(&p);
        for _ in 0..1000 {
            fc.step(&p, &Vector3::new(1.2, 0.0, 5.0), &a, &m, 0.01);
        }
        // (1.2 - 0.3) N / 100 N/m = 9 mm, along x only; the axial 5 N moves nothing.
        assert!(
            (fc.lateral - Vector3::new(0.009, 0.0, 0.0)).norm() < 1e-5,
            "{}",
            fc.lateral
        );
        for _ in 0..1000 {
            fc.step(&p, &Vector3::new(0.0, 9.0, 0.0), &a, &m, 0.01);
        }
        assert!((fc.lateral.norm() - p.max_displacement_m).abs() < 1e-9);
        // Below the dead-band while steering: back to zero.
        for _ in 0..2000 {
            fc.step(&p, &Vector3::new(0.2, 0.0, 0.0), &a, &m, 0.01);
        }
        assert!(fc.lateral.norm() < 1e-6);
        // Non-finite input: nothing changes.
        let before = fc;
        fc.step(
            &p,
            &Vector3::new(f64::NAN, 0.0, 0.0),
            &a,
            &steer(Vector3::x(), 0.03),
            0.01,
        );
        assert_eq!(fc, before);
        // The shipped law has no spring: past the dead-band the fulcrum moves at
        // (f - band) / D, steering or not, and stays where the force left it.
        let p = FulcrumParams::default();
        assert_eq!(p.stiffness_n_per_m, 0.0);
        let mut fc = Fulcrum::new(&p);
        for _ in 0..10 {
            fc.step(&p, &Vector3::new(0.6, 0.0, 0.0), &a, &m, 0.01);
        }
        let past = 0.6 - p.force_deadband_n;
        assert!(
            (fc.lateral.x - past / p.damping_ns_per_m * 0.1).abs() < 1e-12,
            "{}",
            fc.lateral
        );
        let held = fc.lateral;
        for _ in 0..100 {
            fc.step(&p, &Vector3::zeros(), &a, &m, 0.01);
        }
        assert_eq!(fc.lateral, held);
        // Past D times the rate bound (0.5 N + the dead-band), no faster than the bound,
        // steering or not, with a spring or without.
        for (q, m) in [(p.clone(), m), (p.clone(), silent())] {
            for stiff in [0.0, 100.0] {
                let q = FulcrumParams {
                    stiffness_n_per_m: stiff,
                    ..q.clone()
                };
                let mut fc = Fulcrum::new(&q);
                fc.step(&q, &Vector3::new(0.0, 30.0, 0.0), &a, &m, 0.01);
                assert!(
                    (fc.lateral.norm() - q.max_lateral_speed_m_s * 0.01).abs() < 1e-12,
                    "{}",
                    fc.lateral
                );
            }
        }
    }

    /// Silent (no command): forces under the still dead-band move nothing, larger ones move
    /// the fulcrum at (f - band) / D, with no spring back.
    #[test]
    fn silent_it_holds_against_small_forces_and_yields_to_large_ones() {
        let p = FulcrumParams::default();
        let a = Unit::new_normalize(Vector3::new(0.0, 0.0, -1.0));
        let mut fc = Fulcrum::new(&p);
        for _ in 0..500 {
            fc.step(
                &p,
                &Vector3::new(0.0, 0.9, 0.0),
                &a,
                &steer(Vector3::zeros(), 0.03),
                0.01,
            );
        }
        let before = fc.lateral;
        assert!(before.y > 0.005);
        for _ in 0..100 {
            fc.step(&p, &Vector3::new(0.0, 1.9, 0.0), &a, &silent(), 0.01);
        }
        fc.step(&p, &Vector3::zeros(), &a, &silent(), 0.01);
        assert!(
            (fc.lateral - before).norm() < 1e-12,
            "no motion and no spring back while silent"
        );
        fc.step(&p, &Vector3::new(0.0, -2.4, 0.0), &a, &silent(), 0.01);
        let expect = -(2.4 - p.still_force_deadband_n) / p.damping_ns_per_m * 0.01;
        assert!((fc.lateral.y - before.y - expect).abs() < 1e-12);
    }

    #[test]
    fn bad_parameters_are_named() {
        let bad = FulcrumParams {
            damping_ns_per_m: 0.0,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().contains("scope.fulcrum.damping_ns_per_m"));
        assert!(FulcrumParams::default().validate().is_ok());
    }

    #[test]
    fn the_depth_yields_along_the_shaft_past_its_dead_band_only() {
        let p = FulcrumParams::default();
        let dt = 0.01;
        // Inside the band: nothing, steering or not.
        assert_eq!(p.axial_yield(1.9, true, dt), 0.0);
        assert_eq!(p.axial_yield(-4.9, false, dt), 0.0);
        // Past it: the way the force pushes, at 1/D per newton over the band.
        let out = p.axial_yield(-2.4, true, dt);
        assert!((out - (-0.4 / p.axial_damping_ns_per_m * dt)).abs() < 1e-15, "{out}");
        assert!(p.axial_yield(5.4, false, dt) > 0.0);
        assert!((p.axial_yield(5.4, false, dt) - 0.4 / p.axial_damping_ns_per_m * dt).abs() < 1e-15);
        // No faster than its rate bound, either way.
        assert_eq!(p.axial_yield(40.0, true, dt), p.axial_max_speed_m_s * dt);
        assert_eq!(p.axial_yield(-40.0, false, dt), -p.axial_max_speed_m_s * dt);
        // Off, or bad input: nothing.
        let off = FulcrumParams {
            axial_damping_ns_per_m: 0.0,
            ..p.clone()
        };
        assert_eq!(off.axial_yield(-40.0, true, dt), 0.0);
        assert_eq!(p.axial_yield(f64::NAN, true, dt), 0.0);
        assert_eq!(p.axial_yield(-40.0, true, f64::NAN), 0.0);
        assert_eq!(p.axial_yield(-40.0, true, -dt), 0.0);
    }
}
