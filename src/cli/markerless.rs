//! `trocar_docking render-trocar` and `trocar-pose`: the markerless synthetic camera (one
//! image, or a sequence along a docking approach with its ground truth) and the markerless
//! axis estimate on a folder of images.

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Unit, Vector3};

use crate::kinematics::lbr::{LbrModel, ToolParams};
use crate::kinematics::LbrKinematics;
use crate::vision::estimator::PoseYaml;
use crate::vision::markerless::approach::docking_approach;
use crate::vision::markerless::render::ToolCylinder;
use crate::vision::markerless::{
    MarkerlessEstimate, MarkerlessEstimator, MarkerlessParams, Scene, TrocarModel, TrocarRenderer,
};
use crate::vision::{CameraModel, GreyImage};

/// Arguments of `render-trocar`.
#[derive(Debug, clap::Args)]
pub struct RenderTrocarArgs {
    /// Camera calibration YAML (ROS camera_info_manager format).
    #[arg(long)]
    pub camera: PathBuf,
    /// Trocar model YAML.
    #[arg(long, default_value = "config/trocar_model.yaml")]
    pub model: PathBuf,
    /// Port pose in the camera frame: x,y,z,qx,qy,qz,qw (z axis along the trocar, into the body).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub pose: Option<Vec<f64>>,
    /// Output image; with --sequence, the output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of the lighting, the wall and the noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Gaussian pixel noise, grey levels.
    #[arg(long, default_value_t = 2.0)]
    pub noise: f64,
    /// Motion blur: length px, direction deg.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub motion_blur: Option<Vec<f64>>,
    /// A tool shaft in view: x0,y0,z0,x1,y1,z1,radius (camera frame, m).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub tool: Option<Vec<f64>>,
    /// Leave the trocar out (wall, and the tool if any).
    #[arg(long)]
    pub no_trocar: bool,
    /// Render this many frames along a docking approach into the folder --out, with truth.json.
    #[arg(long)]
    pub sequence: Option<usize>,
    /// The camera mount (a lbr_med_sim parameter file: camera.flange_t_camera), for --sequence.
    #[arg(long, default_value = "config/lbr_med_sim.yaml")]
    pub mount: PathBuf,
    /// Camera-to-port distances of the sequence, far,near (m).
    #[arg(long, value_delimiter = ',', default_value = "0.4,0.1")]
    pub range: Vec<f64>,
    /// With --sequence: also render the stereo pair's right camera (the calibration of a
    /// rectified pair's right camera, e.g. config/camera_zedm_right.yaml) into OUT/right/,
    /// the same scene seen from the baseline to the right.
    #[arg(long)]
    pub right_camera: Option<PathBuf>,
    /// Draw the endoscope's own shaft where the camera on --mount sees it (the built-in
    /// arm's tool: 0.25 m from the flange to the tip, 5 mm across), in both images.
    #[arg(long, conflicts_with = "tool")]
    pub endoscope: bool,
}

/// Arguments of `trocar-pose`.
#[derive(Debug, clap::Args)]
pub struct TrocarPoseArgs {
    /// Camera calibration YAML (as `detect`).
    #[arg(long)]
    pub camera: PathBuf,
    /// Trocar model YAML.
    #[arg(long, default_value = "config/trocar_model.yaml")]
    pub model: PathBuf,
    /// Folder of images, taken in name order.
    #[arg(long)]
    pub images: PathBuf,
    /// A prior port pose in the camera frame (x,y,z,qx,qy,qz,qw): its z axis picks between
    /// the two poses an ellipse admits.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub init_pose: Option<Vec<f64>>,
    /// One JSON object per image and line (else text).
    #[arg(long)]
    pub json: bool,
    /// The stereo pair's right camera (a rectified pair's right calibration); with
    /// --right-images, its image decides between the two poses and triangulates the port.
    #[arg(long, requires = "right_images")]
    pub right_camera: Option<PathBuf>,
    /// Folder of the right camera's images, paired with --images in name order (as many).
    #[arg(long, requires = "right_camera")]
    pub right_images: Option<PathBuf>,
    /// Mask the endoscope in view as the estimator node does, seen through the hand-eye of
    /// this file (`flange_t_camera` of a hand-eye result, or `camera.flange_t_camera` of a
    /// lbr_med_sim parameter file): the built-in arm's flange-to-tip length and the radius
    /// `markerless.endoscope_radius_m` of config/trocar_estimator.yaml.
    #[arg(long)]
    pub endoscope_mount: Option<PathBuf>,
}

