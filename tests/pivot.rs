//! After docking, in closed loop on the realistic simulated plant (`config/sim.yaml`'s
//! `realistic` protocol: breathing trocar on a compliant mount, seal, elastic joints, torque
//! model error, a biased 15 Hz pose sensor) with the shipped `config/controller.yaml`:
//! the pivot's "done when" sequence, the fulcrum's adaptation against a fixed fulcrum and a
//! wrong prior, a biased trocar estimate, the dead-man and bad commands, retract.
//!
//! The bounds are the measured figures (docs/after-docking.md) with a margin; where they
//! are wider than the pivot's targets, docs/after-docking.md says so and why.

use std::sync::Arc;

use trocar_docking::control::{ControllerParams, Phase, ScopeCommand, Stamped};
use trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use trocar_docking::kinematics::{Kinematics, LbrKinematics};
use trocar_docking::trials::config::{load_controller, SimConfig};
use trocar_docking::trials::pivot::{
    done_when_script, fixed_fulcrum, random_script, run_pivot, PivotResult, PivotSession, PivotTiming, Segment,
};

fn kin() -> Arc<dyn Kinematics> {
    Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap())
}

fn realistic() -> SimConfig {
    SimConfig::load_default().unwrap().with_protocol("realistic").unwrap()
}

fn shipped() -> ControllerParams {
    load_controller(None).unwrap()
}

fn run(cfg: &SimConfig, controller: &ControllerParams, seed: u64) -> PivotResult {
    let r = run_pivot(
        &cfg.sim,
        controller,
        kin(),
        seed,
        &done_when_script(),
        &PivotTiming::default(),
    )
    .unwrap();
    eprintln!("{}", serde_json::to_string(&r).unwrap());
    assert!(r.docked, "seed {seed}: {}", r.reason);
    r
}

const SEEDS: [u64; 3] = [1, 2, 3];

/// Two figures of the done-when runs on `SEEDS`, each summed over the seeds, with the
/// controllers `a` and `b`: `[(a's first, b's first), (a's second, b's second)]`.
fn sums(a: &ControllerParams, b: &ControllerParams, figures: [fn(&PivotResult) -> f64; 2]) -> [(f64, f64); 2] {
    let cfg = realistic();
    let mut out = [(0.0, 0.0); 2];
    for seed in SEEDS {
        let (ra, rb) = (run(&cfg, a, seed), run(&cfg, b, seed));
        assert!(ra.held_steps == 0 && ra.swept_deg >= 15.0, "seed {seed}");
        for (o, f) in out.iter_mut().zip(figures) {
            o.0 += f(&ra);
            o.1 += f(&rb);
        }
    }
    out
}

