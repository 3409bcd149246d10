//! `trocar_docking fk`: tip pose and Jacobian of a URDF chain at a joint vector.

use std::path::PathBuf;

use crate::kinematics::{KdlChain, BASE_LINK};

/// Arguments of `fk`.
#[derive(Debug, clap::Args)]
pub struct FkArgs {
    /// URDF file.
    #[arg(long)]
    pub urdf: PathBuf,
    /// Base link.
    #[arg(long, default_value = BASE_LINK)]
    pub base: String,
    /// Tip link.
    #[arg(long, default_value = crate::kinematics::TIP_LINK)]
    pub tip: String,
    /// Joint positions, rad, comma-separated (q1,...,qn).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub q: Vec<f64>,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Run `fk`.
pub fn run(a: &FkArgs) -> super::CliResult {
    let chain = KdlChain::from_urdf_file(&a.urdf, &a.base, &a.tip)?;
    let n = chain.n_joints();
    let mut jac = vec![0.0; 6 * a.q.len()];
    let pose = chain.fk_jacobian_slice(&a.q, &mut jac)?;
    let p = pose.translation.vector;
    let r = pose.rotation;
    // Rows of the 6 x n Jacobian (stored column-major).
    let rows: Vec<Vec<f64>> = (0..6).map(|i| (0..n).map(|j| jac[6 * j + i]).collect()).collect();
    if a.json {
        let v = serde_json::json!({
            "base": a.base, "tip": a.tip, "joints": chain.joint_names(), "q": a.q,
            "position": [p.x, p.y, p.z],
            "quaternion_xyzw": [r.i, r.j, r.k, r.w],
            "jacobian": rows,
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{} -> {} ({} joints: {})",
            a.base,
            a.tip,
            n,
            chain.joint_names().join(", ")
        );
        println!("position [m]:          {:+.6} {:+.6} {:+.6}", p.x, p.y, p.z);
        println!("quaternion [x y z w]:  {:+.6} {:+.6} {:+.6} {:+.6}", r.i, r.j, r.k, r.w);
        println!("jacobian (rows vx vy vz wx wy wz):");
        for row in rows {
            let s: Vec<String> = row.iter().map(|x| format!("{x:+.5}")).collect();
            println!("  {}", s.join(" "));
        }
    }
    Ok(())
}
