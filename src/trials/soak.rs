//! The soak (`trocar_docking soak`): the simulated pipeline through repeated docking cycles at the
//! control rate (the shipped 100 Hz by default) for a wall-clock duration, with ONE controller for the
//! whole run (reset and started again every cycle, as the node would be), every cycle a
//! fresh draw of the world (seed, seed + 1, ...), so that what a long run accumulates
//! shows: every cycle's outcome, judged at DONE by the trials' rule, the time of every
//! controller step (percentiles and the worst, wall clock and the thread's CPU clock), and
//! the resident memory (RSS) growth per hour. Not part of CI: a 60-minute run is
//! `trocar_docking soak --minutes 60 --json`.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::closed_loop::{control_input, ClosedLoop};
use super::config::{load_controller, Protocol, SimConfig};
use super::run::{docked_at_done, over_abort_force, TrialParams};
use crate::control::{Controller, Phase};
use crate::kinematics::lbr::{LbrModel, ToolParams};
use crate::kinematics::{Kinematics, LbrKinematics};
use crate::realtime::thread_cpu_time;
use crate::sim::SimWorld;
use crate::stats::LogHistogram;

/// What a soak runs: its duration, rate, world, seeds and controller.
#[derive(Debug, Clone)]
pub struct SoakOptions {
    /// Wall-clock duration of the run, minutes.
    pub minutes: f64,
    /// Control rate, Hz (the physics runs at its own rate, 1 kHz); `None`: the controller
    /// configuration's own (`dt_s`).
    pub rate: Option<f64>,
    /// World protocol of `config/sim.yaml`.
    pub protocol: Protocol,
    /// First seed: cycle k runs the world drawn with seed + k (every cycle a new draw).
    pub seed: u64,
    /// Simulated time a cycle may take to reach DONE, s.
    pub cycle_timeout: f64,
    /// Controller configuration (default: config/controller.yaml).
    pub controller_config: Option<std::path::PathBuf>,
    /// Seconds of the fixed reference workload timed before the run (0: none).
    pub reference_seconds: f64,
}

/// A cycle that did not dock: its seed and how it ended.
#[derive(Debug, Clone, Serialize)]
pub struct Failure {
    /// Its seed.
    pub seed: u64,
    /// How it ended (the trials' outcome names: `false_done`, `held`, `timeout`, `aborted`,
    /// `force_abort`; `error`: the cycle failed, its error in `error`).
    pub outcome: &'static str,
    /// The error of a cycle that failed ('' = none).
    pub error: String,
    /// Its final phase.
    pub phase: &'static str,
    /// Its final hold code ('' = none).
    pub hold_code: &'static str,
}

/// Percentiles of a time over every step (the rule of [`crate::stats`] within 0.2 %; the maximum exact), µs.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct StepTimes {
    /// Median.
    pub p50_us: f64,
    /// 99th percentile.
    pub p99_us: f64,
    /// 99.9th percentile.
    pub p999_us: f64,
    /// The longest step.
    pub max_us: f64,
}

