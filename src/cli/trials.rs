//! `trocar_docking trials`: the paper's experiment at scale. N closed-loop trials per arm
//! (with and without force feedback) on the same seeds, under one protocol of
//! `config/sim.yaml` (`paper` or `realistic`), with the controller of
//! `config/controller.yaml` unchanged but for `force_feedback` (its `dt_s` is the trials' period); in parallel, with a
//! progress bar on stderr; prints a summary and a per-trial table (JSON with `--json`) and
//! writes to `--out`: `summary.json`, `trials.csv`, `series/<arm>_<seed>.csv` and the
//! plots `force_<protocol>.png`, `m_box_<protocol>.png`. With `--sensor camera` the trocar pose
//! comes from the markerless camera pipeline ([`crate::sim_vision`]) instead of the protocol's
//! noise model.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::control::ControllerParams;
use crate::kinematics::lbr::{LbrModel, ToolParams};
use crate::kinematics::{JointLimits, Kinematics, LbrKinematics};
use crate::sim::noise::NoiseModel;
use crate::sim_vision::{CameraPoseSource, CameraSetup, FrameCounts};
use crate::trials::batch::{run_arm_with, ArmReport, ArmSetup, ArmSummary, PolicyFactory, PoseSourceFactory, Stats};
use crate::trials::config::{load_controller, PolicyKind, Protocol, SimConfig};
use crate::trials::run::TrialResult;
use crate::vision::sim_camera::SimCameraParams;
use crate::vision::CameraModel;

use super::CliResult;

/// Arguments of `trials`.
#[derive(Debug, clap::Args)]
pub struct TrialsArgs {
    /// Trials per arm.
    #[arg(long, default_value_t = 50)]
    pub trials: usize,
    /// First seed; trial k uses seed + k (the same seeds in every arm).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Only the arm without force feedback.
    #[arg(long, conflicts_with_all = ["ff", "both"])]
    pub no_ff: bool,
    /// Only the arm with force feedback.
    #[arg(long, conflicts_with_all = ["no_ff", "both"])]
    pub ff: bool,
    /// Both arms (the default).
    #[arg(long)]
    pub both: bool,
    /// The protocol (a block of `protocols:` in the configuration).
    #[arg(long, value_enum, default_value_t = Protocol::Realistic)]
    pub protocol: Protocol,
    /// Trocar pose noise (default: the protocol's).
    #[arg(long, value_enum)]
    pub noise: Option<NoiseModel>,
    /// Timeout per trial, s (default: the config's).
    #[arg(long)]
    pub timeout: Option<f64>,
    /// Configuration file (default: config/sim.yaml when present, else built-in defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Controller configuration (default: config/controller.yaml when present, else the
    /// copy built into the binary): run unchanged but for `force_feedback` (its `dt_s` is the control period).
    #[arg(long)]
    pub controller_config: Option<PathBuf>,
    /// Output directory for CSV, JSON and PNG.
    #[arg(long, default_value = "out/trials")]
    pub out: PathBuf,
    /// Policy (default: the config's, normally the docking controller).
    #[arg(long, value_enum)]
    pub policy: Option<PolicyKind>,
    /// Do not draw the PNG plots.
    #[arg(long)]
    pub no_plots: bool,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    /// The trocar pose sensor: `model` (the protocol's noise model) or `camera` (the
    /// markerless camera pipeline in the loop: each capture rendered as the simulator's camera
    /// renders it, estimated and filtered as the trocar estimator does, at the protocol's
    /// rate, latency and hand-eye bias; much slower).
    #[arg(long, value_enum, default_value_t = Sensor::Model)]
    pub sensor: Sensor,
    /// With `--sensor camera`: the camera calibration YAML the images are rendered and
    /// estimated with.
    #[arg(long, default_value = "config/camera_zedm.yaml")]
    pub camera_calibration: PathBuf,
    /// With `--sensor camera`: the calibration YAML of the stereo pair's right camera (its
    /// image, with every `camera.right_every`-th frame of config/lbr_med_sim.yaml, resolves
    /// the opening's two-fold ambiguity); '' = a mono camera.
    #[arg(long, default_value = "config/camera_zedm_right.yaml")]
    pub right_camera_calibration: PathBuf,
}

/// The trocar pose sensor of the trials.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Sensor {
    /// The protocol's noise model of the pose (`measurement:` in config/sim.yaml).
    Model,
    /// The markerless camera pipeline: render, estimate, filter.
    Camera,
}