#[test]
fn the_done_when_sequence_pivots_about_the_port_without_a_hold() {
    let cfg = realistic();
    for seed in SEEDS {
        let r = run(&cfg, &shipped(), seed);
        assert_eq!(r.final_phase, "DONE");
        assert_eq!(r.held_steps, 0, "seed {seed}: a hold while commanded");
        assert!(r.swept_deg >= 15.0, "seed {seed}: swept {:.1} deg", r.swept_deg);
        // The trace for `pivot --plot`: every step after docking (0.5 s settle, the 10 s
        // script, 0.5 s settle, 2 s still at 100 Hz), the script's steps marked commanded,
        // its peak the figure's max.
        assert_eq!(r.trace.len(), 1300, "seed {seed}");
        assert_eq!(r.trace.iter().filter(|s| s.commanded).count(), 1000);
        assert!(r.trace.windows(2).all(|w| w[1].t > w[0].t));
        let peak = r
            .trace
            .iter()
            .filter(|s| s.commanded)
            .map(|s| s.distance_m)
            .fold(0.0, f64::max);
        assert_eq!(peak, r.distance_max_m);
        let at_most = |what: &str, value: f64, bound: f64| {
            assert!(value <= bound, "seed {seed}: {what} {value:.5} over {bound}");
        };
        at_most(
            "mean force estimate across the shaft, N",
            r.lateral_force_est_mean_n,
            1.0,
        );
        at_most("true force across the shaft, max, N", r.lateral_force_true_max_n, 5.0);
        at_most("true force across the shaft, mean, N", r.lateral_force_true_mean_n, 1.0);
        // The rigid cannula keeps the shaft line within its clearance of the trocar's
        // fulcrum (measured 0.2-0.5 mm; the soft penalty bore let it sink 0.8-3.1 mm); the
        // wall dragged by at most 1.2 mm (p95, measured 0.59-0.80; 0.8-1.1 before the
        // torques' low-pass and the payload fit); the shaft line within 1.6 mm of the port
        // (measured 0.73-1.26 mm, not the target's 1 mm on seed 3: docs/after-docking.md; 0.8-1.7 before the
        // low-pass, 1.7-3.6 with the soft bore and the fulcrum's force through the tare's
        // dead-band).
        at_most("shaft from the trocar's fulcrum, p95, m", r.bore_distance_p95_m, 0.0008);
        at_most("wall dragged, p95, m", r.wall_displacement_p95_m, 0.0012);
        at_most("shaft from the true port, p95, m", r.distance_p95_m, 0.0016);
        // Once the commands stop the scope yields only to a wall pushing over 2 N: it moved
        // 0.21-0.82 mm in these seeds (0.8-1.2 before the low-pass; docs/after-docking.md: the target's
        // 0.5 mm not met on seed 2), while the port goes on breathing.
        at_most("motion once silent, m", r.still_motion_m, 0.001);
        at_most(
            "motion once silent relative to the port, m",
            r.still_motion_port_m,
            0.0015,
        );
        assert!(
            r.port_motion_m > 0.002,
            "seed {seed}: breathing {:.2} mm",
            r.port_motion_m * 1e3
        );
    }
}

#[test]
fn the_torques_low_pass_lowers_the_wall_drag_and_the_force_across_the_shaft() {
    // The shipped 5 ms low-pass at the plant's 1 kHz against the newest sample alone (the
    // controller's read once per 10 ms period), everything else equal.
    let raw = ControllerParams {
        torque_filter_time_constant_s: 0.0,
        ..shipped()
    };
    assert!(shipped().torque_filter_time_constant_s > 0.0);
    let [(wall, wall_raw), (force, force_raw)] = sums(
        &shipped(),
        &raw,
        [|r| r.wall_displacement_p95_m, |r| r.lateral_force_true_mean_n],
    );
    // Measured 0.73 x and 0.67 x.
    assert!(wall < 0.85 * wall_raw, "wall dragged p95 sums: {wall} vs {wall_raw}");
    assert!(
        force < 0.85 * force_raw,
        "true lateral force sums: {force} vs {force_raw}"
    );
}

#[test]
fn the_adapted_fulcrum_drags_the_wall_less_than_a_fixed_one() {
    let [(adapted, fixed), (f_adapted, f_fixed)] = sums(
        &shipped(),
        &fixed_fulcrum(&shipped()),
        [|r| r.wall_displacement_p95_m, |r| r.lateral_force_true_mean_n],
    );
    // Measured 0.22 x and 0.16 x (0.33 x and 0.35 x with the soft bore and the fulcrum's
    // force through the tare's dead-band).
    assert!(
        adapted < 0.3 * fixed,
        "wall displacement p95 sums: {adapted} vs {fixed}"
    );
    assert!(
        f_adapted < 0.3 * f_fixed,
        "true lateral force sums: {f_adapted} vs {f_fixed}"
    );
}

#[test]
fn a_wrong_prior_depth_is_corrected_while_pivoting() {
    let cfg = realistic();
    let truth = cfg.sim.trocar.pivot_depth_m;
    for prior in [0.0, 0.045] {
        let mut c = shipped();
        c.scope.fulcrum.prior_depth_m = prior;
        let r = run(&cfg, &c, 2);
        assert!(
            (r.fulcrum_depth_m - truth).abs() < 0.6 * (prior - truth).abs(),
            "prior {prior}: ended at {:.1} mm (the wall holds at {truth})",
            r.fulcrum_depth_m * 1e3
        );
    }
}

