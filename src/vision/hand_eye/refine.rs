//! Non-linear refinement of a hand-eye calibration over all samples: the camera pose in the
//! flange (eMc) and the marker pose in the base (fixed), by Levenberg–Marquardt on the
//! marker's corners reprojected into each image (when the corners and the camera are known),
//! else on the marker pose in the camera. Optionally with a free marker scale, the ratio of
//! the true marker size to the configured one (the set-up fault "marker size wrong").

use nalgebra::{DMatrix, DVector, Isometry3, Point3, Vector3};

use super::super::{CameraModel, VisionError};

/// One calibration sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// Flange pose in the base frame (FK).
    pub base_t_flange: Isometry3<f64>,
    /// Marker pose in the camera optical frame (detection).
    pub camera_t_marker: Isometry3<f64>,
    /// Detected corners (in the family's order, [`crate::vision::MarkerFrame`]), px, when known.
    pub corners: Option<[[f64; 2]; 4]>,
}

/// How a sample's marker is observed: the camera (for corners) and the marker's side.
#[derive(Debug, Clone, PartialEq)]
pub struct ObservationModel {
    /// The camera the corners were detected in; `None`: poses only.
    pub camera: Option<CameraModel>,
    /// Side of the marker's black square, m.
    pub marker_size: f64,
}

/// Noise scales that weight the residuals.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineOptions {
    /// Corner noise, px.
    pub sigma_px: f64,
    /// Marker position noise in the camera (pose residuals), m.
    pub sigma_m: f64,
    /// Marker rotation noise in the camera (pose residuals), rad.
    pub sigma_rad: f64,
    /// Estimate the marker scale too.
    pub free_scale: bool,
    /// Iteration limit.
    pub max_iterations: usize,
}

impl Default for RefineOptions {
    fn default() -> Self {
        Self {
            sigma_px: 0.5,
            sigma_m: 0.001,
            sigma_rad: 0.5_f64.to_radians(),
            free_scale: false,
            max_iterations: 100,
        }
    }
}

/// The refined calibration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refined {
    /// Camera pose in the flange (eMc).
    pub flange_t_camera: Isometry3<f64>,
    /// Marker pose in the base.
    pub base_t_marker: Isometry3<f64>,
    /// True marker size over the configured one (1 unless `free_scale`).
    pub scale: f64,
    /// RMS of the weighted residuals (about 1 when the noise scales are right).
    pub rms: f64,
    /// Corner reprojection RMS, px, when every sample had corners.
    pub reprojection_rms_px: Option<f64>,
}

/// The marker's corners in its frame, in the order a detection reports them: (-s, s), (s, s),
/// (s, -s), (-s, -s) for half side s (ArUco TL, TR, BR, BL with y up; AprilTag left-bottom,
/// right-bottom, right-top, left-top with y down: [`crate::vision::MarkerFrame`]).
pub fn marker_corners(size: f64) -> [Point3<f64>; 4] {
    let h = size / 2.0;
    [
        Point3::new(-h, h, 0.0),
        Point3::new(h, h, 0.0),
        Point3::new(h, -h, 0.0),
        Point3::new(-h, -h, 0.0),
    ]
}

/// The marker pose in the camera that a calibration predicts for a flange pose.
pub fn predicted_camera_t_marker(
    base_t_flange: &Isometry3<f64>,
    flange_t_camera: &Isometry3<f64>,
    base_t_marker: &Isometry3<f64>,
) -> Isometry3<f64> {
    (base_t_flange * flange_t_camera).inverse() * base_t_marker
}

/// Residuals of every sample for a calibration (weighted by `o`), appended to `out`.
fn residuals_into(
    samples: &[Sample],
    model: &ObservationModel,
    o: &RefineOptions,
    emc: &Isometry3<f64>,
    bm: &Isometry3<f64>,
    scale: f64,
    out: &mut Vec<f64>,
) {
    let corners = marker_corners(model.marker_size * scale);
    for s in samples {
        let ctm = predicted_camera_t_marker(&s.base_t_flange, emc, bm);
        match (&model.camera, &s.corners) {
            (Some(cam), Some(measured)) => {
                for (c, m) in corners.iter().zip(measured) {
                    // A corner behind the camera: a large, smooth penalty instead of a pixel.
                    let p = cam.project(&(ctm * c).coords).unwrap_or([1e4, 1e4]);
                    out.push((p[0] - m[0]) / o.sigma_px);
                    out.push((p[1] - m[1]) / o.sigma_px);
                }
            }
            _ => {
                let dt = (ctm.translation.vector - s.camera_t_marker.translation.vector * scale) / o.sigma_m;
                let dr = (s.camera_t_marker.rotation.inverse() * ctm.rotation).scaled_axis() / o.sigma_rad;
                out.extend(dt.iter().chain(dr.iter()));
            }
        }
    }
}

