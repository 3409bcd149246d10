//! `trocar_docking pivot`: the pivoting benchmark. In N worlds of a protocol (the same
//! seeds in each arm), dock with the shipped controller, then steer the scope through the
//! port with a script of surgeon's commands (random pan/tilt and zoom segments at
//! `--speed-deg` deg/s, then the same back; or the "done-when" sequence of the pivot's targets), with the
//! force-adapted fulcrum and with the fulcrum fixed where it starts. Prints per arm the
//! statistics over the runs of each figure of [`PivotResult`] and every run (`--json`).

use std::path::PathBuf;
use std::sync::Arc;

use rayon::prelude::*;
use serde::Serialize;

use crate::control::ControllerParams;
use crate::kinematics::lbr::{LbrModel, ToolParams};
use crate::kinematics::{Kinematics, LbrKinematics};
use crate::stats::finite_quantile;
use crate::trials::batch::Stats;
use crate::trials::config::{load_controller, Protocol, SimConfig};
use crate::trials::pivot::{done_when_script, fixed_fulcrum, random_script, run_pivot, PivotResult};

use super::CliResult;

/// Which script of commands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Script {
    /// Random pan/tilt/zoom segments, then the same back.
    Random,
    /// The pivot's acceptance sequence ("done when", docs/after-docking.md): pan, tilt, back, in, out.
    DoneWhen,
}

/// Arguments of `pivot`.
#[derive(Debug, clap::Args)]
pub struct PivotArgs {
    /// Runs per arm.
    #[arg(long, default_value_t = 10)]
    pub trials: usize,
    /// First seed; run k uses seed + k (the world and the random script).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The script.
    #[arg(long, value_enum, default_value_t = Script::Random)]
    pub script: Script,
    /// Random segments before the way back.
    #[arg(long, default_value_t = 6)]
    pub segments: usize,
    /// Pan/tilt speed of the random script, deg/s.
    #[arg(long, default_value_t = 10.0)]
    pub speed_deg: f64,
    /// The protocol (a block of `protocols:` in the configuration).
    #[arg(long, value_enum, default_value_t = Protocol::Realistic)]
    pub protocol: Protocol,
    /// Simulator configuration (default: config/sim.yaml).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Controller configuration (default: config/controller.yaml).
    #[arg(long)]
    pub controller_config: Option<PathBuf>,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    /// Also plot the first docked run of each arm over time to this PNG.
    #[arg(long)]
    pub plot: Option<PathBuf>,
}

/// The p95 of the shaft's distance from the true port over the commanded steps of `runs`.
fn pooled_p95(runs: &[&PivotResult]) -> f64 {
    let all: Vec<f64> = runs
        .iter()
        .flat_map(|r| r.trace.iter().filter(|s| s.commanded).map(|s| s.distance_m))
        .collect();
    finite_quantile(&all, 0.95)
}

/// One arm's figures over its runs.
#[derive(Debug, Serialize)]
struct ArmPivot {
    arm: &'static str,
    runs: usize,
    docked: usize,
    /// The shaft's distance from the true port over every commanded step of every docked
    /// run: p95 (the benchmark's whole sample, where `distance_p95_m` is per run).
    distance_all_p95_m: f64,
    /// Docked runs whose own p95 is within 1 mm.
    runs_within_1mm: usize,
    distance_p95_m: Stats,
    face_port_distance_p95_m: Stats,
    wall_displacement_p95_m: Stats,
    bore_distance_p95_m: Stats,
    bore_angle_p95_deg: Stats,
    contact_depth_p95_m: Stats,
    fulcrum_estimate_p95_m: Stats,
    rcm_tracking_p95_m: Stats,
    breathing_across_p95_m: Stats,
    port_along_p95_m: Stats,
    lateral_force_est_mean_n: Stats,
    lateral_force_est_max_n: Stats,
    lateral_force_true_mean_n: Stats,
    lateral_force_true_max_n: Stats,
    axial_force_true_max_n: Stats,
    swept_deg: Stats,
    still_motion_port_m: Stats,
    solve_us_p99: Stats,
    solve_us_max: Stats,
    held_steps: usize,
    failures: Vec<String>,
    trials: Vec<PivotResult>,
}

impl ArmPivot {
    fn of(arm: &'static str, trials: Vec<PivotResult>) -> Self {
        let ok: Vec<&PivotResult> = trials.iter().filter(|r| r.docked).collect();
        let s = |f: fn(&PivotResult) -> f64| Stats::of(ok.iter().map(|r| f(r)));
        Self {
            arm,
            runs: trials.len(),
            docked: ok.len(),
            distance_all_p95_m: pooled_p95(&ok),
            runs_within_1mm: ok.iter().filter(|r| r.distance_p95_m <= 1e-3).count(),
            distance_p95_m: s(|r| r.distance_p95_m),
            face_port_distance_p95_m: s(|r| r.face_port_distance_p95_m),
            wall_displacement_p95_m: s(|r| r.wall_displacement_p95_m),
            bore_distance_p95_m: s(|r| r.bore_distance_p95_m),
            bore_angle_p95_deg: s(|r| r.bore_angle_p95_deg),
            contact_depth_p95_m: s(|r| r.contact_depth_p95_m),
            fulcrum_estimate_p95_m: s(|r| r.fulcrum_estimate_p95_m),
            rcm_tracking_p95_m: s(|r| r.rcm_tracking_p95_m),
            breathing_across_p95_m: s(|r| r.breathing_across_p95_m),
            port_along_p95_m: s(|r| r.port_along_p95_m),
            lateral_force_est_mean_n: s(|r| r.lateral_force_est_mean_n),
            lateral_force_est_max_n: s(|r| r.lateral_force_est_max_n),
            lateral_force_true_mean_n: s(|r| r.lateral_force_true_mean_n),
            lateral_force_true_max_n: s(|r| r.lateral_force_true_max_n),
            axial_force_true_max_n: s(|r| r.axial_force_true_max_n),
            swept_deg: s(|r| r.swept_deg),
            still_motion_port_m: s(|r| r.still_motion_port_m),
            solve_us_p99: s(|r| r.solve_us_p99),
            solve_us_max: s(|r| r.solve_us_max),
            held_steps: ok.iter().map(|r| r.held_steps).sum(),
            failures: trials
                .iter()
                .filter(|r| !r.docked)
                .map(|r| format!("seed {}: {}", r.seed, r.reason))
                .collect(),
            trials,
        }
    }

