//! Vision suite: render synthetic 1280x720 frames over a grid of poses (distance, tilt,
//! marker size, focal length), detect + estimate the pose, and report latency and the
//! accuracy against the true pose (median/max translation and rotation errors in `extra`).

use rand::{RngExt, SeedableRng};

use super::{time_each, LatencyStats, SuiteReport};
use crate::stats::quantile_sorted;
use crate::vision::{
    facing_pose, facing_pose_in, pose_distance, render_marker_image, CameraModel, GreyImage, MarkerDetector,
    MarkerFamily, MarkerSpec, RenderOptions, VisionError,
};
use nalgebra::Isometry3;

/// One synthetic frame with its truth.
#[derive(Debug, Clone)]
pub struct SyntheticFrame {
    /// The camera.
    pub camera: CameraModel,
    /// The marker.
    pub spec: MarkerSpec,
    /// True marker pose in the camera.
    pub truth: Isometry3<f64>,
    /// The image.
    pub image: GreyImage,
}

/// Sweep configuration.
#[derive(Debug, Clone)]
pub struct SweepConfig {
    /// Family.
    pub family: MarkerFamily,
    /// Number of random poses.
    pub frames: usize,
    /// Pixel noise sigma, grey levels.
    pub noise_sigma: f64,
    /// Blur sigma, px.
    pub blur_sigma: f64,
    /// Seed.
    pub seed: u64,
}

/// Accuracy of a sweep.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SweepResult {
    /// Frames rendered.
    pub frames: usize,
    /// Frames where the marker was found.
    pub detected: usize,
    /// Translation errors, m, one per detected frame.
    pub translation_errors_m: Vec<f64>,
    /// Rotation errors, rad, one per detected frame.
    pub rotation_errors_rad: Vec<f64>,
}

impl SweepResult {
    /// Median and max of the translation errors, m.
    pub fn translation_median_max(&self) -> (f64, f64) {
        median_max(&self.translation_errors_m)
    }
    /// Median and max of the rotation errors, rad.
    pub fn rotation_median_max(&self) -> (f64, f64) {
        median_max(&self.rotation_errors_rad)
    }
}

fn median_max(v: &[f64]) -> (f64, f64) {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    (quantile_sorted(&s, 0.5), quantile_sorted(&s, 1.0))
}

/// Random frames within the target envelope: 1280x720, fx 700–1000 px, marker 4–8 cm,
/// 0.2–0.8 m away, tilts up to 45°, the marker fully in view.
pub fn synthetic_frames(cfg: &SweepConfig) -> Result<Vec<SyntheticFrame>, VisionError> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(cfg.seed);
    let mut out = Vec::with_capacity(cfg.frames);
    for k in 0..cfg.frames {
        let f = rng.random_range(700.0..1000.0);
        let camera = CameraModel::pinhole(1280, 720, f, f, 640.0 + rng.random_range(-8.0..8.0), 360.0)?;
        let size = rng.random_range(0.04..0.08);
        let d = rng.random_range(0.2..0.8);
        // Keep the whole plane (3x the marker) in view: bound the lateral offset.
        let half_w = (0.5 * 720.0 / f) * d - 1.6 * size;
        let off = half_w.max(0.0) * 0.8;
        let x = rng.random_range(-1.0..1.0) * off;
        let y = rng.random_range(-1.0..1.0) * off;
        let tilt = rng.random_range(0.0..45f64.to_radians());
        let dir = rng.random_range(0.0..std::f64::consts::TAU);
        let yaw = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let truth = facing_pose_in(cfg.family.frame(), d, x, y, tilt * dir.cos(), tilt * dir.sin(), yaw);
        let id = rng.random_range(0..cfg.family.id_count().clamp(1, 50));
        let spec = MarkerSpec {
            family: cfg.family.clone(),
            id: Some(id),
            size_m: size,
        };
        let opts = RenderOptions {
            noise_sigma: cfg.noise_sigma,
            blur_sigma: cfg.blur_sigma,
            seed: cfg.seed.wrapping_add(k as u64),
            ..Default::default()
        };
        let image = render_marker_image(&spec, &camera, &truth, &opts)?;
        out.push(SyntheticFrame {
            camera,
            spec,
            truth,
            image,
        });
    }
    Ok(out)
}

