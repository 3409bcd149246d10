//! The simulated world seen through the vision pipeline: [`CameraPoseSource`], a trocar pose
//! source ([`crate::sim::noise::PoseSource`]) that replaces the noise-model sensor by the
//! markerless camera pipeline of the ROS loop (`sim.launch marker:=false`).
//!
//! At the protocol's capture rate it renders the image the `lbr_med_sim` node's camera
//! renders ([`TrocarCamera`]: the true port pose seen through the true camera mount
//! `camera.flange_t_camera` of `config/lbr_med_sim.yaml` from the link-side joints, the
//! scene drawn once per trial from the trial's seed, the pixel noise per frame), runs the
//! markerless estimate into the trocar estimator as the estimator node does per frame
//! ([`track`]: the previous estimate as the prior, the confidence gate, the outlier gate and
//! the filter of `config/trocar_estimator.yaml`), through the hand-eye the controller
//! believes (the true mount times the protocol's calibration bias, drawn as the noise-model
//! sensor draws it for the same seed) and the joints the arm reports, and delivers the
//! filtered pose after the protocol's latency. A frame the pipeline rejects delivers nothing.
//! The endoscope's shaft is in the images (`camera.show_endoscope`) and the estimator masks
//! it where the believed hand-eye puts it, fitted to each image (`markerless.endoscope_radius_m`).
//!
//! Its own layer: it imports the simulator and the vision (which do not import each other)
//! and is wired by the command line.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use nalgebra::Isometry3;

use crate::kinematics::lbr::LbrModel;
use crate::kinematics::{Kinematics, LbrKinematics, FLANGE_LINK};
use crate::sim::noise::{BiasFrame, CaptureSchedule, PoseSource, SensorInput, TrocarMeasurement};
use crate::sim::world::measurement_stream;
use crate::sim::MeasurementParams;
use crate::vision::estimator::{marker_in_camera, EstimatorParams, PoseYaml, TrocarEstimator};
use crate::vision::markerless::measurement::track;
use crate::vision::markerless::{MarkerlessEstimator, MarkerlessParams, TrocarModel};
use crate::vision::sim_camera::{right_due, SimCameraParams, TrocarCamera};
use crate::vision::{CameraModel, ImageView};

/// What the camera pose source is built from (one per run; each trial builds its source).
#[derive(Debug, Clone)]
pub struct CameraSetup {
    /// The simulated camera (`camera:` of `config/lbr_med_sim.yaml`: the true mount, the
    /// pixel noise, the blur, the wall step, the trocar model shown).
    pub camera: SimCameraParams,
    /// The camera's intrinsics and distortion (the calibration file the node renders with).
    pub calibration: CameraModel,
    /// The stereo pair's right camera (`camera.right_calibration_file`; `None`: mono): its
    /// image, rendered with every `camera.right_every`-th frame, resolves the two-fold
    /// ambiguity of the opening's ellipse.
    pub right: Option<CameraModel>,
    /// The markerless gate (`markerless:` of `config/trocar_estimator.yaml`).
    pub markerless: MarkerlessParams,
    /// The estimator's filter and gates (`estimator:` of `config/trocar_estimator.yaml`; its
    /// `flange_t_camera` is replaced by the hand-eye the controller believes).
    pub estimator: EstimatorParams,
    /// The trocar model the estimate looks for.
    pub trocar: TrocarModel,
    /// The arm model (the flange chain the camera rides on).
    pub model: LbrModel,
}

impl CameraSetup {
    /// The shipped set-up (`config/lbr_med_sim.yaml`, `config/trocar_estimator.yaml`, the
    /// shipped trocar model, the LBR Med 7) for the camera `calibration` and the stereo
    /// pair's `right` camera (`None`: mono).
    pub fn shipped(calibration: CameraModel, right: Option<CameraModel>) -> Self {
        Self {
            camera: SimCameraParams::default(),
            calibration,
            right,
            markerless: MarkerlessParams::default(),
            estimator: EstimatorParams::default(),
            trocar: TrocarModel::shipped(),
            model: LbrModel::Med7,
        }
    }
}

