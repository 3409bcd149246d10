//! The simulated camera's parameters (`camera:` in `config/lbr_med_sim.yaml`) and its
//! markerless scene ([`TrocarCamera`]): the trocar without a marker, rendered as the
//! `lbr_med_sim` node publishes it and as the trials' camera pose source sees it, by one
//! set-up (lighting, materials and wall tilt drawn once from a seed; the region-of-interest
//! render with `wall_step_px`; the pixel noise per frame).

use nalgebra::Isometry3;

use crate::kinematics::lbr::ToolParams;

use super::estimator::PoseYaml;
use super::markerless::render::ToolCylinder;
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
    /// With the marker: once the camera comes this close to the port, m, the marker is gone
    /// for the rest of the run (covered, or knocked off) and the trocar is rendered without
    /// it, as with `show_marker: false` (0 = never): what the estimator's `fused` method
    /// falls back on.
    pub marker_hidden_within_m: f64,
    /// The trocar model YAML the markerless image shows ('' = the shipped
    /// `config/trocar_model.yaml`, built in).
    pub trocar_model_file: String,
    /// Without the marker: the wall's radiance is traced every this many pixels and
    /// interpolated (1 = every pixel; the trocar and every edge are always per pixel).
    pub wall_step_px: usize,
    /// Without the marker: the ROS camera calibration YAML of the stereo pair's right camera
    /// (a rectified pair: its projection's `Tx` gives the baseline); '' = a mono camera.
    pub right_calibration_file: String,
    /// With a right camera: its image is rendered with every this many left frames (1 =
    /// every frame, as a real stereo camera delivers it; more keeps the render time within
    /// the frame period).
    pub right_every: u64,
    /// Without the marker: draw the endoscope's own shaft (the simulated arm's tool,
    /// [`ToolParams`]: 0.25 m from the flange, 5 mm across) where the true mount puts it in
    /// each image, as the real camera beside it sees it.
    pub show_endoscope: bool,
}

impl SimCameraParams {
    /// The trocar the camera sees: `trocar_model_file`, or the shipped
    /// `config/trocar_model.yaml` when it is ''.
    pub fn trocar_model(&self) -> Result<TrocarModel, CameraSetupError> {
        if self.trocar_model_file.is_empty() {
            return Ok(TrocarModel::shipped());
        }
        TrocarModel::from_yaml_file(std::path::Path::new(&self.trocar_model_file)).map_err(|error| CameraSetupError {
            key: "trocar_model_file",
            error,
        })
    }

    /// The right camera of `right_calibration_file` (`None`: '', a mono camera). It must be
    /// the right camera of a rectified pair: a baseline of 1 mm to 1 m.
    pub fn right_camera(&self) -> Result<Option<CameraModel>, CameraSetupError> {
        if self.right_calibration_file.is_empty() {
            return Ok(None);
        }
        let err = |error| CameraSetupError {
            key: "right_calibration_file",
            error,
        };
        let m = CameraModel::from_yaml_file(std::path::Path::new(&self.right_calibration_file)).map_err(err)?;
        m.check_stereo_right().map_err(|e| match e {
            VisionError::InvalidInput(why) => err(VisionError::InvalidInput(format!(
                "{}: {why}",
                self.right_calibration_file
            ))),
            other => err(other),
        })?;
        if self.right_every == 0 {
            return Err(CameraSetupError {
                key: "right_every",
                error: VisionError::InvalidInput("right_every must be at least 1".into()),
            });
        }
        Ok(Some(m))
    }

    /// The camera-to-port distance within which the marker is hidden for good
    /// (`marker_hidden_within_m`; `None`: never, 0 or no marker shown).
    pub fn marker_hidden_within(&self) -> Result<Option<f64>, CameraSetupError> {
        let d = self.marker_hidden_within_m;
        if !(d.is_finite() && d >= 0.0) {
            return Err(CameraSetupError {
                key: "marker_hidden_within_m",
                error: VisionError::InvalidInput(format!("must be finite and >= 0 (0 = never), got {d}")),
            });
        }
        Ok((self.show_marker && d > 0.0).then_some(d))
    }