/// A biased trocar estimate (up to 6 mm off, fixed in the port's frame) biases the fulcrum
/// by at most half as much, over the fulcrum's own 1.5 mm (the bore's clearance and the
/// breathing): within 1.5 mm at the start, under half the estimate's error at the start
/// where that is over 3 mm, and at the end within 1.5 mm or half the estimate's error,
/// whichever is more.
#[test]
fn a_biased_trocar_estimate_biases_the_fulcrum_at_most_half_as_much() {
    let mut cfg = realistic();
    // Up to 6 mm off (uniform length, random direction), no rotation.
    cfg.sim.measurement.bias_position_m = 0.006;
    cfg.sim.measurement.bias_rotation_rad = 0.0;
    cfg.sim.measurement.bias_frame = trocar_docking::sim::noise::BiasFrame::Port;
    let (mut biased, mut strongly) = (0, 0);
    for seed in SEEDS {
        let r = run(&cfg, &shipped(), seed);
        biased += usize::from(r.estimate_error_m > 0.0015);
        if r.estimate_error_m > 0.003 {
            strongly += 1;
            // Where the estimate is off by more than twice the absolute bound below, the
            // start (the estimate's port projected onto the shaft) keeps under half of its
            // error: a fulcrum that followed the estimate would keep all of it (seed 2: 3.4
            // mm off, 0.26 kept; at 1.7-2.5 mm off, seeds 1 and 3, the start's own 0.9-1.1 mm
            // of clearance and breathing make a ratio meaningless, and the absolute bound
            // is the one that matters).
            assert!(
                r.fulcrum_error_start_m < 0.5 * r.estimate_error_m,
                "seed {seed}: estimate {:.2} mm off, fulcrum {:.2} mm at the start",
                r.estimate_error_m * 1e3,
                r.fulcrum_error_start_m * 1e3
            );
        }
        // At the end (a snapshot after the silence, the port breathing) within 1.5 mm, or
        // half the estimate's error where that is more: with the breathing followed along
        // the docking axis (`scope.breathing`) a bias fixed in the trocar's frame turns with
        // the trocar the scope tilts, and a part of it is followed while tilted (seed 2:
        // 3.48 mm off, 1.53 mm at the end; 1.09 without the following).
        assert!(
            r.fulcrum_error_start_m < 0.0015 && r.fulcrum_error_end_m < 0.0015f64.max(0.5 * r.estimate_error_m),
            "seed {seed}: estimate {:.2} mm off, fulcrum {:.2} then {:.2} mm",
            r.estimate_error_m * 1e3,
            r.fulcrum_error_start_m * 1e3,
            r.fulcrum_error_end_m * 1e3
        );
    }
    assert!(biased >= 2, "only {biased} estimates were off by more than 1.5 mm");
    assert!(strongly >= 1, "no estimate was off by more than 3 mm");
}

fn docked(seed: u64) -> PivotSession {
    let cfg = realistic();
    PivotSession::dock(&cfg.sim, &shipped(), kin(), seed, 20.0)
        .unwrap()
        .unwrap()
}

#[test]
fn old_or_bad_commands_hold_still_and_fresh_ones_steer() {
    let mut s = docked(2);
    let a0 = s.shaft().1;
    let pan = ScopeCommand {
        pan: 0.17,
        ..Default::default()
    };
    // 0.3 s old (dead-man at 0.2 s): nothing moves.
    for _ in 0..100 {
        let t = s.world().time();
        let o = s
            .tick_stamped(Some(Stamped {
                stamp: t - 0.3,
                value: pan,
            }))
            .unwrap();
        assert_eq!(o.phase, Phase::Done);
        assert_eq!(
            o.pivot.unwrap().ignored,
            None,
            "an old command is silence, not an error"
        );
    }
    assert!(
        s.shaft().1.angle(&a0).to_degrees() < 0.3,
        "{}",
        s.shaft().1.angle(&a0).to_degrees()
    );
    // Not finite: ignored, with the reason, and nothing jumps.
    let mut last: Option<trocar_docking::kinematics::JointVector> = None;
    for bad in [f64::NAN, f64::INFINITY] {
        for _ in 0..50 {
            let o = s.tick(Some(ScopeCommand { tilt: bad, ..pan })).unwrap();
            assert!(o.pivot.unwrap().ignored.unwrap().contains("not finite"));
            let q = o.command.unwrap();
            if let Some(l) = last {
                // Well inside the guard's per-step box (0.5 x 98 deg/s x 10 ms = 8.6 mrad).
                assert!((q - l).amax() < 3e-3, "a step of {} rad", (q - l).amax());
            }
            last = Some(q);
        }
    }
    assert!(s.shaft().1.angle(&a0).to_degrees() < 0.3);
    // Fresh: 1 s of pan at 0.17 rad/s turns the shaft by about 10 deg.
    for _ in 0..100 {
        s.tick(Some(pan)).unwrap();
    }
    let turned = s.shaft().1.angle(&a0).to_degrees();
    assert!((7.0..12.0).contains(&turned), "{turned} deg");
}