/// Frame counts over every source that shares them (a run's trials).
#[derive(Debug, Default)]
pub struct FrameCounts {
    /// Frames captured (rendered and estimated).
    pub captured: AtomicU64,
    /// Frames whose estimate passed the confidence gate.
    pub gated: AtomicU64,
    /// Frames fused by the estimator (not rejected as outliers): each delivers a pose.
    pub fused: AtomicU64,
}

impl FrameCounts {
    /// (captured, gated, fused).
    pub fn get(&self) -> (u64, u64, u64) {
        (
            self.captured.load(Ordering::Relaxed),
            self.gated.load(Ordering::Relaxed),
            self.fused.load(Ordering::Relaxed),
        )
    }
}

/// The markerless camera pipeline as a trocar pose source (see the module doc).
pub struct CameraPoseSource {
    flange: LbrKinematics,
    /// The true camera mount (renders).
    true_mount: Isometry3<f64>,
    camera: TrocarCamera,
    estimator: MarkerlessEstimator,
    filter: TrocarEstimator,
    markerless: MarkerlessParams,
    schedule: CaptureSchedule,
    /// The right image comes with every this many frames ([`right_due`]).
    right_every: u64,
    noise_sigma: f64,
    seed: u64,
    seq: u64,
    counts: Option<Arc<FrameCounts>>,
}

impl CameraPoseSource {
    /// The source of the trial of `seed` under the protocol's `measurement` (its rate,
    /// latency and calibration bias, which must act in the camera frame).
    pub fn new(setup: &CameraSetup, measurement: &MeasurementParams, seed: u64) -> Result<Self, String> {
        measurement.validate().map_err(|e| e.to_string())?;
        if measurement.bias_frame != BiasFrame::Camera {
            return Err("the camera pose source needs measurement.bias_frame: camera (a hand-eye error)".into());
        }
        // The same first draw as the noise-model sensor of this seed: the same bias.
        let bias = measurement.draw_bias(&mut measurement_stream(seed));
        let true_mount = setup.camera.flange_t_camera.to_isometry().map_err(|e| e.to_string())?;
        let believed = true_mount * bias;
        let filter = TrocarEstimator::new(EstimatorParams {
            flange_t_camera: PoseYaml::from_isometry(&believed),
            ..setup.estimator.clone()
        })
        .map_err(|e| format!("estimator: {e}"))?;
        setup.markerless.validate().map_err(|e| e.to_string())?;
        // The endoscope in view, masked where the believed hand-eye puts it.
        let length = LbrKinematics::flange_to_tip_m(setup.model, "").map_err(|e| e.to_string())?;
        let occluder = setup.markerless.endoscope(&believed, length);
        Ok(Self {
            flange: LbrKinematics::from_model_or_file(setup.model, "", FLANGE_LINK).map_err(|e| e.to_string())?,
            true_mount,
            camera: TrocarCamera::new(&setup.camera, seed, &setup.calibration, setup.right.as_ref())
                .map_err(|e| e.to_string())?,
            estimator: MarkerlessEstimator::for_cameras(&setup.calibration, setup.right.as_ref(), &setup.trocar)
                .and_then(|e| e.with_occluder(occluder))
                .map_err(|e| e.to_string())?,
            right_every: setup.camera.right_every,
            filter,
            markerless: setup.markerless.clone(),
            schedule: CaptureSchedule::new(measurement.rate_hz, measurement.latency_s),
            noise_sigma: setup.camera.noise_sigma,
            seed,
            seq: 0,
            counts: None,
        })
    }

    /// Add this source's frames to `counts`.
    pub fn with_counts(mut self, counts: Arc<FrameCounts>) -> Self {
        self.counts = Some(counts);
        self
    }

    /// The hand-eye the estimate uses (the true mount times the calibration bias).
    pub fn believed_mount(&self) -> Isometry3<f64> {
        self.filter.flange_t_camera()
    }

