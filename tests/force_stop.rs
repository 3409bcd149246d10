//! The force stop after docking, in closed loop on the realistic simulated plant
//! (`config/sim.yaml`'s `realistic` protocol) with the shipped `config/controller.yaml`: a
//! stiff obstacle catches the scope's tip ([`trocar_docking::sim::jam`]) while the surgeon
//! pans, while the scope withdraws (RETRACT), and while the scope is held still and the
//! law follows the port's breathing. The stop must hold the arm (HOLD `FORCE_LIMIT`) with
//! the true contact force, read at every physics step (10 per control period), under the
//! limit + 20 %, keep it held until the operator's start, and resume the interrupted phase;
//! without the stop (its limits at the largest values the parameters allow) the same
//! scenario passes that bound, so the tests can fail.

use std::sync::Arc;

use nalgebra::Point3;
use trocar_docking::control::{ControllerParams, Phase, ScopeCommand};
use trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use trocar_docking::kinematics::{Kinematics, LbrKinematics};
use trocar_docking::sim::Jam;
use trocar_docking::trials::config::{load_controller, SimConfig};
use trocar_docking::trials::pivot::PivotSession;

fn kin() -> Arc<dyn Kinematics> {
    Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap())
}

fn shipped() -> ControllerParams {
    load_controller(None).unwrap()
}

/// The shipped controller with both force stops at the largest values allowed: no stop.
fn without_stop() -> ControllerParams {
    let mut c = shipped();
    c.guard.force_stop_n = 200.0;
    c.scope.retract_force_stop_n = 200.0;
    c
}

/// The obstacle's damping, N s/m.
const JAM_DAMPING: f64 = 20.0;

/// What a jammed run showed.
struct Jammed {
    /// Largest true contact force on the shaft from the jam on, N.
    peak_n: f64,
    /// Phase and hold code at the end.
    phase: Phase,
    code: &'static str,
    /// Steps in HOLD after the first.
    held: usize,
    /// How far the true tip moved from 0.2 s into the hold (the braking done) to the end, m.
    moved_while_held_m: f64,
    session: PivotSession,
}

/// What the scope does when the jam catches it.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Motion {
    /// Panning at 0.17 rad/s (the pivot targets' pan).
    Pan,
    /// Withdrawing (RETRACT, begun 0.3 s before).
    Retract,
    /// Held still by the surgeon (no command): the law follows the port's breathing.
    Still,
}

/// Dock `seed`, settle, then (`Retract`: begin a withdrawal and let it run 0.3 s) catch
/// the tip with an obstacle of `stiffness` N/m and go on (`motion`) for `for_s`.
fn jam(controller: &ControllerParams, seed: u64, motion: Motion, stiffness: f64, for_s: f64) -> Jammed {
    let retract = motion == Motion::Retract;
    let cfg = SimConfig::load_default().unwrap().with_protocol("realistic").unwrap();
    let mut s = PivotSession::dock(&cfg.sim, controller, kin(), seed, 20.0)
        .unwrap()
        .unwrap();
    let pan = ScopeCommand {
        pan: 0.17,
        ..Default::default()
    };
    let t0 = s.world().time();
    while s.world().time() < t0 + 0.5 {
        s.tick(None).unwrap();
    }
    if retract {
        s.controller().retract().unwrap();
        let t1 = s.world().time();
        while s.world().time() < t1 + 0.3 {
            assert_eq!(s.tick(None).unwrap().phase, Phase::Retract);
        }
    }
    let tip = Point3::from(s.world().tip_pose().translation.vector);
    s.world_mut()
        .set_jam(Some(Jam::new(tip, stiffness, JAM_DAMPING).unwrap()));
    let t2 = s.world().time();
    let (mut peak, mut held, mut held_at) = (0.0f64, 0usize, None);
    let mut moved = 0.0f64;
    let mut last = None;
    while s.world().time() < t2 + for_s {
        let command = (motion == Motion::Pan).then_some(pan);
        let o = s
            .tick_watched(command, |w| peak = peak.max(w.contact().force.norm()))
            .unwrap();
        if o.phase == Phase::Hold {
            held += 1;
        }
        let now = s.world().time();
        let p = Point3::from(s.world().tip_pose().translation.vector);
        if held_at.is_none() && held >= 20 {
            held_at = Some(p);
        }
        if let Some(a) = held_at {
            moved = moved.max(nalgebra::distance(&a, &p));
        }
        assert!(now < t2 + for_s + 1.0);
        last = Some((o.phase, o.reason_code()));
    }
    let (phase, code) = last.unwrap();
    eprintln!(
        "{motion:?} seed {seed}, {stiffness} N/m, stop at {} N: true peak {peak:.2} N (every physics step), {held} steps held, {code}",
        if retract {
            controller.scope.retract_force_stop_n
        } else {
            controller.guard.force_stop_n
        },
    );
    Jammed {
        peak_n: peak,
        phase,
        code,
        held,
        moved_while_held_m: moved,
        session: s,
    }
}

