//! The LBR Med arm models and their URDF, generated from the kinematic facts of the robots.
//!
//! The URDF files in `urdf/` are written by [`urdf`] (see `trocar_docking urdf --help`), so
//! that the tool length and diameter can be changed without hand-editing XML. Link and joint
//! names follow the LBR driver's naming: `lbr_link_0..7`, the flange `lbr_link_ee`, joints
//! `lbr_joint_1..7`; the endoscope ends in `endoscope_tip`, whose z axis is the optical axis.

use std::fmt::Write as _;

/// Which LBR Med arm.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LbrModel {
    /// LBR Med 7 R800.
    Med7,
    /// LBR Med 14 R820.
    Med14,
}

/// The endoscope held by the flange: a straight rigid scope along the flange z axis.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ToolParams {
    /// Length from the flange to the tip, m.
    pub length_m: f64,
    /// Shaft diameter, m.
    pub diameter_m: f64,
}

impl Default for ToolParams {
    fn default() -> Self {
        Self {
            length_m: 0.25,
            diameter_m: 0.005,
        }
    }
}

/// Kinematic and limit data of one arm, in the URDF's terms.
#[derive(Debug, Clone, PartialEq)]
pub struct ArmSpec {
    /// Robot name used in the URDF.
    pub name: &'static str,
    /// Joint origins relative to the previous joint (the last one is the flange), m.
    pub origins: [[f64; 3]; 8],
    /// Joint axes.
    pub axes: [[f64; 3]; 7],
    /// Position limits, symmetric, degrees.
    pub limit_deg: [f64; 7],
    /// Velocity limits, degrees per second.
    pub velocity_deg: [f64; 7],
    /// Torque limits, Nm.
    pub effort: [f64; 7],
}

const AXES: [[f64; 3]; 7] = [
    [0.0, 0.0, 1.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, -1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
];
const LIMITS_DEG: [f64; 7] = [170.0, 120.0, 170.0, 120.0, 170.0, 120.0, 175.0];

impl LbrModel {
    /// The kinematic facts of this arm.
    pub fn spec(self) -> ArmSpec {
        match self {
            LbrModel::Med7 => ArmSpec {
                name: "lbr_med7_r800",
                origins: [
                    [0.0, 0.0, 0.1475],
                    [0.0, -0.0105, 0.1925],
                    [0.0, 0.0105, 0.2075],
                    [0.0, 0.0105, 0.1925],
                    [0.0, -0.0105, 0.2075],
                    [0.0, -0.0707, 0.1925],
                    [0.0, 0.0707, 0.091],
                    [0.0, 0.0, 0.035],
                ],
                axes: AXES,
                limit_deg: LIMITS_DEG,
                velocity_deg: [98.0, 98.0, 100.0, 130.0, 140.0, 180.0, 180.0],
                effort: [176.0, 176.0, 110.0, 110.0, 110.0, 40.0, 40.0],
            },
            LbrModel::Med14 => ArmSpec {
                name: "lbr_med14_r820",
                origins: [
                    [0.0, 0.0, 0.147],
                    [0.0, -0.01, 0.2125],
                    [0.0, 0.01, 0.228],
                    [0.0, 0.0105, 0.192],
                    [0.0, -0.0105, 0.2075],
                    [0.0, -0.0707, 0.1925],
                    [0.0, 0.0707, 0.091],
                    [0.0, 0.0, 0.035],
                ],
                axes: AXES,
                limit_deg: LIMITS_DEG,
                velocity_deg: [85.0, 85.0, 100.0, 75.0, 130.0, 135.0, 135.0],
                effort: [320.0, 320.0, 176.0, 176.0, 110.0, 40.0, 40.0],
            },
        }
    }

    /// The default file name of this arm's URDF in `urdf/`.
    pub fn file_name(self) -> &'static str {
        match self {
            LbrModel::Med7 => "lbr_med7_r800_endoscope.urdf",
            LbrModel::Med14 => "lbr_med14_r820_endoscope.urdf",
        }
    }
}

/// Errors in the tool parameters.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ModelError {
    /// A tool dimension (m) is not a positive finite length of sane size.
    #[error("tool {0}")]
    BadTool(#[from] crate::validate::RangeError),
}

fn check_tool(tool: &ToolParams) -> Result<(), ModelError> {
    crate::validate::positive_at_most("length_m", tool.length_m, 1.0)?;
    crate::validate::positive_at_most("diameter_m", tool.diameter_m, 0.05)?;
    Ok(())
}

