//! `trocar_docking bench`: time the hot paths and print latency statistics (JSON with
//! `--json`). Each suite lives in `crate::bench`.

use serde::Deserialize;

use crate::bench::{LatencyStats, SuiteReport};

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
            println!("{}", stats_row(&r.name, &r.latency));
            for (k, v) in &r.extra {
                match latency_of(v) {
                    // Nested latency statistics (e.g. the controller's thread CPU time).
                    Some(s) => println!("{}", stats_row(&format!("  {k}"), &s)),
                    None => println!("    {k}: {v}"),
                }
            }
        }
    }
    Ok(())
}

/// One row of the text table.
fn stats_row(name: &str, l: &LatencyStats) -> String {
    format!(
        "{name:<36} {:>8} {:>10.2} {:>10.2} {:>10.2} {:>10.2}",
        l.samples, l.median_us, l.p90_us, l.p99_us, l.max_us
    )
}

/// The statistics in a JSON value shaped like [`LatencyStats`] (a report's extra figure).
fn latency_of(v: &serde_json::Value) -> Option<LatencyStats> {
    LatencyStats::deserialize(v).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_nested_latency_figure_is_read_back_and_anything_else_is_not() {
        let l = LatencyStats::from_samples(&[1.0, 2.0, 3.0, 4.0]).unwrap();
        let v = serde_json::json!(l);
        assert_eq!(latency_of(&v), Some(l.clone()));
        assert_eq!(latency_of(&serde_json::json!({"count": 3, "wall": v})), None);
        assert_eq!(latency_of(&serde_json::json!(null)), None);
        let row = stats_row("step", &l);
        assert!(row.starts_with("step ") && row.contains("       4 "), "{row}");
        assert!(row.ends_with("      4.00"), "{row}");
    }
}
