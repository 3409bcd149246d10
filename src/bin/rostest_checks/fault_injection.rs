//! The `bad_input` rostest check: the test node plays the driver and the camera (joint
//! states, LBRState, trocar pose at 100 Hz, all valid; an ideal arm that is where it was
//! last commanded, so that no fault but the injected one holds), starts the controller, then breaks
//! one input at a time (wrong joint names, NaN, a short torque vector, a wrong frame, a
//! stamp that goes back, a driver that stops) and asserts that the controller holds with a
//! reason naming the fault (its `hold_code`, and the text naming what was wrong), keeps
//! publishing its status (it did not crash) and does not move: over `hold_observe` after the
//! hold, neither the arm (the joints the driver reports) nor the command moves more than
//! `max_hold_motion_deg` on any joint.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use nalgebra::{Isometry3, Translation3, Vector3};

use crate::common::{subscribe_latest, trigger, wait_for, wait_until_still, CheckParams};
use ::trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use ::trocar_docking::kinematics::{JointVector, Kinematics, LbrKinematics};
use ::trocar_docking::ros::convert;
use ::trocar_docking::ros::msgs::{geometry_msgs, lbr_msgs, sensor_msgs, trajectory_msgs, trocar_docking};
use ::trocar_docking::ros::node::lock;
use ::trocar_docking::ros::topics;

/// One way to break the inputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fault {
    None,
    WrongJointNames,
    NanJoint,
    ShortTorques,
    WrongFrame,
    StampBack,
    DriverStops,
}

impl Fault {
    /// The hold code the status must carry (`hold_code`).
    fn expected(self) -> &'static str {
        match self {
            Fault::WrongJointNames | Fault::NanJoint | Fault::ShortTorques | Fault::WrongFrame | Fault::StampBack => {
                "INPUT_REJECTED"
            }
            Fault::DriverStops => "STALE_JOINT_STATE",
            Fault::None => "",
        }
    }

    /// What the hold's text must say: the input that was wrong, and how.
    fn named_in_reason(self) -> &'static [&'static str] {
        match self {
            Fault::WrongJointNames => &["/lbr/joint_states", "missing"],
            Fault::NanJoint => &["/lbr/joint_states", "not finite"],
            Fault::ShortTorques => &["/lbr/states", "external_torque has 6 values"],
            Fault::WrongFrame => &["/trocar/pose", "frame 'world'"],
            Fault::StampBack => &["/trocar/pose", "is not after the previous"],
            Fault::DriverStops => &["joint state stale"],
            Fault::None => &[],
        }
    }
}

/// The largest joint difference, rad, of two optional joint vectors (infinite when one is
/// missing).
fn joint_gap(a: Option<JointVector>, b: Option<JointVector>) -> f64 {
    match (a, b) {
        (Some(a), Some(b)) => (a - b).amax(),
        _ => f64::INFINITY,
    }
}

/// The fake driver's thread, its command subscription, and the joints it reports.
struct Driver {
    thread: std::thread::JoinHandle<()>,
    _commands: rosrust::Subscriber,
    arm: Arc<Mutex<JointVector>>,
}

/// Publish the fake driver and camera until `stop`, applying the current fault; the arm
/// follows the commands on `command_topic`.
fn play_driver(
    q0: JointVector,
    trocar: Isometry3<f64>,
    command_topic: &str,
    fault: Arc<Mutex<Fault>>,
    stop: Arc<AtomicBool>,
) -> Result<Driver, String> {
    let js = rosrust::publish::<sensor_msgs::JointState>(topics::JOINT_STATES, 10).map_err(|e| e.to_string())?;
    let lbr = rosrust::publish::<lbr_msgs::LBRState>(topics::LBR_STATE, 10).map_err(|e| e.to_string())?;
    let pose = rosrust::publish::<geometry_msgs::PoseStamped>(topics::TROCAR_POSE, 10).map_err(|e| e.to_string())?;
    let names: Vec<String> = ::trocar_docking::kinematics::joint_names();
    let q = Arc::new(Mutex::new(q0));
    let arm = q.clone();
    let sub = {
        let (q, names, topic) = (q.clone(), names.clone(), command_topic.to_string());
        rosrust::subscribe(command_topic, 10, move |m: trajectory_msgs::JointTrajectory| {
            if let Ok(cmd) = convert::trajectory_positions(&topic, &m, &names) {
                *lock(&q) = cmd;
            }
        })
        .map_err(|e| e.to_string())?
    };
    let thread = std::thread::spawn(move || {
        let rate = rosrust::rate(100.0);
        let zeros = JointVector::zeros();
        while rosrust::is_ok() && !stop.load(Ordering::Relaxed) {
            let f = fault.lock().map(|f| *f).unwrap_or(Fault::None);
            let now = rosrust::now();
            let q0 = *lock(&q);
            if f != Fault::DriverStops {
                let mut m = convert::joint_state(now, &names, &q0, &zeros);
                match f {
                    Fault::WrongJointNames => m.name = (1..=7).map(|i| format!("A{i}")).collect(),
                    Fault::NanJoint => m.position[2] = f64::NAN,
                    _ => {}
                }
                let _ = js.send(m);
                let mut s = convert::lbr_state(now, 0.01, &q0, &zeros, &zeros);
                if f == Fault::ShortTorques {
                    s.external_torque.pop();
                }
                let _ = lbr.send(s);
            }
            let (frame, stamp) = match f {
                Fault::WrongFrame => ("world", now),
                Fault::StampBack => ("lbr_link_0", convert::ros_time(convert::seconds(now) - 5.0)),
                _ => ("lbr_link_0", now),
            };
            let _ = pose.send(convert::pose_stamped(stamp, frame, &trocar));
            rate.sleep();
        }
    });
    Ok(Driver {
        thread,
        _commands: sub,
        arm,
    })
}

