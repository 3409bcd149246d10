//! rostest checks of a real robot's failure modes, against the controller alone (and the
//! estimator for the flood): the test node is the arm ([`Plant`]: an ideal position-
//! controlled arm that follows each command at once, publishing joint states and LBRState at
//! 500 Hz and a fixed trocar pose at 100 Hz, optionally owning `/clock`; the trocar's cannula
//! has the realistic world's seal ([`PlantSeal`]), whose friction the external torques carry,
//! so that a docking feels it as on the bench), and breaks it one way per check:
//!
//! - `blocked_arm`: the arm stops following mid-APPROACH. The command never leads the
//!   measured joints by more than `max_lead_deg`; HOLD `ARM_NOT_FOLLOWING` within
//!   `max_hold_delay_s` of the lead reaching a quarter of its bound (where the guard's
//!   not-following watch starts); the arm freed, nothing moves until
//!   `~start`, and the new start begins from the measured joints (no command step over
//!   `max_step_deg`).
//! - `clock_back`, `clock_forward`: the test node's `/clock` jumps 5 s back or forward:
//!   HOLD `CLOCK_BACK` / `CLOCK_FORWARD` within 1 s, the status keeps coming, nothing moves
//!   until `~start`, and it moves again after one.
//! - `driver_restart`: the driver goes silent for 1 s and comes back with its joint names
//!   in reverse order; then its stamps step back by 50 ms: each time HOLD `DRIVER_RESTART`,
//!   nothing moves until `~start`, and after it the commands start from the true joints
//!   (the names were mapped by name).
//! - `flood`: every input at `flood_factor` times its rate (joint states and LBRState 5 kHz,
//!   the trocar pose 1 kHz, camera frames 150 Hz to the estimator), every tenth joint state
//!   duplicated: no hold, DONE by the end of the flood (the tip's depth refined at the seal:
//!   the seal felt through the flood of torques and poses), the control loop's rate (its
//!   steps over its clock, over the flood) within `rate_tolerance`, the RSS of the
//!   controller and the estimator flat (`max_rss_growth_mb`), the estimator's poses fresh
//!   (it drops frames rather than queueing them).
//!
//! "Nothing moves" is judged once the hold has braked to rest (its command unchanged for
//! 50 ms): a hold brakes within the guard's acceleration limit, never at once from speed.
//! `blocked_arm`, the clock jumps and `driver_restart` also audit every command of the run,
//! holds and re-anchors included, against the guard's speed and acceleration limits
//! ([`crate::command_audit`]).

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Translation3, Vector3, Vector6};

use crate::camera_checks::camera_frame;
use crate::command_audit::TopicAudit;
use crate::common::{subscribe_latest, trigger, wait_for, wait_until_still, CheckParams, Latest};
use ::trocar_docking::control::safety::guard::LEAD_WATCH_FRACTION;
use ::trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use ::trocar_docking::kinematics::{JointVector, Kinematics, LbrKinematics};
use ::trocar_docking::ros::convert;
use ::trocar_docking::ros::convert::image as image_msgs;
use ::trocar_docking::ros::msgs::{
    geometry_msgs, lbr_msgs, rosgraph_msgs, sensor_msgs, trajectory_msgs, trocar_docking,
};
use ::trocar_docking::ros::node::lock;
use ::trocar_docking::ros::topics;
use ::trocar_docking::sim::seal::Seal;
use ::trocar_docking::trials::config::SimConfig;
use ::trocar_docking::vision::CameraModel;

/// The FRI rate the plant publishes at (times the flood factor), Hz.
const FRI_HZ: f64 = 500.0;
/// The trocar pose rate (times the flood factor), Hz.
const POSE_HZ: f64 = 100.0;
/// The camera rate (times the flood factor), Hz.
const CAMERA_HZ: f64 = 15.0;

/// How the played arm misbehaves now.
#[derive(Debug, Clone, Copy, Default)]
struct Mode {
    /// The arm stops following the commands.
    blocked: bool,
    /// The driver publishes nothing.
    silent: bool,
    /// Joint names (and positions) in reverse order.
    reversed: bool,
    /// Added to the clock (`/clock` and every stamp), s.
    clock_offset: f64,
    /// Added to the driver's stamps only, s.
    stamp_offset: f64,
}