/// A start while the tip is still caught: refused while the force estimate is over
/// `limit`; taken, the phase resumes and the force stop holds it again within 0.5 s, the
/// true force under `limit` + 20 %.
fn start_while_caught(s: &mut PivotSession, limit: f64, seed: u64) {
    match s.controller().start() {
        Err(refused) => assert!(refused.contains("still over"), "seed {seed}: {refused}"),
        Ok(()) => {
            let t = s.world().time();
            let mut held = None;
            while s.world().time() < t + 0.5 && held.is_none() {
                let mut f = 0.0f64;
                let o = s.tick_watched(None, |w| f = f.max(w.contact().force.norm())).unwrap();
                assert!(f < 1.2 * limit, "seed {seed}: {f:.1} N after the start");
                held = (o.phase == Phase::Hold).then(|| o.reason_code());
            }
            assert_eq!(
                held,
                Some("FORCE_LIMIT"),
                "seed {seed}: a start into the jam holds again"
            );
        }
    }
}

/// A 3 s jam of `stiffness` N/m while the scope moves as `motion`: the true force under the
/// guard's stop + 20 %, and held with `FORCE_LIMIT` wherever the run held.
fn under_the_stop(c: &ControllerParams, seed: u64, motion: Motion, stiffness: f64) -> Jammed {
    let j = jam(c, seed, motion, stiffness, 3.0);
    assert!(
        j.peak_n < 1.2 * c.guard.force_stop_n,
        "{motion:?} seed {seed}, {stiffness} N/m: true force {:.1} N",
        j.peak_n
    );
    if j.held > 0 {
        assert_eq!(
            (j.phase, j.code),
            (Phase::Hold, "FORCE_LIMIT"),
            "{motion:?} seed {seed}, {stiffness} N/m"
        );
    }
    j
}

/// The jams of the tests: from soft (5000 N/m: three times the abdominal wall's 1500 N/m,
/// config/sim.yaml) to stiff (50 000 N/m, the order of the arm's own stiffness at the tip).
const STIFFNESSES: [f64; 4] = [5000.0, 8000.0, 20_000.0, 50_000.0];

/// A withdrawal into a stiff obstacle brakes at `scope.retract_force_stop_n` and holds, the
/// tip still. The true force, at every physics step, stays under that stop + 20 % (14.4 N)
/// in jams of 5000, 20 000 and 50 000 N/m; without the stop it goes on pulling (over 130 N).
/// Freed and started, it withdraws on, to IDLE. (At the shipped 15 mm/s, the port's
/// breathing not followed while withdrawing; at 20 mm/s the 50 000 N/m jam peaked at 15.9 N:
/// docs/after-docking.md.)
#[test]
fn a_jammed_withdrawal_brakes_and_holds_until_the_operator_starts_it_again() {
    let c = shipped();
    for seed in [1, 2, 3] {
        // 3 s: the 5000 N/m jam reaches the stop well within it (2.4 mm at 15 mm/s).
        let j = jam(&c, seed, Motion::Retract, 5000.0, 3.0);
        assert_eq!((j.phase, j.code), (Phase::Hold, "FORCE_LIMIT"), "seed {seed}");
        assert!(
            j.held >= 150,
            "seed {seed}: held {} steps, never resumed by itself",
            j.held
        );
        assert!(
            j.peak_n < 1.2 * c.scope.retract_force_stop_n,
            "seed {seed}: true force {:.1} N, over the {} N retract stop + 20 %",
            j.peak_n,
            c.scope.retract_force_stop_n
        );
        assert!(
            j.moved_while_held_m < 0.0002,
            "seed {seed}: moved {:.3} mm held",
            j.moved_while_held_m * 1e3
        );
        let mut j = jam(&c, seed, Motion::Retract, 20_000.0, 1.0);
        assert_eq!((j.phase, j.code), (Phase::Hold, "FORCE_LIMIT"), "seed {seed}");
        assert!(
            j.peak_n < 1.2 * c.scope.retract_force_stop_n,
            "seed {seed}: 20 000 N/m: true force {:.1} N, over the {} N retract stop + 20 %",
            j.peak_n,
            c.scope.retract_force_stop_n
        );
        let stiff = jam(&c, seed, Motion::Retract, 50_000.0, 1.0);
        assert!(
            stiff.peak_n < 1.2 * c.scope.retract_force_stop_n,
            "seed {seed}: 50 000 N/m: true force {:.1} N, over the {} N retract stop + 20 %",
            stiff.peak_n,
            c.scope.retract_force_stop_n
        );
        // Still caught: a start is refused while the estimate is over the limit, and one
        // taken (the stop acted on the predicted force) meets the stop again, under the
        // retract stop + 20 %.
        let s = &mut j.session;
        start_while_caught(s, c.scope.retract_force_stop_n, seed);
        // Freed: once the estimate is under the limit a start goes on withdrawing, to IDLE.
        s.world_mut().set_jam(None);
        let t = s.world().time();
        while s.world().time() < t + 0.5 {
            s.tick(None).unwrap();
        }
        s.controller().start().unwrap();
        let o = s.tick(None).unwrap();
        assert_eq!(
            o.phase,
            Phase::Retract,
            "seed {seed}: the start continues the withdrawal"
        );
        // The longest withdrawal (the deepest tip, `max_depth_m`, to the stand-off point) at
        // its speed, and a second.
        let longest = 1.0 + (c.scope.max_depth_m + c.standoff_m) / c.scope.retract_speed_m_s;
        let mut phase = o.phase;
        while phase == Phase::Retract {
            phase = s.tick(None).unwrap().phase;
            assert!(s.world().time() < t + longest, "seed {seed}: still withdrawing");
        }
        assert_eq!(phase, Phase::Idle, "seed {seed}");
        let without = jam(&without_stop(), seed, Motion::Retract, 5000.0, 2.0);
        assert!(
            without.peak_n > 1.2 * c.guard.force_stop_n,
            "seed {seed}: without the stop only {:.1} N",
            without.peak_n
        );
    }
}

