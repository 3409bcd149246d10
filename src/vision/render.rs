//! The synthetic camera: a marker on a textured plane (inverse-homography sampler with 3x3
//! supersampling, in the C++ bridge; vpImageSimulator shifted edges by ~0.17 px), seen from a
//! given pose through given intrinsics and distortion, with optional blur and Gaussian noise.
//! ArUco markers are drawn by OpenCV (`cv::aruco::drawMarker`), AprilTags from the official
//! library's codes (libapriltag's `apriltag_to_image`, [`official_tag_image`]), each in its
//! family's frame ([`super::MarkerFrame`]), the frame the detector reports.

use nalgebra::Isometry3;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

use super::{rt_from_isometry, CameraModel, GreyImage, MarkerFamily, MarkerFrame, MarkerSpec, VisionError};
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

/// An official AprilTag as the official library draws it.
#[derive(Debug, Clone, PartialEq)]
pub struct OfficialTag {
    /// One pixel a cell, row 0 the top of the upright tag, the white border included.
    pub image: GreyImage,
    /// The black square's side, cells (the marker size of a [`MarkerSpec`]).
    pub width_at_border: u32,
    /// The family's number of ids.
    pub id_count: u32,
}

/// The official tag `id` of an AprilTag family: libapriltag's `apriltag_to_image()` on the
/// official family object (`tag36h11_create()`, ...). An ArUco family or an id out of the
/// family -> an error.
pub fn official_tag_image(family: &MarkerFamily, id: u32) -> Result<OfficialTag, VisionError> {
    if family.frame() != MarkerFrame::AprilTag {
        return Err(VisionError::InvalidInput(format!("{family} is not an AprilTag family")));
    }
    let id = i32::try_from(id).map_err(|_| VisionError::InvalidInput(format!("id {id} out of range")))?;
    let mut dims = [0i32; 3];
    let data = ffi::official_apriltag(family.name(), id, &mut dims)?;
    let side = u32::try_from(dims[0]).map_err(|_| VisionError::Backend("negative tag width".into()))?;
    Ok(OfficialTag {
        image: GreyImage {
            data,
            width: side,
            height: side,
        },
        width_at_border: dims[1].max(0) as u32,
        id_count: dims[2].max(0) as u32,
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

/// The pose of a marker in OpenCV's frame ([`MarkerFrame::OpenCv`], z out of the marker)
/// facing the camera: [`facing_pose_in`] for ArUco markers.
pub fn facing_pose(distance: f64, x: f64, y: f64, tilt_x: f64, tilt_y: f64, yaw: f64) -> Isometry3<f64> {
    facing_pose_in(MarkerFrame::OpenCv, distance, x, y, tilt_x, tilt_y, yaw)
}

/// A marker pose in the camera frame facing the camera, for a marker of `frame`: centre at
/// (`x`, `y`, `distance`) m, the marker upright in the image (OpenCV's frame turned 180°
/// about x, its z out of the marker towards the camera; the official AprilTag frame as the
/// camera's, its z into the tag), then tilted about the marker's x and y axes and turned
/// about its z axis (rad).
pub fn facing_pose_in(
    frame: MarkerFrame,
    distance: f64,
    x: f64,
    y: f64,
    tilt_x: f64,
    tilt_y: f64,
    yaw: f64,
) -> Isometry3<f64> {
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    let facing = match frame {
        MarkerFrame::OpenCv => UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        MarkerFrame::AprilTag => UnitQuaternion::identity(),
    };
    let r = facing
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), tilt_x)
        * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), tilt_y)
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
    Isometry3::from_parts(Translation3::new(x, y, distance), r)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn official_tags_come_from_the_official_library() {
        for (name, ids) in super::super::marker::APRILTAG_FAMILIES {
            let family: MarkerFamily = name.parse().unwrap();
            let last = official_tag_image(&family, ids - 1).unwrap();
            assert_eq!(last.id_count, *ids, "{name}");
            assert_eq!(
                last.image.width,
                last.width_at_border + 2,
                "{name}: one white cell around"
            );
            assert!(official_tag_image(&family, *ids).is_err(), "{name}: id past the family");
        }
        // A white ring, a black ring, the data inside (whether it decodes to its id is for the
        // official detector to say: tests/apriltag_official.rs).
        let tag = official_tag_image(&"tag36h11".parse().unwrap(), 0).unwrap();
        let px = |r: u32, c: u32| tag.image.data[(r * tag.image.width + c) as usize];
        assert_eq!((tag.image.width, tag.width_at_border), (10, 8));
        for k in 0..10 {
            assert_eq!((px(0, k), px(k, 0), px(9, k), px(k, 9)), (255, 255, 255, 255));
        }
        for k in 1..9 {
            assert_eq!((px(1, k), px(k, 1), px(8, k), px(k, 8)), (0, 0, 0, 0));
        }
        let other = official_tag_image(&"tag36h11".parse().unwrap(), 1).unwrap();
        assert_ne!(tag.image.data, other.image.data);
        assert!(official_tag_image(&"DICT_4X4_50".parse().unwrap(), 0).is_err());
    }

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