/// What the plant saw of the commands.
#[derive(Debug, Clone, Default)]
struct Seen {
    /// Commands received.
    commands: u64,
    /// The newest command.
    last: Option<JointVector>,
    /// Largest |command - measured| on any joint since the last [`Plant::clear`], rad.
    max_lead: f64,
    /// The number of the first command since the last clear whose lead reached the
    /// not-following watch ([`LEAD_WATCH_FRACTION`] of the bound).
    saturated_seq: Option<u32>,
    /// The controller's step time of each command, by number (its stamped copy), newest
    /// last, at most [`STAMPS_KEPT`]; never cleared.
    stamps: VecDeque<(u32, f64)>,
    /// Largest step between consecutive commands since the last clear, rad.
    max_step: f64,
    /// Largest |command - measured| of the first command after the last clear, rad.
    first_lead: Option<f64>,
    /// Over the whole run (never cleared), holds and re-anchors included: every pair of
    /// consecutive commands against the guard's speed and acceleration limits.
    audit: TopicAudit,
}

impl Seen {
    /// Record a command `cmd`, message `seq`, against the `measured` joints and the lead
    /// bound (rad).
    fn record(&mut self, cmd: &JointVector, measured: &JointVector, seq: u32, lead_bound: f64) {
        let lead = (cmd - measured).amax();
        self.max_lead = self.max_lead.max(lead);
        // The guard's not-following watch runs from a quarter of the bound.
        if lead >= LEAD_WATCH_FRACTION * lead_bound && self.saturated_seq.is_none() {
            self.saturated_seq = Some(seq);
        }
        if let Some(prev) = self.last {
            self.max_step = self.max_step.max((cmd - prev).amax());
        }
        self.audit.command(seq, cmd);
        if self.first_lead.is_none() {
            self.first_lead = Some(lead);
        }
        self.last = Some(*cmd);
        self.commands += 1;
    }

    /// Record the stamped copy `q` of command `seq`, its step at `stamp` (s).
    fn copy(&mut self, seq: u32, stamp: f64, q: &JointVector) {
        self.audit.copy(seq, stamp, q);
        if self.stamps.len() == STAMPS_KEPT {
            self.stamps.pop_front();
        }
        self.stamps.push_back((seq, stamp));
    }

    /// The controller's step time of command `seq`, if its copy came.
    fn stamp_of(&self, seq: u32) -> Option<f64> {
        self.stamps.iter().find(|(s, _)| *s == seq).map(|(_, t)| *t)
    }
}

/// Command step times kept: 20 s at 100 Hz.
const STAMPS_KEPT: usize = 2000;

/// The played arm: state shared with its publishing thread and the command subscriber.
struct Plant {
    mode: Arc<Mutex<Mode>>,
    q: Arc<Mutex<JointVector>>,
    seen: Arc<Mutex<Seen>>,
    lead_bound: f64,
    stop: Arc<AtomicBool>,
    threads: [Option<std::thread::JoinHandle<()>>; 2],
    _subs: [rosrust::Subscriber; 2],
}

/// The publishers of the plant's thread.
struct Pubs {
    js: rosrust::Publisher<sensor_msgs::JointState>,
    lbr: rosrust::Publisher<lbr_msgs::LBRState>,
    pose: rosrust::Publisher<geometry_msgs::PoseStamped>,
    clock: Option<rosrust::Publisher<rosgraph_msgs::Clock>>,
}

/// The played camera: its publishers, model and frame.
struct Camera {
    img: rosrust::Publisher<sensor_msgs::Image>,
    info: rosrust::Publisher<sensor_msgs::CameraInfo>,
    model: CameraModel,
    frame: Vec<u8>,
}

/// The camera's thread (wall-clock stamps): frames at `hz` until `stop`.
fn play_camera(c: &Camera, hz: f64, stop: &AtomicBool) {
    let period = Duration::from_secs_f64(1.0 / hz);
    let mut next = Instant::now();
    while rosrust::is_ok() && !stop.load(Ordering::Relaxed) {
        let s = rosrust::now();
        let _ = c
            .info
            .send(image_msgs::camera_info(s, "camera_optical_frame", &c.model));
        let _ = c.img.send(image_msgs::image(
            s,
            "camera_optical_frame",
            c.model.width,
            c.model.height,
            "mono8",
            1,
            c.frame.clone(),
        ));
        next += period;
        if let Some(wait) = next.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
    }
}

