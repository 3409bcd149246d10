//! `trocar_docking soak`: the simulated pipeline through repeated docking cycles at the
//! control rate (1 kHz by default) for a wall-clock duration, with ONE controller for the
//! whole run (reset and started again every cycle, as the node would be), so that what a
//! long run accumulates shows: the longest controller step, the resident memory (RSS)
//! growth per hour, and every cycle's end (each must be DONE). Not part of CI: a 60-minute
//! run is `trocar_docking soak --minutes 60 --json`.

use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::CliResult;
use crate::control::{ControlInput, Controller, Phase, Stamped};
use crate::kinematics::lbr::{LbrModel, ToolParams};
use crate::kinematics::{Kinematics, LbrKinematics};
use crate::realtime::thread_cpu_time;
use crate::signal::StreamLowPass;
use crate::sim::SimWorld;
use crate::trials::config::{load_controller, Protocol, SimConfig};

/// Arguments of `soak`.
#[derive(Debug, clap::Args)]
pub struct SoakArgs {
    /// Wall-clock duration of the run, minutes.
    #[arg(long, default_value_t = 60.0)]
    pub minutes: f64,
    /// Control rate, Hz (the physics runs at its own rate, 1 kHz).
    #[arg(long, default_value_t = 1000.0)]
    pub rate: f64,
    /// World protocol of `config/sim.yaml`.
    #[arg(long, value_enum, default_value_t = Protocol::Paper)]
    pub protocol: Protocol,
    /// First seed (cycle k runs seed + k % seed_count).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// How many seeds the cycles go through (seeds 1-4 dock; seed 5 is a start pose where
    /// a joint limit prevents the alignment, see the README).
    #[arg(long, default_value_t = 4)]
    pub seed_count: u64,
    /// Simulated time a cycle may take to reach DONE, s.
    #[arg(long, default_value_t = 30.0)]
    pub cycle_timeout: f64,
    /// Controller configuration (default: config/controller.yaml).
    #[arg(long)]
    pub controller_config: Option<std::path::PathBuf>,
    /// Times each step over 1 ms of CPU is replayed (its cycle run again with a new
    /// controller and world) to measure its own cost.
    #[arg(long, default_value_t = 5)]
    pub replays: usize,
    /// At most this many steps over 1 ms of CPU are replayed (the longest).
    #[arg(long, default_value_t = 300)]
    pub max_replayed: usize,
    /// Seconds of the fixed reference workload timed before the run (0: none).
    #[arg(long, default_value_t = 60.0)]
    pub reference_seconds: f64,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// A cycle that did not end in DONE.
#[derive(Debug, Clone, Serialize)]
pub struct Failure {
    /// Its seed.
    pub seed: u64,
    /// Its final phase.
    pub phase: &'static str,
    /// Its final hold code ('' = none).
    pub hold_code: &'static str,
}

/// What a soak run reports.
#[derive(Debug, Clone, Serialize)]
pub struct SoakReport {
    /// Wall time run, s.
    pub wall_s: f64,
    /// Simulated time run, s.
    pub sim_s: f64,
    /// Control rate, Hz.
    pub rate_hz: f64,
    /// Docking cycles run.
    pub cycles: usize,
    /// Cycles that ended DONE.
    pub done: usize,
    /// Whether every cycle ended DONE.
    pub every_cycle_done: bool,
    /// The cycles that did not, with how they ended.
    pub failures: Vec<Failure>,
    /// Controller steps.
    pub steps: u64,
    /// Longest controller step (wall clock, preemption included), µs.
    pub max_step_us: f64,
    /// Controller steps over 1 ms (wall clock).
    pub steps_over_1ms: u64,
    /// Longest controller step on the thread's CPU clock (its own work), µs.
    pub max_step_cpu_us: f64,
    /// Controller steps over 1 ms on the thread's CPU clock.
    pub steps_over_1ms_cpu: u64,
    /// Of those, the steps in which Clarabel solved a QP.
    pub steps_over_1ms_cpu_clarabel: u64,
    /// The controller steps' CPU time in all, s (to compare with the reference's rate).
    pub steps_cpu_s: f64,
    /// The steps over 1 ms of CPU replayed: their own cost.
    pub replay: Replay,
    /// The machine's share: a fixed workload timed the same way, before the run.
    pub reference: Reference,
    /// Largest lead of a command over the measured joints, deg (bound:
    /// `guard.max_command_lead`).
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

/// One docking cycle in a fresh world with `ctrl` reset and started: its final phase and
/// hold code, the simulated time it took, and a checksum of its commands (a
/// replay that commands the same bit for bit computed the same steps).
struct Cycle {
    phase: Phase,
    hold_code: &'static str,
    sim_s: f64,
    checksum: u64,
}

/// One controller step as the soak saw it.
struct Sample {
    /// Its index in the cycle.
    index: u64,
    wall: Duration,
    cpu: Option<Duration>,
    /// Whether Clarabel solved a QP in it.
    clarabel: bool,
}

/// A step over 1 ms of thread CPU: where it was, to replay it.
#[derive(Debug, Clone, Copy)]
struct SlowStep {
    /// The cycle's number in the run.
    cycle: usize,
    /// Its thread CPU time in the run.
    cpu: Duration,
    /// The cycle's seed.
    seed: u64,
    /// The step's index in its cycle.
    index: u64,
    /// The cycle's command checksum.
    checksum: u64,
}

/// At most this many slow steps are kept for the replay.
const MAX_SLOW: usize = 10_000;

/// Per-step timing (and the command's lead over the arm) over the whole run.
#[derive(Default)]
struct Timing {
    steps: u64,
    max: Duration,
    over_1ms: u64,
    max_cpu: Duration,
    cpu_total: Duration,
    over_1ms_cpu: u64,
    /// Of those, the steps in which Clarabel solved a QP (the active set did not settle it).
    over_1ms_cpu_clarabel: u64,
    max_lead: f64,
    /// This cycle's steps over 1 ms of CPU (their indices and CPU times).
    slow_in_cycle: Vec<(u64, Duration)>,
}

impl Timing {
    fn add(&mut self, s: &Sample) {
        let ms = Duration::from_millis(1);
        self.steps += 1;
        self.max = self.max.max(s.wall);
        self.over_1ms += u64::from(s.wall > ms);
        if let Some(c) = s.cpu {
            self.max_cpu = self.max_cpu.max(c);
            self.cpu_total += c;
            self.over_1ms_cpu += u64::from(c > ms);
            self.over_1ms_cpu_clarabel += u64::from(c > ms && s.clarabel);
            if c > ms && self.slow_in_cycle.len() < MAX_SLOW {
                self.slow_in_cycle.push((s.index, c));
            }
        }
    }
}

/// Fold a command into a checksum (its bits, order-sensitive).
fn fold(sum: u64, q: &crate::kinematics::JointVector) -> u64 {
    q.iter().fold(sum, |h, x| {
        h.rotate_left(5) ^ x.to_bits().wrapping_mul(0x9E37_79B9_7F4A_7C15)
    })
}

/// Run one cycle; `on_step` sees every step (its index, its wall and CPU time) and the
/// command's lead over the arm.
fn run_cycle(
    world: &mut SimWorld,
    ctrl: &mut Controller,
    kin: &dyn Kinematics,
    a: &SoakArgs,
    on_step: &mut dyn FnMut(&Sample, f64),
) -> Result<Cycle, String> {
    ctrl.reset();
    ctrl.start()?;
    let period = 1.0 / a.rate;
    let physics = (period * world.params().physics_rate_hz).round().max(1.0) as usize;
    let mut out_phase = ctrl.phase();
    let mut hold_code = "";
    let (mut index, mut checksum) = (0u64, 0u64);
    let mut torques = StreamLowPass::new(ctrl.params().torque_filter_time_constant);
    let mut tau_ext = torques.update(world.time(), &world.external_torques());
    while world.time() < a.cycle_timeout {
        let t = world.time();
        let stamped = |value| Some(Stamped { stamp: t, value });
        let input = ControlInput {
            scope: None,
            now: t,
            joints: stamped(world.joint_positions()),
            tau_ext: stamped(tau_ext),
            trocar: world.measure_trocar(t).map(|m| Stamped {
                stamp: m.stamp,
                value: m.pose,
            }),
        };
        let (started, cpu0) = (Instant::now(), thread_cpu_time());
        let out = ctrl.step(kin, &input);
        let cpu = thread_cpu_time().zip(cpu0).map(|(b, a)| b.saturating_sub(a));
        let sample = Sample {
            index,
            wall: started.elapsed(),
            cpu,
            clarabel: out.solve.as_ref().is_some_and(|r| r.clarabel_qps > 0),
        };
        index += 1;
        let lead = out.command.map_or(0.0, |q| (q - world.joint_positions()).amax());
        on_step(&sample, lead);
        out_phase = out.phase;
        hold_code = out.hold.as_ref().map_or("", |h| h.code());
        if matches!(out.phase, Phase::Done | Phase::Aborted | Phase::Idle) {
            break;
        }
        if let Some(q) = out.command {
            checksum = fold(checksum, &q);
            world.set_command(&q).map_err(|e| e.to_string())?;
        }
        for _ in 0..physics {
            world.step_physics().map_err(|e| e.to_string())?;
            tau_ext = torques.update(world.time(), &world.external_torques());
        }
    }
    Ok(Cycle {
        phase: out_phase,
        hold_code,
        sim_s: world.time(),
        checksum,
    })
}

/// What the replay of the slow steps found.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Replay {
    /// Times each slow step's cycle was replayed (a new controller and world each time).
    pub replays_per_step: usize,
    /// Slow steps replayed: all of them, or the `--max-replayed` longest.
    pub steps: usize,
    /// Of those, the steps whose replays commanded the same as the run, bit for bit (the
    /// same computation; a replay that differs is not a measure of the step).
    pub identical: usize,
    /// The largest own cost of a slow step: over the slow steps, the maximum of the
    /// fastest of its replays, µs of thread CPU.
    pub max_own_cpu_us: f64,
    /// Slow steps whose fastest replay also took over 1 ms of CPU: the steps whose own
    /// cost is over 1 ms.
    pub own_cost_over_1ms: usize,
}

/// The machine's own share of the timing: a fixed arithmetic workload timed in chunks on
/// the thread's CPU clock, as the controller steps are. On a VM whose hypervisor runs
/// other guests, stolen time shows up in the thread's CPU clock; the chunks over 1 ms
/// are that, since the workload never changes.
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
    // A histogram in 1 µs bins up to 10 ms, for the median.
    let mut bins = vec![0u64; 10_001];
    let mut x = 1.0f64;
    let (mut max, mut total) = (Duration::ZERO, Duration::ZERO);
    while t0.elapsed().as_secs_f64() < seconds {
        let Some(c0) = thread_cpu_time() else {
            return r;
        };
        for i in 0..2000u32 {
            x = (x * 1.000_000_1 + f64::from(i).sqrt()).sin();
        }
        std::hint::black_box(x);
        let c = thread_cpu_time().map_or(Duration::ZERO, |c1| c1.saturating_sub(c0));
        r.chunks += 1;
        r.over_1ms += u64::from(c > Duration::from_millis(1));
        max = max.max(c);
        total += c;
        bins[(c.as_micros() as usize).min(10_000)] += 1;
    }
    let mut seen = 0;
    r.median_us = bins
        .iter()
        .position(|&n| {
            seen += n;
            2 * seen >= r.chunks
        })
        .unwrap_or(0) as f64;
    r.max_us = max.as_secs_f64() * 1e6;
    r.cpu_s = total.as_secs_f64();
    r
}