/// The right camera of a stereo pair from its calibration YAML (a baseline of 1 mm to 1 m).
fn stereo_right_camera(path: &Path) -> Result<CameraModel, String> {
    let m = CameraModel::from_yaml_file(path).map_err(|e| format!("--right-camera {}: {e}", path.display()))?;
    m.check_stereo_right()
        .map_err(|e| format!("--right-camera {}: {e}", path.display()))?;
    Ok(m)
}

/// A pose from x,y,z,qx,qy,qz,qw.
pub fn parse_pose(v: &[f64], what: &str) -> Result<Isometry3<f64>, String> {
    if v.len() != 7 {
        return Err(format!(
            "{what} takes 7 comma-separated numbers x,y,z,qx,qy,qz,qw, got {}",
            v.len()
        ));
    }
    PoseYaml {
        translation: [v[0], v[1], v[2]],
        quaternion_xyzw: [v[3], v[4], v[5], v[6]],
    }
    .to_isometry()
    .map_err(|e| format!("{what}: {e}"))
}

/// The camera mount of a parameter file: `camera.flange_t_camera` (a lbr_med_sim parameter
/// file) or a hand-eye file in either format (the project's `flange_t_camera`, or
/// easy_handeye's, its effector frame carried to the flange through the built-in arm's URDF).
pub fn read_mount(path: &Path) -> Result<Isometry3<f64>, String> {
    let v: crate::config::Value = crate::config::from_yaml_file(path).map_err(|e| e.to_string())?;
    if let Some(m) = v.get("camera").and_then(|c| c.get("flange_t_camera")) {
        let p: PoseYaml =
            crate::config::from_yaml_value(&path.display().to_string(), m.clone()).map_err(|e| e.to_string())?;
        return p.to_isometry().map_err(|e| format!("{}: {e}", path.display()));
    }
    let resolve = |frame: &str| {
        let xml = crate::kinematics::lbr::urdf(LbrModel::Med7, &ToolParams::default()).map_err(|e| e.to_string())?;
        crate::kinematics::fixed_transform(&xml, crate::kinematics::FLANGE_LINK, frame).map_err(|e| e.to_string())
    };
    crate::vision::hand_eye::load_mount(path, &resolve)
        .map(|m| m.flange_t_camera)
        .map_err(|e| e.to_string())
}

/// The built-in arm's endoscope seen from the camera at `mount` (its tip `start`).
fn endoscope_seen_from(mount: &Isometry3<f64>) -> ToolCylinder {
    let tool = ToolParams::default();
    ToolCylinder::endoscope(mount, tool.length_m, 0.5 * tool.diameter_m)
}

fn scene_of(a: &RenderTrocarArgs, seed: u64) -> Result<Scene, String> {
    let mut s = Scene::random(seed, a.noise);
    s.show_trocar = !a.no_trocar;
    if let Some(mb) = &a.motion_blur {
        if mb.len() != 2 {
            return Err("--motion-blur takes length_px,angle_deg".into());
        }
        s.motion_blur_px = mb[0];
        s.motion_blur_angle = mb[1].to_radians();
    }
    if a.endoscope {
        s.tool = Some(endoscope_seen_from(&read_mount(&a.mount)?));
    }
    if let Some(t) = &a.tool {
        if t.len() != 7 {
            return Err("--tool takes x0,y0,z0,x1,y1,z1,radius".into());
        }
        s.tool = Some(ToolCylinder {
            start: [t[0], t[1], t[2]],
            end: [t[3], t[4], t[5]],
            radius: t[6],
        });
    }
    Ok(s)
}

/// The truth of one port pose: axis point and direction in the camera frame.
fn truth_json(p: &Isometry3<f64>) -> serde_json::Value {
    let y = PoseYaml::from_isometry(p);
    let dir = p.rotation * Vector3::z();
    serde_json::json!({
        "camera_t_port": {"translation": y.translation, "quaternion_xyzw": y.quaternion_xyzw},
        "axis_point": y.translation,
        "axis_direction": [dir.x, dir.y, dir.z],
    })
}

