//! `trocar_docking bench`: time the hot paths and print latency statistics (JSON with
//! `--json`). Each suite lives in `crate::bench`.

use crate::bench::SuiteReport;

/// Which suite to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Suite {
    /// FK + Jacobian through KDL.
    Kinematics,
    /// Simulator: physics step and closed-loop real-time factor.
    Sim,
    /// One control step (FK + Jacobian + SQP + guard), two scenarios.
    Controller,
    /// Marker detection + pose on synthetic frames (latency and accuracy).
    Vision,
    /// Every suite.
    All,
}

/// Arguments of `bench`.
#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    /// Suite to run.
    #[arg(long, value_enum, default_value = "all")]
    pub suite: Suite,
    /// Samples per operation.
    #[arg(long, default_value_t = 20000)]
    pub samples: usize,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    /// Run the benchmarks on a SCHED_FIFO thread at this priority (1..=99; needs root or
    /// CAP_SYS_NICE), as a real-time control thread runs; default: the ordinary scheduler.
    #[arg(long)]
    pub realtime_priority: Option<i32>,
    /// Controller parameters (YAML, as `config/controller.yaml`; missing fields take the
    /// defaults) for the controller suite, e.g. to time a `sqp.time_budget_us`.
    #[arg(long)]
    pub controller_config: Option<std::path::PathBuf>,
}

/// Run `bench`.
pub fn run(a: &BenchArgs) -> super::CliResult {
    let samples = i64::try_from(a.samples).unwrap_or(i64::MAX);
    crate::validate::integer_in_range("--samples", samples, 1, 100_000_000)?;
    if let Some(p) = a.realtime_priority {
        crate::validate::integer_in_range("--realtime-priority", i64::from(p), 1, 99)?;
        crate::bench::set_realtime_priority(p)?;
    }
    let mut reports: Vec<SuiteReport> = vec![];
    let all = a.suite == Suite::All;
    if all || a.suite == Suite::Kinematics {
        reports.extend(crate::bench::kinematics::run(a.samples)?);
    }
    if all || a.suite == Suite::Sim {
        let cfg = crate::trials::config::SimConfig::load_default()?;
        reports.extend(crate::bench::sim::run(&cfg, a.samples, 10)?);
    }
    if all || a.suite == Suite::Controller {
        let params = match &a.controller_config {
            Some(path) => {
                let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
                crate::control::ControllerParams::from_yaml_str(&text)?
            }
            None => crate::control::ControllerParams::default(),
        };
        reports.extend(crate::bench::controller::run(a.samples.min(5000), &params)?);
    }
    if all || a.suite == Suite::Vision {
        reports.extend(crate::bench::vision::run(a.samples)?);
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&reports)?);
    } else {
        println!(
            "{:<36} {:>8} {:>10} {:>10} {:>10} {:>10}",
            "operation (wall clock)", "samples", "median µs", "p90 µs", "p99 µs", "max µs"
        );
        for r in &reports {
            let l = &r.latency;
            println!(
                "{}",
                stats_row(&r.name, l.samples, l.median_us, l.p90_us, l.p99_us, l.max_us)
            );
            for (k, v) in &r.extra {
                match latency_of(v) {
                    // Nested latency statistics (e.g. the controller's thread CPU time).
                    Some(s) => println!(
                        "{}",
                        stats_row(&format!("  {k}"), s[0] as usize, s[1], s[2], s[3], s[4])
                    ),
                    None => println!("    {k}: {v}"),
                }
            }
        }
    }
    Ok(())
}

/// One row of the text table.
fn stats_row(name: &str, samples: usize, median: f64, p90: f64, p99: f64, max: f64) -> String {
    format!("{name:<36} {samples:>8} {median:>10.2} {p90:>10.2} {p99:>10.2} {max:>10.2}")
}

/// [samples, median, p90, p99, max] of a JSON value shaped like `LatencyStats`.
fn latency_of(v: &serde_json::Value) -> Option<[f64; 5]> {
    let f = |k: &str| v.get(k).and_then(serde_json::Value::as_f64);
    Some([f("samples")?, f("median_us")?, f("p90_us")?, f("p99_us")?, f("max_us")?])
}
