//! After docking: the port's breathing along the docking axis, followed from the trocar
//! estimate.
//!
//! The abdominal wall moves the trocar with breathing, mostly along its axis (millimetres:
//! `config/sim.yaml`'s realistic world moves it 4 mm along and 1 mm across). The fulcrum
//! follows the motion across the shaft only through the force it takes to drag the wall
//! ([`crate::control::scope::fulcrum`]), and along the shaft not at all below the axial dead-band: the
//! trocar slides up and down a scope that holds its depth, so that the tip rises above the
//! wall's fulcrum and the shaft, guided by less of the bore, cocks in its clearance; once
//! the scope is panned, the axial breathing also moves the port across the shaft.
//!
//! The trocar estimate (camera and marker) still sees the port after DONE. Its position
//! along the docking axis is a measure of the breathing that the scope's lever hardly
//! touches: levering the trocar tilts it about the wall, which moves its face across its
//! axis (by the face's distance from the wall times the tilt) and along it only by the
//! tilt's cosine (1 - cos 2° = 6e-4 of 30 mm: 0.02 mm). Its position across the axis is not
//! used: it moves with the lever (a fulcrum that followed it follows the wrong pivot).
//!
//! **Law.** o = a · (p - p0) - s_f (1 - a · u), the estimated port's displacement along the
//! docking axis a since DONE (p0: the controller's filtered estimate at DONE) less what
//! tilting about the fulcrum adds there (u the estimated axis, s_f the fulcrum's depth), is
//! low-passed at `cutoff_hz` on each fresh estimate and cut to ±`max_offset_m`. While the
//! surgeon steers (a command, even a zero one: the dead-man pressed; not a withdrawal), the law's port and
//! fulcrum move with a part of it, a g o (`gain` g), at most `max_speed_m_s`; while no command
//! comes they stay (the scope holds still: the pivot's stillness target), and when commands resume
//! they catch up at `max_speed_m_s`. A missing, stale, non-finite or old-stamped estimate
//! changes nothing: the offset holds; one more than `max_jump_m` from the followed offset (a
//! misdetected marker) is used only when the next one agrees with it.
//!
//! Nothing here allocates.

use nalgebra::{Point3, Unit, Vector1, Vector3};
use serde::{Deserialize, Serialize};

use crate::signal::StreamLowPass;
use crate::validate::in_range;

/// Parameters (`scope.breathing` in `config/controller.yaml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct PortFollowParams {
    /// Follow the estimated port along the docking axis (false: the port stays where DONE
    /// found it, as before).
    pub follow: bool,
    /// Cut-off of the first-order low-pass on the estimate's displacement, Hz.
    pub cutoff_hz: f64,
    /// The part of the estimated displacement followed, 0..1: while the seal sticks, the
    /// trocar moves with a scope that follows it, and a gain under one keeps that loop
    /// from carrying it further (at the cost of following less of the breathing).
    pub gain: f64,
    /// Largest offset followed, m: a port estimated further away is followed this far.
    pub max_offset_m: f64,
    /// Largest speed of the followed offset, m/s.
    pub max_speed_m_s: f64,
    /// An estimate older than this is not used, s.
    pub max_age_s: f64,
    /// An estimate this far (m) from the followed offset is an outlier (a breath moves the
    /// port well under 1 mm between two 15 Hz frames) and is used only when the next one
    /// agrees with it within the same distance (the port did move: the marker came back
    /// into view elsewhere).
    pub max_jump_m: f64,
}

crate::shipped_defaults!(PortFollowParams, crate::config::CONTROLLER, ["scope", "breathing"]);

impl PortFollowParams {
    /// Check every range; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        for (key, v, lo, hi) in [
            ("scope.breathing.cutoff_hz", self.cutoff_hz, 1e-3, 100.0),
            ("scope.breathing.gain", self.gain, 0.0, 1.0),
            ("scope.breathing.max_offset_m", self.max_offset_m, 0.0, 0.05),
            ("scope.breathing.max_speed_m_s", self.max_speed_m_s, 1e-4, 0.1),
            ("scope.breathing.max_age_s", self.max_age_s, 1e-3, 5.0),
            ("scope.breathing.max_jump_m", self.max_jump_m, 1e-4, 0.05),
        ] {
            in_range(key, v, lo, hi).map_err(|e| e.to_string())?;
        }
        Ok(())
    }
}

/// The followed breathing offset, from DONE until the run ends.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PortFollow {
    axis: Unit<Vector3<f64>>,
    origin: Point3<f64>,
    /// The low-pass of the displacement along the axis (time constant 1 / (2 pi cutoff)) ...
    filter: StreamLowPass<1>,
    /// ... and its output, m.
    tracked: f64,
    /// The offset the law has taken, m.
    applied: f64,
    /// The stamp of the newest estimate used, s.
    stamp: f64,
    /// An outlier waiting for the next estimate to agree with it, m.
    pending: Option<f64>,
}

