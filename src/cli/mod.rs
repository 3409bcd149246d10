//! The offline command-line tool `trocar_docking`: one subcommand per file in this module.

use clap::{Parser, Subcommand};

pub mod bench;
pub mod fk;
pub mod markerless;
pub mod pivot;
pub mod soak;
pub mod trials;
pub mod urdf;
pub mod vision;

/// Errors a subcommand reports to the user (printed, exit code 1).
pub type CliResult = Result<(), Box<dyn std::error::Error + Send + Sync>>;

/// trocar_docking: autonomous endoscope-to-trocar docking for the KUKA LBR Med.
#[derive(Debug, Parser)]
#[command(name = "trocar_docking", version, about)]
pub struct Cli {
    /// The subcommand.
    #[command(subcommand)]
    pub command: Command,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Time the hot paths (latency statistics, `--json`).
    Bench(bench::BenchArgs),
    /// Forward kinematics and Jacobian of a URDF chain.
    Fk(fk::FkArgs),
    /// After docking: steer the scope through the port (random pan/tilt/zoom), with and
    /// without the force-adapted fulcrum; the pivoting benchmark.
    Pivot(pivot::PivotArgs),
    /// Run the paper's experiment in simulation: trials with and without force feedback.
    Trials(trials::TrialsArgs),
    /// Repeated docking cycles at 1 kHz for a long run: max step time, RSS growth, every
    /// cycle DONE (not in CI).
    Soak(soak::SoakArgs),
    /// Detect markers in an image file and print their poses.
    Detect(vision::DetectArgs),
    /// Render a synthetic marker image and print its true pose.
    Render(vision::RenderArgs),
    /// Hand-eye calibration (camera in the flange) from pose pairs.
    HandEye(vision::HandEyeArgs),
    /// Render a synthetic markerless trocar image (or a docking-approach sequence with truth).
    RenderTrocar(markerless::RenderTrocarArgs),
    /// Estimate the trocar's axis without a marker in a folder of images.
    TrocarPose(markerless::TrocarPoseArgs),
    /// Write the URDF of an LBR Med with an endoscope.
    Urdf(urdf::UrdfArgs),
    /// Print the versions of the C++ libraries linked.
    Versions,
}

/// Run the parsed command line.
pub fn run(cli: Cli) -> CliResult {
    match cli.command {
        Command::Bench(a) => bench::run(&a),
        Command::Fk(a) => fk::run(&a),
        Command::Trials(a) => trials::run(&a),
        Command::Pivot(a) => pivot::run(&a),
        Command::Soak(a) => soak::run(&a),
        Command::Urdf(a) => urdf::run(&a),
        Command::Detect(a) => vision::run_detect(&a),
        Command::Render(a) => vision::run_render(&a),
        Command::HandEye(a) => vision::run_hand_eye(&a),
        Command::RenderTrocar(a) => markerless::run_render(&a),
        Command::TrocarPose(a) => markerless::run_pose(&a),
        Command::Versions => {
            println!("{}", crate::vision::backend_versions());
            Ok(())
        }
    }
}
