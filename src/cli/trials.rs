//! `trocar_docking trials`: the paper's experiment at scale. N closed-loop trials per arm
//! (with and without force feedback) on the same seeds and noise, in parallel, with a
//! progress bar on stderr; prints a summary and a per-trial table (JSON with `--json`) and
//! writes to `--out`: `summary.json`, `trials.csv`, `series/<arm>_<seed>.csv` and the
//! plots `force_<noise>.png`, `m_box_<noise>.png`.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::kinematics::lbr::{LbrModel, ToolParams};
use crate::kinematics::{JointLimits, Kinematics, LbrKinematics};
use crate::sim::noise::NoiseModel;
use crate::trials::batch::{run_arm, ArmReport, ArmSummary, PolicyFactory, Stats};
use crate::trials::config::{PolicyKind, SimConfig};
use crate::trials::run::TrialResult;

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
    /// Trocar pose noise (default: the config's).
    #[arg(long, value_enum)]
    pub noise: Option<NoiseModel>,
    /// Timeout per trial, s (default: the config's).
    #[arg(long)]
    pub timeout: Option<f64>,
    /// Configuration file (default: config/sim.yaml when present, else built-in defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
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
    let mut c = match &a.config {
        Some(p) => SimConfig::from_file(p)?,
        None => SimConfig::load_default()?,
    };
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
fn factory(c: &SimConfig, ff: bool) -> Box<PolicyFactory> {
    crate::trials::policy::factory(c, ff, &JointLimits::of_model(LbrModel::Med7))
}