#[test]
fn retract_withdraws_to_the_stand_off_point_then_idles() {
    let c = shipped();
    let mut s = docked(1);
    let mut max_force: f64 = 0.0;
    assert!(s.controller().retract().is_ok());
    let mut phase = Phase::Retract;
    let mut depth = f64::NAN;
    while phase == Phase::Retract {
        let o = s
            .tick(Some(ScopeCommand {
                pan: 0.3,
                ..Default::default()
            }))
            .unwrap();
        assert!(o.hold.is_none(), "{:?}", o.hold);
        phase = o.phase;
        depth = o.pivot.map_or(depth, |p| p.depth);
        max_force = max_force.max(s.world().contact().force.norm());
        assert!(s.world().time() < 30.0, "still retracting");
    }
    assert_eq!(phase, Phase::Idle);
    // At the stand-off point as the controller knows the port (the trocar estimate's face,
    // which breathing moves by up to 4 mm and the hand-eye error biases), and out of the
    // real trocar.
    assert!(
        (depth + c.standoff_m).abs() < 0.002,
        "tip {:.1} mm past the port",
        depth * 1e3
    );
    let tip = s.world().tip_in_port();
    assert!(tip.z < -0.005, "tip {:.1} mm along the true axis", tip.z * 1e3);
    assert!(max_force < 5.0, "{max_force} N");
    // Nothing is sent in IDLE; a retract now is refused.
    assert_eq!(s.tick(None).unwrap().command, None);
    assert!(s.controller().retract().unwrap_err().contains("IDLE"));
}

/// The surgeon holds the scope still with the dead-man pressed (zero commands) for 8 s
/// while the port breathes 3 mm across its axis: the adapted fulcrum follows it, so the wall
/// is dragged less and pushes less than with the fulcrum fixed.
#[test]
fn the_fulcrum_follows_a_breathing_port() {
    let mut cfg = realistic();
    cfg.sim.breathing.amplitude_lateral_m = 0.003;
    let hold = [Segment {
        duration: 8.0,
        command: ScopeCommand::default(),
    }];
    let (mut adapted, mut fixed, mut wall_a, mut wall_f) = (0.0, 0.0, 0.0, 0.0);
    for seed in SEEDS {
        let go = |c: &ControllerParams| {
            let r = run_pivot(&cfg.sim, c, kin(), seed, &hold, &PivotTiming::default()).unwrap();
            eprintln!("{}", serde_json::to_string(&r).unwrap());
            assert!(r.docked && r.held_steps == 0, "seed {seed}: {}", r.reason);
            r
        };
        let a = go(&shipped());
        let f = go(&fixed_fulcrum(&shipped()));
        assert!(
            a.swept_deg < 1.0,
            "seed {seed}: a zero command turned the scope {}",
            a.swept_deg
        );
        adapted += a.lateral_force_true_mean_n;
        fixed += f.lateral_force_true_mean_n;
        wall_a += a.wall_displacement_p95_m;
        wall_f += f.wall_displacement_p95_m;
    }
    // Measured: 0.40-0.42 N against 3.3-5.0 N, and 0.52-0.65 mm against 4.7-6.0 mm (sums
    // 0.09 x and 0.10 x; before the torques' low-pass 0.48-0.64 N and 0.74-0.99 mm, 0.12 x
    // and 0.15 x; with the soft bore and the fulcrum's force through the tare's dead-band
    // 0.9-1.1 N against 4.0-5.5 N, 1.0-1.3 mm against 5.1-6.3 mm: 0.2 x).
    assert!(adapted < 0.15 * fixed, "true lateral force sums: {adapted} vs {fixed}");
    assert!(wall_a < 0.15 * wall_f, "wall displacement sums: {wall_a} vs {wall_f}");
}