    /// Render, estimate and fuse the frame captured at `t`; the filtered pose, if the frame
    /// gives one.
    fn capture(&mut self, t: f64, at: &SensorInput<'_>) -> Option<Isometry3<f64>> {
        self.seq += 1;
        let count = |c: &Option<Arc<FrameCounts>>, f: fn(&FrameCounts) -> &AtomicU64| {
            if let Some(c) = c {
                f(c).fetch_add(1, Ordering::Relaxed);
            }
        };
        count(&self.counts, |c| &c.captured);
        // The camera rides on the link side: where the (elastic) arm really is.
        let base_t_flange = self.flange.fk(at.q_link).ok()?;
        let camera_t_trocar = marker_in_camera(&base_t_flange, &self.true_mount, at.true_pose, &Isometry3::identity());
        // The pixel noise of frame `seq` of this trial (the node numbers its frames alone).
        let noise_seed = self.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ self.seq;
        let grey = self.camera.frame(&camera_t_trocar, self.noise_sigma, noise_seed);
        let view = ImageView::grey(&grey, self.camera.camera());
        // The right image with every `right_every`-th frame, as the node publishes it.
        let right = if right_due(self.right_every, self.seq) {
            self.camera.right_frame(&camera_t_trocar, self.noise_sigma, noise_seed)
        } else {
            None
        };
        let right_view = match (&right, self.camera.right_camera()) {
            (Some(g), Some(c)) => Some(ImageView::grey(g, c)),
            _ => None,
        };
        // The estimator pairs the frame with the joints the arm reports at its stamp.
        let base_t_camera = self.flange.fk(at.q).ok()? * self.filter.flange_t_camera();
        let tracked = track(
            &mut self.estimator,
            &mut self.filter,
            &view,
            right_view.as_ref(),
            t,
            &base_t_camera,
            &self.markerless,
        )
        .ok()?;
        count(&self.counts, |c| &c.gated);
        let pose = tracked.pose?;
        count(&self.counts, |c| &c.fused);
        Some(pose)
    }
}

impl PoseSource for CameraPoseSource {
    fn update(&mut self, t: f64, at: &SensorInput<'_>) {
        if self.schedule.capture_due(t) {
            if let Some(pose) = self.capture(t, at) {
                self.schedule.push(TrocarMeasurement { stamp: t, pose });
            }
        }
        self.schedule.deliver(t);
    }

    fn latest(&self, now: f64) -> Option<TrocarMeasurement> {
        self.schedule.latest(now)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::ControllerParams;
    use crate::kinematics::lbr::ToolParams;
    use crate::kinematics::JointVector;
    use crate::sim::SimWorld;
    use crate::trials::config::SimConfig;
    use crate::trials::run::{run_trial, Outcome};

    fn setup() -> CameraSetup {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/camera_zedm.yaml");
        CameraSetup::shipped(CameraModel::from_yaml_file(&path).unwrap(), None)
    }

    fn config() -> SimConfig {
        SimConfig::default().with_protocol("realistic_markerless").unwrap()
    }

    /// The protocol's sensor without its calibration bias (the pipeline's own error).
    fn unbiased() -> MeasurementParams {
        MeasurementParams {
            bias_position_m: 0.0,
            bias_rotation_rad: 0.0,
            ..config().sim.measurement
        }
    }

    fn world(seed: u64) -> SimWorld {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).unwrap();
        SimWorld::new(&config().sim, Arc::new(kin), seed).unwrap()
    }

    /// A fixed scene: the start of the world of `seed` (arm and trocar still).
    struct Still {
        trocar: Isometry3<f64>,
        tip: Isometry3<f64>,
        q: JointVector,
        q_link: JointVector,
    }

    impl Still {
        fn of(w: &SimWorld) -> Self {
            Self {
                trocar: w.trocar_pose_true(),
                tip: w.tip_pose(),
                q: w.joint_positions(),
                q_link: w.joint_positions_link(),
            }
        }