/// The hold's text names the input that was wrong, and how.
fn reason_names(f: Fault, reason: &str) -> Result<(), String> {
    let missing: Vec<_> = f.named_in_reason().iter().filter(|w| !reason.contains(*w)).collect();
    if missing.is_empty() {
        Ok(())
    } else {
        Err(format!("{f:?}: the reason '{reason}' does not say {missing:?}"))
    }
}

/// Over `hold_observe` after a hold for `f` has braked to rest (within the guard's
/// acceleration limit: [`wait_until_still`]), neither the arm (the joints the driver
/// reports) nor the command moves more than `max_hold_motion_deg`: the largest motion, rad.
fn held_still(
    p: &CheckParams,
    f: Fault,
    arm: &Arc<Mutex<JointVector>>,
    commanded: &dyn Fn() -> Option<JointVector>,
) -> Result<f64, String> {
    wait_until_still(1.0, commanded);
    let (arm_at, cmd_at) = (*lock(arm), commanded());
    let (mut arm_moved, mut cmd_moved) = (0.0_f64, 0.0_f64);
    let t0 = std::time::Instant::now();
    while t0.elapsed().as_secs_f64() < p.hold_observe {
        std::thread::sleep(Duration::from_millis(10));
        arm_moved = arm_moved.max((*lock(arm) - arm_at).amax());
        cmd_moved = cmd_moved.max(joint_gap(commanded(), cmd_at));
    }
    let bound = p.max_hold_motion_deg.to_radians();
    if arm_moved.is_nan() || arm_moved > bound || cmd_moved.is_nan() || cmd_moved > bound {
        return Err(format!(
            "{f:?}: held, but in {:.1} s the arm moved {:.4} deg and the command {:.4} deg (bound {} deg)",
            p.hold_observe,
            arm_moved.to_degrees(),
            cmd_moved.to_degrees(),
            p.max_hold_motion_deg
        ));
    }
    Ok(arm_moved.max(cmd_moved))
}

/// Run the check; a summary on success.
pub fn bad_input(p: &CheckParams) -> Result<String, String> {
    let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).map_err(|e| e.to_string())?;
    let q0 = JointVector::from_column_slice(&[0.3, 0.6, -0.2, -1.2, 0.4, 0.8, 0.1]);
    let tip = kin.fk(&q0).map_err(|e| e.to_string())?;
    // A trocar 8 cm ahead of the tip on its optical axis, axis along it.
    let trocar = Isometry3::from_parts(
        Translation3::from(tip.translation.vector + tip.rotation * Vector3::new(0.0, 0.0, 0.08)),
        tip.rotation,
    );
    let fault = Arc::new(Mutex::new(Fault::None));
    let stop = Arc::new(AtomicBool::new(false));
    let (status, _sub) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let (command, _sub_command) = subscribe_latest::<trajectory_msgs::JointTrajectory>(&p.command_topic)?;
    let names = ::trocar_docking::kinematics::joint_names();
    let commanded = || {
        command
            .get()
            .and_then(|m| convert::trajectory_positions("", &m, &names).ok())
    };
    let driver = play_driver(q0, trocar, &p.command_topic, fault.clone(), stop.clone())?;
    let result = (|| {
        wait_for(p.startup_timeout, || status.get()).ok_or("no status from the controller")?;
        let mut seen = Vec::new();
        let mut worst = 0.0_f64;
        for f in [
            Fault::WrongJointNames,
            Fault::NanJoint,
            Fault::ShortTorques,
            Fault::WrongFrame,
            Fault::StampBack,
            Fault::DriverStops,
        ] {
            // Clean inputs, re-arm, then break one.
            *fault.lock().map_err(|e| e.to_string())? = Fault::None;
            trigger(&format!("{}/reset", p.controller), p.startup_timeout)?;
            std::thread::sleep(Duration::from_millis(300));
            trigger(&format!("{}/start", p.controller), p.startup_timeout)?;
            std::thread::sleep(Duration::from_millis(300));
            // Break it only once the controller has tared and moves (on a loaded machine the
            // first joint state, or the end of the tare window, can come later than the
            // 300 ms): a fault during TARE keeps the arm still in TARE with the reason (the
            // supervisor's rule for a hold before the arm moves), not in HOLD.
            let started = status.count();
            wait_for(p.startup_timeout, || {
                status
                    .get()
                    .filter(|s| status.count() > started && (s.phase == "APPROACH" || s.phase == "INSERT"))
            })
            .ok_or_else(|| format!("{f:?}: the controller did not leave TARE on clean inputs after ~start"))?;
            *fault.lock().map_err(|e| e.to_string())? = f;
            let before = status.count();
            let held = wait_for(3.0, || {
                status
                    .get()
                    .filter(|s| s.phase == "HOLD" && s.hold_code == f.expected())
            })
            .ok_or_else(|| {
                let s = status.get().unwrap_or_default();
                format!(
                    "{f:?}: phase {} code '{}' reason '{}' (expected HOLD with code '{}')",
                    s.phase,
                    s.hold_code,
                    s.hold_reason,
                    f.expected()
                )
            })?;
            reason_names(f, &held.hold_reason)?;
            let moved = held_still(p, f, &driver.arm, &commanded)?;
            if status.count() <= before {
                return Err(format!("{f:?}: the controller stopped publishing its status"));
            }
            worst = worst.max(moved);
            seen.push(format!("{f:?}: {}", held.hold_reason));
        }
        Ok(format!(
            "{}; held still: arm and command moved at most {:.2e} deg",
            seen.join(" | "),
            worst.to_degrees()
        ))
    })();
    stop.store(true, Ordering::Relaxed);
    let _ = driver.thread.join();
    result
}