/// "Bounded tip speed, acceleration and jerk in every phase", after docking:
/// the surgeon's commands start and stop at once (a button, the dead-man), zoom in and out,
/// then retract. The commanded tip (forward kinematics of each command) keeps within the
/// shipped `motion:` limits in DONE and RETRACT, at the shipped 100 Hz.
#[test]
fn pivoting_and_retract_keep_the_tip_motion_limits() {
    let c = shipped();
    let lim = &c.motion;
    let kin = kin();
    let mut s = docked(3);
    let pan = |pan, tilt, zoom| {
        Some(ScopeCommand {
            pan,
            tilt,
            zoom,
            ..Default::default()
        })
    };
    let mut commands = Vec::new();
    let script = [
        (30, pan(0.17, 0.0, 0.0)),
        (20, pan(-0.17, 0.0, 0.0)),
        (20, None),
        (30, pan(0.0, 0.17, 0.01)),
        (20, pan(0.0, 0.0, -0.01)),
        (20, None),
    ];
    for (n, cmd) in script {
        for _ in 0..n {
            let o = s.tick(cmd).unwrap();
            assert_eq!(o.phase, Phase::Done);
            commands.push(o.command.unwrap());
        }
    }
    assert!(s.controller().retract().is_ok());
    for _ in 0..200 {
        let o = s.tick(None).unwrap();
        match o.command {
            Some(q) if o.phase == Phase::Retract => commands.push(q),
            _ => break,
        }
    }
    let dt = shipped().dt_s;
    let poses: Vec<_> = commands.iter().map(|q| kin.fk(q).unwrap()).collect();
    let diff = |x: &[nalgebra::Vector3<f64>]| -> Vec<nalgebra::Vector3<f64>> {
        x.windows(2).map(|w| (w[1] - w[0]) / dt).collect()
    };
    let v: Vec<_> = poses
        .windows(2)
        .map(|w| (w[1].translation.vector - w[0].translation.vector) / dt)
        .collect();
    let w: Vec<_> = poses
        .windows(2)
        .map(|p| (p[1].rotation * p[0].rotation.inverse()).scaled_axis() / dt)
        .collect();
    let max = |x: &[nalgebra::Vector3<f64>]| x.iter().map(|v| v.norm()).fold(0.0, f64::max);
    let (a, al) = (diff(&v), diff(&w));
    let (j, jl) = (diff(&a), diff(&al));
    let got = [
        ("speed", max(&v), lim.max_speed_m_s),
        ("accel", max(&a), lim.max_accel_m_s2),
        ("jerk", max(&j), lim.max_jerk_m_s3),
        ("angular speed", max(&w), lim.max_angular_speed_rad_s),
        ("angular accel", max(&al), lim.max_angular_accel_rad_s2),
        ("angular jerk", max(&jl), lim.max_angular_jerk_rad_s3),
    ];
    eprintln!("{got:?}");
    for (what, value, bound) in got {
        // 5 % for the SQP's tracking of the shaped target and the fulcrum's adaptation.
        assert!(value <= 1.05 * bound, "tip {what} {value:.3} over the limit {bound}");
    }
}

