//! The `latency` rostest check: end-to-end latency from a camera image to the joint command
//! that first uses it. The test node plays an ideal camera (the marker rendered once for the
//! arm's pose, each frame stamped at the moment it is sent, so the camera adds no latency of
//! its own) and the driver (joint states and LBRState at the FRI rate, the arm still); the
//! trocar estimator stamps its pose with the image's stamp, and the controller measures
//! stamp -> command (DockingStatus `latency_*`). The check starts the controller, lets it
//! run, and asserts the 99th percentile below `max_latency_ms`.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use nalgebra::{Isometry3, Translation3, Vector3};

use super::checks::{subscribe_latest, trigger, wait_for, CheckParams};
use super::convert;
use super::image_msgs;
use super::msgs::{lbr_msgs, sensor_msgs, trocar_docking};
use crate::kinematics::{JointVector, Kinematics, LbrKinematics, FLANGE_LINK};
use crate::robot_model::{LbrModel, ToolParams};
use crate::vision::{render_marker_image, CameraModel, EstimatorParams, MarkerSpec, RenderOptions};

/// One camera frame: the marker seen from the arm at `q0` with the nominal mount, for a
/// trocar 12 cm ahead of the tip on its optical axis.
fn camera_frame(camera: &CameraModel, q0: &JointVector) -> Result<Vec<u8>, String> {
    let tip_kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).map_err(|e| e.to_string())?;
    let flange_kin = LbrKinematics::from_model_or_file(LbrModel::Med7, "", FLANGE_LINK).map_err(|e| e.to_string())?;
    let tip = tip_kin.fk(q0).map_err(|e| e.to_string())?;
    let trocar = Isometry3::from_parts(
        Translation3::from(tip.translation.vector + tip.rotation * Vector3::new(0.0, 0.0, 0.12)),
        tip.rotation,
    );
    let nominal = EstimatorParams::default();
    let flange_t_camera = nominal.flange_t_camera.to_isometry().map_err(|e| e.to_string())?;
    let marker_t_trocar = nominal.marker_t_trocar.to_isometry().map_err(|e| e.to_string())?;
    let base_t_camera = flange_kin.fk(q0).map_err(|e| e.to_string())? * flange_t_camera;
    let camera_t_marker = base_t_camera.inverse() * trocar * marker_t_trocar.inverse();
    let opts = RenderOptions {
        plane_scale: 1.6,
        noise_sigma: 2.0,
        ..RenderOptions::default()
    };
    render_marker_image(&MarkerSpec::default(), camera, &camera_t_marker, &opts)
        .map(|g| g.data)
        .map_err(|e| format!("render: {e}"))
}

/// Publish the still arm at 500 Hz and the camera at `camera_hz` until `stop`.
fn play(
    q0: JointVector,
    camera: CameraModel,
    frame: Vec<u8>,
    camera_hz: f64,
    stop: Arc<AtomicBool>,
) -> Result<std::thread::JoinHandle<()>, String> {
    let e = |e: rosrust::error::Error| e.to_string();
    let js = rosrust::publish::<sensor_msgs::JointState>("/lbr/joint_states", 10).map_err(e)?;
    let lbr = rosrust::publish::<lbr_msgs::LBRState>("/lbr/states", 10).map_err(e)?;
    let img = rosrust::publish::<sensor_msgs::Image>("/zedm/zed_node/left/image_rect_color", 2).map_err(e)?;
    let info = rosrust::publish::<sensor_msgs::CameraInfo>("/zedm/zed_node/left/camera_info", 2).map_err(e)?;
    let names: Vec<String> = (1..=7).map(|i| format!("lbr_joint_{i}")).collect();
    let every = (500.0 / camera_hz.clamp(1.0, 100.0)).round().max(1.0) as u64;
    Ok(std::thread::spawn(move || {
        let rate = rosrust::rate(500.0);
        let zeros = JointVector::zeros();
        let mut k = 0u64;
        while rosrust::is_ok() && !stop.load(Ordering::Relaxed) {
            let now = rosrust::now();
            let _ = js.send(convert::joint_state(now, &names, &q0, &zeros));
            let _ = lbr.send(convert::lbr_state(now, 0.002, &q0, &zeros, &zeros));
            if k % every == 0 {
                let _ = info.send(image_msgs::camera_info(now, "camera_optical_frame", &camera));
                // Stamped as it leaves: the camera itself adds no latency.
                let stamp = rosrust::now();
                let _ = img.send(image_msgs::image(
                    stamp,
                    "camera_optical_frame",
                    camera.width,
                    camera.height,
                    "mono8",
                    1,
                    frame.clone(),
                ));
            }
            k += 1;
            rate.sleep();
        }
    }))
}

/// Run the check; a summary on success.
pub fn latency(p: &CheckParams) -> Result<String, String> {
    let camera = CameraModel::from_yaml_file(std::path::Path::new(&p.camera_calibration))
        .map_err(|e| format!("camera_calibration: {e}"))?;
    let q0 = JointVector::from_column_slice(&[0.0, 0.6, 0.0, -1.2, 0.0, 0.9, 0.0]);
    let frame = camera_frame(&camera, &q0)?;
    let stop = Arc::new(AtomicBool::new(false));
    let (status, _sub) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let player = play(q0, camera, frame, p.camera_rate_hz, stop.clone())?;
    let result = (|| {
        wait_for(p.startup_timeout, || status.get()).ok_or("no status from the controller")?;
        trigger(&format!("{}/start", p.controller), p.startup_timeout)?;
        std::thread::sleep(Duration::from_secs_f64(p.hold_observe.max(1.0)));
        let s = status.get().ok_or("no status")?;
        let frames = (p.hold_observe * p.camera_rate_hz * 0.5).floor();
        if s.latency_p99_ms <= 0.0 || (s.steps as f64) < frames {
            return Err(format!(
                "no latency measured (phase {}, {}, {} steps)",
                s.phase, s.hold_reason, s.steps
            ));
        }
        let summary = format!(
            "image -> command latency p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms at a {:.0} Hz control loop ({} steps, phase {})",
            s.latency_p50_ms, s.latency_p99_ms, s.latency_max_ms, s.loop_rate_hz, s.steps, s.phase
        );
        if s.latency_p99_ms.is_nan() || s.latency_p99_ms > p.max_latency_ms {
            return Err(format!("{summary}: p99 above {} ms", p.max_latency_ms));
        }
        Ok(summary)
    })();
    stop.store(true, Ordering::Relaxed);
    let _ = player.join();
    result
}