/// What a soak run reports.
#[derive(Debug, Clone, Serialize)]
pub struct SoakReport {
    /// World protocol.
    pub protocol: &'static str,
    /// Seeds of the first and the last cycle.
    pub seeds: [u64; 2],
    /// Wall time run, s.
    pub wall_s: f64,
    /// Simulated time run, s.
    pub sim_s: f64,
    /// Control rate, Hz.
    pub rate_hz: f64,
    /// Docking cycles run.
    pub cycles: usize,
    /// Cycles that ended DONE with the truth agreeing (the trials' `docked`).
    pub docked: usize,
    /// Cycles that ended DONE with the truth disagreeing.
    pub false_done: usize,
    /// Whether every cycle docked.
    pub every_cycle_docked: bool,
    /// Every cycle by outcome, e.g. `docked`, `held (FORCE_LIMIT)`.
    pub outcomes: BTreeMap<String, usize>,
    /// The first [`MAX_LISTED`] cycles that did not dock, with how they ended (`outcomes`
    /// counts them all; the list is bounded so that the run's own records do not grow the
    /// RSS it measures).
    pub failures: Vec<Failure>,
    /// Controller steps, every one of them timed.
    pub steps: u64,
    /// Every step's wall time (preemption included).
    pub step_wall: StepTimes,
    /// Every step's time on the thread's CPU clock (its own work, and on a virtual machine
    /// the time the hypervisor took from it).
    pub step_cpu: StepTimes,
    /// Controller steps over 1 ms (wall clock).
    pub steps_over_1ms: u64,
    /// Controller steps over 1 ms on the thread's CPU clock.
    pub steps_over_1ms_cpu: u64,
    /// Of those, the steps in which Clarabel solved a QP.
    pub steps_over_1ms_cpu_clarabel: u64,
    /// The controller steps' CPU time in all, s (to compare with the reference's rate).
    pub steps_cpu_s: f64,
    /// The machine's share: a fixed workload timed the same way, before the run.
    pub reference: Reference,
    /// Largest lead of a command over the measured joints, deg (bound:
    /// `guard.max_command_lead_rad`).
    pub max_command_lead_deg: f64,
    /// RSS after the first cycle (the baseline), kB.
    pub rss_start_kb: u64,
    /// RSS at the end, kB.
    pub rss_end_kb: u64,
    /// Largest RSS seen, kB.
    pub rss_max_kb: u64,
    /// (end - start) RSS per hour of wall time after the first cycle, MB/h.
    pub rss_growth_mb_per_h: f64,
}

/// At most this many failed cycles are listed one by one.
pub const MAX_LISTED: usize = 100;

/// Step durations in the project's log-linear histogram (nanoseconds, 3 significant digits,
/// [`crate::stats::LogHistogram`]) with the exact maximum: percentiles over millions of steps
/// by the one quantile rule of [`crate::stats`] without keeping the steps.
#[derive(Debug, Clone)]
struct Histogram {
    counts: LogHistogram,
    max: Duration,
}

impl Histogram {
    fn new() -> Self {
        Self {
            counts: LogHistogram::new(),
            max: Duration::ZERO,
        }
    }

    fn add(&mut self, d: Duration) {
        self.counts.record(u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
        self.max = self.max.max(d);
    }

    /// The `q` quantile, µs (0 when empty).
    fn quantile_us(&self, q: f64) -> f64 {
        self.counts.quantile(q) * 1e-3
    }

    fn count(&self) -> u64 {
        self.counts.len()
    }

    fn times(&self) -> StepTimes {
        StepTimes {
            p50_us: self.quantile_us(0.5),
            p99_us: self.quantile_us(0.99),
            p999_us: self.quantile_us(0.999),
            max_us: self.max.as_secs_f64() * 1e6,
        }
    }
}

/// The resident set size of this process, kB (0 where /proc is not readable).
fn rss_kb() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse().ok())
        })
        .unwrap_or(0)
}

/// One docking cycle in a fresh world with `ctrl` reset and started: how it ended, the
/// simulated time it took, and a checksum of its commands (a cycle that commands the same
/// bit for bit computed the same steps).
struct Cycle {
    phase: Phase,
    hold_code: &'static str,
    /// It ended in a latched hold (only an operator resumes it).
    latched: bool,
    /// It ended DONE and the truth agreed.
    docked: bool,
    /// The true contact force passed the trials' `abort_force_n` (its value, N).
    force_abort: Option<f64>,
    sim_s: f64,
    /// Read by the tests: a reset controller must command what a new one does.
    #[cfg_attr(not(test), allow(dead_code))]
    checksum: u64,
}

impl Cycle {
    /// Its outcome by the trials' names.
    fn outcome(&self) -> &'static str {
        if self.force_abort.is_some() {
            return "force_abort";
        }
        match self.phase {
            Phase::Done if self.docked => "docked",
            Phase::Done => "false_done",
            Phase::Aborted | Phase::Idle => "aborted",
            _ if self.latched && self.hold_code == "DEPTH_UNCERTAIN" => "depth_uncertain",
            _ if self.latched => "held",
            _ => "timeout",
        }
    }
}

/// One controller step as the soak saw it.
struct Sample {
    wall: Duration,
    cpu: Option<Duration>,
    /// Whether Clarabel solved a QP in it.
    clarabel: bool,
}

