//! `trocar_docking detect`, `render` and `hand-eye`: marker detection on an image file, the
//! synthetic camera, and hand-eye calibration from a file of pose pairs (or an easy_handeye
//! calibration converted to the project's file).

use std::path::{Path, PathBuf};

use nalgebra::Isometry3;

use crate::kinematics::{fixed_transform, FLANGE_LINK};
use crate::vision::estimator::PoseYaml;
use crate::vision::{
    facing_pose_in, hand_eye, render_marker_image, CameraModel, GreyImage, MarkerDetection, MarkerDetector,
    MarkerFamily, MarkerSpec, RenderOptions,
};

/// The marker options shared by `detect` and `render`. Family and size default to the
/// marker the simulator shows and the estimator expects (`marker:` of
/// config/trocar_estimator.yaml: DICT_4X4_50, 40 mm).
#[derive(Debug, clap::Args)]
pub struct MarkerArgs {
    /// Family: an OpenCV ArUco dictionary name (DICT_4X4_50, DICT_ARUCO_ORIGINAL, ...) or an
    /// official AprilTag family (tag16h5, tag25h9, tag36h10, tag36h11; DICT_APRILTAG_* names
    /// read as these) [default: the estimator's, DICT_4X4_50]. Each in its library's frame
    /// (docs/vision.md): ArUco corners TL TR BR BL, x right, y up, z out of the marker;
    /// AprilTag corners left-bottom, right-bottom, right-top, left-top, x right, y down, z
    /// into the tag.
    #[arg(long)]
    pub family: Option<String>,
    /// Marker id (detect: keep only this id, default all; render: default the estimator's, 7).
    #[arg(long)]
    pub id: Option<u32>,
    /// Marker side, m [default: the estimator's, 0.04].
    #[arg(long)]
    pub size: Option<f64>,
}

impl MarkerArgs {
    fn spec(&self) -> Result<MarkerSpec, crate::vision::VisionError> {
        let shipped = MarkerSpec::default();
        let family: MarkerFamily = match &self.family {
            Some(f) => f.parse()?,
            None => shipped.family,
        };
        let spec = MarkerSpec {
            family,
            id: self.id,
            size_m: self.size.unwrap_or(shipped.size_m),
        };
        spec.validate()?;
        Ok(spec)
    }
}