/// Detect the marker in each frame and compare with the truth.
pub fn evaluate(frames: &[SyntheticFrame]) -> Result<SweepResult, VisionError> {
    let mut r = SweepResult {
        frames: frames.len(),
        detected: 0,
        translation_errors_m: vec![],
        rotation_errors_rad: vec![],
    };
    for fr in frames {
        let mut det = MarkerDetector::new(fr.spec.clone(), &fr.camera)?;
        if let Some(m) = det.detect(&fr.image.view())?.first() {
            let (dt, dr) = pose_distance(&m.pose_camera_marker, &fr.truth);
            r.detected += 1;
            r.translation_errors_m.push(dt);
            r.rotation_errors_rad.push(dr);
        }
    }
    Ok(r)
}

/// Run the suite: `n` timed detections per case (frames cycle), plus the accuracy sweep.
pub fn run(n: usize) -> Result<Vec<SuiteReport>, VisionError> {
    let frames_n = 60;
    let mut out = vec![];
    let cases: [(&str, &str, f64); 4] = [
        ("detect_pose_aruco_4x4_1280x720", "DICT_4X4_50", 0.0),
        ("detect_pose_aruco_4x4_noise3_1280x720", "DICT_4X4_50", 3.0),
        ("detect_pose_tag36h11_1280x720", "tag36h11", 0.0),
        ("detect_pose_tag36h11_noise3_1280x720", "tag36h11", 3.0),
    ];
    for (name, fam, noise) in cases {
        let cfg = SweepConfig {
            family: fam.parse()?,
            frames: frames_n,
            noise_sigma: noise,
            blur_sigma: 0.0,
            seed: 11,
        };
        let frames = synthetic_frames(&cfg)?;
        let acc = evaluate(&frames)?;
        // Timing: one detector per frame built beforehand; cycle frames.
        let mut dets: Vec<MarkerDetector> = frames
            .iter()
            .map(|f| MarkerDetector::new(f.spec.clone(), &f.camera))
            .collect::<Result<_, _>>()?;
        let idx: Vec<usize> = (0..n.clamp(1, 2000)).map(|i| i % frames.len()).collect();
        let t = time_each(&idx, 10, |&i| dets[i].detect(&frames[i].image.view()).map(|v| v.len()));
        let Some(latency) = LatencyStats::from_samples(&t) else {
            continue;
        };
        let (tm, tx) = acc.translation_median_max();
        let (rm, rx) = acc.rotation_median_max();
        let mut extra = serde_json::Map::new();
        extra.insert("frames".into(), acc.frames.into());
        extra.insert("detected".into(), acc.detected.into());
        extra.insert("noise_sigma".into(), noise.into());
        extra.insert("translation_error_median_mm".into(), (tm * 1e3).into());
        extra.insert("translation_error_max_mm".into(), (tx * 1e3).into());
        extra.insert("rotation_error_median_deg".into(), rm.to_degrees().into());
        extra.insert("rotation_error_max_deg".into(), rx.to_degrees().into());
        out.push(SuiteReport {
            name: name.into(),
            latency,
            extra,
        });
    }
    // The synthetic camera itself (the simulated ZED: distortion on, noise on).
    let zed = CameraModel::from_yaml_str(ZEDM_YAML)?;
    let spec = MarkerSpec {
        family: "DICT_4X4_50".parse()?,
        id: Some(0),
        size_m: 0.05,
    };
    let poses: Vec<Isometry3<f64>> = (0..n.clamp(1, 200))
        .map(|i| facing_pose(0.3 + 0.002 * (i % 100) as f64, 0.01, 0.0, 0.3, 0.2, 0.1))
        .collect();
    let opts = RenderOptions {
        noise_sigma: 2.0,
        ..Default::default()
    };
    let t = time_each(&poses, 3, |p| {
        render_marker_image(&spec, &zed, p, &opts).map(|i| i.data.len())
    });
    if let Some(latency) = LatencyStats::from_samples(&t) {
        out.push(SuiteReport {
            name: "render_marker_zedm_1280x720".into(),
            latency,
            extra: Default::default(),
        });
    }
    out.extend(super::markerless::run(n)?);
    Ok(out)
}

/// The shipped ZED mini calibration (distortion included).
const ZEDM_YAML: &str = include_str!("../../config/camera_zedm.yaml");