/// Per-step timing (and the command's lead over the arm) over the whole run.
struct Timing {
    wall: Histogram,
    cpu: Histogram,
    over_1ms: u64,
    cpu_total: Duration,
    over_1ms_cpu: u64,
    /// Of those, the steps in which Clarabel solved a QP (the active set did not settle it).
    over_1ms_cpu_clarabel: u64,
    max_lead: f64,
}

impl Timing {
    fn new() -> Self {
        Self {
            wall: Histogram::new(),
            cpu: Histogram::new(),
            over_1ms: 0,
            cpu_total: Duration::ZERO,
            over_1ms_cpu: 0,
            over_1ms_cpu_clarabel: 0,
            max_lead: 0.0,
        }
    }

    fn add(&mut self, s: &Sample) {
        let ms = Duration::from_millis(1);
        self.wall.add(s.wall);
        self.over_1ms += u64::from(s.wall > ms);
        if let Some(c) = s.cpu {
            self.cpu.add(c);
            self.cpu_total += c;
            self.over_1ms_cpu += u64::from(c > ms);
            self.over_1ms_cpu_clarabel += u64::from(c > ms && s.clarabel);
        }
    }
}

/// Fold a command into a checksum (its bits, order-sensitive).
fn fold(sum: u64, q: &crate::kinematics::JointVector) -> u64 {
    q.iter().fold(sum, |h, x| {
        h.rotate_left(5) ^ x.to_bits().wrapping_mul(0x9E37_79B9_7F4A_7C15)
    })
}

/// Run one cycle to DONE, an abort, a latched hold, the trials' force abort
/// ([`over_abort_force`]) or the timeout, as a trial ends; `on_step` sees every step (its
/// wall and CPU time) and the command's lead over the arm.
fn run_cycle(
    world: &mut SimWorld,
    ctrl: &mut Controller,
    setup: &Setup,
    a: &SoakOptions,
    on_step: &mut dyn FnMut(&Sample, f64),
) -> Result<Cycle, String> {
    ctrl.reset();
    ctrl.start()?;
    let kin = &setup.kin;
    let mut out_phase = ctrl.phase();
    let (mut hold_code, mut latched) = ("", false);
    let mut checksum = 0u64;
    let mut force_abort = None;
    let mut plant = ClosedLoop::new(world, ctrl.params().dt_s);
    while world.time() < a.cycle_timeout {
        let input = control_input(&plant.observe(world), None);
        let (started, cpu0) = (Instant::now(), thread_cpu_time());
        let out = ctrl.step(kin, &input);
        let cpu = thread_cpu_time().zip(cpu0).map(|(b, a)| b.saturating_sub(a));
        let sample = Sample {
            wall: started.elapsed(),
            cpu,
            clarabel: out.solve.as_ref().is_some_and(|r| r.clarabel_qps > 0),
        };
        let lead = out.command.map_or(0.0, |q| (q - world.joint_positions()).amax());
        on_step(&sample, lead);
        out_phase = out.phase;
        hold_code = out.hold.as_ref().map_or("", |h| h.code());
        latched = ctrl.hold_latched();
        if latched || matches!(out.phase, Phase::Done | Phase::Aborted | Phase::Idle) {
            break;
        }
        if let Some(q) = &out.command {
            checksum = fold(checksum, q);
        }
        let over = over_abort_force(setup.trial.abort_force_n);
        match plant.advance_until(world, out.command.as_ref(), over) {
            Ok(std::ops::ControlFlow::Continue(())) => {}
            Ok(std::ops::ControlFlow::Break(f)) => {
                force_abort = Some(f);
                break;
            }
            Err(e) => return Err(e.to_string()),
        }
    }
    Ok(Cycle {
        phase: out_phase,
        hold_code,
        latched,
        docked: force_abort.is_none() && out_phase == Phase::Done && docked_at_done(world, &setup.trial),
        force_abort,
        sim_s: world.time(),
        checksum,
    })
}

/// The machine's own share of the timing: a fixed arithmetic workload timed in chunks on
/// the thread's CPU clock, as the controller steps are. On a virtual machine whose
/// hypervisor runs other guests, stolen time shows up in the thread's CPU clock; the
/// chunks over 1 ms are that, since the workload never changes.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Reference {
    /// Seconds run.
    pub seconds: f64,
    /// Chunks timed.
    pub chunks: u64,
    /// Median chunk, µs of thread CPU.
    pub median_us: f64,
    /// Total CPU timed, s.
    pub cpu_s: f64,
    /// Chunks over 1 ms of thread CPU.
    pub over_1ms: u64,
    /// Longest chunk, µs of thread CPU.
    pub max_us: f64,
}