fn v3(v: [f64; 3]) -> String {
    format!("{} {} {}", v[0], v[1], v[2])
}

/// The URDF of `model` with the endoscope `tool` on its flange.
pub fn urdf(model: LbrModel, tool: &ToolParams) -> Result<String, ModelError> {
    check_tool(tool)?;
    let s = model.spec();
    let mut x = String::new();
    write_header(&mut x, model, tool, &s);
    write_arm_links(&mut x, &s);
    write_arm_joints(&mut x, &s);
    write_endoscope(&mut x, tool);
    write_camera(&mut x);
    Ok(x)
}

// `write!` into a String cannot fail: the results below are ignored.

/// The XML header, the robot element and the materials.
fn write_header(w: &mut String, model: LbrModel, tool: &ToolParams, s: &ArmSpec) {
    let _ = writeln!(w, "<?xml version=\"1.0\"?>");
    let _ = writeln!(
        w,
        "<!-- Generated by `trocar_docking urdf --model {:?} --tool-length {} --tool-diameter {}`; do not edit. -->",
        model, tool.length_m, tool.diameter_m
    );
    let _ = writeln!(w, "<robot name=\"{}\">", s.name);
    let _ = writeln!(
        w,
        "  <material name=\"kuka_white\"><color rgba=\"0.92 0.92 0.92 1\"/></material>"
    );
    let _ = writeln!(
        w,
        "  <material name=\"kuka_orange\"><color rgba=\"1.0 0.42 0.04 1\"/></material>"
    );
    let _ = writeln!(
        w,
        "  <material name=\"steel\"><color rgba=\"0.7 0.72 0.75 1\"/></material>"
    );
    let _ = writeln!(
        w,
        "  <material name=\"dark\"><color rgba=\"0.15 0.15 0.17 1\"/></material>"
    );
}

/// Links 0..=7: link i spans from its joint to the next joint, a cylinder of the arm's
/// radius.
fn write_arm_links(w: &mut String, s: &ArmSpec) {
    for i in 0..=7 {
        let next = s.origins[i];
        let len = (next[0].powi(2) + next[1].powi(2) + next[2].powi(2)).sqrt();
        let radius = if i == 7 { 0.045 } else { 0.065 };
        let mat = if i % 2 == 1 { "kuka_orange" } else { "kuka_white" };
        let geometry = format!(
            "<origin xyz=\"{} {} {}\" rpy=\"0 0 0\"/><geometry><cylinder radius=\"{radius}\" length=\"{len}\"/></geometry>",
            next[0] / 2.0,
            next[1] / 2.0,
            next[2] / 2.0
        );
        let _ = writeln!(w, "  <link name=\"lbr_link_{i}\">");
        let _ = writeln!(w, "    <visual>{geometry}<material name=\"{mat}\"/></visual>");
        let _ = writeln!(w, "    <collision>{geometry}</collision>");
        let _ = writeln!(w, "  </link>");
    }
}

/// Joints `lbr_joint_1..7` with their limits, then the flange `lbr_link_ee`.
fn write_arm_joints(w: &mut String, s: &ArmSpec) {
    for j in 0..7 {
        let lim = s.limit_deg[j].to_radians();
        let _ = writeln!(w, "  <joint name=\"{}\" type=\"revolute\">", super::joint_name(j + 1));
        let _ = writeln!(
            w,
            "    <parent link=\"lbr_link_{j}\"/><child link=\"lbr_link_{}\"/>",
            j + 1
        );
        let _ = writeln!(
            w,
            "    <origin xyz=\"{}\" rpy=\"0 0 0\"/><axis xyz=\"{}\"/>",
            v3(s.origins[j]),
            v3(s.axes[j])
        );
        let _ = writeln!(
            w,
            "    <limit lower=\"{:.6}\" upper=\"{:.6}\" velocity=\"{:.6}\" effort=\"{}\"/>",
            -lim,
            lim,
            s.velocity_deg[j].to_radians(),
            s.effort[j]
        );
        let _ = writeln!(w, "  </joint>");
    }
    let _ = writeln!(w, "  <link name=\"lbr_link_ee\"/>");
    let _ = writeln!(w, "  <joint name=\"lbr_joint_ee\" type=\"fixed\">");
    let _ = writeln!(w, "    <parent link=\"lbr_link_7\"/><child link=\"lbr_link_ee\"/>");
    let _ = writeln!(w, "    <origin xyz=\"{}\" rpy=\"0 0 0\"/>", v3(s.origins[7]));
    let _ = writeln!(w, "  </joint>");
}