/// The cannula's seal on the played arm's shaft: the realistic world's seal (config/sim.yaml,
/// `protocols.realistic.sim.seal`; the stick-slip model of `src/sim/seal.rs`) at its depth
/// below the fixed trocar's port, stepped once for each new joint position (the ideal arm
/// moves in its commands' steps). The shaft feels the seal's friction along the trocar's axis,
/// through the tip's line (no moment): the external torques J^T [f; 0], as the simulated
/// world reports them (`SimWorld::external_torques`).
struct PlantSeal {
    seal: Seal,
    depth_m: f64,
    kin: LbrKinematics,
    trocar: Isometry3<f64>,
    /// The joints the seal last saw, the tip's depth there and when.
    last: Option<(JointVector, f64, Instant)>,
    tau: JointVector,
}

impl PlantSeal {
    fn new(trocar: &Isometry3<f64>) -> Result<Self, String> {
        let world = SimConfig::load_default()
            .and_then(|c| c.with_protocol("realistic"))
            .map_err(|e| e.to_string())?;
        let params = world.sim.seal;
        Ok(Self {
            seal: Seal::new(&params).map_err(|e| e.to_string())?,
            depth_m: params.depth_m,
            kin: LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).map_err(|e| e.to_string())?,
            trocar: *trocar,
            last: None,
            tau: JointVector::zeros(),
        })
    }

    /// The external torques with the arm at `q`.
    fn torques(&mut self, q: &JointVector) -> JointVector {
        if self.last.as_ref().is_some_and(|(q0, ..)| q0 == q) {
            return self.tau;
        }
        let Ok((tip, jac)) = self.kin.fk_jacobian(q) else {
            return self.tau;
        };
        let axis = self.trocar.rotation * Vector3::z();
        let depth = (tip.translation.vector - self.trocar.translation.vector).dot(&axis);
        let now = Instant::now();
        // The force on the trocar along its axis (the shaft feels its opposite).
        let f = match self.last {
            Some((_, before, then)) if depth > self.depth_m => {
                let h = now.duration_since(then).as_secs_f64().max(1e-4);
                self.seal.step_axial((depth - before.max(self.depth_m)) / h, h)
            }
            _ => {
                self.seal.release();
                0.0
            }
        };
        self.last = Some((*q, depth, now));
        let on_shaft = -f * axis;
        self.tau = jac.transpose() * Vector6::new(on_shaft.x, on_shaft.y, on_shaft.z, 0.0, 0.0, 0.0);
        self.tau
    }
}

/// The plant's start pose.
fn q_start() -> JointVector {
    JointVector::from_column_slice(&[0.0, 0.6, 0.0, -1.2, 0.0, 0.9, 0.0])
}

/// A trocar 12 cm ahead of the tip on its optical axis (the camera frame's trocar).
fn trocar_ahead(q: &JointVector) -> Result<Isometry3<f64>, String> {
    let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).map_err(|e| e.to_string())?;
    let tip = kin.fk(q).map_err(|e| e.to_string())?;
    Ok(Isometry3::from_parts(
        Translation3::from(tip.translation.vector + tip.rotation * Vector3::new(0.0, 0.0, 0.12)),
        tip.rotation,
    ))
}