/// Time the fixed workload for `seconds`.
fn reference(seconds: f64) -> Reference {
    let t0 = Instant::now();
    let mut r = Reference {
        seconds,
        ..Reference::default()
    };
    let mut h = Histogram::new();
    let mut x = 1.0f64;
    let mut total = Duration::ZERO;
    while t0.elapsed().as_secs_f64() < seconds {
        let Some(c0) = thread_cpu_time() else {
            return r;
        };
        for i in 0..2000u32 {
            x = (x * 1.000_000_1 + f64::from(i).sqrt()).sin();
        }
        std::hint::black_box(x);
        let c = thread_cpu_time().map_or(Duration::ZERO, |c1| c1.saturating_sub(c0));
        r.over_1ms += u64::from(c > Duration::from_millis(1));
        total += c;
        h.add(c);
    }
    r.chunks = h.count();
    r.median_us = h.quantile_us(0.5);
    r.max_us = h.max.as_secs_f64() * 1e6;
    r.cpu_s = total.as_secs_f64();
    r
}

/// What a cycle starts from: the world's configuration, the trial's rule, the controller's.
struct Setup {
    sim: crate::sim::SimParams,
    trial: TrialParams,
    kin: LbrKinematics,
    shared: Arc<dyn Kinematics>,
    params: crate::control::ControllerParams,
}

impl Setup {
    /// The world of `a.protocol` and the controller of `a.controller_config` at `a.rate`,
    /// with force feedback.
    fn new(a: &SoakOptions) -> Result<Self, Box<dyn std::error::Error + Send + Sync>> {
        let cfg = SimConfig::load_default()?.with_protocol(a.protocol.name())?;
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())?;
        let mut params = load_controller(a.controller_config.as_deref())?;
        if let Some(rate) = a.rate {
            params.dt_s = 1.0 / rate;
        }
        params.force_feedback = true;
        Ok(Self {
            sim: cfg.sim,
            trial: cfg.trial,
            shared: Arc::new(kin.clone()),
            kin,
            params,
        })
    }

    /// A new world with `seed`.
    fn world(&self, seed: u64) -> Result<SimWorld, String> {
        SimWorld::new(&self.sim, self.shared.clone(), seed).map_err(|e| e.to_string())
    }

    /// A new controller.
    fn controller(&self) -> Result<Controller, String> {
        Controller::new(self.params.clone(), self.kin.limits().clone()).map_err(|e| e.to_string())
    }
}

/// The cycles of a run: how they ended, and their timing.
struct Cycles {
    count: usize,
    docked: usize,
    false_done: usize,
    sim_s: f64,
    outcomes: BTreeMap<String, usize>,
    failures: Vec<Failure>,
    timing: Timing,
    rss_start: u64,
    rss_max: u64,
}