/// Which arms to run.
fn arms(a: &TrialsArgs) -> Vec<bool> {
    match (a.no_ff, a.ff) {
        (true, _) => vec![false],
        (_, true) => vec![true],
        _ => vec![false, true],
    }
}

fn arm_label(ff: bool) -> &'static str {
    if ff {
        "ff"
    } else {
        "no_ff"
    }
}

fn load_config(a: &TrialsArgs) -> Result<SimConfig, Box<dyn std::error::Error + Send + Sync>> {
    let base = match &a.config {
        Some(p) => SimConfig::from_file(p)?,
        None => SimConfig::load_default()?,
    };
    let mut c = base.with_protocol(a.protocol.name())?;
    if let Some(n) = a.noise {
        c.sim.measurement.model = n;
    }
    if let Some(p) = a.policy {
        c.policy = p;
    }
    if let Some(t) = a.timeout {
        c.trial.timeout_s = t;
    }
    c.validate()?;
    Ok(c)
}

/// The policy of one arm.
fn factory(c: &SimConfig, controller: &ControllerParams, ff: bool) -> Box<PolicyFactory> {
    crate::trials::policy::factory(c, controller, ff, &JointLimits::of_model(LbrModel::Med7))
}

/// What one run ran: protocol, world, controller, and the camera pipeline if it replaces the
/// noise model.
struct RunSetup {
    protocol: Protocol,
    cfg: SimConfig,
    controller: ControllerParams,
    camera: Option<CameraSetup>,
    frames: Arc<FrameCounts>,
}

/// The camera pipeline of `--sensor camera`: the shipped set-up with the cameras of
/// `--camera-calibration` and `--right-camera-calibration`.
fn camera_setup(a: &TrialsArgs) -> Result<CameraSetup, String> {
    let left = CameraModel::from_yaml_file(&a.camera_calibration)
        .map_err(|e| format!("--camera-calibration {}: {e}", a.camera_calibration.display()))?;
    let camera = SimCameraParams {
        right_calibration_file: a.right_camera_calibration.to_string_lossy().into_owned(),
        ..SimCameraParams::default()
    };
    let right = camera.right_camera().map_err(|e| {
        format!(
            "--right-camera-calibration {}: {e}",
            a.right_camera_calibration.display()
        )
    })?;
    Ok(CameraSetup {
        camera,
        ..CameraSetup::shipped(left, right)
    })
}

/// Run `trials`.
pub fn run(a: &TrialsArgs) -> CliResult {
    if a.trials == 0 {
        return Err("--trials must be at least 1".into());
    }
    let setup = RunSetup {
        protocol: a.protocol,
        cfg: load_config(a)?,
        controller: load_controller(a.controller_config.as_deref())?,
        camera: match a.sensor {
            Sensor::Model => None,
            Sensor::Camera => Some(camera_setup(a)?),
        },
        frames: Arc::new(FrameCounts::default()),
    };
    // Fail early on a broken model; each trial then builds its own chain (see KinematicsFactory).
    LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())?;
    let seeds: Vec<u64> = (0..a.trials as u64).map(|k| a.seed.wrapping_add(k)).collect();
    let t0 = std::time::Instant::now();
    let reports = run_arms(a, &setup, &seeds)?;
    let wall = t0.elapsed().as_secs_f64();
    let simulated: f64 = reports.iter().flat_map(|r| r.trials.iter()).map(|t| t.time_s).sum();
    write_outputs(a, &setup, &reports)?;
    let ratio = ratio(&reports);
    if a.json {
        let mut v = run_json(&setup, &reports, ratio);
        if let Some(c) = &setup.camera {
            let (captured, gated, fused) = setup.frames.get();
            v["sensor"] = "camera".into();
            v["stereo_right_every"] = match c.right {
                Some(_) => c.camera.right_every.into(),
                None => serde_json::Value::Null,
            };
            v["camera_frames"] = serde_json::json!({"captured": captured, "gated": gated, "fused": fused});
        }
        v["seeds"] = serde_json::json!([a.seed, a.seed.wrapping_add(a.trials as u64 - 1)]);
        v["wall_s"] = wall.into();
        v["simulated_s"] = simulated.into();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        print_text(&reports, &setup, ratio, wall, simulated, &a.out);
    }
    Ok(())
}