impl Plant {
    /// Start the plant: `flood` times the nominal rates, `sim_clock` to own `/clock`,
    /// `camera` to play the camera too.
    fn start(p: &CheckParams, flood: f64, sim_clock: bool, camera: bool) -> Result<Self, String> {
        let e = |e: rosrust::error::Error| e.to_string();
        let q0 = q_start();
        let trocar = trocar_ahead(&q0)?;
        let camera = if camera {
            // Sent on the rectified topic (topics::CAMERA_IMAGE): the calibration's rectified
            // camera (P, no distortion), as a ZED publishes it.
            let model = CameraModel::from_yaml_file(std::path::Path::new(&p.camera_calibration))
                .map_err(|e| format!("camera_calibration: {e}"))?
                .rectified();
            let frame = camera_frame(&model, &q0)?;
            Some(Camera {
                img: rosrust::publish(topics::CAMERA_IMAGE, 1).map_err(e)?,
                info: rosrust::publish(topics::CAMERA_INFO, 1).map_err(e)?,
                model,
                frame,
            })
        } else {
            None
        };
        let pubs = Pubs {
            js: rosrust::publish(topics::JOINT_STATES, 100).map_err(e)?,
            lbr: rosrust::publish(topics::LBR_STATE, 100).map_err(e)?,
            pose: rosrust::publish(topics::TROCAR_POSE, 100).map_err(e)?,
            clock: if sim_clock {
                Some(rosrust::publish(topics::CLOCK, 10).map_err(e)?)
            } else {
                None
            },
        };
        let mode = Arc::new(Mutex::new(Mode::default()));
        let q = Arc::new(Mutex::new(q0));
        let seen = Arc::new(Mutex::new(Seen::default()));
        let lead_bound = p.max_lead_deg.to_radians();
        let sub = {
            let (q, seen, mode) = (q.clone(), seen.clone(), mode.clone());
            let names = ::trocar_docking::kinematics::joint_names();
            let topic = p.command_topic.clone();
            rosrust::subscribe(&p.command_topic, 100, move |m: trajectory_msgs::JointTrajectory| {
                let Ok(cmd) = convert::trajectory_positions(&topic, &m, &names) else {
                    return;
                };
                let measured = *lock(&q);
                lock(&seen).record(&cmd, &measured, m.header.seq, lead_bound);
                if !lock(&mode).blocked {
                    // An ideal position-controlled arm: it is where it was commanded.
                    *lock(&q) = cmd;
                }
            })
            .map_err(e)?
        };
        let copies = {
            let seen = seen.clone();
            let names = ::trocar_docking::kinematics::joint_names();
            rosrust::subscribe(&p.command_joints_topic, 1000, move |m: sensor_msgs::JointState| {
                if let Ok(q) = convert::joint_positions("command copy", &m, &names) {
                    lock(&seen).copy(m.header.seq, convert::seconds(m.header.stamp), &q);
                }
            })
            .map_err(e)?
        };
        let stop = Arc::new(AtomicBool::new(false));
        let mut seal = PlantSeal::new(&trocar)?;
        let thread = {
            let (mode, q, stop) = (mode.clone(), q.clone(), stop.clone());
            std::thread::spawn(move || play(&pubs, &mode, &q, (&trocar, &mut seal), flood, &stop))
        };
        let camera = camera.map(|c| {
            let stop = stop.clone();
            std::thread::spawn(move || play_camera(&c, CAMERA_HZ * flood, &stop))
        });
        Ok(Self {
            mode,
            q,
            seen,
            lead_bound,
            stop,
            threads: [Some(thread), camera],
            _subs: [sub, copies],
        })
    }

    fn set(&self, f: impl FnOnce(&mut Mode)) {
        f(&mut lock(&self.mode));
    }

    fn seen(&self) -> Seen {
        lock(&self.seen).clone()
    }

    /// Forget the lead, step and first-command records (the last command stays).
    fn clear(&self) {
        let mut s = lock(&self.seen);
        *s = Seen {
            commands: s.commands,
            last: s.last,
            audit: s.audit.clone(),
            stamps: std::mem::take(&mut s.stamps),
            ..Seen::default()
        };
    }

    fn measured(&self) -> JointVector {
        *lock(&self.q)
    }
}

impl Drop for Plant {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.iter_mut().filter_map(Option::take) {
            let _ = t.join();
        }
    }
}