/// The pivot targets' pan (0.17 rad/s) with the tip caught, from soft to stiff
/// ([`STIFFNESSES`], seeds 1-3): the true force stays under the 20 N stop + 20 % (measured
/// 4.4-21.3 N; before the rate bounds and the predicted stop 24.9-28.2 N at 8000 N/m and
/// up to 67 N at 20 000 N/m). Against the soft jams the fulcrum and the depth give way to
/// the caught tip and the force stays under the stop; against the stiff ones DONE holds,
/// `FORCE_LIMIT`, the scope stays where it stopped and stays held until a start; without
/// the stop the force passes the bound in the worst of the seeds (50 000 N/m: 24.6-30.5 N,
/// the fulcrum and the depth giving way).
#[test]
fn a_jammed_pan_stays_under_the_stop_and_holds_with_the_scope_where_it_stopped() {
    let c = shipped();
    let mut worst_without = 0.0f64;
    for seed in [1, 2, 3] {
        for k in STIFFNESSES {
            under_the_stop(&c, seed, Motion::Pan, k);
        }
        let mut j = jam(&c, seed, Motion::Pan, 50_000.0, 3.0);
        assert_eq!((j.phase, j.code), (Phase::Hold, "FORCE_LIMIT"), "seed {seed}");
        assert!(j.held >= 100, "seed {seed}: held {} steps", j.held);
        assert!(
            j.moved_while_held_m < 0.00025,
            "seed {seed}: moved {:.3} mm held",
            j.moved_while_held_m * 1e3
        );
        worst_without = worst_without.max(jam(&without_stop(), seed, Motion::Pan, 50_000.0, 3.0).peak_n);
        // Freed and started: DONE again, re-anchored where the scope is (no jump: the guard
        // would hold on one), steering again.
        let s = &mut j.session;
        s.world_mut().set_jam(None);
        let t = s.world().time();
        while s.world().time() < t + 0.5 {
            s.tick(None).unwrap();
        }
        s.controller().start().unwrap();
        let pan = ScopeCommand {
            pan: -0.17,
            ..Default::default()
        };
        for _ in 0..50 {
            let o = s.tick(Some(pan)).unwrap();
            assert_eq!(o.phase, Phase::Done, "seed {seed}: {:?}", o.hold);
        }
    }
    assert!(
        worst_without > 1.2 * c.guard.force_stop_n,
        "without the stop only {worst_without:.1} N"
    );
}

/// The scope held still (no command) while the law follows the port's breathing, the tip
/// caught from soft to stiff ([`STIFFNESSES`], seeds 1-3): the true force, at every
/// physics step, stays under the guard's 20 N stop + 20 %; where a run holds, it holds with
/// `FORCE_LIMIT` and the scope stays where it stopped (under 0.25 mm, as the pan).
#[test]
fn a_jam_while_the_scope_is_held_still_and_follows_the_breathing_stays_under_the_stop() {
    let c = shipped();
    assert!(c.scope.breathing.follow, "the shipped law follows the breathing");
    for seed in [1, 2, 3] {
        for k in STIFFNESSES {
            let j = under_the_stop(&c, seed, Motion::Still, k);
            if j.held > 0 {
                assert!(
                    j.moved_while_held_m < 0.00025,
                    "seed {seed}, {k} N/m: moved {:.3} mm held",
                    j.moved_while_held_m * 1e3
                );
            }
        }
    }
}