/// Pan at 0.3 rad/s for 3 s (into the cone's edge) in a docked world of `seed` with
/// `controller`; returns the largest true contact force along the shaft (N) and whether the
/// cone stopped the pan.
fn pan_to_the_cone(controller: &ControllerParams, seed: u64) -> (f64, bool) {
    let cfg = realistic();
    let mut s = PivotSession::dock(&cfg.sim, controller, kin(), seed, 20.0)
        .unwrap()
        .unwrap();
    let pan = ScopeCommand {
        pan: 0.3,
        ..Default::default()
    };
    let (mut along, mut cone) = (0.0_f64, false);
    for _ in 0..300 {
        let o = s.tick(Some(pan)).unwrap();
        assert_eq!(o.phase, Phase::Done);
        let p = o.pivot.unwrap();
        assert_eq!(p.ignored, None);
        cone |= p.limit == Some(trocar_docking::control::scope::command::ScopeLimit::Cone);
        let (_, a) = s.shaft();
        along = along.max(a.dot(&s.world().contact().force).abs());
    }
    (along, cone)
}

/// A shaft pivoted far tilts the trocar and wedges in its bore; with the breathing, the
/// trocar then pulls or pushes it along its axis. The target depth yields to that force
/// (`scope.fulcrum.axial_damping_ns_per_m`): without it, 8-10 N along the shaft on seeds 1 and 2.
#[test]
fn pivoting_to_the_cone_does_not_push_the_trocar_along_its_axis() {
    let shipped = shipped();
    let mut rigid = shipped.clone();
    rigid.scope.fulcrum.axial_damping_ns_per_m = 0.0;
    let mut before: f64 = 0.0;
    for seed in 1..=3 {
        let (along, cone) = pan_to_the_cone(&shipped, seed);
        assert!(cone, "seed {seed}: the pan never reached the cone");
        assert!(along < 3.5, "seed {seed}: {along:.2} N along the shaft");
        let without = pan_to_the_cone(&rigid, seed).0;
        eprintln!("seed {seed}: {along:.2} N along the shaft (without the yield {without:.2} N)");
        before = before.max(without);
    }
    assert!(
        before > 6.0,
        "without the yield only {before:.2} N: the test no longer tells"
    );
}

/// The random benchmark's runs that zoom out (seeds 7 and 10: 10 mm/s out for 1.5-2 s,
/// with pans at 10 deg/s): the shipped minimum depth (the docking's 30 mm) stops the zoom and
/// the shaft stays on the wall's port; at the seal's 15 mm (the limit before) the tip left
/// the part of the bore that guides it and the shaft's line passed 3.2 and 9 mm from the
/// port (docs/after-docking.md).
#[test]
fn zooming_out_stops_at_the_docked_depth_and_keeps_the_port() {
    let cfg = realistic();
    let shallow = ControllerParams {
        scope: trocar_docking::control::ScopeParams {
            min_depth_m: 0.015,
            ..shipped().scope
        },
        ..shipped()
    };
    let mut worst: f64 = 0.0;
    for seed in [7, 10] {
        let script = random_script(seed, 6, 10f64.to_radians());
        let go = |c: &ControllerParams| {
            let r = run_pivot(&cfg.sim, c, kin(), seed, &script, &PivotTiming::default()).unwrap();
            assert!(r.docked, "seed {seed}: {}", r.reason);
            r
        };
        let (r, before) = (go(&shipped()), go(&shallow));
        eprintln!(
            "seed {seed}: shaft p95 {:.2} mm ({} steps limited); min depth 15 mm: {:.2} mm",
            r.distance_p95_m * 1e3,
            r.limited_steps,
            before.distance_p95_m * 1e3
        );
        assert!(r.limited_steps > 0, "seed {seed}: the zoom never reached a limit");
        assert_eq!(r.held_steps, 0);
        assert!(r.distance_p95_m < 1.5e-3, "seed {seed}: {} m", r.distance_p95_m);
        // Measured 1.46 against 0.93 mm (seed 7) and 6.06 against 0.77 (seed 10); before the
        // breathing was followed along the docking axis 3.25 and 9.03 mm.
        assert!(
            before.distance_p95_m > 1.3 * r.distance_p95_m,
            "seed {seed}: {} against {} m",
            before.distance_p95_m,
            r.distance_p95_m
        );
        worst = worst.max(before.distance_p95_m);
    }
    assert!(worst > 2.5e-3, "min depth 15 mm: at worst {worst} m");
}