/// Run every requested arm on `seeds`, with a progress bar.
fn run_arms(
    a: &TrialsArgs,
    s: &RunSetup,
    seeds: &[u64],
) -> Result<Vec<ArmReport>, Box<dyn std::error::Error + Send + Sync>> {
    let kin = || -> Result<Arc<dyn Kinematics>, String> {
        LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())
            .map(|k| Arc::new(k) as Arc<dyn Kinematics>)
            .map_err(|e| e.to_string())
    };
    let arms = arms(a);
    let bar = ProgressBar::with_draw_target(Some((seeds.len() * arms.len()) as u64), ProgressDrawTarget::stderr());
    bar.set_style(
        ProgressStyle::with_template("{prefix} [{bar:40}] {pos}/{len} trials {elapsed_precise} (eta {eta})")
            .map_err(|e| e.to_string())?
            .progress_chars("=> "),
    );
    bar.set_prefix(format!("trials ({} protocol)", s.protocol));
    let tick = || bar.inc(1);
    let camera = s.camera.clone().map(|c| {
        let (measurement, frames) = (s.cfg.sim.measurement.clone(), s.frames.clone());
        move |seed: u64, _: &crate::sim::SimWorld| {
            CameraPoseSource::new(&c, &measurement, seed)
                .map(|src| Box::new(src.with_counts(frames.clone())) as Box<dyn crate::sim::noise::PoseSource>)
        }
    });
    let setup = ArmSetup {
        params: &s.cfg.sim,
        trial: &s.cfg.trial,
        kin: &kin,
        source: camera.as_ref().map(|f| f as &PoseSourceFactory),
    };
    let reports = arms
        .iter()
        .map(|&ff| {
            run_arm_with(
                arm_label(ff),
                &setup,
                seeds,
                factory(&s.cfg, &s.controller, ff).as_ref(),
                &tick,
            )
        })
        .collect();
    bar.finish_and_clear();
    Ok(reports)
}

/// The JSON record of a run: protocol, the controller's full parameter set (as the FF arm
/// ran it; the no-FF arm differs only in `force_feedback`), the world, and per arm (`ff`,
/// `no_ff`) its summary and trials.
fn run_json(s: &RunSetup, r: &[ArmReport], ratio: Option<(f64, f64)>) -> serde_json::Value {
    let ff = r.iter().any(|x| x.summary.label == "ff");
    let arms: serde_json::Map<String, serde_json::Value> = r
        .iter()
        .map(|x| {
            let mut v = serde_json::to_value(&x.summary).unwrap_or_default();
            v["force_feedback"] = (x.summary.label == "ff").into();
            (x.summary.label.clone(), v)
        })
        .collect();
    let trials: serde_json::Map<String, serde_json::Value> = r
        .iter()
        .map(|x| {
            (
                x.summary.label.clone(),
                serde_json::to_value(&x.trials).unwrap_or_default(),
            )
        })
        .collect();
    serde_json::json!({
        "protocol": s.protocol.name(),
        "controller": crate::trials::policy::controller_params(&s.controller, &s.cfg, ff),
        "world": {"sim": &s.cfg.sim, "trial": &s.cfg.trial, "policy": s.cfg.policy},
        "m_ratio_no_ff_over_ff": ratio.map(|r| r.0),
        "m_true_ratio_no_ff_over_ff": ratio.map(|r| r.1),
        "m_lateral_true_all_ratio_no_ff_over_ff": lateral_ratio(r),
        "arms": arms,
        "trials": trials,
    })
}

/// `f(no_ff) / f(ff)` of the two arms' summaries, when both ran.
fn arm_ratio(r: &[ArmReport], f: impl Fn(&ArmSummary) -> f64) -> Option<f64> {
    let arm = |l: &str| r.iter().find(|x| x.summary.label == l).map(|x| &x.summary);
    let div = |a: f64, b: f64| if b > 0.0 && a.is_finite() { a / b } else { f64::NAN };
    match (arm("no_ff"), arm("ff")) {
        (Some(a), Some(b)) => Some(div(f(a), f(b))),
        _ => None,
    }
}

/// Mean M without FF over mean M with FF on the successes: (estimated, true force).
fn ratio(r: &[ArmReport]) -> Option<(f64, f64)> {
    Some((arm_ratio(r, |s| s.m_est.mean)?, arm_ratio(r, |s| s.m_true.mean)?))
}

/// Mean lateral M (true force, every trial) without FF over with FF.
fn lateral_ratio(r: &[ArmReport]) -> Option<f64> {
    arm_ratio(r, |s| s.m_lateral_true_all.mean)
}

/// `mean ± std`, or how many trials have no value (they errored before they had one).
fn ms(s: &Stats) -> String {
    if s.missing > 0 {
        format!("n/a ({} missing)", s.missing)
    } else {
        format!("{:.2} ± {:.2}", s.mean, s.std)
    }
}