/// The plant's thread: publish at `flood` times the nominal rates until `stop`, paced on
/// the wall clock (its own `/clock`, when it owns it, may jump).
fn play(
    pubs: &Pubs,
    mode: &Mutex<Mode>,
    q: &Mutex<JointVector>,
    (trocar, seal): (&Isometry3<f64>, &mut PlantSeal),
    flood: f64,
    stop: &AtomicBool,
) {
    let names = ::trocar_docking::kinematics::joint_names();
    let mut reversed_names = names.clone();
    reversed_names.reverse();
    let zeros = JointVector::zeros();
    let rate = FRI_HZ * flood;
    let period = Duration::from_secs_f64(1.0 / rate);
    let every = |hz: f64| ((rate / (hz * flood)).round() as u64).max(1);
    let pose_every = every(POSE_HZ);
    let wall0 = Instant::now();
    let t0 = convert::seconds(rosrust::Time::from(std::time::SystemTime::now()));
    let mut k = 0u64;
    let mut next = Instant::now();
    while rosrust::is_ok() && !stop.load(Ordering::Relaxed) {
        let m = *lock(mode);
        let t = t0 + wall0.elapsed().as_secs_f64() + m.clock_offset;
        if let Some(c) = &pubs.clock {
            let _ = c.send(rosgraph_msgs::Clock {
                clock: convert::ros_time(t),
            });
        }
        let stamp = convert::ros_time(t + m.stamp_offset);
        if !m.silent {
            let qm = *lock(q);
            let tau_ext = seal.torques(&qm);
            let mut js = convert::joint_state(stamp, &names, &qm, &zeros);
            if m.reversed {
                js.name.clone_from(&reversed_names);
                js.position.reverse();
                js.effort.reverse();
            }
            // Every tenth message twice in a flood: duplicates.
            let copies = if flood > 1.0 && k.is_multiple_of(10) { 2 } else { 1 };
            for _ in 0..copies {
                let _ = pubs.js.send(js.clone());
            }
            let _ = pubs
                .lbr
                .send(convert::lbr_state(stamp, 1.0 / rate, &qm, &zeros, &tau_ext));
        }
        if k.is_multiple_of(pose_every) {
            let _ = pubs
                .pose
                .send(convert::pose_stamped(convert::ros_time(t), topics_base(), trocar));
        }
        k += 1;
        next += period;
        let now = Instant::now();
        if next > now {
            std::thread::sleep(next - now);
        } else if now - next > period * 10 {
            next = now;
        }
    }
}

/// The robot's base frame.
fn topics_base() -> &'static str {
    ::trocar_docking::kinematics::BASE_LINK
}

/// The status, waited for until `f` accepts it (wall clock), or why not.
fn wait_status(
    status: &Latest<trocar_docking::DockingStatus>,
    timeout: f64,
    what: &str,
    f: impl Fn(&trocar_docking::DockingStatus) -> bool,
) -> Result<trocar_docking::DockingStatus, String> {
    wait_for(timeout, || status.get().filter(|s| f(s))).ok_or_else(|| {
        let s = status.get().unwrap_or_default();
        format!(
            "{what}: not within {timeout} s (phase {}, code '{}', reason '{}')",
            s.phase, s.hold_code, s.hold_reason
        )
    })
}

fn moving(s: &trocar_docking::DockingStatus) -> bool {
    s.phase == "APPROACH" || s.phase == "INSERT"
}

/// Start the controller and wait until it moves; the status subscription.
fn start_moving(p: &CheckParams) -> Result<(Latest<trocar_docking::DockingStatus>, rosrust::Subscriber), String> {
    let (status, sub) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    wait_for(p.startup_timeout, || status.get()).ok_or("no status from the controller")?;
    trigger(&format!("{}/start", p.controller), p.startup_timeout)?;
    wait_status(&status, 5.0, "moving after ~start", moving)?;
    std::thread::sleep(Duration::from_millis(300));
    Ok((status, sub))
}

