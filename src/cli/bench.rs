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
}

/// Run `bench`.
pub fn run(a: &BenchArgs) -> super::CliResult {
    let mut reports: Vec<SuiteReport> = vec![];
    let all = a.suite == Suite::All;
    if all || a.suite == Suite::Kinematics {
        reports.extend(crate::bench::kinematics::run(a.samples)?);
    }
    if all || a.suite == Suite::Sim {
        let cfg = crate::sim::config::SimConfig::load_default()?;
        reports.extend(crate::bench::sim::run(&cfg, a.samples, 10)?);
    }
    if all || a.suite == Suite::Controller {
        reports.extend(crate::bench::controller::run(a.samples.min(5000))?);
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&reports)?);
    } else {
        println!(
            "{:<36} {:>8} {:>10} {:>10} {:>10} {:>10}",
            "operation", "samples", "median µs", "p90 µs", "p99 µs", "max µs"
        );
        for r in &reports {
            let l = &r.latency;
            println!(
                "{:<36} {:>8} {:>10.2} {:>10.2} {:>10.2} {:>10.2}",
                r.name, l.samples, l.median_us, l.p90_us, l.p99_us, l.max_us
            );
            for (k, v) in &r.extra {
                println!("    {k}: {v}");
            }
        }
    }
    Ok(())
}