/// Run `render-trocar`.
pub fn run_render(a: &RenderTrocarArgs) -> super::CliResult {
    let camera = CameraModel::from_yaml_file(&a.camera)?;
    let model = TrocarModel::from_yaml_file(&a.model)?;
    let renderer = TrocarRenderer::new(&camera)?;
    if let Some(n) = a.sequence {
        if a.range.len() != 2 {
            return Err("--range takes far,near".into());
        }
        let mount = read_mount(&a.mount)?;
        let poses = docking_approach(&mount, a.range[0], a.range[1], n, a.seed)?;
        std::fs::create_dir_all(&a.out).map_err(|e| format!("{}: {e}", a.out.display()))?;
        let right = match &a.right_camera {
            Some(path) => {
                let m = stereo_right_camera(path)?;
                let dir = a.out.join("right");
                std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
                Some((TrocarRenderer::new(&m)?, m.stereo_right_t_left(), dir))
            }
            None => None,
        };
        let mut frames = vec![];
        for (k, p) in poses.iter().enumerate() {
            let seed = a.seed.wrapping_mul(1_000_003).wrapping_add(k as u64);
            let scene = scene_of(a, seed)?;
            let img = renderer.render(&model, p, &scene)?;
            let name = format!("frame_{k:04}.png");
            img.write(&a.out.join(&name))?;
            if let Some((r, right_t_left, dir)) = &right {
                let seen = Scene {
                    tool: scene.tool.map(|t| t.transformed(right_t_left)),
                    ..scene.clone()
                };
                r.render(&model, &(right_t_left * p), &seen)?.write(&dir.join(&name))?;
            }
            let mut t = truth_json(p);
            t["image"] = name.into();
            t["distance_m"] = p.translation.vector.norm().into();
            t["scene"] = serde_json::to_value(&scene)?;
            frames.push(t);
        }
        let truth = serde_json::json!({"camera": a.camera, "model": model_json(&model), "frames": frames});
        std::fs::write(a.out.join("truth.json"), serde_json::to_string_pretty(&truth)?)?;
        println!("wrote {} frames and truth.json to {}", poses.len(), a.out.display());
        return Ok(());
    }
    let pose = parse_pose(a.pose.as_deref().ok_or("--pose (or --sequence) is required")?, "--pose")?;
    let scene = scene_of(a, a.seed)?;
    let img = renderer.render(&model, &pose, &scene)?;
    img.write(&a.out)?;
    let mut t = truth_json(&pose);
    t["image"] = a.out.display().to_string().into();
    println!("{}", serde_json::to_string(&t)?);
    Ok(())
}

fn model_json(m: &TrocarModel) -> serde_json::Value {
    serde_json::to_value(m).unwrap_or_default()
}

/// Image files of a folder in name order.
fn image_files(dir: &Path) -> Result<Vec<PathBuf>, String> {
    let rd = std::fs::read_dir(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut v: Vec<PathBuf> = rd
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.extension().and_then(|x| x.to_str()).is_some_and(|x| {
                matches!(
                    x.to_ascii_lowercase().as_str(),
                    "png" | "pgm" | "ppm" | "jpg" | "jpeg" | "bmp" | "tif" | "tiff"
                )
            })
        })
        .collect();
    v.sort();
    if v.is_empty() {
        return Err(format!(
            "{}: no image files (png, pgm, ppm, jpg, bmp, tif)",
            dir.display()
        ));
    }
    Ok(v)
}

/// The right camera of `--right-camera` and the images of `--right-images`, as many as the
/// left images (`n`); `None` without them.
fn stereo_pair(a: &TrocarPoseArgs, n: usize) -> Result<Option<(CameraModel, Vec<PathBuf>)>, String> {
    let (Some(cam), Some(dir)) = (&a.right_camera, &a.right_images) else {
        return Ok(None);
    };
    let m = stereo_right_camera(cam)?;
    let r = image_files(dir)?;
    if r.len() != n {
        return Err(format!(
            "--right-images {} has {} images, --images {} has {n}: they pair in name order",
            dir.display(),
            r.len(),
            a.images.display(),
        ));
    }
    Ok(Some((m, r)))
}