impl PortFollow {
    /// Begin at the estimated port `origin` (stamped `stamp`) on the docking axis `axis`.
    pub fn new(p: &PortFollowParams, axis: Unit<Vector3<f64>>, origin: Point3<f64>, stamp: f64) -> Self {
        let mut filter = StreamLowPass::new(1.0 / (std::f64::consts::TAU * p.cutoff_hz));
        filter.update(stamp, &Vector1::zeros());
        Self {
            axis,
            origin,
            filter,
            tracked: 0.0,
            applied: 0.0,
            stamp,
            pending: None,
        }
    }

    /// Feed the estimated port `port` and axis `axis` stamped `stamp` at time `now`, with the
    /// fulcrum `depth` m past the port: the point of the estimated axis at that depth is
    /// followed, which tilting about the fulcrum does not move (the face itself, `depth`
    /// above it, moves along the docking axis by `depth` (1 - cos tilt): 1.8 mm of 30 mm at
    /// 20 deg). An estimate that is not finite, older than `max_age_s`, or not newer than the
    /// last one is not used; one over `max_jump_m` from the followed offset only when the next
    /// one confirms it.
    pub fn observe(
        &mut self,
        p: &PortFollowParams,
        (port, axis): (&Point3<f64>, &Vector3<f64>),
        depth: f64,
        stamp: f64,
        now: f64,
    ) {
        let fresh = stamp > self.stamp && now - stamp <= p.max_age_s;
        let finite = port.coords.iter().chain(axis.iter()).all(|x| x.is_finite()) && depth.is_finite();
        let Some(u) = Unit::try_new(*axis, 1e-9).filter(|_| fresh && finite && now.is_finite()) else {
            return;
        };
        let tilt = 1.0 - self.axis.dot(&u).clamp(-1.0, 1.0);
        let raw = (self.axis.dot(&(port - self.origin)) - depth * tilt).clamp(-p.max_offset_m, p.max_offset_m);
        if (raw - self.tracked).abs() > p.max_jump_m {
            let confirmed = self.pending.is_some_and(|q| (raw - q).abs() <= p.max_jump_m);
            if !confirmed {
                self.pending = Some(raw);
                return;
            }
        }
        self.pending = None;
        self.tracked = self.filter.update(stamp, &Vector1::new(raw)).x;
        self.stamp = stamp;
    }

    /// One step of `dt`: the displacement of the law's port and fulcrum (base frame, m),
    /// zero while not `steering` or when off.
    pub fn step(&mut self, p: &PortFollowParams, steering: bool, dt: f64) -> Vector3<f64> {
        if !(p.follow && steering && dt.is_finite() && dt > 0.0) {
            return Vector3::zeros();
        }
        let room = p.max_speed_m_s * dt;
        let d = (p.gain * self.tracked - self.applied).clamp(-room, room);
        self.applied += d;
        self.axis.into_inner() * d
    }