/// Arguments of `detect`.
#[derive(Debug, clap::Args)]
pub struct DetectArgs {
    /// Image file (PNG, PGM, JPEG...).
    #[arg(long)]
    pub image: PathBuf,
    /// Camera calibration YAML (ROS camera_info_manager format).
    #[arg(long)]
    pub camera: PathBuf,
    /// Marker.
    #[command(flatten)]
    pub marker: MarkerArgs,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `render`.
#[derive(Debug, clap::Args)]
pub struct RenderArgs {
    /// Output image (format by extension: .png, .pgm, ...).
    #[arg(long)]
    pub out: PathBuf,
    /// Camera calibration YAML.
    #[arg(long)]
    pub camera: PathBuf,
    /// Marker (id defaults to 0).
    #[command(flatten)]
    pub marker: MarkerArgs,
    /// Distance of the marker centre along the optical axis, m.
    #[arg(long, default_value_t = 0.4)]
    pub distance: f64,
    /// Lateral offset x, y in the camera frame, m.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_value = "0,0")]
    pub offset: Vec<f64>,
    /// Tilt about the marker x and y axes, deg.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_value = "0,0")]
    pub tilt_deg: Vec<f64>,
    /// Turn about the marker z axis, deg.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub yaw_deg: f64,
    /// Gaussian pixel noise sigma, grey levels.
    #[arg(long, default_value_t = 0.0)]
    pub noise: f64,
    /// Gaussian blur sigma, px.
    #[arg(long, default_value_t = 0.0)]
    pub blur: f64,
    /// Seed of noise and texture.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `hand-eye`.
#[derive(Debug, clap::Args)]
pub struct HandEyeArgs {
    /// YAML/JSON file: `samples: [{base_t_flange: {translation, quaternion_xyzw}, camera_t_marker: {...}}, ...]`.
    #[arg(
        long,
        required_unless_present = "from_easy_handeye",
        conflicts_with = "from_easy_handeye"
    )]
    pub input: Option<PathBuf>,
    /// Instead of calibrating: convert an easy_handeye calibration (eye on hand;
    /// `~/.ros/easy_handeye/NAME.yaml`), its robot_effector_frame carried to the flange
    /// lbr_link_ee through the fixed joints of --urdf.
    #[arg(long, requires = "urdf")]
    pub from_easy_handeye: Option<PathBuf>,
    /// The robot's URDF (robot_description), for --from-easy-handeye.
    #[arg(long)]
    pub urdf: Option<PathBuf>,
    /// Write the result (flange_t_camera and residuals) as YAML here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

fn pose_json(p: &Isometry3<f64>) -> serde_json::Value {
    let y = PoseYaml::from_isometry(p);
    serde_json::json!({ "translation": y.translation, "quaternion_xyzw": y.quaternion_xyzw })
}

fn detection_json(d: &MarkerDetection) -> serde_json::Value {
    serde_json::json!({
        "id": d.id,
        "pose_camera_marker": pose_json(&d.pose_camera_marker),
        "corners_px": d.corners,
        "reprojection_error_px": d.reprojection_error_px,
    })
}

/// Run `detect`.
pub fn run_detect(a: &DetectArgs) -> super::CliResult {
    let camera = CameraModel::from_yaml_file(&a.camera)?;
    let spec = a.marker.spec()?;
    let (family, size_m, frame) = (spec.family.name().to_string(), spec.size_m, spec.family.frame());
    let image = GreyImage::read(&a.image)?;
    let mut det = MarkerDetector::new(spec, &camera)?;
    let t0 = std::time::Instant::now();
    let found = det.detect(&image.view())?;
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    if a.json {
        let v = serde_json::json!({
            "image": a.image, "family": family, "size_m": size_m, "time_ms": ms,
            "corner_order": frame.corner_names(), "axes": frame.axes(),
            "markers": found.iter().map(detection_json).collect::<Vec<_>>(),
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("{} marker(s) in {:.2} ms", found.len(), ms);
        for d in &found {
            let t = d.pose_camera_marker.translation.vector;
            let q = d.pose_camera_marker.rotation;
            println!(
                "id {}: t [m] {:+.5} {:+.5} {:+.5}  q [x y z w] {:+.5} {:+.5} {:+.5} {:+.5}  reproj {:.3} px",
                d.id, t.x, t.y, t.z, q.i, q.j, q.k, q.w, d.reprojection_error_px
            );
            let c: Vec<String> = d
                .corners
                .iter()
                .map(|c| format!("({:.2}, {:.2})", c[0], c[1]))
                .collect();
            println!("   corners {}: {}", frame.corner_names(), c.join(" "));
        }
    }
    Ok(())
}

/// Run `render`.
pub fn run_render(a: &RenderArgs) -> super::CliResult {
    let camera = CameraModel::from_yaml_file(&a.camera)?;
    let mut spec = a.marker.spec()?;
    spec.id = spec.id.or(MarkerSpec::default().id).or(Some(0));
    if a.offset.len() != 2 || a.tilt_deg.len() != 2 {
        return Err("--offset and --tilt-deg take two comma-separated numbers".into());
    }
    let truth = facing_pose_in(
        spec.family.frame(),
        a.distance,
        a.offset[0],
        a.offset[1],
        a.tilt_deg[0].to_radians(),
        a.tilt_deg[1].to_radians(),
        a.yaw_deg.to_radians(),
    );
    let opts = RenderOptions {
        noise_sigma: a.noise,
        blur_sigma: a.blur,
        seed: a.seed,
        ..Default::default()
    };
    let img = render_marker_image(&spec, &camera, &truth, &opts)?;
    img.write(&a.out)?;
    if a.json {
        let v = serde_json::json!({
            "out": a.out, "family": spec.family.name(), "id": spec.id, "size_m": spec.size_m,
            "width": img.width, "height": img.height, "pose_camera_marker": pose_json(&truth),
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        let t = truth.translation.vector;
        let q = truth.rotation;
        println!("wrote {} ({}x{})", a.out.display(), img.width, img.height);
        println!(
            "true pose_camera_marker: t [m] {:+.5} {:+.5} {:+.5}  q [x y z w] {:+.5} {:+.5} {:+.5} {:+.5}",
            t.x, t.y, t.z, q.i, q.j, q.k, q.w
        );
    }
    Ok(())
}

/// Seconds since the Unix epoch of `t`.
fn unix_s(t: std::time::SystemTime) -> f64 {
    t.duration_since(std::time::UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64())
}

/// `hand-eye --from-easy-handeye`: the mount in the flange, written as the project's file
/// dated by the easy_handeye file's modification time (it carries no date of its own).
fn convert_easy_handeye(file: &Path, urdf: &Path, out: Option<&Path>, json: bool) -> super::CliResult {
    let xml = std::fs::read_to_string(urdf).map_err(|e| format!("{}: cannot read: {e}", urdf.display()))?;
    let resolve = |frame: &str| fixed_transform(&xml, FLANGE_LINK, frame).map_err(|e| e.to_string());
    let mount = hand_eye::load_mount(file, &resolve)?;
    let source = format!("easy_handeye's {} through {}", file.display(), urdf.display());
    if let Some(out) = out {
        let modified = std::fs::metadata(file)?.modified()?;
        std::fs::write(
            out,
            mount.file_text(&source, &crate::preflight::date_of(unix_s(modified)))?,
        )?;
    }
    let pose = pose_json(&mount.flange_t_camera);
    if json {
        let v = serde_json::json!({ "flange_t_camera": pose, "camera_frame": mount.camera_frame });
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        let y = PoseYaml::from_isometry(&mount.flange_t_camera);
        let frame = mount.camera_frame.as_deref().unwrap_or("camera");
        println!(
            "flange_t_camera ({FLANGE_LINK} -> {frame}): t [m] {:+.5?}  q [x y z w] {:+.5?}",
            y.translation, y.quaternion_xyzw
        );
    }
    Ok(())
}

/// Run `hand-eye`.
pub fn run_hand_eye(a: &HandEyeArgs) -> super::CliResult {
    if let (Some(file), Some(urdf)) = (&a.from_easy_handeye, &a.urdf) {
        return convert_easy_handeye(file, urdf, a.out.as_deref(), a.json);
    }
    let input = a.input.as_ref().ok_or("--input or --from-easy-handeye is needed")?;
    let input = hand_eye::HandEyeInput::from_file(input)?;
    let r = hand_eye::calibrate_input(&input)?;
    if let Some(out) = &a.out {
        let date = crate::preflight::date_of(unix_s(std::time::SystemTime::now()));
        std::fs::write(
            out,
            hand_eye::file_text("`trocar_docking hand-eye`", &date, &r, None, &[])?,
        )?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        let t = r.flange_t_camera.translation;
        let q = r.flange_t_camera.quaternion_xyzw;
        println!(
            "flange_t_camera: t [m] {:+.5} {:+.5} {:+.5}  q [x y z w] {:+.5} {:+.5} {:+.5} {:+.5}",
            t[0], t[1], t[2], q[0], q[1], q[2], q[3]
        );
        println!(
            "residuals over {} samples: translation rms {:.3} mm (max {:.3}), rotation rms {:.3} deg (max {:.3})",
            r.samples,
            r.residual_translation_rms_m * 1e3,
            r.residual_translation_max_m * 1e3,
            r.residual_rotation_rms_rad.to_degrees(),
            r.residual_rotation_max_rad.to_degrees()
        );
    }
    Ok(())
}
