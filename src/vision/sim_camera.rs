//! The simulated camera's parameters (`camera:` in `config/lbr_med_sim.yaml`) and its
//! markerless scene ([`TrocarCamera`]): the trocar without a marker, rendered as the
//! `lbr_med_sim` node publishes it and as the trials' camera pose source sees it, by one
//! set-up (lighting, materials and wall tilt drawn once from a seed; the region-of-interest
//! render with `wall_step_px`; the pixel noise per frame).

use nalgebra::Isometry3;

use super::estimator::PoseYaml;
use super::markerless::{Scene, TrocarModel, TrocarRenderer};
use super::render::add_fast_gaussian_noise;
use super::{CameraModel, MarkerSpec, VisionError};

/// The simulated camera (`camera:` in `config/lbr_med_sim.yaml`): a marker on the trocar
/// rendered from the true arm pose through the true camera mount, published as the real
/// camera's topics with the capture time as stamp.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(remote = "Self", deny_unknown_fields)]
pub struct SimCameraParams {
    /// ROS camera calibration YAML of the simulated camera (required with `camera_enabled`).
    pub calibration_file: String,
    /// Optical frame of the images.
    pub frame: String,
    /// Image encoding: mono8, rgb8, bgr8, rgba8 or bgra8 (the ZED publishes bgra8).
    pub encoding: String,
    /// Gaussian pixel noise, grey levels.
    pub noise_sigma: f64,
    /// Optical blur, px.
    pub blur_sigma_px: f64,
    /// Side of the textured plate around the marker, in marker sizes (>= 1.25; a smaller
    /// plate renders faster).
    pub plane_scale: f64,
    /// The true camera pose in the flange frame (the estimator's hand-eye may differ).
    pub flange_t_camera: PoseYaml,
    /// The marker on the trocar.
    pub marker: MarkerSpec,
    /// The true trocar port pose in the marker frame.
    pub marker_t_trocar: PoseYaml,
    /// Render the marker (on its textured plate); false: render the trocar without a marker
    /// (the markerless renderer: shaded head and cannula, the dark opening, the abdominal
    /// wall, lighting drawn from `seed` per run).
    pub show_marker: bool,
    /// The trocar model YAML the markerless image shows ('' = the shipped
    /// `config/trocar_model.yaml`, built in).
    pub trocar_model_file: String,
    /// Without the marker: the wall's radiance is traced every this many pixels and
    /// interpolated (1 = every pixel; the trocar and every edge are always per pixel).
    pub wall_step_px: usize,
}

crate::shipped_defaults!(
    SimCameraParams,
    crate::config::LBR_MED_SIM,
    ["camera"],
    deserialize_only
);

/// A camera set-up that failed: the key of `camera:` at fault and why.
#[derive(Debug)]
pub struct CameraSetupError {
    /// The key under `camera:` (e.g. `trocar_model_file`).
    pub key: &'static str,
    /// What is wrong.
    pub error: VisionError,
}

impl std::fmt::Display for CameraSetupError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "camera.{}: {}", self.key, self.error)
    }
}

impl std::error::Error for CameraSetupError {}

/// The frame a camera delivers when the render fails (out of view, behind the camera): mid
/// grey, as a real camera still delivers a frame.
pub fn blank_frame(model: &CameraModel) -> Vec<u8> {
    vec![128; model.width as usize * model.height as usize]
}

/// The trocar without a marker as the simulated camera renders it: the renderer of one
/// camera, the trocar model and the scene drawn once from a seed.
pub struct TrocarCamera {
    renderer: TrocarRenderer,
    model: TrocarModel,
    scene: Scene,
}

impl TrocarCamera {
    /// The scene of the camera parameters `c` for a camera `model`: the trocar of
    /// `c.trocar_model_file`, lighting, materials and the wall drawn once from `seed`, the
    /// blur of `c.blur_sigma_px`, the wall traced every `c.wall_step_px` (the pixel noise is
    /// added per frame, [`TrocarCamera::add_noise`]).
    pub fn new(c: &SimCameraParams, seed: u64, model: &CameraModel) -> Result<Self, CameraSetupError> {
        let trocar = if c.trocar_model_file.is_empty() {
            TrocarModel::shipped()
        } else {
            TrocarModel::from_yaml_file(std::path::Path::new(&c.trocar_model_file)).map_err(|error| {
                CameraSetupError {
                    key: "trocar_model_file",
                    error,
                }
            })?
        };
        let mut scene = Scene::random(seed, 0.0);
        scene.blur_sigma = c.blur_sigma_px;
        let renderer = TrocarRenderer::new(model).map_err(|error| CameraSetupError {
            key: "calibration_file",
            error,
        })?;
        Ok(Self {
            renderer: renderer.with_wall_step(c.wall_step_px),
            model: trocar,
            scene,
        })
    }

    /// The camera it renders for.
    pub fn camera(&self) -> &CameraModel {
        self.renderer.camera()
    }

    /// The grey image of the port at `camera_t_trocar`, without noise.
    pub fn render(&self, camera_t_trocar: &Isometry3<f64>) -> Result<Vec<u8>, VisionError> {
        self.renderer
            .render(&self.model, camera_t_trocar, &self.scene)
            .map(|g| g.data)
    }

    /// Add the camera's pixel noise of `sigma` grey levels to frame number `seq`.
    pub fn add_noise(grey: &mut [u8], sigma: f64, seq: u64) {
        if sigma > 0.0 {
            add_fast_gaussian_noise(grey, sigma, seq);
        }
    }

    /// One frame of the port at `camera_t_trocar`: the render (a blank frame when it fails)
    /// with the pixel noise of `sigma` drawn from `noise_seed`.
    pub fn frame(&self, camera_t_trocar: &Isometry3<f64>, sigma: f64, noise_seed: u64) -> Vec<u8> {
        let mut grey = self
            .render(camera_t_trocar)
            .unwrap_or_else(|_| blank_frame(self.camera()));
        Self::add_noise(&mut grey, sigma, noise_seed);
        grey
    }
}