    /// Whether frame number `seq` (from 1) of a stereo camera comes with a right image
    /// ([`right_due`] of `right_every`).
    pub fn right_due(&self, seq: u64) -> bool {
        right_due(self.right_every, seq)
    }
}

/// Whether frame number `seq` (from 1) of a stereo camera that renders its right image with
/// every `right_every`-th frame comes with one: the first, then every `right_every`-th.
pub fn right_due(right_every: u64, seq: u64) -> bool {
    seq.saturating_sub(1).is_multiple_of(right_every.max(1))
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
/// camera (and of the right camera of a stereo pair), the trocar model and the scene drawn
/// once from a seed.
pub struct TrocarCamera {
    renderer: TrocarRenderer,
    right: Option<TrocarRenderer>,
    model: TrocarModel,
    scene: Scene,
    /// The scene as the right camera sees it (its endoscope in the right camera's frame).
    right_scene: Scene,
}

impl TrocarCamera {
    /// The scene of the camera parameters `c` for a camera `model`: the trocar of
    /// `c.trocar_model_file`, lighting, materials and the wall drawn once from `seed`, the
    /// blur of `c.blur_sigma_px`, the wall traced every `c.wall_step_px` (the pixel noise is
    /// added per frame, [`TrocarCamera::add_noise`]), the endoscope with `c.show_endoscope`;
    /// `right`: the right camera of a stereo pair ([`SimCameraParams::right_camera`]), which
    /// sees the same scene.
    pub fn new(
        c: &SimCameraParams,
        seed: u64,
        model: &CameraModel,
        right: Option<&CameraModel>,
    ) -> Result<Self, CameraSetupError> {
        let trocar = c.trocar_model()?;
        let mut scene = Scene::random(seed, 0.0);
        scene.blur_sigma = c.blur_sigma_px;
        if c.show_endoscope {
            let mount = c.flange_t_camera.to_isometry().map_err(|error| CameraSetupError {
                key: "flange_t_camera",
                error,
            })?;
            let tool = ToolParams::default();
            scene.tool = Some(ToolCylinder::endoscope(&mount, tool.length_m, 0.5 * tool.diameter_m));
        }
        let renderer = TrocarRenderer::new(model).map_err(|error| CameraSetupError {
            key: "calibration_file",
            error,
        })?;
        let right = right
            .map(|m| {
                TrocarRenderer::new(m)
                    .map(|r| r.with_wall_step(c.wall_step_px))
                    .map_err(|error| CameraSetupError {
                        key: "right_calibration_file",
                        error,
                    })
            })
            .transpose()?;
        let right_scene = Scene {
            tool: match (&right, scene.tool) {
                (Some(r), Some(t)) => Some(t.transformed(&r.camera().stereo_right_t_left())),
                (_, tool) => tool,
            },
            ..scene.clone()
        };
        Ok(Self {
            renderer: renderer.with_wall_step(c.wall_step_px),
            right,
            model: trocar,
            scene,
            right_scene,
        })
    }

    /// The camera it renders for.
    pub fn camera(&self) -> &CameraModel {
        self.renderer.camera()
    }

    /// The right camera of the stereo pair, if it has one.
    pub fn right_camera(&self) -> Option<&CameraModel> {
        self.right.as_ref().map(TrocarRenderer::camera)
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

    /// The right camera's image of the port at `camera_t_trocar` (the left camera's view),
    /// without noise; `None` for a mono camera.
    pub fn render_right(&self, camera_t_trocar: &Isometry3<f64>) -> Option<Result<Vec<u8>, VisionError>> {
        let r = self.right.as_ref()?;
        let right_t_trocar = r.camera().stereo_right_t_left() * camera_t_trocar;
        Some(
            r.render(&self.model, &right_t_trocar, &self.right_scene)
                .map(|g| g.data),
        )
    }

    /// The right camera's frame captured with the left frame [`TrocarCamera::frame`] of the
    /// same arguments (its own pixel noise); `None` for a mono camera.
    pub fn right_frame(&self, camera_t_trocar: &Isometry3<f64>, sigma: f64, noise_seed: u64) -> Option<Vec<u8>> {
        let r = self.right.as_ref()?;
        let mut grey = self
            .render_right(camera_t_trocar)?
            .unwrap_or_else(|_| blank_frame(r.camera()));
        Self::add_noise(&mut grey, sigma, right_noise_seed(noise_seed));
        Some(grey)
    }
}

/// The right image's noise seed of the left frame's `noise_seed` (independent noise).
pub fn right_noise_seed(noise_seed: u64) -> u64 {
    noise_seed ^ 0xA5A5_5A5A_C3C3_3C3C
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::markerless::MarkerlessEstimator;
    use crate::vision::ImageView;
    use nalgebra::{UnitQuaternion, Vector3};

    fn config(file: &str) -> String {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("config")
            .join(file)
            .to_string_lossy()
            .into_owned()
    }

    fn stereo() -> SimCameraParams {
        SimCameraParams {
            right_calibration_file: config("camera_zedm_right.yaml"),
            ..SimCameraParams::default()
        }
    }

    use crate::kinematics::lbr::ToolParams;
    use crate::vision::markerless::render::ToolCylinder;

    #[test]
    fn the_right_camera_is_read_with_its_baseline_and_a_mono_or_bad_one_is_refused() {
        // '' (the shipped value): a mono camera.
        assert!(SimCameraParams::default().right_camera().unwrap().is_none());
        let r = stereo().right_camera().unwrap().unwrap();
        assert!((r.baseline_m - 0.063).abs() < 1e-9, "{}", r.baseline_m);
        // The left calibration has no baseline: not a right camera.
        let mono = SimCameraParams {
            right_calibration_file: config("camera_zedm.yaml"),
            ..stereo()
        };
        let e = mono.right_camera().unwrap_err().to_string();
        assert!(
            e.contains("camera.right_calibration_file") && e.contains("baseline 0.0 mm"),
            "{e}"
        );
        let missing = SimCameraParams {
            right_calibration_file: "/nonexistent/right.yaml".into(),
            ..stereo()
        };
        assert!(missing
            .right_camera()
            .unwrap_err()
            .to_string()
            .contains("right_calibration_file"));
        let never = SimCameraParams {
            right_every: 0,
            ..stereo()
        };
        assert!(never
            .right_camera()
            .unwrap_err()
            .to_string()
            .contains("camera.right_every"));
    }

    #[test]
    fn the_right_image_comes_with_the_first_frame_then_every_right_every_th() {
        let due = |every: u64| (1..=7).filter(|&s| right_due(every, s)).collect::<Vec<u64>>();
        assert_eq!(due(1), vec![1, 2, 3, 4, 5, 6, 7]);
        assert_eq!(due(3), vec![1, 4, 7]);
        assert_eq!(due(0), due(1), "0 is refused at set-up; the schedule treats it as 1");
        assert!(
            stereo().right_due(1)
                && !SimCameraParams {
                    right_every: 2,
                    ..stereo()
                }
                .right_due(2)
        );
    }

    #[test]
    fn the_right_image_shows_the_trocar_where_the_right_camera_sees_it() {
        let c = stereo();
        let left = CameraModel::from_yaml_file(std::path::Path::new(&config("camera_zedm.yaml"))).unwrap();
        let right = c.right_camera().unwrap().unwrap();
        let cam = TrocarCamera::new(&c, 3, &left, Some(&right)).unwrap();
        let mono = TrocarCamera::new(&c, 3, &left, None).unwrap();
        assert!(mono.right_camera().is_none() && mono.right_frame(&Isometry3::identity(), 2.0, 1).is_none());
        // The port 0.25 m ahead, its axis tilted 20 deg, 1 cm left of the optical axis.
        let camera_t_trocar = Isometry3::from_parts(
            nalgebra::Translation3::new(-0.01, 0.005, 0.25),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 20f64.to_radians()),
        );
        let l = cam.frame(&camera_t_trocar, 2.0, 7);
        let r = cam.right_frame(&camera_t_trocar, 2.0, 7).unwrap();
        assert_eq!(r.len(), l.len());
        assert_ne!(l, r);
        // Found by an estimator of the right camera alone, the port sits where the right
        // camera sees it (63 mm to the left in its frame), the axis as the left sees it.
        let model = TrocarModel::shipped();
        let mut est = MarkerlessEstimator::new(&right, &model).unwrap();
        let truth = right.stereo_right_t_left() * camera_t_trocar;
        let z = truth.rotation * Vector3::z();
        let e = est
            .estimate(&ImageView::grey(&r, &right), Some(&nalgebra::Unit::new_normalize(z)))
            .unwrap()
            .unwrap();
        let dp = (e.axis.point - truth.translation.vector).norm();
        assert!(dp < 3e-3, "{dp} m");
        assert!(e.axis.direction.angle(&z) < 2f64.to_radians());
        assert!((truth.translation.x - camera_t_trocar.translation.x + 0.063).abs() < 1e-12);
    }

    #[test]
    fn the_endoscope_is_drawn_where_the_true_mount_puts_it_in_both_images() {
        let c = stereo();
        let left = CameraModel::from_yaml_file(std::path::Path::new(&config("camera_zedm.yaml"))).unwrap();
        let right = c.right_camera().unwrap().unwrap();
        let without = SimCameraParams {
            show_endoscope: false,
            ..c.clone()
        };
        let (with, bare) = (
            TrocarCamera::new(&c, 3, &left, Some(&right)).unwrap(),
            TrocarCamera::new(&without, 3, &left, Some(&right)).unwrap(),
        );
        // The stand-off point: the port 2 cm beyond the tip, on the endoscope's axis.
        let mount = c.flange_t_camera.to_isometry().unwrap();
        let tool = ToolParams::default();
        let camera_t_trocar = mount.inverse()
            * Isometry3::from_parts(
                nalgebra::Translation3::new(0.0, 0.0, tool.length_m + 0.02),
                UnitQuaternion::identity(),
            );
        let shaft = ToolCylinder::endoscope(&mount, tool.length_m, 0.5 * tool.diameter_m);
        let images = [
            (
                &left,
                with.render(&camera_t_trocar).unwrap(),
                bare.render(&camera_t_trocar).unwrap(),
                shaft,
            ),
            (
                &right,
                with.render_right(&camera_t_trocar).unwrap().unwrap(),
                bare.render_right(&camera_t_trocar).unwrap().unwrap(),
                shaft.transformed(&right.stereo_right_t_left()),
            ),
        ];
        for (cam, a, b, shaft) in images {
            // The shaft's image: from its tip to where it is 5 cm from the camera.
            let (tip, back) = (Vector3::from(shaft.start), Vector3::from(shaft.end));
            let near = tip + (back - tip) * ((tip.z - 0.05) / (tip.z - back.z));
            let px = |p: Vector3<f64>| nalgebra::Vector2::new(cam.fx * p.x / p.z + cam.cx, cam.fy * p.y / p.z + cam.cy);
            let (p, q) = (px(tip), px(near));
            let half_width = cam.fx * shaft.radius / tip.z;
            let dist = |x: nalgebra::Vector2<f64>| {
                let t = ((x - p).dot(&(q - p)) / (q - p).norm_squared()).clamp(0.0, 1.0);
                (x - (p + t * (q - p))).norm()
            };
            let changed: Vec<nalgebra::Vector2<f64>> = (0..a.len())
                .filter(|&i| a[i].abs_diff(b[i]) > 8)
                .map(|i| {
                    let w = cam.width as usize;
                    nalgebra::Vector2::new((i % w) as f64 + 0.5, (i / w) as f64 + 0.5)
                })
                .collect();
            // Where the shaft is (a band ~10 px wide and hundreds long), and nowhere else
            // (its shadow is not drawn; the blur spreads its edge by a pixel or two).
            assert!(changed.len() > 2000, "{} pixels changed", changed.len());
            let far = changed.iter().filter(|x| dist(**x) > 4.0 * half_width + 4.0).count();
            assert_eq!(far, 0, "{far} changed pixels away from the shaft");
            assert!(
                changed.iter().any(|x| dist(*x) < 1.0 && (x - p).norm() < 3.0),
                "the tip is drawn"
            );
        }
    }
}