/// An isometry moved by a small twist (translation, rotation vector) on its right.
fn retract(p: &Isometry3<f64>, d: &[f64]) -> Isometry3<f64> {
    p * Isometry3::new(Vector3::new(d[0], d[1], d[2]), Vector3::new(d[3], d[4], d[5]))
}

/// Refine `flange_t_camera` and `base_t_marker` from initial guesses over all samples.
pub fn refine(
    samples: &[Sample],
    model: &ObservationModel,
    flange_t_camera: &Isometry3<f64>,
    base_t_marker: &Isometry3<f64>,
    o: &RefineOptions,
) -> Result<Refined, VisionError> {
    if samples.len() < 3 {
        return Err(VisionError::InvalidInput("at least 3 samples are needed".into()));
    }
    if !(model.marker_size.is_finite() && model.marker_size > 0.0) {
        return Err(VisionError::InvalidInput("the marker size must be positive".into()));
    }
    let n = if o.free_scale { 13 } else { 12 };
    let eval = |x: &[f64], out: &mut Vec<f64>| {
        out.clear();
        let scale = if o.free_scale { x[12].exp() } else { 1.0 };
        residuals_into(
            samples,
            model,
            o,
            &retract(flange_t_camera, &x[..6]),
            &retract(base_t_marker, &x[6..12]),
            scale,
            out,
        );
    };
    let LeastSquares {
        x,
        cost: c,
        residuals: m,
    } = levenberg_marquardt(eval, n, o.max_iterations);
    if !c.is_finite() {
        return Err(VisionError::InvalidInput("the refinement diverged".into()));
    }
    let scale = if o.free_scale { x[12].exp() } else { 1.0 };
    let emc = retract(flange_t_camera, &x[..6]);
    let bm = retract(base_t_marker, &x[6..12]);
    let all_corners = model.camera.is_some() && samples.iter().all(|s| s.corners.is_some());
    Ok(Refined {
        flange_t_camera: emc,
        base_t_marker: bm,
        scale,
        rms: (c / m as f64).sqrt(),
        reprojection_rms_px: all_corners.then(|| (c / m as f64).sqrt() * o.sigma_px),
    })
}

/// A least-squares solution.
struct LeastSquares {
    /// The unknowns.
    x: Vec<f64>,
    /// The sum of the squared residuals at `x`.
    cost: f64,
    /// The number of residuals.
    residuals: usize,
}

/// Levenberg–Marquardt on `n` unknowns from zero: `eval(x, out)` writes the residuals.
fn levenberg_marquardt(eval: impl Fn(&[f64], &mut Vec<f64>), n: usize, max_iterations: usize) -> LeastSquares {
    let cost = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let mut x = vec![0.0; n];
    let mut r = Vec::new();
    eval(&x, &mut r);
    let m = r.len();
    let mut c = cost(&r);
    let mut lambda = 1e-3;
    let (mut rp, mut rm) = (Vec::with_capacity(m), Vec::with_capacity(m));
    for _ in 0..max_iterations {
        // Central differences: 12-13 unknowns, a few hundred residuals.
        let mut jac = DMatrix::zeros(m, n);
        for k in 0..n {
            let h = 1e-6;
            let mut xp = x.clone();
            xp[k] += h;
            eval(&xp, &mut rp);
            xp[k] -= 2.0 * h;
            eval(&xp, &mut rm);
            for i in 0..m {
                jac[(i, k)] = (rp[i] - rm[i]) / (2.0 * h);
            }
        }
        let jtj = jac.transpose() * &jac;
        let g = jac.transpose() * DVector::from_column_slice(&r);
        let mut improved = false;
        while lambda < 1e10 {
            let mut a = jtj.clone();
            for k in 0..n {
                a[(k, k)] += lambda * jtj[(k, k)].max(1e-9);
            }
            let Some(step) = a.cholesky().map(|ch| ch.solve(&(-&g))) else {
                lambda *= 10.0;
                continue;
            };
            let xn: Vec<f64> = x.iter().zip(step.iter()).map(|(a, b)| a + b).collect();
            eval(&xn, &mut rp);
            let cn = cost(&rp);
            if cn.is_finite() && cn < c {
                improved = step.norm() > 1e-12 && (c - cn) > 1e-14 * c.max(1e-30);
                x = xn;
                std::mem::swap(&mut r, &mut rp);
                c = cn;
                lambda = (lambda / 10.0).max(1e-12);
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    LeastSquares {
        x,
        cost: c,
        residuals: m,
    }
}
