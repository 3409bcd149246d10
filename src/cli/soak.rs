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
/// hold code, and the simulated time it took.
struct Cycle {
    phase: Phase,
    hold_code: &'static str,
    sim_s: f64,
}

/// Per-step timing (and the command's lead over the arm) over the whole run.
#[derive(Default)]
struct Timing {
    steps: u64,
    max: Duration,
    over_1ms: u64,
    max_cpu: Duration,
    over_1ms_cpu: u64,
    /// Of those, the steps in which Clarabel solved a QP (the active set did not settle it).
    over_1ms_cpu_clarabel: u64,
    max_lead: f64,
}

impl Timing {
    fn add(&mut self, wall: Duration, cpu: Option<Duration>, clarabel: bool) {
        let ms = Duration::from_millis(1);
        self.steps += 1;
        self.max = self.max.max(wall);
        self.over_1ms += u64::from(wall > ms);
        if let Some(c) = cpu {
            self.max_cpu = self.max_cpu.max(c);
            self.over_1ms_cpu += u64::from(c > ms);
            self.over_1ms_cpu_clarabel += u64::from(c > ms && clarabel);
        }
    }
}

fn run_cycle(
    world: &mut SimWorld,
    ctrl: &mut Controller,
    kin: &dyn Kinematics,
    a: &SoakArgs,
    timing: &mut Timing,
) -> Result<Cycle, String> {
    ctrl.reset();
    ctrl.start()?;
    let period = 1.0 / a.rate;
    let physics = (period * world.params().physics_rate_hz).round().max(1.0) as usize;
    let mut out_phase = ctrl.phase();
    let mut hold_code = "";
    while world.time() < a.cycle_timeout {
        let t = world.time();
        let stamped = |value| Some(Stamped { stamp: t, value });
        let input = ControlInput {
            scope: None,
            now: t,
            joints: stamped(world.joint_positions()),
            tau_ext: stamped(world.external_torques()),
            trocar: world.measure_trocar(t).map(|m| Stamped {
                stamp: m.stamp,
                value: m.pose,
            }),
        };
        let (started, cpu0) = (Instant::now(), thread_cpu_time());
        let out = ctrl.step(kin, &input);
        let cpu = thread_cpu_time().zip(cpu0).map(|(b, a)| b.saturating_sub(a));
        let clarabel = out.solve.as_ref().is_some_and(|r| r.clarabel_qps > 0);
        timing.add(started.elapsed(), cpu, clarabel);
        out_phase = out.phase;
        hold_code = out.hold.as_ref().map_or("", |h| h.code());
        if matches!(out.phase, Phase::Done | Phase::Aborted | Phase::Idle) {
            break;
        }
        if let Some(q) = out.command {
            timing.max_lead = timing.max_lead.max((q - world.joint_positions()).amax());
            world.set_command(&q).map_err(|e| e.to_string())?;
        }
        for _ in 0..physics {
            world.step_physics().map_err(|e| e.to_string())?;
        }
    }
    Ok(Cycle {
        phase: out_phase,
        hold_code,
        sim_s: world.time(),
    })
}

/// Run the soak; the report.
pub fn soak(a: &SoakArgs) -> Result<SoakReport, Box<dyn std::error::Error + Send + Sync>> {
    crate::validate::positive_at_most("rate", a.rate, 1000.0)?;
    crate::validate::positive("minutes", a.minutes)?;
    crate::validate::positive("cycle_timeout", a.cycle_timeout)?;
    let cfg = SimConfig::load_default()?.with_protocol(a.protocol.name())?;
    let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())?;
    let shared: Arc<dyn Kinematics> = Arc::new(kin.clone());
    let mut params = load_controller(a.controller_config.as_deref())?;
    params.dt = 1.0 / a.rate;
    params.force_feedback = true;
    let mut ctrl = Controller::new(params, kin.limits().clone())?;
    let deadline = Duration::from_secs_f64(a.minutes * 60.0);
    let t0 = Instant::now();
    let mut timing = Timing::default();
    let (mut cycles, mut done, mut sim_s) = (0usize, 0usize, 0.0);
    let mut failures = Vec::new();
    let (mut rss_start, mut rss_max, mut baseline_at) = (0u64, 0u64, t0);
    while cycles == 0 || t0.elapsed() < deadline {
        let seed = a.seed + cycles as u64 % a.seed_count.max(1);
        let mut world = SimWorld::new(&cfg.sim, shared.clone(), seed)?;
        let c = run_cycle(&mut world, &mut ctrl, &kin, a, &mut timing)?;
        cycles += 1;
        sim_s += c.sim_s;
        if c.phase == Phase::Done {
            done += 1;
        } else {
            failures.push(Failure {
                seed,
                phase: c.phase.as_str(),
                hold_code: c.hold_code,
            });
        }
        let rss = rss_kb();
        rss_max = rss_max.max(rss);
        if cycles == 1 {
            // The first cycle warms up (allocator pools, lazy statics): the baseline.
            (rss_start, baseline_at) = (rss, Instant::now());
        }
    }
    let rss_end = rss_kb();
    let hours = baseline_at.elapsed().as_secs_f64() / 3600.0;
    Ok(SoakReport {
        wall_s: t0.elapsed().as_secs_f64(),
        sim_s,
        rate_hz: a.rate,
        cycles,
        done,
        every_cycle_done: done == cycles,
        failures,
        steps: timing.steps,
        max_step_us: timing.max.as_secs_f64() * 1e6,
        steps_over_1ms: timing.over_1ms,
        max_step_cpu_us: timing.max_cpu.as_secs_f64() * 1e6,
        steps_over_1ms_cpu: timing.over_1ms_cpu,
        steps_over_1ms_cpu_clarabel: timing.over_1ms_cpu_clarabel,
        max_command_lead_deg: timing.max_lead.to_degrees(),
        rss_start_kb: rss_start,
        rss_end_kb: rss_end,
        rss_max_kb: rss_max,
        rss_growth_mb_per_h: if hours > 0.0 {
            (rss_end as f64 - rss_start as f64) / 1024.0 / hours
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