        fn input(&self) -> SensorInput<'_> {
            SensorInput {
                true_pose: &self.trocar,
                tip: &self.tip,
                q: &self.q,
                q_link: &self.q_link,
            }
        }
    }

    /// Every distinct delivery of `source` on the still scene over `seconds` at 1 kHz:
    /// (time first seen, measurement).
    fn run(source: &mut CameraPoseSource, scene: &Still, seconds: f64) -> Vec<(f64, TrocarMeasurement)> {
        let mut out: Vec<(f64, TrocarMeasurement)> = vec![];
        for k in 0..=(seconds * 1000.0).round() as usize {
            let t = k as f64 * 1e-3;
            source.update(t, &scene.input());
            if let Some(m) = source.latest(t) {
                if out.last().is_none_or(|(_, l)| l.stamp != m.stamp) {
                    out.push((t, m));
                }
            }
        }
        out
    }

    /// Position error (m) and axis angle (rad) of `m` against the truth.
    fn error(m: &TrocarMeasurement, truth: &Isometry3<f64>) -> (f64, f64) {
        let dp = (m.pose.translation.vector - truth.translation.vector).norm();
        let z = |p: &Isometry3<f64>| p.rotation * nalgebra::Vector3::z();
        (dp, z(&m.pose).angle(&z(truth)))
    }

    /// The largest position error (m) and axis angle (rad) of `d` against the truth.
    fn worst(d: &[(f64, TrocarMeasurement)], truth: &Isometry3<f64>) -> (f64, f64) {
        d.iter()
            .map(|(_, m)| error(m, truth))
            .fold((0.0, 0.0), |a: (f64, f64), b| (a.0.max(b.0), a.1.max(b.1)))
    }

    /// The start of the world of `seed` through `setup` without calibration bias, 1 s: the
    /// poses delivered, and the largest position error (m) and axis angle (rad) among them.
    fn on_the_start(setup: &CameraSetup, seed: u64) -> (usize, f64, f64) {
        let scene = Still::of(&world(seed));
        let mut s = CameraPoseSource::new(setup, &unbiased(), seed).unwrap();
        let d = run(&mut s, &scene, 1.0);
        let (dp, da) = worst(&d, &scene.trocar);
        (d.len(), dp, da)
    }

    #[test]
    fn the_endoscope_in_view_corrects_the_hand_eye_only_when_told_to() {
        // The starts of seeds with the protocol's calibration bias (a hand-eye error up to
        // 2 mm and 1 deg), 1 s with the stereo pair: the last pose delivered with the
        // correction on and off (`markerless.endoscope_corrects_hand_eye`).
        let last = |seed: u64, on: bool| {
            let setup = CameraSetup {
                markerless: MarkerlessParams {
                    endoscope_corrects_hand_eye: on,
                    ..MarkerlessParams::default()
                },
                ..stereo()
            };
            let scene = Still::of(&world(seed));
            let mut s = CameraPoseSource::new(&setup, &config().sim.measurement, seed).unwrap();
            let d = run(&mut s, &scene, 1.0);
            d.last().map(|(_, m)| error(m, &scene.trocar))
        };
        // Measured: seeds 1, 2, 4 and 6 corrected, the port 4.90 -> 1.15, 2.80 -> 0.12,
        // 4.56 -> 0.93 and 2.96 -> 0.87 mm off; seeds 3 and 5 give no frame both of the
        // shaft's lines hold in both eyes: the same poses either way.
        for seed in [1, 2, 4, 6] {
            let (off, on) = (last(seed, false).unwrap(), last(seed, true).unwrap());
            eprintln!("seed {seed}: off {off:?}, on {on:?}");
            assert!(
                off.0 > 2e-3 && on.0 < 0.4 * off.0,
                "seed {seed}: off {off:?}, on {on:?}"
            );
        }
        for seed in [3, 5] {
            assert_eq!(last(seed, false), last(seed, true), "seed {seed}");
        }
    }

    #[test]
    fn a_still_scene_is_delivered_within_the_measured_error_of_the_truth() {
        // Measured on the starts of seeds 1, 3 and 4 (the trocar 0.13-0.15 m from the tip,
        // no calibration bias), 1 s at 15 Hz: 14-15 poses delivered, the worst 1.53 mm and
        // 0.72 deg off the true port and axis (filter start included). Bounds: 2x that.
        for seed in [1, 3, 4] {
            let (n, dp, da) = on_the_start(&setup(), seed);
            assert!(n >= 12, "seed {seed}: {n} poses in 1 s");
            assert!(dp < 3e-3 && da < 1.5f64.to_radians(), "seed {seed}: {dp} m, {da} rad");
        }
    }

    /// The shipped set-up with the stereo pair's right camera.
    fn stereo() -> CameraSetup {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        CameraSetup {
            right: Some(CameraModel::from_yaml_file(&dir.join("camera_zedm_right.yaml")).unwrap()),
            ..setup()
        }
    }

    #[test]
    fn the_right_image_gives_a_pose_where_the_left_image_alone_cannot() {
        // The start of seed 78 (0.34 m, the axis 5 deg from the line of sight): the left
        // image refines its two circle poses 5.5 and 13.8 deg off the axis, under the
        // confidence gate without a prior; the right image finds the axis within 1 deg, and
        // where none of its poses agrees with the left's the left image does not decide.
        let scene = Still::of(&world(78));
        let mut mono = CameraPoseSource::new(&setup(), &unbiased(), 78).unwrap();
        assert!(run(&mut mono, &scene, 1.0).is_empty(), "mono gave a pose");
        let mut s = CameraPoseSource::new(&stereo(), &unbiased(), 78).unwrap();
        let d = run(&mut s, &scene, 1.0);
        for (t, m) in &d {
            let e = error(m, &scene.trocar);
            eprintln!("{t:.3}: {:.2} mm {:.2} deg", e.0 * 1e3, e.1.to_degrees());
        }
        let (dp, da) = worst(&d, &scene.trocar);
        // Measured: 15 poses in 1 s, the worst 1.83 mm and 1.24 deg off (filter start included).
        assert!(d.len() >= 12, "{} poses in 1 s", d.len());
        assert!(dp < 4e-3 && da < 3f64.to_radians(), "{dp} m, {da} rad");
        // A still scene of seed 1 through the stereo pair: as near the truth as mono.
        let scene = Still::of(&world(1));
        let d = run(
            &mut CameraPoseSource::new(&stereo(), &unbiased(), 1).unwrap(),
            &scene,
            1.0,
        );
        let (dp, da) = worst(&d, &scene.trocar);
        assert!(
            d.len() >= 12 && dp < 3e-3 && da < 1.5f64.to_radians(),
            "{} {dp} {da}",
            d.len()
        );
    }

    #[test]
    fn one_axis_fitted_to_both_images_gives_a_pose_where_the_eyes_disagree() {
        // The starts of seeds 7810 and 7870 (0.34 m): the left image's two circle poses and
        // the right image's disagree by more than 4 deg; one axis refined on both images
        // from each of them settles on one. Measured: 15 poses in 1 s each, the worst
        // 0.21 mm / 1.59 deg and 0.33 mm / 0.93 deg off (filter start included; the true
        // mount believed, the endoscope in view correcting it by 0.03 mm at 7810's tip).
        for seed in [7810, 7870] {
            let (n, dp, da) = on_the_start(&stereo(), seed);
            assert!(n >= 12, "seed {seed}: {n} poses in 1 s");
            assert!(dp < 1e-3 && da < 3f64.to_radians(), "seed {seed}: {dp} m, {da} rad");
        }
        // The start of seed 109 (0.34 m, the axis 11 deg from the line of sight): the joint
        // fit settles on two axes 17-21 deg apart, neither the true one, with scores too
        // close to choose, or every start on one of them: nothing confident, a hold.
        let (n, dp, da) = on_the_start(&stereo(), 109);
        assert!(
            dp < 0.01 && da < 5f64.to_radians(),
            "seed 109: {n} poses, {dp} m, {da} rad"
        );
    }

    #[test]
    fn the_hand_eye_is_the_true_mount_times_the_noise_models_bias_and_moves_the_pose() {
        let (seed, p) = (3, config().sim.measurement);
        let s = CameraPoseSource::new(&setup(), &p, seed).unwrap();
        let mount = setup().camera.flange_t_camera.to_isometry().unwrap();
        let bias = p.draw_bias(&mut measurement_stream(seed));
        let believed = s.believed_mount();
        assert!((believed.translation.vector - (mount * bias).translation.vector).norm() < 1e-6);
        assert!(believed.rotation.angle_to(&(mount * bias).rotation) < 1e-6);
        assert!(bias.translation.vector.norm() > 0.0 && bias.translation.vector.norm() <= p.bias_position_m);
        // A port-frame bias is no hand-eye error: refused.
        let port = MeasurementParams {
            bias_frame: BiasFrame::Port,
            ..p
        };
        let e = CameraPoseSource::new(&setup(), &port, seed).err().unwrap();
        assert!(e.contains("bias_frame"), "{e}");
    }

    #[test]
    fn no_trocar_in_view_or_a_gate_nothing_passes_delivers_nothing() {
        let w = world(3);
        let mut away = Still::of(&w);
        // The trocar 2 m to the side: the camera sees only the wall.
        away.trocar.translation.vector.x += 2.0;
        let counts = Arc::new(FrameCounts::default());
        let mut s = CameraPoseSource::new(&setup(), &unbiased(), 3)
            .unwrap()
            .with_counts(counts.clone());
        assert!(run(&mut s, &away, 0.5).is_empty());
        assert_eq!(
            counts.get(),
            (8, 0, 0),
            "8 frames captured in 0.5 s, none past the gate"
        );
        // In view, but a gate no estimate passes.
        let strict = CameraSetup {
            markerless: MarkerlessParams {
                min_confidence: 1.0,
                ..MarkerlessParams::default()
            },
            ..setup()
        };
        let mut s = CameraPoseSource::new(&strict, &unbiased(), 3).unwrap();
        assert!(run(&mut s, &Still::of(&w), 0.5).is_empty());
        // Joints the kinematics refuse: nothing, no panic.
        let mut bad = Still::of(&w);
        bad.q = JointVector::repeat(f64::NAN);
        bad.q_link = bad.q;
        let mut s = CameraPoseSource::new(&setup(), &unbiased(), 3).unwrap();
        assert!(run(&mut s, &bad, 0.3).is_empty());
    }

    #[test]
    fn a_seed_fixes_the_poses_and_another_seed_changes_them() {
        let scene = Still::of(&world(4));
        let poses = |seed: u64| {
            let mut s = CameraPoseSource::new(&setup(), &config().sim.measurement, seed).unwrap();
            run(&mut s, &scene, 0.5)
        };
        let (a, b, c) = (poses(4), poses(4), poses(5));
        assert!(!a.is_empty());
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn poses_come_at_the_protocols_rate_after_its_latency() {
        let p = unbiased();
        let scene = Still::of(&world(1));
        let mut s = CameraPoseSource::new(&setup(), &p, 1).unwrap();
        let d = run(&mut s, &scene, 1.0);
        assert!(d.len() >= 12, "{}", d.len());
        let period = 1.0 / p.rate_hz;
        for (seen, m) in &d {
            // Captured at the first physics tick (1 ms) on or after a point of the rate's
            // grid, first seen once the latency has passed.
            let on_grid = m.stamp - (m.stamp / period + 1e-9).floor() * period;
            assert!((-1e-9..1e-3).contains(&on_grid), "stamp {}", m.stamp);
            assert!(
                *seen - m.stamp >= p.latency_s - 1e-9 && *seen - m.stamp < p.latency_s + 1e-3,
                "{seen} {}",
                m.stamp
            );
        }
        for pair in d.windows(2) {
            let gap = (pair[1].1.stamp - pair[0].1.stamp) / period;
            assert!(gap > 0.98 && (gap - gap.round()).abs() < 0.02, "{gap} periods");
        }
    }

    /// One trial of the docking controller (FF) with the camera pose source, `setup` its
    /// camera, `timeout_s` its timeout.
    fn trial(setup: &CameraSetup, seed: u64, timeout_s: f64) -> crate::trials::run::TrialResult {
        trial_counted(setup, seed, timeout_s, Arc::default())
    }

    /// [`trial`], its frames counted in `counts`.
    fn trial_counted(
        setup: &CameraSetup,
        seed: u64,
        timeout_s: f64,
        counts: Arc<FrameCounts>,
    ) -> crate::trials::run::TrialResult {
        let mut c = config();
        c.trial.timeout_s = timeout_s;
        let controller = ControllerParams::default();
        let limits = crate::kinematics::JointLimits::of_model(LbrModel::Med7);
        let make = crate::trials::policy::factory(&c, &controller, true, &limits);
        let mut w = world(seed);
        w.set_pose_source(Box::new(
            CameraPoseSource::new(setup, &c.sim.measurement, seed)
                .unwrap()
                .with_counts(counts),
        ));
        let mut policy = make(seed).unwrap();
        run_trial(&mut w, policy.as_mut(), &c.trial, seed)
    }

    #[test]
    fn a_trial_through_the_camera_docks_and_a_blind_camera_holds() {
        let r = trial(&setup(), 11, 30.0);
        assert_eq!(r.outcome, Outcome::Docked, "{}", r.reason);
        // The camera turned away from the scope's axis: no pose ever, the controller never
        // moves in, and nothing panics.
        let mut blind = setup();
        blind.camera.flange_t_camera.quaternion_xyzw = [1.0, 0.0, 0.0, 0.0];
        let r = trial(&blind, 11, 2.0);
        assert!(
            matches!(r.outcome, Outcome::Timeout | Outcome::Held) && !r.paper_success,
            "{:?}: {}",
            r.outcome,
            r.reason
        );
    }

    #[test]
    fn with_the_endoscope_in_the_port_every_frame_but_one_still_gives_a_pose() {
        // The stereo camera sees the endoscope go into the port (seed 40 of the realistic
        // trials, its hand-eye 2 mm / 1 deg off at most). Masked to its tip, the shaft's mask
        // reached over the opening's far rim once the tip was in: 13 of 61 frames gave no
        // pose, the last 0.5 s before DONE none, and DONE came on a stale, breathing port
        // (5.1 mm deep of the goal). Ended where it goes into the port, every frame fuses but
        // one: under the acceleration limits the tip crosses the port's near rim in frame 28
        // (t = 1.8 s, 2026-12-07), where the tip's mask touches the opening and the
        // detector finds none; the next frame finds it again.
        let path = |f: &str| std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config").join(f);
        let right = CameraModel::from_yaml_file(&path("camera_zedm_right.yaml")).unwrap();
        let stereo = CameraSetup::shipped(
            CameraModel::from_yaml_file(&path("camera_zedm.yaml")).unwrap(),
            Some(right),
        );
        assert!(stereo.camera.show_endoscope && stereo.markerless.endoscope_radius_m > 0.0);
        let counts = Arc::new(FrameCounts::default());
        let r = trial_counted(&stereo, 40, 30.0, counts.clone());
        let (captured, gated, fused) = counts.get();
        assert!(r.time_s < 5.0 && r.paper_success, "{:?}: {}", r.outcome, r.reason);
        assert!(
            captured >= 55 && fused + 1 >= captured && gated + 1 >= captured,
            "{:?}",
            counts.get()
        );
    }
}