/// After a hold: nothing moves for `observe` s (the status keeps coming); then `~start`
/// moves it again, from the measured joints. A summary.
fn no_motion_until_start(
    p: &CheckParams,
    plant: &Plant,
    status: &Latest<trocar_docking::DockingStatus>,
    code: &str,
) -> Result<String, String> {
    // The hold's braking (its commands are audited against the guard's limits) first.
    wait_until_still(1.0, || plant.seen().last);
    let before = (plant.seen().last, status.count());
    plant.clear();
    std::thread::sleep(Duration::from_secs_f64(p.hold_observe));
    let s = status.get().ok_or("no status")?;
    let seen = plant.seen();
    let moved = match (before.0, seen.last) {
        (Some(a), Some(b)) => (b - a).amax(),
        _ => 0.0,
    };
    if s.phase != "HOLD" || s.hold_code != code {
        return Err(format!(
            "{code}: before any ~start the phase became {} ('{}', '{}')",
            s.phase, s.hold_code, s.hold_reason
        ));
    }
    if moved > 1e-9 {
        return Err(format!(
            "{code}: the command moved {:.4} deg while held, before any ~start",
            moved.to_degrees()
        ));
    }
    let statuses = status.count() - before.1;
    if (statuses as f64) < 0.5 * p.hold_observe * p.control_rate_hz {
        return Err(format!(
            "{code}: only {statuses} statuses in {} s: the loop froze",
            p.hold_observe
        ));
    }
    plant.clear();
    let measured = plant.measured();
    trigger(&format!("{}/start", p.controller), p.startup_timeout)?;
    wait_status(status, 5.0, &format!("{code}: moving after ~start"), moving)?;
    let start_commands = plant.seen().commands;
    wait_for(3.0, || (plant.seen().commands > start_commands + 20).then_some(()))
        .ok_or_else(|| format!("{code}: no commands after ~start"))?;
    let after = plant.seen();
    let first = after.first_lead.unwrap_or(f64::NAN);
    if first.is_nan() || first > plant.lead_bound + 1e-6 || after.max_step > p.max_step_deg.to_radians() {
        return Err(format!(
            "{code}: the new start jumped: first command {:.3} deg from the measured joints, largest step {:.3} deg",
            first.to_degrees(),
            after.max_step.to_degrees()
        ));
    }
    let moved = after.last.map_or(0.0, |c| (c - measured).amax());
    Ok(format!(
        "HOLD {code} ('{}'), {statuses} statuses and no motion in {} s; after ~start: first command {:.3} deg from the arm, steps <= {:.3} deg, {:.2} deg moved",
        s.hold_reason,
        p.hold_observe,
        first.to_degrees(),
        after.max_step.to_degrees(),
        moved.to_degrees()
    ))
}

/// The `blocked_arm` check.
pub fn blocked_arm(p: &CheckParams) -> Result<String, String> {
    let plant = Plant::start(p, 1.0, false, false)?;
    let (status, _sub) = start_moving(p)?;
    // The first HOLD's step time, from every status (the latest one may be steps later).
    let first_hold = Arc::new(Mutex::new(None));
    let _holds = {
        let first_hold = first_hold.clone();
        rosrust::subscribe(&p.status_topic, 1000, move |s: trocar_docking::DockingStatus| {
            let mut h = lock(&first_hold);
            if s.phase == "HOLD" && h.is_none() {
                *h = Some(convert::seconds(s.header.stamp));
            }
        })
        .map_err(|e| e.to_string())?
    };
    plant.clear();
    plant.set(|m| m.blocked = true);
    let blocked_at = Instant::now();
    let held = wait_status(&status, 5.0, "HOLD ARM_NOT_FOLLOWING on a blocked arm", |s| {
        s.phase == "HOLD"
    })
    .map_err(|e| format!("{e}; the command led by {:.2} deg", plant.seen().max_lead.to_degrees()))?;
    let held_after = blocked_at.elapsed().as_secs_f64();
    std::thread::sleep(Duration::from_millis(200));
    let seen = plant.seen();
    if held.hold_code != "ARM_NOT_FOLLOWING" {
        return Err(format!(
            "the blocked arm held with '{}' ({}), not ARM_NOT_FOLLOWING; the command led by {:.2} deg",
            held.hold_code,
            held.hold_reason,
            seen.max_lead.to_degrees()
        ));
    }
    if seen.max_lead > plant.lead_bound + 0.05f64.to_radians() {
        return Err(format!(
            "the command led the blocked arm by {:.2} deg (bound {} deg)",
            seen.max_lead.to_degrees(),
            p.max_lead_deg
        ));
    }
    let Some(led) = seen.saturated_seq else {
        return Err("HOLD, but the command never led the blocked arm by a quarter of its bound".into());
    };
    // Both ends on the controller's clock (the step of the command, the step of the hold),
    // as the guard times its watch: a host that delays the plant's or this node's threads
    // does not move them.
    let led_at = seen
        .stamp_of(led)
        .ok_or_else(|| format!("no stamped copy of command {led}, the first to lead by a quarter of the bound"))?;
    let hold_at = (*lock(&first_hold)).ok_or("HOLD seen, but no HOLD status recorded")?;
    let delay = hold_at - led_at;
    if delay > p.max_hold_delay_s {
        return Err(format!(
            "HOLD {delay:.3} s after the command led by a quarter of its bound (bound {} s, the controller's clock)",
            p.max_hold_delay_s
        ));
    }
    // The arm frees itself: it is at the held command, and nothing moves until ~start.
    plant.set(|m| m.blocked = false);
    let rest = no_motion_until_start(p, &plant, &status, "ARM_NOT_FOLLOWING")?;
    let speed = plant.seen().audit.verdict("ARM_NOT_FOLLOWING")?;
    Ok(format!(
        "lead at most {:.3} deg; HOLD seen {held_after:.3} s after blocking (wall clock), {delay:.3} s after the lead reached a quarter of its bound (the controller's clock); {rest}; {speed}",
        seen.max_lead.to_degrees(),
    ))
}