fn print_text(r: &[ArmReport], s: &RunSetup, ratio: Option<(f64, f64)>, wall: f64, simulated: f64, out: &Path) {
    let cfg = &s.cfg;
    let sensor = match &s.camera {
        Some(c) => {
            let (captured, gated, fused) = s.frames.get();
            let eyes = match c.right {
                Some(_) => format!("stereo, the right image with every {}. frame", c.camera.right_every),
                None => "mono".into(),
            };
            format!("sensor: the markerless camera pipeline, {eyes} ({captured} frames, {gated} past the confidence gate, {fused} fused)")
        }
        None => format!("noise {}", cfg.sim.measurement.model),
    };
    println!(
        "protocol {}; {sensor}; {} trials per arm, each run to DONE, a latched hold or the {} s timeout",
        s.protocol,
        r.first().map_or(0, |x| x.trials.len()),
        cfg.trial.timeout_s,
    );
    println!(
        "docked = DONE with the true tip within {} mm of the goal depth ({} mm) inside the port and the shaft within {} deg of the true axis; paper = tip within {} mm of the goal at any time",
        cfg.trial.done_depth_tolerance_m * 1e3,
        cfg.trial.goal_depth_m * 1e3,
        cfg.trial.done_angle_tolerance_deg,
        cfg.trial.tolerance_m * 1e3,
    );
    println!(
        "{:<6} {:>8} {:>8} {:>5} {:>15} {:>15} {:>15} {:>15} {:>15} {:>9} {:>17} {:>8}  failures",
        "arm",
        "docked",
        "paper",
        "falseD",
        "M true all [N]",
        "M true [N]",
        "M est [N]",
        "M lat all [N]",
        "T [s]",
        "max f [N]",
        "v_rms INSERT [m/s]",
        "a_max"
    );
    for a in r {
        let x: &ArmSummary = &a.summary;
        println!(
            "{:<6} {:>3}/{:<4} {:>3}/{:<4} {:>5} {:>15} {:>15} {:>15} {:>15} {:>15} {:>9.1} {:>17} {:>8.2}  {:?}",
            x.label,
            x.successes,
            x.trials,
            x.paper_successes,
            x.trials,
            x.false_done,
            ms(&x.m_true_all),
            ms(&x.m_true),
            ms(&x.m_est),
            ms(&x.m_lateral_true_all),
            ms(&x.time_s),
            x.max_force_true_n,
            format!(
                "{:.3} (max {:.3})",
                x.rms_tip_speed_insert.mean, x.rms_tip_speed_insert.max
            ),
            x.max_tip_accel,
            x.failures
        );
    }
    println!("M true all, M lat all, max f: every trial to its end (failures included); M true, M est, T (to DONE): docked trials only");
    if let Some((e, t)) = ratio {
        println!(
            "M(no FF) / M(FF) on successes = {e:.2} estimated, {t:.2} true (paper: 21.4 / 3.4 = 6.3); lateral, all trials: {:.2}",
            lateral_ratio(r).unwrap_or(f64::NAN)
        );
    }
    println!(
        "wall {wall:.2} s for {simulated:.0} s simulated ({:.0}x real time across cores)",
        simulated / wall.max(1e-9)
    );
    print_trials(r);
    println!("\noutputs in {}", out.display());
}

/// The per-trial table.
fn print_trials(r: &[ArmReport]) {
    println!("\nper trial:");
    println!(
        "{:<6} {:>6} {:<12} {:>7} {:>8} {:>8} {:>8} {:>9} {:>6} {:>7} {:>7}  reason",
        "arm", "seed", "outcome", "T [s]", "M est", "M true", "M lat", "max f [N]", "paper", "dz [mm]", "ang [°]"
    );
    for a in r {
        for t in &a.trials {
            println!(
                "{:<6} {:>6} {:<12} {:>7.2} {:>8.3} {:>8.3} {:>8.3} {:>9.2} {:>6} {:>7.2} {:>7.2}  {} {} {}",
                a.summary.label,
                t.seed,
                t.outcome.name(),
                t.time_s,
                t.m_est,
                t.m_true,
                t.m_lateral_true,
                t.max_f_true,
                if t.paper_success { "yes" } else { "no" },
                t.done_depth_error_m * 1e3,
                t.done_angle_deg,
                t.final_phase,
                t.final_hold,
                t.reason
            );
        }
    }
}

