//! The synthetic camera: a marker on a textured plane (inverse-homography sampler with 3x3
//! supersampling, in the C++ bridge; vpImageSimulator shifted edges by ~0.17 px), seen from a
//! given pose through given intrinsics and distortion, with optional blur and Gaussian noise.

use nalgebra::Isometry3;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

use super::{rt_from_isometry, CameraModel, GreyImage, MarkerSpec, VisionError};
use crate::ffi::vision::ffi;
use crate::validate;

/// Rendering options.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RenderOptions {
    /// Side of the textured plane around the marker, as a multiple of the marker size (>= 1.25).
    pub plane_scale: f64,
    /// Gaussian blur sigma, px (0 = none).
    pub blur_sigma: f64,
    /// Gaussian pixel noise sigma, grey levels (0 = none).
    pub noise_sigma: f64,
    /// Seed of the noise and of the plane texture.
    pub seed: u64,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            plane_scale: 3.0,
            blur_sigma: 0.0,
            noise_sigma: 0.0,
            seed: 1,
        }
    }
}

/// Render `spec` (its id, or 0 when none is set) at `camera_t_marker` (marker pose in the
/// camera optical frame) into a grey image of the camera's size.
pub fn render_marker_image(
    spec: &MarkerSpec,
    camera: &CameraModel,
    camera_t_marker: &Isometry3<f64>,
    opts: &RenderOptions,
) -> Result<GreyImage, VisionError> {
    spec.validate()?;
    camera.validate()?;
    validate::in_range("plane_scale", opts.plane_scale, 1.25, 100.0)?;
    validate::in_range("noise_sigma", opts.noise_sigma, 0.0, 100.0)?;
    validate::in_range("blur_sigma", opts.blur_sigma, 0.0, 50.0)?;
    let rt = rt_from_isometry(camera_t_marker);
    if rt.iter().any(|v| !v.is_finite()) {
        return Err(VisionError::InvalidInput("pose must be finite".into()));
    }
    if rt[11] <= 1e-3 {
        return Err(VisionError::InvalidInput(
            "the marker must be in front of the camera".into(),
        ));
    }
    let mut data = ffi::render_marker(
        spec.family.name(),
        spec.id.unwrap_or(0) as i32,
        spec.size,
        spec.size * opts.plane_scale,
        &rt,
        &camera.intrinsics(),
        &camera.distortion,
        camera.width as i32,
        camera.height as i32,
        opts.blur_sigma,
        (opts.seed & 0xffff_ffff) as u32,
    )?;
    if opts.noise_sigma > 0.0 {
        add_gaussian_noise(&mut data, opts.noise_sigma, opts.seed);
    }
    Ok(GreyImage {
        data,
        width: camera.width,
        height: camera.height,
    })
}

/// Add zero-mean Gaussian noise of `sigma` grey levels, clamped to 0..=255.
pub fn add_gaussian_noise(data: &mut [u8], sigma: f64, seed: u64) {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x9e37_79b9_7f4a_7c15);
    let Ok(n) = Normal::new(0.0, sigma) else { return };
    for p in data.iter_mut() {
        let v = f64::from(*p) + n.sample(&mut rng);
        *p = v.round().clamp(0.0, 255.0) as u8;
    }
}

/// A marker pose in the camera frame facing the camera: centre at (`x`, `y`, `distance`) m,
/// then tilted about the marker's x and y axes and turned about its z axis (rad).
pub fn facing_pose(distance: f64, x: f64, y: f64, tilt_x: f64, tilt_y: f64, yaw: f64) -> Isometry3<f64> {
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    let facing = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    let r = facing
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), tilt_x)
        * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), tilt_y)
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
    Isometry3::from_parts(Translation3::new(x, y, distance), r)
}