/// The `clock_back` and `clock_forward` checks: the plant's `/clock` jumps by `jump` s.
pub fn clock_jump(p: &CheckParams, jump: f64) -> Result<String, String> {
    let plant = Plant::start(p, 1.0, true, false)?;
    let (status, _sub) = start_moving(p)?;
    let code = if jump < 0.0 { "CLOCK_BACK" } else { "CLOCK_FORWARD" };
    // The clock jumps while the driver is quiet for a moment, so that the jump (and not
    // the driver's stamps jumping with it) is what the controller meets first.
    plant.set(|m| m.silent = true);
    std::thread::sleep(Duration::from_millis(20));
    plant.set(|m| m.clock_offset += jump);
    std::thread::sleep(Duration::from_millis(30));
    plant.set(|m| m.silent = false);
    let jumped_at = Instant::now();
    let held = wait_status(&status, 1.0, &format!("HOLD {code}"), |s| {
        s.phase == "HOLD" && s.hold_code == code
    })?;
    let delay = jumped_at.elapsed().as_secs_f64();
    let rest = no_motion_until_start(p, &plant, &status, code)?;
    let speed = plant.seen().audit.verdict(code)?;
    Ok(format!(
        "clock {jump:+} s: {} within {delay:.2} s; {rest}; {speed}",
        held.hold_code
    ))
}

/// The `driver_restart` check.
pub fn driver_restart(p: &CheckParams) -> Result<String, String> {
    let plant = Plant::start(p, 1.0, false, false)?;
    let (status, _sub) = start_moving(p)?;
    let mut seen = Vec::new();
    for (what, restart) in [
        ("silent 1 s, names reversed", (1.0, true, 0.0)),
        ("stamps 50 ms back", (0.0, true, -0.05)),
    ] {
        let (silence, reversed, back) = restart;
        plant.set(|m| m.silent = silence > 0.0);
        std::thread::sleep(Duration::from_secs_f64(silence));
        plant.set(|m| {
            m.silent = false;
            m.reversed = reversed;
            m.stamp_offset += back;
        });
        wait_status(&status, 2.0, &format!("{what}: HOLD DRIVER_RESTART"), |s| {
            s.phase == "HOLD" && s.hold_code == "DRIVER_RESTART"
        })?;
        let rest = no_motion_until_start(p, &plant, &status, "DRIVER_RESTART")?;
        seen.push(format!("{what}: {rest}"));
        std::thread::sleep(Duration::from_millis(300));
    }
    seen.push(plant.seen().audit.verdict("DRIVER_RESTART")?);
    Ok(seen.join(" | "))
}

/// The RSS of the process running the node `name` (found by its `__name:=` argument), kB.
fn node_rss_kb(name: &str) -> Option<u64> {
    let arg = format!("__name:={name}");
    std::fs::read_dir("/proc").ok()?.flatten().find_map(|d| {
        let cmd = std::fs::read(d.path().join("cmdline")).ok()?;
        cmd.split(|b| *b == 0).any(|a| a == arg.as_bytes()).then_some(())?;
        let status = std::fs::read_to_string(d.path().join("status")).ok()?;
        status
            .lines()
            .find(|l| l.starts_with("VmRSS:"))?
            .split_whitespace()
            .nth(1)?
            .parse()
            .ok()
    })
}