/// The columns of `trials.csv`, one row per trial.
const TABLE_HEADER: [&str; 19] = [
    "arm",
    "seed",
    "outcome",
    "final_phase",
    "time_s",
    "paper_success",
    "paper_time_s",
    "done_depth_error_m",
    "done_radial_m",
    "done_angle_deg",
    "done_estimate_depth_m",
    "m_est_n",
    "m_paper_code_scale",
    "m_true_n",
    "m_lateral_true_n",
    "max_f_est_n",
    "max_f_true_n",
    "seal_breakaways",
    "reason",
];

/// `trials.csv`. The fields are written as formatted (each figure with its own precision) and
/// unquoted but for the reason, which is always quoted (its own quotes made `'`).
fn write_table(path: &Path, r: &[ArmReport]) -> CliResult {
    let mut table = csv::WriterBuilder::new()
        .quote_style(csv::QuoteStyle::Never)
        .from_path(path)?;
    table.write_record(TABLE_HEADER)?;
    for arm in r {
        for t in &arm.trials {
            table.write_record([
                arm.summary.label.clone(),
                t.seed.to_string(),
                t.outcome.name().to_string(),
                t.final_phase.to_string(),
                format!("{:.4}", t.time_s),
                t.paper_success.to_string(),
                format!("{:.4}", t.paper_time_s),
                format!("{:.6}", t.done_depth_error_m),
                format!("{:.6}", t.done_radial_m),
                format!("{:.4}", t.done_angle_deg),
                format!("{:.6}", t.done_estimate_depth_m),
                format!("{:.5}", t.m_est),
                format!("{:.5}", crate::trials::run::PAPER_CODE_SCALE * t.m_est),
                format!("{:.5}", t.m_true),
                format!("{:.5}", t.m_lateral_true),
                format!("{:.4}", t.max_f_est),
                format!("{:.4}", t.max_f_true),
                t.seal_breakaways.to_string(),
                format!("\"{}\"", t.reason.replace('"', "'")),
            ])?;
        }
    }
    table.flush()?;
    Ok(())
}

fn write_outputs(a: &TrialsArgs, s: &RunSetup, r: &[ArmReport]) -> CliResult {
    let series = a.out.join("series");
    std::fs::create_dir_all(&series)?;
    write_table(&a.out.join("trials.csv"), r)?;
    for arm in r {
        for t in &arm.trials {
            write_series(&series.join(format!("{}_{}.csv", arm.summary.label, t.seed)), t)?;
        }
    }
    let summary = run_json(s, r, ratio(r));
    std::fs::write(a.out.join("summary.json"), serde_json::to_string_pretty(&summary)?)?;
    if a.no_plots {
        return Ok(());
    }
    let protocol = s.protocol.name();
    let labelled: Vec<(&str, &[TrialResult])> = r
        .iter()
        .map(|x| {
            let name = if x.summary.label == "ff" {
                "with FF"
            } else {
                "without FF"
            };
            (name, x.trials.as_slice())
        })
        .collect();
    crate::trials::plot::force_over_time(&a.out.join(format!("force_{protocol}.png")), &labelled)?;
    let groups: Vec<(String, Vec<f64>)> = r
        .iter()
        .map(|x| (x.summary.label.clone(), x.trials.iter().map(|t| t.m_true).collect()))
        .collect();
    crate::trials::plot::box_plot(
        &a.out.join(format!("m_box_{protocol}.png")),
        &format!("M on the true contact force, every trial ({protocol} protocol)"),
        "M [N]",
        &groups,
    )?;
    Ok(())
}

/// One trial's samples, `series/<arm>_<seed>.csv`, each figure with its own precision.
fn write_series(path: &Path, t: &TrialResult) -> CliResult {
    let mut f = csv::Writer::from_path(path)?;
    f.write_record([
        "t_s",
        "f_est_n",
        "f_true_n",
        "f_lateral_true_n",
        "depth_m",
        "radial_m",
        "goal_dist_m",
        "trocar_shift_m",
        "phase",
    ])?;
    for s in &t.samples {
        f.write_record([
            format!("{:.3}", s.t),
            format!("{:.5}", s.f_est),
            format!("{:.5}", s.f_true),
            format!("{:.5}", s.f_lateral_true),
            format!("{:.6}", s.depth),
            format!("{:.6}", s.radial),
            format!("{:.6}", s.goal_dist),
            format!("{:.6}", s.trocar_shift),
            s.phase.to_string(),
        ])?;
    }
    f.flush()?;
    Ok(())
}