/// The JSON object of one image's estimate.
fn pose_json(name: &str, ms: f64, e: &MarkerlessEstimate) -> serde_json::Value {
    serde_json::json!({
        "image": name, "found": true,
        "axis_point": [e.axis.point.x, e.axis.point.y, e.axis.point.z],
        "axis_direction": [e.axis.direction.x, e.axis.direction.y, e.axis.direction.z],
        "confidence": e.confidence, "ms": ms,
        "fit_rms_px": e.fit_rms_px, "edge_support": e.edge_support,
        "opening_support": e.opening_support, "ambiguity_margin": e.ambiguity_margin,
    })
}

/// One image's line of `trocar-pose`: the JSON object, or text.
fn print_pose_line(json: bool, name: &str, ms: f64, v: &serde_json::Value) -> super::CliResult {
    if json {
        println!("{}", serde_json::to_string(&v)?);
    } else if let Some(err) = v.get("error") {
        println!("{name}: error: {}", err.as_str().unwrap_or_default());
    } else if v["found"] == true {
        let p = &v["axis_point"];
        let d = &v["axis_direction"];
        println!(
            "{name}: port [m] {:+.4} {:+.4} {:+.4}  axis {:+.4} {:+.4} {:+.4}  confidence {:.2}  {ms:.1} ms",
            p[0].as_f64().unwrap_or(f64::NAN),
            p[1].as_f64().unwrap_or(f64::NAN),
            p[2].as_f64().unwrap_or(f64::NAN),
            d[0].as_f64().unwrap_or(f64::NAN),
            d[1].as_f64().unwrap_or(f64::NAN),
            d[2].as_f64().unwrap_or(f64::NAN),
            v["confidence"].as_f64().unwrap_or(0.0)
        );
    } else {
        println!("{name}: not found  {ms:.1} ms");
    }
    Ok(())
}

/// Run `trocar-pose`.
pub fn run_pose(a: &TrocarPoseArgs) -> super::CliResult {
    let camera = CameraModel::from_yaml_file(&a.camera)?;
    let model = TrocarModel::from_yaml_file(&a.model)?;
    let prior: Option<Unit<Vector3<f64>>> = match &a.init_pose {
        Some(v) => Some(Unit::new_normalize(
            parse_pose(v, "--init-pose")?.rotation * Vector3::z(),
        )),
        None => None,
    };
    let files = image_files(&a.images)?;
    let pair = stereo_pair(a, files.len())?;
    let occluder = match &a.endoscope_mount {
        Some(path) => MarkerlessParams::default().endoscope(
            &read_mount(path)?,
            LbrKinematics::flange_to_tip_m(LbrModel::Med7, "").map_err(|e| e.to_string())?,
        ),
        None => None,
    };
    let mut est =
        MarkerlessEstimator::for_cameras(&camera, pair.as_ref().map(|p| &p.0), &model)?.with_occluder(occluder)?;
    let right_files = pair.map(|p| p.1);
    let mut failures = 0usize;
    for (k, f) in files.iter().enumerate() {
        let name = f
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let t0 = std::time::Instant::now();
        let right = right_files.as_ref().map(|r| GreyImage::read(&r[k])).transpose();
        let result = right.and_then(|right| {
            let img = GreyImage::read(f)?;
            est.estimate_stereo(
                &img.view(),
                right.as_ref().map(GreyImage::view).as_ref(),
                prior.as_ref(),
            )
        });
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        let v = match result {
            Ok(Some(e)) => pose_json(&name, ms, &e),
            Ok(None) => serde_json::json!({"image": name, "found": false, "confidence": 0.0, "ms": ms}),
            Err(err) => {
                failures += 1;
                serde_json::json!({"image": name, "found": false, "error": err.to_string(), "ms": ms})
            }
        };
        print_pose_line(a.json, &name, ms, &v)?;
    }
    if failures > 0 {
        return Err(format!("{failures} of {} images could not be read or used", files.len()).into());
    }
    Ok(())
}