/// After DONE the status's force (`f_ext`) is the shaft's force from its whole wrench, not
/// the docking's estimate from the Jacobian's linear rows, which reads the trocar's tilt
/// spring (a couple across the bore) as a force: through the done-when sequence it follows
/// the true contact force on the shaft.
#[test]
fn after_done_the_reported_force_is_the_shafts_force() {
    for seed in [1, 2] {
        let mut s = docked(seed);
        let (mut err, mut n) = (0.0, 0.0);
        for seg in done_when_script() {
            for _ in 0..(seg.duration * 100.0).round() as usize {
                let o = s.tick(Some(seg.command)).unwrap();
                assert_eq!(o.phase, Phase::Done);
                let truth = s.world().contact().force;
                err += (o.f_ext - truth).norm();
                n += 1.0;
            }
        }
        let mean = err / n;
        eprintln!("seed {seed}: mean |f_ext - true| {mean:.3} N over {n} steps");
        // 0.37-0.42 N measured; the linear rows gave 0.75 N on seed 1.
        assert!(mean < 0.55, "seed {seed}: {mean} N");
    }
}

#[test]
fn the_port_follows_the_breathing_along_the_docking_axis_while_steering() {
    // The trocar breathes 4 mm along its axis (the realistic world). With the shipped
    // `scope.breathing` the law's port moves with the estimated port along the docking
    // axis while the surgeon steers; without it, the port stays where DONE found it and the
    // trocar slides up and down the shaft.
    let cfg = realistic();
    assert!(cfg.sim.breathing.amplitude_axial_m >= 0.003);
    let off = {
        let mut c = shipped();
        c.scope.breathing.follow = false;
        c
    };
    assert!(shipped().scope.breathing.follow);
    let [(along, along_off), (dist, dist_off)] = sums(&shipped(), &off, [|r| r.port_along_p95_m, |r| r.distance_p95_m]);
    // The law's port from the true face along the shaft (since DONE): measured 1.5-2.5 mm
    // against 5.1-9.2 mm (0.25 x).
    assert!(
        along < 0.4 * along_off,
        "law's port from the true face along the shaft, p95 sums: {along} vs {along_off}"
    );
    // Across the shaft (the axial breathing's part once the scope is panned) it does not
    // cost: the shaft from the true port, measured 2.33 against 2.57 mm (0.9 x; seeds 1-40
    // of both benchmark scripts: docs/after-docking.md).
    assert!(
        dist <= dist_off,
        "shaft from the true port, p95 sums: {dist} vs {dist_off}"
    );
}

/// A withdrawal leaves at `scope.retract_speed_m_s` along the shaft, although the port
/// breathed while the scope held still before it: the law's port does not follow the
/// breathing while withdrawing (the seal drags the trocar out with the scope, and a port
/// followed there fed the withdrawal back into itself: measured 25-26 mm/s along the shaft
/// for a 5 mm/s withdrawal, seed 1, before). The true tip, every control period.
#[test]
fn a_withdrawal_leaves_at_its_own_speed_along_the_shaft() {
    let c = shipped();
    for seed in SEEDS {
        let mut s = docked(seed);
        let t0 = s.world().time();
        while s.world().time() < t0 + 1.0 {
            s.tick(None).unwrap();
        }
        assert!(s.controller().retract().is_ok());
        let (mut last, axis) = s.shaft();
        let mut fastest = 0.0f64;
        loop {
            let o = s.tick(None).unwrap();
            if o.phase != Phase::Retract {
                assert_eq!(o.phase, Phase::Idle, "seed {seed}: {:?}", o.hold);
                break;
            }
            let (tip, _) = s.shaft();
            fastest = fastest.max(-(tip - last).dot(&axis) / c.dt_s);
            last = tip;
            assert!(s.world().time() < t0 + 30.0, "seed {seed}: still withdrawing");
        }
        eprintln!("seed {seed}: fastest {:.1} mm/s along the shaft", fastest * 1e3);
        assert!(
            fastest < 1.25 * c.scope.retract_speed_m_s,
            "seed {seed}: the tip withdrew at {:.1} mm/s",
            fastest * 1e3
        );
    }
}