    fn print(&self) {
        let mm = |s: &Stats| format!("mean {:.2} max {:.2} mm", s.mean * 1e3, s.max * 1e3);
        let n = |s: &Stats| format!("mean {:.2} max {:.2} N", s.mean, s.max);
        println!("{} ({} of {} docked)", self.arm, self.docked, self.runs);
        println!(
            "  shaft from the true port, p95:  {} per run ({} within 1 mm); {:.2} mm over every step",
            mm(&self.distance_p95_m),
            self.runs_within_1mm,
            self.distance_all_p95_m * 1e3
        );
        println!(
            "  wall dragged, p95:              {}",
            mm(&self.wall_displacement_p95_m)
        );
        println!(
            "  shaft from the trocar's fulcrum, p95: {}",
            mm(&self.bore_distance_p95_m)
        );
        println!(
            "  shaft to the trocar's axis, p95: mean {:.2} max {:.2} deg; contact depth p95 {}",
            self.bore_angle_p95_deg.mean,
            self.bore_angle_p95_deg.max,
            mm(&self.contact_depth_p95_m)
        );
        println!(
            "  controller's fulcrum from the true port, p95: {}",
            mm(&self.fulcrum_estimate_p95_m)
        );
        println!(
            "  shaft from the controller's fulcrum, p95: {}",
            mm(&self.rcm_tracking_p95_m)
        );
        println!(
            "  true port's breathing across the shaft, p95: {}",
            mm(&self.breathing_across_p95_m)
        );
        println!(
            "  lateral force estimate, mean:   {}",
            n(&self.lateral_force_est_mean_n)
        );
        println!("  lateral force estimate, max:    {}", n(&self.lateral_force_est_max_n));
        println!(
            "  true lateral force, mean:       {}",
            n(&self.lateral_force_true_mean_n)
        );
        println!(
            "  true lateral force, max:        {}",
            n(&self.lateral_force_true_max_n)
        );
        println!("  true axial force, max:          {}", n(&self.axial_force_true_max_n));
        println!(
            "  swept {:.1}-{:.1} deg, steps held {}",
            self.swept_deg.min, self.swept_deg.max, self.held_steps
        );
        println!(
            "  SQP per step: p99 {:.0} µs (worst run), max {:.0} µs",
            self.solve_us_p99.max, self.solve_us_max.max
        );
        for f in &self.failures {
            println!("  failed: {f}");
        }
    }
}

/// The whole report.
#[derive(Debug, Serialize)]
struct PivotReportJson {
    protocol: &'static str,
    script: Script,
    segments: usize,
    speed_deg_s: f64,
    first_seed: u64,
    arms: Vec<ArmPivot>,
    controller: ControllerParams,
}

/// Run `pivot`.
pub fn run(a: &PivotArgs) -> CliResult {
    if a.trials == 0 || !(a.speed_deg.is_finite() && a.speed_deg > 0.0) {
        return Err("--trials must be > 0 and --speed-deg a speed > 0".into());
    }
    let base = match &a.config {
        Some(p) => SimConfig::from_file(p)?,
        None => SimConfig::load_default()?,
    };
    let cfg = base.with_protocol(a.protocol.name())?;
    let controller = load_controller(a.controller_config.as_deref())?;
    let kin: Arc<dyn Kinematics> = Arc::new(LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())?);
    let seeds: Vec<u64> = (0..a.trials as u64).map(|k| a.seed + k).collect();
    let script = |seed: u64| match a.script {
        Script::Random => random_script(seed, a.segments, a.speed_deg.to_radians()),
        Script::DoneWhen => done_when_script(),
    };
    let arm = |name: &'static str, c: &ControllerParams| -> Result<ArmPivot, String> {
        let runs = seeds
            .par_iter()
            .map(|&s| run_pivot(&cfg.sim, c, kin.clone(), s, &script(s), &cfg.pivot))
            .collect::<Result<Vec<_>, String>>()?;
        Ok(ArmPivot::of(name, runs))
    };
    let arms = vec![arm("adapted", &controller)?, arm("fixed", &fixed_fulcrum(&controller))?];
    let report = PivotReportJson {
        protocol: a.protocol.name(),
        script: a.script,
        segments: a.segments,
        speed_deg_s: a.speed_deg,
        first_seed: a.seed,
        arms,
        controller,
    };
    if let Some(path) = &a.plot {
        let first: Vec<(&str, &PivotResult)> = report
            .arms
            .iter()
            .filter_map(|arm| arm.trials.iter().find(|r| r.docked).map(|r| (arm.arm, r)))
            .collect();
        crate::trials::plot::pivot_runs(path, &first)?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        for arm in &report.arms {
            arm.print();
        }
    }
    Ok(())
}