/// Run `trials`.
pub fn run(a: &TrialsArgs) -> CliResult {
    if a.trials == 0 {
        return Err("--trials must be at least 1".into());
    }
    let cfg = load_config(a)?;
    // Fail early on a broken model; each trial then builds its own chain (see KinematicsFactory).
    LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())?;
    let kin = || -> Result<Arc<dyn Kinematics>, String> {
        LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default())
            .map(|k| Arc::new(k) as Arc<dyn Kinematics>)
            .map_err(|e| e.to_string())
    };
    let seeds: Vec<u64> = (0..a.trials as u64).map(|k| a.seed.wrapping_add(k)).collect();
    let arms = arms(a);
    let bar = ProgressBar::with_draw_target(Some((seeds.len() * arms.len()) as u64), ProgressDrawTarget::stderr());
    bar.set_style(
        ProgressStyle::with_template("{prefix} [{bar:40}] {pos}/{len} trials {elapsed_precise} (eta {eta})")
            .map_err(|e| e.to_string())?
            .progress_chars("=> "),
    );
    bar.set_prefix(format!("trials ({} noise)", cfg.sim.measurement.model));
    let t0 = std::time::Instant::now();
    let tick = || bar.inc(1);
    let reports: Vec<ArmReport> = arms
        .iter()
        .map(|&ff| {
            run_arm(
                arm_label(ff),
                &cfg.sim,
                &cfg.trial,
                &kin,
                &seeds,
                factory(&cfg, ff).as_ref(),
                &tick,
            )
        })
        .collect();
    bar.finish_and_clear();
    let wall = t0.elapsed().as_secs_f64();
    let simulated: f64 = reports.iter().flat_map(|r| r.trials.iter()).map(|t| t.time_s).sum();
    write_outputs(a, &cfg, &reports)?;
    let ratio = ratio(&reports);
    if a.json {
        let v = serde_json::json!({
            "noise": cfg.sim.measurement.model.to_string(),
            "seeds": [a.seed, a.seed.wrapping_add(a.trials as u64 - 1)],
            "wall_s": wall,
            "simulated_s": simulated,
            "m_ratio_no_ff_over_ff": ratio.map(|r| r.0),
            "m_true_ratio_no_ff_over_ff": ratio.map(|r| r.1),
            "arms": reports,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        print_text(&reports, &cfg, ratio, wall, simulated, &a.out);
    }
    Ok(())
}

/// Mean M without FF over mean M with FF, when both arms ran: (estimated, true force).
fn ratio(r: &[ArmReport]) -> Option<(f64, f64)> {
    let arm = |l: &str| r.iter().find(|x| x.summary.label == l).map(|x| &x.summary);
    let div = |a: f64, b: f64| if b > 0.0 && a.is_finite() { a / b } else { f64::NAN };
    match (arm("no_ff"), arm("ff")) {
        (Some(a), Some(b)) => Some((div(a.m_est.mean, b.m_est.mean), div(a.m_true.mean, b.m_true.mean))),
        _ => None,
    }
}

fn ms(s: &Stats) -> String {
    format!("{:.2} ± {:.2}", s.mean, s.std)
}

fn print_text(r: &[ArmReport], cfg: &SimConfig, ratio: Option<(f64, f64)>, wall: f64, simulated: f64, out: &Path) {
    println!(
        "noise {}; {} trials per arm; timeout {} s; success = tip within {} mm of the goal {} mm deep, inside the port",
        cfg.sim.measurement.model,
        r.first().map_or(0, |x| x.trials.len()),
        cfg.trial.timeout_s,
        cfg.trial.tolerance_m * 1e3,
        cfg.trial.goal_depth_m * 1e3
    );
    println!(
        "{:<7} {:>9} {:>15} {:>17} {:>15} {:>15} {:>7} {:>9} {:>9}",
        "arm", "success", "M [N]", "2.4xM (paper-code)", "M true [N]", "T [s]", "T max", "max f [N]", "outcomes"
    );
    for a in r {
        let s: &ArmSummary = &a.summary;
        println!(
            "{:<7} {:>3}/{:<3}{:>3} {:>15} {:>17} {:>15} {:>15} {:>7.2} {:>9.1} {:?}",
            s.label,
            s.successes,
            s.trials,
            "",
            ms(&s.m_est),
            ms(&s.m_paper_code_scale),
            ms(&s.m_true),
            ms(&s.time_s),
            s.time_s.max,
            s.max_force_true_n,
            s.outcomes
        );
    }
    if let Some((e, t)) = ratio {
        println!("M(no FF) / M(FF) = {e:.2} (true contact force: {t:.2}; paper: 21.4 / 3.4 = 6.3)");
    }
    println!("outcomes: [docked, timeout, force abort, policy abort, sim error]");
    println!(
        "wall {wall:.2} s for {simulated:.0} s simulated ({:.0}x real time across cores)",
        simulated / wall.max(1e-9)
    );
    println!("\nper trial:");
    println!(
        "{:<7} {:>6} {:<12} {:>7} {:>8} {:>8} {:>9}  reason",
        "arm", "seed", "outcome", "T [s]", "M [N]", "M true", "max f [N]"
    );
    for a in r {
        for t in &a.trials {
            println!(
                "{:<7} {:>6} {:<12} {:>7.2} {:>8.3} {:>8.3} {:>9.2}  {}",
                a.summary.label,
                t.seed,
                format!("{:?}", t.outcome),
                t.time_s,
                t.m_est,
                t.m_true,
                t.max_f_true,
                t.reason
            );
        }
    }
    println!("\noutputs in {}", out.display());
}

fn write_outputs(a: &TrialsArgs, cfg: &SimConfig, r: &[ArmReport]) -> CliResult {
    let series = a.out.join("series");
    std::fs::create_dir_all(&series)?;
    let mut table = std::io::BufWriter::new(std::fs::File::create(a.out.join("trials.csv"))?);
    writeln!(
        table,
        "arm,seed,outcome,time_s,m_est_n,m_paper_code_scale,m_true_n,max_f_est_n,max_f_true_n,reason"
    )?;
    for arm in r {
        for t in &arm.trials {
            writeln!(
                table,
                "{},{},{:?},{:.4},{:.5},{:.5},{:.5},{:.4},{:.4},\"{}\"",
                arm.summary.label,
                t.seed,
                t.outcome,
                t.time_s,
                t.m_est,
                crate::trials::run::PAPER_CODE_SCALE * t.m_est,
                t.m_true,
                t.max_f_est,
                t.max_f_true,
                t.reason.replace('"', "'")
            )?;
            write_series(&series.join(format!("{}_{}.csv", arm.summary.label, t.seed)), t)?;
        }
    }
    table.flush()?;
    let summary = serde_json::json!({
        "noise": cfg.sim.measurement.model.to_string(),
        "config": cfg,
        "arms": r.iter().map(|x| &x.summary).collect::<Vec<_>>(),
        "trials": r.iter().map(|x| serde_json::json!({"arm": x.summary.label, "results": x.trials})).collect::<Vec<_>>(),
    });
    std::fs::write(a.out.join("summary.json"), serde_json::to_string_pretty(&summary)?)?;
    if !a.no_plots {
        let noise = cfg.sim.measurement.model.to_string();
        let labelled: Vec<(&str, &[TrialResult])> = r
            .iter()
            .map(|x| {
                (
                    if x.summary.label == "ff" {
                        "with FF"
                    } else {
                        "without FF"
                    },
                    x.trials.as_slice(),
                )
            })
            .collect();
        crate::trials::plot::force_over_time(&a.out.join(format!("force_{noise}.png")), &labelled)?;
        let groups: Vec<(String, Vec<f64>)> = r
            .iter()
            .map(|x| {
                (
                    x.summary.label.clone(),
                    x.trials.iter().filter(|t| t.success()).map(|t| t.m_est).collect(),
                )
            })
            .collect();
        crate::trials::plot::box_plot(
            &a.out.join(format!("m_box_{noise}.png")),
            &format!("M per successful trial ({noise} noise)"),
            "M [N]",
            &groups,
        )?;
    }
    Ok(())
}

fn write_series(path: &Path, t: &TrialResult) -> CliResult {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    writeln!(
        f,
        "t_s,f_est_n,f_true_n,depth_m,radial_m,goal_dist_m,trocar_shift_m,phase"
    )?;
    for s in &t.samples {
        writeln!(
            f,
            "{:.3},{:.5},{:.5},{:.6},{:.6},{:.6},{:.6},{}",
            s.t, s.f_est, s.f_true, s.depth, s.radial, s.goal_dist, s.trocar_shift, s.phase
        )?;
    }
    f.flush()?;
    Ok(())
}