/// The `flood` check.
pub fn flood(p: &CheckParams) -> Result<String, String> {
    // The estimator's poses: how many, and the oldest at its arrival (a queueing estimator
    // would publish ever older poses).
    let poses = Arc::new(Mutex::new((0u64, 0.0f64)));
    let _pose_sub = {
        let poses = poses.clone();
        rosrust::subscribe(&p.pose_topic, 100, move |m: geometry_msgs::PoseStamped| {
            let age = convert::seconds(rosrust::now()) - convert::seconds(m.header.stamp);
            let mut g = lock(&poses);
            g.0 += 1;
            g.1 = g.1.max(age);
        })
        .map_err(|e| e.to_string())?
    };
    let plant = Plant::start(p, p.flood_factor, false, true)?;
    let (status, _sub) = start_moving(p)?;
    let warm = Duration::from_secs(3);
    let t0 = Instant::now();
    std::thread::sleep(warm);
    let rss0 = [node_rss_kb("docking_controller"), node_rss_kb("trocar_estimator")];
    let (mut rate_min, mut rate_max, mut last_status) = (f64::INFINITY, 0.0f64, 0);
    let first = status.get().ok_or("no status")?;
    *lock(&poses) = (0, 0.0);
    while t0.elapsed().as_secs_f64() < p.hold_observe {
        std::thread::sleep(Duration::from_millis(100));
        let s = status.get().ok_or("no status")?;
        if status.count() == last_status {
            return Err("the status stopped".into());
        }
        last_status = status.count();
        if s.phase == "HOLD" || s.phase == "ABORTED" || s.phase == "IDLE" || !s.hold_code.is_empty() {
            return Err(format!(
                "flooded: phase {} code '{}' ({})",
                s.phase, s.hold_code, s.hold_reason
            ));
        }
        rate_min = rate_min.min(s.loop_rate_hz);
        rate_max = rate_max.max(s.loop_rate_hz);
    }
    let last = status.get().ok_or("no status")?;
    // The loop's rate over the whole flood: its steps over its clock (the status's 1 s
    // windows, min and max above, move by a tick where a late tick is caught up).
    let span = convert::seconds(last.header.stamp) - convert::seconds(first.header.stamp);
    let rate = (last.steps - first.steps) as f64 / span;
    let rss1 = [node_rss_kb("docking_controller"), node_rss_kb("trocar_estimator")];
    let (poses, max_age) = *lock(&poses);
    let tol = p.rate_tolerance * p.control_rate_hz;
    let growth: Vec<f64> = rss0
        .iter()
        .zip(&rss1)
        .map(|(a, b)| match (a, b) {
            (Some(a), Some(b)) => (*b as f64 - *a as f64) / 1024.0,
            _ => f64::NAN,
        })
        .collect();
    let summary = format!(
        "x{} flood: loop rate {rate:.2} Hz over {span:.1} s (1 s windows {rate_min:.1}-{rate_max:.1} Hz), RSS growth controller {:.2} MB, estimator {:.2} MB over {:.0} s, {poses} estimator poses, each at most {:.0} ms old on arrival, {} commands",
        p.flood_factor,
        growth[0],
        growth[1],
        p.hold_observe - warm.as_secs_f64(),
        max_age * 1e3,
        plant.seen().commands
    );
    if rate.is_nan() || (rate - p.control_rate_hz).abs() > tol {
        return Err(format!(
            "{summary}: the loop rate left {} Hz +- {tol}",
            p.control_rate_hz
        ));
    }
    if !growth.iter().all(|g| *g <= p.max_rss_growth_mb) {
        return Err(format!("{summary}: memory grew (bound {} MB)", p.max_rss_growth_mb));
    }
    if poses == 0 || max_age > 0.25 {
        return Err(format!("{summary}: the estimator queued (or dropped every) frame"));
    }
    // Docked through the flood: DONE plainly (no hold above), the depth refined at the seal.
    if last.phase != "DONE" {
        return Err(format!(
            "{summary}: not DONE by the end of the flood (phase {}, tip {:.1} mm from the goal)",
            last.phase,
            last.tip_to_goal * 1e3
        ));
    }
    Ok(format!("{summary}, DONE"))
}