/// What a cycle starts from: the world's configuration and the controller's.
struct Setup {
    sim: crate::sim::SimParams,
    kin: LbrKinematics,
    shared: Arc<dyn Kinematics>,
    params: crate::control::ControllerParams,
}

impl Setup {
    /// The world of `a.protocol` and the controller of `a.controller_config` at `a.rate`,
    /// with force feedback.
    fn new(a: &SoakArgs) -> Result<Self, Box<dyn std::error::Error + Send + Sync>> {
        let cfg = SimConfig::load_default()?.with_protocol(a.protocol.name())?;
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())?;
        let mut params = load_controller(a.controller_config.as_deref())?;
        params.dt = 1.0 / a.rate;
        params.force_feedback = true;
        Ok(Self {
            sim: cfg.sim,
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

/// Replay every slow step's cycle `times` times with a new controller and world (the
/// same seed), timing that step again: the fastest of the replays is its own cost.
fn replay(slow: &[SlowStep], times: usize, setup: &Setup, a: &SoakArgs) -> Result<Replay, String> {
    let mut r = Replay {
        replays_per_step: times,
        steps: slow.len(),
        ..Replay::default()
    };
    let mut i = 0;
    while i < slow.len() {
        // The slow steps of one cycle sit together.
        let n = slow[i..].iter().take_while(|s| s.cycle == slow[i].cycle).count();
        let cycle = &slow[i..i + n];
        let mut best = vec![Duration::MAX; n];
        let mut identical = true;
        for _ in 0..times {
            let (mut world, mut ctrl) = (setup.world(cycle[0].seed)?, setup.controller()?);
            let mut watch = |s: &Sample, _lead: f64| {
                if let (Some(k), Some(c)) = (cycle.iter().position(|x| x.index == s.index), s.cpu) {
                    best[k] = best[k].min(c);
                }
            };
            let c = run_cycle(&mut world, &mut ctrl, &setup.kin, a, &mut watch)?;
            identical &= c.checksum == cycle[0].checksum;
        }
        if identical {
            r.identical += n;
        }
        for b in best.iter().filter(|b| **b < Duration::MAX) {
            r.max_own_cpu_us = r.max_own_cpu_us.max(b.as_secs_f64() * 1e6);
            r.own_cost_over_1ms += usize::from(*b > Duration::from_millis(1));
        }
        i += n;
    }
    Ok(r)
}

/// The cycles of a run: how they ended, and their timing.
#[derive(Default)]
struct Cycles {
    count: usize,
    done: usize,
    sim_s: f64,
    failures: Vec<Failure>,
    /// The steps over 1 ms of CPU, to replay.
    slow: Vec<SlowStep>,
    timing: Timing,
    rss_start: u64,
    rss_max: u64,
}

/// Docking cycles until `deadline` of wall time (at least one), with one controller.
fn run_cycles(a: &SoakArgs, setup: &Setup, deadline: Duration) -> Result<(Cycles, Instant), String> {
    let mut ctrl = setup.controller()?;
    let t0 = Instant::now();
    let mut baseline_at = t0;
    let mut r = Cycles::default();
    while r.count == 0 || t0.elapsed() < deadline {
        let seed = a.seed + r.count as u64 % a.seed_count.max(1);
        let mut world = setup.world(seed)?;
        let timing = &mut r.timing;
        let mut on_step = |s: &Sample, lead: f64| {
            timing.add(s);
            timing.max_lead = timing.max_lead.max(lead);
        };
        let c = run_cycle(&mut world, &mut ctrl, &setup.kin, a, &mut on_step)?;
        for &(index, cpu) in &r.timing.slow_in_cycle {
            if r.slow.len() < MAX_SLOW {
                r.slow.push(SlowStep {
                    cycle: r.count,
                    cpu,
                    seed,
                    index,
                    checksum: c.checksum,
                });
            }
        }
        r.timing.slow_in_cycle.clear();
        r.count += 1;
        r.sim_s += c.sim_s;
        if c.phase == Phase::Done {
            r.done += 1;
        } else {
            r.failures.push(Failure {
                seed,
                phase: c.phase.as_str(),
                hold_code: c.hold_code,
            });
        }
        let rss = rss_kb();
        r.rss_max = r.rss_max.max(rss);
        if r.count == 1 {
            // The first cycle warms up (allocator pools, lazy statics): the baseline.
            (r.rss_start, baseline_at) = (rss, Instant::now());
        }
    }
    Ok((r, baseline_at))
}

/// Run the soak; the report.
pub fn soak(a: &SoakArgs) -> Result<SoakReport, Box<dyn std::error::Error + Send + Sync>> {
    crate::validate::positive_at_most("rate", a.rate, 1000.0)?;
    crate::validate::positive("minutes", a.minutes)?;
    crate::validate::positive("cycle_timeout", a.cycle_timeout)?;
    crate::validate::non_negative("reference_seconds", a.reference_seconds)?;
    let setup = Setup::new(a)?;
    let reference = reference(a.reference_seconds);
    let t0 = Instant::now();
    let (c, baseline_at) = run_cycles(a, &setup, Duration::from_secs_f64(a.minutes * 60.0))?;
    let rss_end = rss_kb();
    let hours = baseline_at.elapsed().as_secs_f64() / 3600.0;
    let wall_s = t0.elapsed().as_secs_f64();
    // The longest `max_replayed` slow steps, in the order they came (a cycle's together).
    let mut slow = c.slow;
    slow.sort_by_key(|x| std::cmp::Reverse(x.cpu));
    slow.truncate(a.max_replayed);
    slow.sort_by_key(|x| (x.cycle, x.index));
    let replay = replay(&slow, a.replays, &setup, a)?;
    let t = &c.timing;
    Ok(SoakReport {
        wall_s,
        sim_s: c.sim_s,
        rate_hz: a.rate,
        cycles: c.count,
        done: c.done,
        every_cycle_done: c.done == c.count,
        failures: c.failures,
        steps: t.steps,
        max_step_us: t.max.as_secs_f64() * 1e6,
        steps_over_1ms: t.over_1ms,
        max_step_cpu_us: t.max_cpu.as_secs_f64() * 1e6,
        steps_cpu_s: t.cpu_total.as_secs_f64(),
        steps_over_1ms_cpu: t.over_1ms_cpu,
        steps_over_1ms_cpu_clarabel: t.over_1ms_cpu_clarabel,
        replay,
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

/// Run `soak` and print its report.
pub fn run(a: &SoakArgs) -> CliResult {
    let r = soak(a)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!(
            "soak: {} cycles in {:.0} s ({:.0} s simulated) at {} Hz, {} DONE; max step {:.0} µs wall ({} over 1 ms), {:.0} µs CPU ({} over 1 ms); command lead <= {:.2} deg; RSS {} -> {} kB ({:+.2} MB/h)",
            r.cycles,
            r.wall_s,
            r.sim_s,
            r.rate_hz,
            r.done,
            r.max_step_us,
            r.steps_over_1ms,
            r.max_step_cpu_us,
            r.steps_over_1ms_cpu,
            r.max_command_lead_deg,
            r.rss_start_kb,
            r.rss_end_kb,
            r.rss_growth_mb_per_h
        );
        println!(
            "  replayed {} steps over 1 ms of CPU {} times each ({} identical): own cost <= {:.0} µs, {} over 1 ms; reference workload ({:.0} s, median {:.0} µs): {} of {} chunks over 1 ms, max {:.0} µs",
            r.replay.steps,
            r.replay.replays_per_step,
            r.replay.identical,
            r.replay.max_own_cpu_us,
            r.replay.own_cost_over_1ms,
            r.reference.seconds,
            r.reference.median_us,
            r.reference.over_1ms,
            r.reference.chunks,
            r.reference.max_us
        );
        for f in &r.failures {
            println!("  seed {}: ended in {} ({})", f.seed, f.phase, f.hold_code);
        }
    }
    if r.every_cycle_done {
        Ok(())
    } else {
        Err(format!("{} of {} cycles did not end DONE", r.cycles - r.done, r.cycles).into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args() -> SoakArgs {
        SoakArgs {
            minutes: 0.01,
            rate: 1000.0,
            protocol: Protocol::Paper,
            seed: 1,
            seed_count: 4,
            cycle_timeout: 30.0,
            controller_config: None,
            replays: 2,
            max_replayed: 10,
            reference_seconds: 0.0,
            json: false,
        }
    }

    #[test]
    fn a_reset_controller_commands_exactly_as_a_new_one() {
        // The replay measures a step again only if a new controller repeats what the
        // soak's one controller (reset every cycle) computed.
        let a = args();
        let s = Setup::new(&a).unwrap();
        let cycle = |seed, ctrl: &mut Controller| {
            run_cycle(&mut s.world(seed).unwrap(), ctrl, &s.kin, &a, &mut |_, _| {}).unwrap()
        };
        let new = cycle(1, &mut s.controller().unwrap());
        let mut used = s.controller().unwrap();
        let other = cycle(2, &mut used);
        let again = cycle(1, &mut used);
        assert_eq!(new.phase, Phase::Done);
        assert_ne!(other.checksum, new.checksum, "seeds 1 and 2 command alike");
        assert_eq!(again.checksum, new.checksum, "the reset controller commanded otherwise");
    }

    #[test]
    fn the_replay_times_the_same_step_and_tells_a_different_cycle() {
        let a = args();
        let s = Setup::new(&a).unwrap();
        let mut ctrl = s.controller().unwrap();
        let cycle = run_cycle(&mut s.world(1).unwrap(), &mut ctrl, &s.kin, &a, &mut |_, _| {}).unwrap();
        let at = |index, checksum| SlowStep {
            cycle: 0,
            cpu: Duration::from_millis(2),
            seed: 1,
            index,
            checksum,
        };
        let same = [at(3, cycle.checksum), at(40, cycle.checksum)];
        let r = replay(&same, 2, &s, &a).unwrap();
        assert_eq!((r.steps, r.identical, r.replays_per_step), (2, 2, 2));
        assert!(r.max_own_cpu_us > 0.0);
        assert_eq!(r.own_cost_over_1ms, 0, "a docking step's own cost over 1 ms: {r:?}");
        let r = replay(&[at(3, cycle.checksum ^ 1)], 1, &s, &a).unwrap();
        assert_eq!((r.steps, r.identical), (1, 0));
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
