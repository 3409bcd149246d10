//! `trocar_docking soak`: the arguments and the printed report of the soak
//! ([`crate::trials::soak`]). Not part of CI: a 60-minute run is
//! `trocar_docking soak --minutes 60 --json`.

use super::CliResult;
use crate::trials::config::Protocol;
use crate::trials::soak::{soak, SoakOptions, StepTimes};

/// Arguments of `soak`.
#[derive(Debug, clap::Args)]
pub struct SoakArgs {
    /// Wall-clock duration of the run, minutes.
    #[arg(long, default_value_t = 60.0)]
    pub minutes: f64,
    /// Control rate, Hz (the physics runs at its own rate, 1 kHz). Default: the controller
    /// configuration's period (`dt_s`; the shipped 0.01 s, 100 Hz).
    #[arg(long)]
    pub rate: Option<f64>,
    /// World protocol of `config/sim.yaml`.
    #[arg(long, value_enum, default_value_t = Protocol::Realistic)]
    pub protocol: Protocol,
    /// First seed: cycle k runs the world drawn with seed + k (every cycle a new draw).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Simulated time a cycle may take to reach DONE, s.
    #[arg(long, default_value_t = 30.0)]
    pub cycle_timeout: f64,
    /// Controller configuration (default: config/controller.yaml).
    #[arg(long)]
    pub controller_config: Option<std::path::PathBuf>,
    /// Seconds of the fixed reference workload timed before the run (0: none).
    #[arg(long, default_value_t = 60.0)]
    pub reference_seconds: f64,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

impl SoakArgs {
    /// What the soak runs.
    fn options(&self) -> SoakOptions {
        SoakOptions {
            minutes: self.minutes,
            rate: self.rate,
            protocol: self.protocol,
            seed: self.seed,
            cycle_timeout: self.cycle_timeout,
            controller_config: self.controller_config.clone(),
            reference_seconds: self.reference_seconds,
        }
    }
}

/// Run `soak` and print its report. Exits with an error when a cycle did not dock.
pub fn run(a: &SoakArgs) -> CliResult {
    let r = soak(&a.options())?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        let us = |s: &StepTimes| {
            format!(
                "p50 {:.0}, p99 {:.0}, p99.9 {:.0}, max {:.0} µs",
                s.p50_us, s.p99_us, s.p999_us, s.max_us
            )
        };
        println!(
            "soak ({} protocol, seeds {}-{}): {} cycles in {:.0} s ({:.0} s simulated) at {} Hz, {} docked, {} false DONE; outcomes {:?}",
            r.protocol, r.seeds[0], r.seeds[1], r.cycles, r.wall_s, r.sim_s, r.rate_hz, r.docked, r.false_done, r.outcomes
        );
        println!(
            "  every one of {} steps: CPU {} ({} over 1 ms, {} of them with a Clarabel solve); wall {} ({} over 1 ms)",
            r.steps,
            us(&r.step_cpu),
            r.steps_over_1ms_cpu,
            r.steps_over_1ms_cpu_clarabel,
            us(&r.step_wall),
            r.steps_over_1ms
        );
        println!(
            "  command lead <= {:.2} deg; RSS {} -> {} kB ({:+.2} MB/h); reference workload ({:.0} s, median {:.0} µs): {} of {} chunks over 1 ms, max {:.0} µs",
            r.max_command_lead_deg,
            r.rss_start_kb,
            r.rss_end_kb,
            r.rss_growth_mb_per_h,
            r.reference.seconds,
            r.reference.median_us,
            r.reference.over_1ms,
            r.reference.chunks,
            r.reference.max_us
        );
        for f in &r.failures {
            println!(
                "  seed {}: {} in {} ({}){}",
                f.seed,
                f.outcome,
                f.phase,
                f.hold_code,
                if f.error.is_empty() {
                    String::new()
                } else {
                    format!(": {}", f.error)
                }
            );
        }
    }
    if r.every_cycle_docked {
        Ok(())
    } else {
        Err(format!("{} of {} cycles did not dock", r.cycles - r.docked, r.cycles).into())
    }
}