/// The endoscope: a mount disc on the flange, the shaft, and the tip frame.
fn write_endoscope(w: &mut String, tool: &ToolParams) {
    let (len, d) = (tool.length_m, tool.diameter_m);
    let _ = writeln!(w, "  <link name=\"endoscope_link\">");
    let _ = writeln!(
        w,
        "    <visual><origin xyz=\"0 0 0.01\"/><geometry><cylinder radius=\"0.04\" length=\"0.02\"/></geometry><material name=\"dark\"/></visual>"
    );
    let _ = writeln!(
        w,
        "    <visual><origin xyz=\"0 0 {}\"/><geometry><cylinder radius=\"{}\" length=\"{len}\"/></geometry><material name=\"steel\"/></visual>",
        len / 2.0,
        d / 2.0
    );
    let _ = writeln!(
        w,
        "    <collision><origin xyz=\"0 0 {}\"/><geometry><cylinder radius=\"{}\" length=\"{len}\"/></geometry></collision>",
        len / 2.0,
        d / 2.0
    );
    let _ = writeln!(w, "  </link>");
    let _ = writeln!(w, "  <joint name=\"endoscope_joint\" type=\"fixed\">");
    let _ = writeln!(
        w,
        "    <parent link=\"lbr_link_ee\"/><child link=\"endoscope_link\"/><origin xyz=\"0 0 0\" rpy=\"0 0 0\"/>"
    );
    let _ = writeln!(w, "  </joint>");
    let _ = writeln!(w, "  <link name=\"endoscope_tip\"/>");
    let _ = writeln!(w, "  <joint name=\"endoscope_tip_joint\" type=\"fixed\">");
    let _ = writeln!(
        w,
        "    <parent link=\"endoscope_link\"/><child link=\"endoscope_tip\"/><origin xyz=\"0 0 {len}\" rpy=\"0 0 0\"/>"
    );
    let _ = writeln!(w, "  </joint>");
}

/// The camera housing (ZED mini) drawn at its nominal mount beside the scope: the link
/// `camera_nominal`, never the images' own frame, whose parent is the flange through the
/// calibrated hand-eye (the trocar estimator's static tf). Closes the robot element.
fn write_camera(w: &mut String) {
    let _ = writeln!(w, "  <link name=\"camera_nominal\">");
    let _ = writeln!(
        w,
        "    <visual><origin xyz=\"0 0 -0.015\"/><geometry><box size=\"0.124 0.03 0.03\"/></geometry><material name=\"dark\"/></visual>"
    );
    let _ = writeln!(w, "  </link>");
    let _ = writeln!(w, "  <joint name=\"camera_joint\" type=\"fixed\">");
    let _ = writeln!(w, "    <parent link=\"lbr_link_ee\"/><child link=\"camera_nominal\"/><origin xyz=\"0 0.07 0.04\" rpy=\"0.2617993877991494 0 0\"/>");
    let _ = writeln!(w, "  </joint>");
    let _ = writeln!(w, "</robot>");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_bad_tool() {
        for (l, d) in [
            (0.0, 0.005),
            (f64::NAN, 0.005),
            (0.25, -1.0),
            (2.0, 0.005),
            (0.25, f64::INFINITY),
        ] {
            let e = urdf(
                LbrModel::Med7,
                &ToolParams {
                    length_m: l,
                    diameter_m: d,
                },
            )
            .unwrap_err();
            let key = if (0.0..=1.0).contains(&l) && l > 0.0 {
                "`diameter_m`"
            } else {
                "`length_m`"
            };
            assert!(e.to_string().starts_with(&format!("tool {key} = ")), "{l} {d}: {e}");
        }
    }

    #[test]
    fn committed_urdfs_match_generator() {
        for m in [LbrModel::Med7, LbrModel::Med14] {
            let path = format!("{}/urdf/{}", env!("CARGO_MANIFEST_DIR"), m.file_name());
            let committed = std::fs::read_to_string(&path).expect("committed URDF");
            assert_eq!(
                committed,
                urdf(m, &ToolParams::default()).unwrap(),
                "{path} is stale: regenerate it"
            );
        }
    }
}
