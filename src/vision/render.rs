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
        spec.size_m,
        spec.size_m * opts.plane_scale,
        &rt,
        &camera.intrinsics(),
        &camera.distortion,
        camera.is_equidistant(),
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

/// Gaussian pixel noise of `sigma` grey levels at a fraction of [`add_gaussian_noise`]'s
/// cost: 4096 normal samples (rounded to grey levels) are drawn from `seed`, and each pixel
/// adds one of them, picked by a wyrand stream (five 12-bit picks per 64-bit draw). The
/// pixels' noise is independent and normal to within the 4096 samples' spread, drawn anew
/// for every `seed`.
pub fn add_fast_gaussian_noise(data: &mut [u8], sigma: f64, seed: u64) {
    const BITS: u32 = 12;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x6a09_e667_f3bc_c909);
    let Ok(n) = Normal::new(0.0, sigma) else { return };
    let table: Vec<i16> = (0..1usize << BITS)
        .map(|_| n.sample(&mut rng).round().clamp(-255.0, 255.0) as i16)
        .collect();
    let mut state = seed ^ 0x243f_6a88_85a3_08d3;
    let mut wyrand = || {
        state = state.wrapping_add(0xa076_1d64_78bd_642f);
        let t = u128::from(state) * u128::from(state ^ 0xe703_7ed1_a0b4_28db);
        ((t >> 64) ^ t) as u64
    };
    let mask = (1u64 << BITS) - 1;
    for chunk in data.chunks_mut(5) {
        let mut r = wyrand();
        for p in chunk {
            let v = i16::from(*p) + table[(r & mask) as usize];
            *p = v.clamp(0, 255) as u8;
            r >>= BITS;
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The noise added to a flat grey image, in grey levels.
    struct NoiseStats {
        mean: f64,
        std_dev: f64,
        /// The correlation of horizontal neighbours.
        neighbour_correlation: f64,
        image: Vec<u8>,
    }

    fn noise_stats(noise: fn(&mut [u8], f64, u64), sigma: f64, seed: u64) -> NoiseStats {
        let mut img = vec![128u8; 640 * 480];
        noise(&mut img, sigma, seed);
        let d: Vec<f64> = img.iter().map(|v| f64::from(*v) - 128.0).collect();
        let n = d.len() as f64;
        let mean = d.iter().sum::<f64>() / n;
        let var = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
        let cov = d.windows(2).map(|w| (w[0] - mean) * (w[1] - mean)).sum::<f64>() / (n - 1.0);
        NoiseStats {
            mean,
            std_dev: var.sqrt(),
            neighbour_correlation: cov / var,
            image: img,
        }
    }

    #[test]
    fn the_fast_noise_has_the_gaussian_noise_s_spread_and_is_white() {
        for sigma in [1.0, 2.0, 4.0] {
            let gaussian = noise_stats(add_gaussian_noise, sigma, 5);
            let (m0, s0) = (gaussian.mean, gaussian.std_dev);
            let fast = noise_stats(add_fast_gaussian_noise, sigma, 5);
            let (m, s, corr) = (fast.mean, fast.std_dev, fast.neighbour_correlation);
            eprintln!("sigma {sigma}: gaussian {m0:.3} +- {s0:.3}, fast {m:.3} +- {s:.3}, corr {corr:.4}");
            // Rounding to grey levels adds 1/12 grey level^2 to both.
            assert!((s - s0).abs() < 0.06 * sigma, "fast {s} against {s0}");
            assert!(m.abs() < 0.08 * sigma, "mean {m}");
            assert!(corr.abs() < 0.01, "neighbours correlated: {corr}");
            let (a, b) = (fast.image, noise_stats(add_fast_gaussian_noise, sigma, 6).image);
            let same = a.iter().zip(&b).filter(|(x, y)| x == y).count() as f64 / a.len() as f64;
            // Two independent draws agree as often as two grey levels of this spread do.
            assert!(same < 0.5 / sigma, "frames repeat: {same:.2} of pixels equal");
        }
    }
}