/// Docking cycles until `deadline` of wall time (at least one), with one controller, each
/// in a new world (seed, seed + 1, ...).
fn run_cycles(a: &SoakOptions, setup: &Setup, deadline: Duration) -> Result<(Cycles, Instant), String> {
    let mut ctrl = setup.controller()?;
    let t0 = Instant::now();
    let mut baseline_at = t0;
    let mut r = Cycles {
        count: 0,
        docked: 0,
        false_done: 0,
        sim_s: 0.0,
        outcomes: BTreeMap::new(),
        failures: vec![],
        timing: Timing::new(),
        rss_start: 0,
        rss_max: 0,
    };
    while r.count == 0 || t0.elapsed() < deadline {
        let seed = a.seed.wrapping_add(r.count as u64);
        let timing = &mut r.timing;
        let mut on_step = |s: &Sample, lead: f64| {
            timing.add(s);
            timing.max_lead = timing.max_lead.max(lead);
        };
        // An error in one cycle (its world, its start, its physics) is that cycle's
        // outcome: the soak goes on with the next.
        let cycle = setup
            .world(seed)
            .and_then(|mut world| run_cycle(&mut world, &mut ctrl, setup, a, &mut on_step));
        r.count += 1;
        let c = match cycle {
            Ok(c) => c,
            Err(error) => {
                *r.outcomes.entry("error".to_string()).or_insert(0) += 1;
                if r.failures.len() < MAX_LISTED {
                    r.failures.push(Failure {
                        seed,
                        outcome: "error",
                        phase: ctrl.phase().as_str(),
                        hold_code: "",
                        error,
                    });
                }
                continue;
            }
        };
        r.sim_s += c.sim_s;
        let outcome = c.outcome();
        let key = match c.hold_code {
            "" => outcome.to_string(),
            code => format!("{outcome} ({code})"),
        };
        *r.outcomes.entry(key).or_insert(0) += 1;
        r.docked += usize::from(c.docked);
        r.false_done += usize::from(outcome == "false_done");
        if !c.docked && r.failures.len() < MAX_LISTED {
            r.failures.push(Failure {
                seed,
                outcome,
                phase: c.phase.as_str(),
                hold_code: c.hold_code,
                error: String::new(),
            });
        }
        let rss = rss_kb();
        r.rss_max = r.rss_max.max(rss);
        if r.rss_start == 0 {
            // The first cycle warms up (allocator pools, lazy statics): the baseline.
            (r.rss_start, baseline_at) = (rss, Instant::now());
        }
    }
    Ok((r, baseline_at))
}

