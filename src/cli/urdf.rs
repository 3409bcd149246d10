//! `trocar_docking urdf`: write the URDF of an LBR Med with an endoscope.

use std::path::PathBuf;

use crate::kinematics::lbr::{urdf, LbrModel, ToolParams};

/// Arguments of `urdf`.
#[derive(Debug, clap::Args)]
pub struct UrdfArgs {
    /// Arm model.
    #[arg(long, value_enum, default_value = "med7")]
    pub model: LbrModel,
    /// Endoscope length from the flange to the tip, m.
    #[arg(long, default_value_t = ToolParams::default().length_m)]
    pub tool_length: f64,
    /// Endoscope shaft diameter, m.
    #[arg(long, default_value_t = ToolParams::default().diameter_m)]
    pub tool_diameter: f64,
    /// Output file (default: standard output).
    #[arg(long, short)]
    pub output: Option<PathBuf>,
}

/// Run `urdf`.
pub fn run(a: &UrdfArgs) -> super::CliResult {
    let xml = urdf(
        a.model,
        &ToolParams {
            length_m: a.tool_length,
            diameter_m: a.tool_diameter,
        },
    )?;
    match &a.output {
        Some(p) => std::fs::write(p, xml).map_err(|e| format!("cannot write {}: {e}", p.display()))?,
        None => print!("{xml}"),
    }
    Ok(())
}