    /// The offset the law has taken along the docking axis, m.
    pub fn offset(&self) -> f64 {
        self.applied
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn follow() -> (PortFollowParams, PortFollow) {
        let p = PortFollowParams::default();
        (
            p,
            PortFollow::new(
                &PortFollowParams::default(),
                Vector3::z_axis(),
                Point3::new(0.1, 0.2, 0.3),
                0.0,
            ),
        )
    }

    #[test]
    fn it_follows_the_port_along_the_axis_only_while_steering() {
        let (p, mut f) = follow();
        // The port 3 mm along the axis and 5 mm across it (the lever: not followed).
        let port = Point3::new(0.105, 0.2, 0.303);
        let mut moved = Vector3::zeros();
        for k in 1..=200 {
            let t = k as f64 * 0.01;
            if k % 7 == 0 {
                f.observe(&p, (&port, &Vector3::z()), 0.03, t, t + 0.04);
            }
            moved += f.step(&p, true, 0.01);
        }
        assert!((moved - Vector3::new(0.0, 0.0, 0.003)).norm() < 2e-5, "{moved:?}");
        // Silent: the offset stays although the port moves back.
        let back = Point3::new(0.1, 0.2, 0.3);
        for k in 201..=400 {
            let t = k as f64 * 0.01;
            f.observe(&p, (&back, &Vector3::z()), 0.03, t, t);
            assert_eq!(f.step(&p, false, 0.01), Vector3::zeros());
        }
        // Steering again: it catches up at max_speed (3 mm at 20 mm/s: 0.15 s).
        let mut back_by = 0.0;
        for k in 0..10 {
            let d = f.step(&p, true, 0.01).z;
            assert!(d.abs() <= p.max_speed_m_s * 0.01 + 1e-15, "step {k}: {d}");
            back_by += d;
        }
        assert!((back_by + 0.002).abs() < 1e-9, "{back_by}");
        for _ in 0..10 {
            f.step(&p, true, 0.01);
        }
        assert!(f.offset().abs() < 1e-5, "{}", f.offset());
    }

    #[test]
    fn the_low_pass_follows_breathing_with_a_small_lag_and_damps_the_noise() {
        use rand::{RngExt, SeedableRng};
        let (p, mut f) = follow();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        // 4 mm at 0.25 Hz, sampled at 15 Hz with 0.3 mm of uniform noise, 40 ms late.
        let (mut worst, mut noise_only): (f64, f64) = (0.0, 0.0);
        for k in 1..=1500 {
            let t = k as f64 * 0.01;
            if k % 7 == 0 {
                let seen = t - 0.04;
                let z = 0.004 * (std::f64::consts::TAU * 0.25 * seen).sin() + rng.random_range(-3e-4..3e-4);
                f.observe(&p, (&Point3::new(0.1, 0.2, 0.3 + z), &Vector3::z()), 0.03, seen, t);
            }
            f.step(&p, true, 0.01);
            if t > 4.0 {
                let truth = 0.004 * (std::f64::consts::TAU * 0.25 * t).sin();
                worst = worst.max((f.offset() - truth).abs());
                noise_only = noise_only.max(f.offset().abs() - 0.004);
            }
        }
        // Lag: the 4 Hz pole's 3.6 deg, the 40 ms's 3.6 deg and the 15 Hz sampling's 3 deg
        // of a 4 mm sine, 0.7 mm, and the noise's rest: measured 0.96 mm (a 1 Hz pole alone
        // lags 14 deg, 1 mm; no following at all misses by 4 mm).
        assert!(worst < 1.2e-3, "{worst}");
        assert!(noise_only < 3e-4, "{noise_only}");
    }

    #[test]
    fn bad_or_old_estimates_change_nothing_and_the_offset_is_bounded() {
        let (p, mut f) = follow();
        f.observe(&p, (&Point3::new(0.1, 0.2, f64::NAN), &Vector3::z()), 0.03, 1.0, 1.0);
        f.observe(&p, (&Point3::new(0.1, 0.2, 0.31), &Vector3::zeros()), 0.03, 1.0, 1.0);
        f.observe(&p, (&Point3::new(0.1, 0.2, 0.31), &Vector3::z()), 0.03, 1.0, 1.5); // stale
        f.observe(&p, (&Point3::new(0.1, 0.2, 0.31), &Vector3::z()), 0.03, -1.0, -1.0); // older than the start
        for _ in 0..100 {
            assert_eq!(f.step(&p, true, 0.01), Vector3::zeros());
        }
        // A port 50 mm away is followed 15 mm (max_offset) and no further.
        for k in 1..=300 {
            let t = k as f64 * 0.07;
            f.observe(&p, (&Point3::new(0.1, 0.2, 0.35), &Vector3::z()), 0.03, t, t);
            f.step(&p, true, 0.01);
        }
        assert!((f.offset() - p.max_offset_m).abs() < 1e-9, "{}", f.offset());
        // An outlier 8 mm away is not followed; the same place seen twice is (the port moved).
        let mut g = PortFollow::new(
            &PortFollowParams::default(),
            Vector3::z_axis(),
            Point3::new(0.1, 0.2, 0.3),
            0.0,
        );
        let seen = |g: &mut PortFollow, z: f64, t: f64| {
            g.observe(&p, (&Point3::new(0.1, 0.2, 0.3 + z), &Vector3::z()), 0.03, t, t)
        };
        seen(&mut g, 0.008, 0.1);
        seen(&mut g, 0.0, 0.2);
        seen(&mut g, 0.008, 0.3);
        for _ in 0..100 {
            g.step(&p, true, 0.01);
        }
        assert!(g.offset().abs() < 1e-12, "{}", g.offset());
        seen(&mut g, 0.008, 0.4);
        for _ in 0..100 {
            g.step(&p, true, 0.01);
        }
        assert!(g.offset() > 0.006, "{}", g.offset());
        // A gain under one follows its part of the displacement.
        let half = PortFollowParams {
            gain: 0.5,
            ..PortFollowParams::default()
        };
        let mut h = PortFollow::new(
            &PortFollowParams::default(),
            Vector3::z_axis(),
            Point3::new(0.1, 0.2, 0.3),
            0.0,
        );
        for k in 1..=30 {
            let t = k as f64 * 0.07;
            h.observe(&half, (&Point3::new(0.1, 0.2, 0.304), &Vector3::z()), 0.03, t, t);
            h.step(&half, true, 0.07);
        }
        assert!((h.offset() - half.gain * 0.004).abs() < 1e-6, "{}", h.offset());
        // Off: nothing moves.
        let off = PortFollowParams {
            follow: true,
            ..p.clone()
        };
        assert_eq!(f.step(&off, true, 0.01), Vector3::zeros());
        assert!(PortFollowParams {
            cutoff_hz: f64::NAN,
            ..p
        }
        .validate()
        .is_err());
    }
}