/// Run the soak; the report.
pub fn soak(a: &SoakOptions) -> Result<SoakReport, Box<dyn std::error::Error + Send + Sync>> {
    if let Some(rate) = a.rate {
        crate::validate::positive_at_most("rate", rate, 1000.0)?;
    }
    crate::validate::positive("minutes", a.minutes)?;
    crate::validate::positive("cycle_timeout", a.cycle_timeout)?;
    crate::validate::non_negative("reference_seconds", a.reference_seconds)?;
    let setup = Setup::new(a)?;
    let reference = reference(a.reference_seconds);
    let t0 = Instant::now();
    let (c, baseline_at) = run_cycles(a, &setup, Duration::from_secs_f64(a.minutes * 60.0))?;
    let rss_end = rss_kb();
    let hours = baseline_at.elapsed().as_secs_f64() / 3600.0;
    let t = &c.timing;
    Ok(SoakReport {
        protocol: a.protocol.name(),
        seeds: [a.seed, a.seed.wrapping_add(c.count as u64 - 1)],
        wall_s: t0.elapsed().as_secs_f64(),
        sim_s: c.sim_s,
        rate_hz: 1.0 / setup.params.dt_s,
        cycles: c.count,
        docked: c.docked,
        false_done: c.false_done,
        every_cycle_docked: c.docked == c.count,
        outcomes: c.outcomes,
        failures: c.failures,
        steps: t.wall.count(),
        step_wall: t.wall.times(),
        step_cpu: t.cpu.times(),
        steps_over_1ms: t.over_1ms,
        steps_cpu_s: t.cpu_total.as_secs_f64(),
        steps_over_1ms_cpu: t.over_1ms_cpu,
        steps_over_1ms_cpu_clarabel: t.over_1ms_cpu_clarabel,
        reference,
        max_command_lead_deg: t.max_lead.to_degrees(),
        rss_start_kb: c.rss_start,
        rss_end_kb: rss_end,
        rss_max_kb: c.rss_max,
        rss_growth_mb_per_h: if hours > 0.0 {
            (rss_end as f64 - c.rss_start as f64) / 1024.0 / hours
        } else {
            0.0
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args() -> SoakOptions {
        SoakOptions {
            minutes: 0.001,
            rate: Some(1000.0),
            protocol: Protocol::Realistic,
            seed: 1,
            cycle_timeout: 30.0,
            controller_config: None,
            reference_seconds: 0.0,
        }
    }

    #[test]
    fn a_reset_controller_commands_exactly_as_a_new_one() {
        // One controller serves the whole soak: reset, it must compute what a new one does.
        // At the shipped rate (the 1 kHz loop docks the realistic world worse: simulation.md).
        let a = SoakOptions { rate: None, ..args() };
        let s = Setup::new(&a).unwrap();
        let cycle =
            |seed, ctrl: &mut Controller| run_cycle(&mut s.world(seed).unwrap(), ctrl, &s, &a, &mut |_, _| {}).unwrap();
        let new = cycle(1, &mut s.controller().unwrap());
        let mut used = s.controller().unwrap();
        let other = cycle(2, &mut used);
        let again = cycle(1, &mut used);
        // To the goal: DONE, or held there on the depth's uncertainty (control::docking::depth).
        assert!(
            matches!(
                (new.phase, new.outcome()),
                (Phase::Done, "docked") | (Phase::Hold, "depth_uncertain")
            ),
            "{:?} {}",
            new.phase,
            new.outcome()
        );
        assert_ne!(other.checksum, new.checksum, "seeds 1 and 2 command alike");
        assert_eq!(again.checksum, new.checksum, "the reset controller commanded otherwise");
    }

    #[test]
    fn every_cycle_is_a_new_world_and_every_step_is_counted() {
        let a = SoakOptions { rate: None, ..args() };
        let r = soak(&a).unwrap();
        assert!(r.cycles >= 1 && r.seeds == [1, r.cycles as u64]);
        assert_eq!(r.outcomes.values().sum::<usize>(), r.cycles);
        assert_eq!(r.failures.len(), (r.cycles - r.docked).min(MAX_LISTED));
        assert_eq!(r.outcomes.get("docked").copied().unwrap_or(0), r.docked);
        // At 100 Hz a docking of 3-5 s is 300-500 steps, each timed.
        assert!(r.steps >= 300 * r.cycles as u64, "{} steps", r.steps);
        let c = r.step_cpu;
        assert!(
            c.p50_us > 0.0 && c.p50_us <= c.p99_us && c.p99_us <= c.p999_us && c.p999_us <= c.max_us,
            "{c:?}"
        );
    }

    /// The trials' force abort ends a soak cycle as it ends a trial (a 0.5 N abort: the
    /// first contact passes it), and a cycle that fails (here its world cannot be made) is
    /// counted as an `error` with its reason, the soak going on.
    #[test]
    fn a_force_abort_and_an_error_are_outcomes_of_their_cycle() {
        let a = args();
        let mut s = Setup::new(&a).unwrap();
        s.trial.abort_force_n = 0.5;
        let c = run_cycle(
            &mut s.world(1).unwrap(),
            &mut s.controller().unwrap(),
            &s,
            &a,
            &mut |_, _| {},
        )
        .unwrap();
        assert_eq!(c.outcome(), "force_abort");
        assert!(c.force_abort.is_some_and(|f| f > 0.5), "{:?}", c.force_abort);
        assert!(!c.docked);
        s.sim.physics_rate_hz = -1.0;
        let (r, _) = run_cycles(&a, &s, Duration::ZERO).unwrap();
        assert_eq!(r.count, 1);
        assert_eq!(r.outcomes.get("error").copied(), Some(1));
        assert_eq!(r.failures[0].outcome, "error");
        assert!(r.failures[0].error.contains("physics_rate"), "{}", r.failures[0].error);
    }

    #[test]
    fn step_times_follow_the_one_quantile_rule() {
        let mut h = Histogram::new();
        for us in 1..=100u64 {
            h.add(Duration::from_micros(us));
        }
        let close = |got: f64, want: f64| (got - want).abs() <= want / 512.0;
        // Interpolated between the closest ranks, as crate::stats::quantile_sorted.
        assert!(close(h.quantile_us(0.5), 50.5), "{}", h.quantile_us(0.5));
        assert!(close(h.quantile_us(0.99), 99.01), "{}", h.quantile_us(0.99));
        assert!(close(h.quantile_us(1.0), 100.0));
        h.add(Duration::from_millis(50));
        assert_eq!(h.times().max_us, 50_000.0, "the maximum is exact");
        assert_eq!(Histogram::new().quantile_us(0.5), 0.0);
    }

    #[test]
    fn the_reference_workload_is_timed_in_chunks() {
        let r = reference(0.05);
        assert!(r.chunks > 10, "{r:?}");
        assert!(r.median_us > 0.0 && r.max_us >= r.median_us, "{r:?}");
        assert!(r.cpu_s > 0.0 && r.cpu_s <= 0.06, "{r:?}");
        assert_eq!(reference(0.0).chunks, 0);
    }
}
