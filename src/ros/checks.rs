//! The rostest checks: a test node (`rostest_checks <check>`) runs one of these against the
//! live graph and writes the JUnit XML rostest asks for (`--gtest_output=xml:PATH`). Each
//! check waits with a bounded timeout, so a broken graph fails the test instead of hanging.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::convert;
use super::junit::TestReport;
use super::msgs::{lbr_msgs, std_srvs, trajectory_msgs, trocar_docking};
use super::params;
use crate::kinematics::JointVector;

/// Settings of the test node (private parameters), every bound a parameter.
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CheckParams {
    /// The controller node's name (its services are `<name>/start` etc.).
    pub controller: String,
    /// Status topic.
    pub status_topic: String,
    /// Command topic (JointTrajectory).
    pub command_topic: String,
    /// Wall-clock limit for the whole docking, s.
    pub time_limit: f64,
    /// Upper bound on M (N) for a successful docking.
    pub max_metric_m: f64,
    /// Wall time to wait for the graph (services, first messages), s.
    pub startup_timeout: f64,
    /// Whether the check calls `~start` itself.
    pub call_start: bool,
    /// For `stale_hold`: the hold reason must contain this text.
    pub hold_reason_contains: String,
    /// For `docking`: the status reason at DONE must contain this text ('' = anything).
    pub done_reason_contains: String,
    /// For `stale_hold`: how long the command must stay still once held, s.
    pub hold_observe: f64,
    /// For `replay`: the minimum number of status messages expected.
    pub min_status: usize,
    /// For `replay`: the phases the controller may report.
    pub allowed_phases: Vec<String>,
    /// For `replay`: the estimated trocar pose topic.
    pub pose_topic: String,
    /// For `replay`: the recorded true trocar pose topic.
    pub true_pose_topic: String,
    /// For `replay`: the largest accepted distance between estimate and truth, m.
    pub max_position_error: f64,
    /// `replay`: trocar poses the check must see before it judges.
    pub min_poses: usize,
    /// `replay`: a HOLD whose reason contains this is accepted too ('' = none is), e.g. the
    /// tracking hold when a bag's arm does not follow the live commands.
    pub allowed_hold_reason: String,
    /// `latency`: the camera calibration YAML of the played camera.
    pub camera_calibration: String,
    /// `latency`: the played camera's rate, Hz.
    pub camera_rate_hz: f64,
    /// `latency`: the largest accepted 99th percentile of image -> command, ms.
    pub max_latency_ms: f64,
    /// `latency`: the largest accepted median of image -> command, ms.
    pub max_latency_p50_ms: f64,
}

impl Default for CheckParams {
    fn default() -> Self {
        Self {
            controller: "/docking_controller".into(),
            status_topic: "/docking/status".into(),
            command_topic: "/lbr/PositionJointInterface_trajectory_controller/command".into(),
            time_limit: 60.0,
            max_metric_m: 10.0,
            startup_timeout: 30.0,
            call_start: true,
            hold_reason_contains: "trocar".into(),
            done_reason_contains: String::new(),
            hold_observe: 1.0,
            min_status: 10,
            allowed_phases: vec!["HOLD".into(), "APPROACH".into(), "INSERT".into(), "DONE".into()],
            pose_topic: "/trocar/pose".into(),
            true_pose_topic: "/trocar/pose_true".into(),
            max_position_error: 0.01,
            min_poses: 1,
            allowed_hold_reason: String::new(),
            camera_calibration: String::new(),
            camera_rate_hz: 30.0,
            max_latency_ms: 10.0,
            max_latency_p50_ms: 10.0,
        }
    }
}

/// The newest message of a topic, shared between the subscriber thread and a reader.
#[derive(Debug)]
pub struct Latest<T> {
    slot: Arc<Mutex<(Option<T>, usize)>>,
}

impl<T> Clone for Latest<T> {
    fn clone(&self) -> Self {
        Self {
            slot: self.slot.clone(),
        }
    }
}

impl<T> Default for Latest<T> {
    fn default() -> Self {
        Self {
            slot: Arc::new(Mutex::new((None, 0))),
        }
    }
}

impl<T: Clone> Latest<T> {
    /// Store a message.
    pub fn put(&self, msg: T) {
        if let Ok(mut s) = self.slot.lock() {
            s.0 = Some(msg);
            s.1 += 1;
        }
    }
    /// The newest message, if any.
    pub fn get(&self) -> Option<T> {
        self.slot.lock().ok().and_then(|s| s.0.clone())
    }
    /// How many messages arrived.
    pub fn count(&self) -> usize {
        self.slot.lock().map(|s| s.1).unwrap_or(0)
    }
}

/// Subscribe `topic` into a [`Latest`].
pub fn subscribe_latest<T: rosrust::Message>(topic: &str) -> Result<(Latest<T>, rosrust::Subscriber), String> {
    let latest = Latest::default();
    let l = latest.clone();
    let sub = rosrust::subscribe(topic, 10, move |m: T| l.put(m)).map_err(|e| format!("subscribe {topic}: {e}"))?;
    Ok((latest, sub))
}

/// Poll `f` every 10 ms until it gives `Some` or `timeout` passes (wall clock).
pub fn wait_for<T, F: FnMut() -> Option<T>>(timeout: f64, mut f: F) -> Option<T> {
    let t0 = Instant::now();
    while t0.elapsed().as_secs_f64() < timeout && rosrust::is_ok() {
        if let Some(v) = f() {
            return Some(v);
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    None
}

/// Call a std_srvs/Trigger service, waiting for it to appear.
pub fn trigger(service: &str, timeout: f64) -> Result<String, String> {
    rosrust::wait_for_service(service, Some(Duration::from_secs_f64(timeout)))
        .map_err(|e| format!("service {service} did not appear: {e}"))?;
    let client = rosrust::client::<std_srvs::Trigger>(service).map_err(|e| format!("client {service}: {e}"))?;
    let res = client
        .req(&std_srvs::TriggerReq {})
        .map_err(|e| format!("{service}: {e}"))?
        .map_err(|e| format!("{service}: {e}"))?;
    if res.success {
        Ok(res.message)
    } else {
        Err(format!("{service} refused: {}", res.message))
    }
}

/// Publish a DockingStatus and an LBRState on `/rostest/{status,lbr}_out` and read them
/// back from `/rostest/{status,lbr}_back`, where a rospy relay (tests/nodes/genpy_relay)
/// republishes them with the genpy classes: message definitions, md5 sums and encodings
/// agree between rosrust and the Python tools.
pub fn roundtrip(p: &CheckParams) -> Result<(), String> {
    let (got, _sub) = subscribe_latest::<trocar_docking::DockingStatus>("/rostest/status_back")?;
    let (got_lbr, _sub2) = subscribe_latest::<lbr_msgs::LBRState>("/rostest/lbr_back")?;
    let publ =
        rosrust::publish::<trocar_docking::DockingStatus>("/rostest/status_out", 10).map_err(|e| e.to_string())?;
    let publ_lbr = rosrust::publish::<lbr_msgs::LBRState>("/rostest/lbr_out", 10).map_err(|e| e.to_string())?;
    let sent = trocar_docking::DockingStatus {
        phase: "INSERT".into(),
        hold_reason: "trocar pose stale (0.6 s)".into(),
        cost_axis: 1.5e-4,
        iterations: 3,
        metric_m: 2.25,
        f_ext: convert::vector_msg(&nalgebra::Vector3::new(0.5, -1.0, 2.0)),
        steps: 1234,
        ..Default::default()
    };
    let q = JointVector::from_fn(|i, _| i as f64 * 0.1);
    let sent_lbr = convert::lbr_state(convert::ros_time(5.0), 0.005, &q, &q, &q);
    let received = wait_for(p.startup_timeout, || {
        let _ = publ.send(sent.clone());
        let _ = publ_lbr.send(sent_lbr.clone());
        std::thread::sleep(Duration::from_millis(100));
        match (got.get(), got_lbr.get()) {
            (Some(a), Some(b)) => Some((a, b)),
            _ => None,
        }
    })
    .ok_or("no message came back through the master")?;
    let mut expected = sent;
    expected.header = received.0.header.clone(); // rosrust fills seq
    if received.0 != expected {
        return Err(format!("DockingStatus changed on the wire: {:?}", received.0));
    }
    if received.1 != sent_lbr {
        return Err(format!("LBRState changed on the wire: {:?}", received.1));
    }
    Ok(())
}

/// Start the controller (unless the launch does) and wait for DONE within the time limit;
/// M must stay under the bound, and the phase never ABORTED.
pub fn docking(p: &CheckParams) -> Result<String, String> {
    let (status, _sub) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let max_force = Arc::new(Mutex::new(0.0_f64));
    let _sub_force = {
        let m = max_force.clone();
        rosrust::subscribe(&p.status_topic, 100, move |s: trocar_docking::DockingStatus| {
            if let Ok(mut m) = m.lock() {
                if s.phase != "IDLE" && s.f_ext_norm.is_finite() {
                    *m = m.max(s.f_ext_norm);
                }
            }
        })
        .map_err(|e| e.to_string())?
    };
    wait_for(p.startup_timeout, || status.get()).ok_or("no status message")?;
    if p.call_start {
        trigger(&format!("{}/start", p.controller), p.startup_timeout)?;
    }
    let t0 = Instant::now();
    let done = wait_for(p.time_limit, || {
        status.get().filter(|s| s.phase == "DONE" || s.phase == "ABORTED")
    })
    .ok_or_else(|| {
        let s = status.get().unwrap_or_default();
        format!(
            "not DONE after {:.0} s: phase {} ({}), tip {:.1} mm from the goal",
            p.time_limit,
            s.phase,
            s.hold_reason,
            s.tip_to_goal * 1e3
        )
    })?;
    if done.phase != "DONE" {
        let fmax = max_force.lock().map(|m| *m).unwrap_or(f64::NAN);
        return Err(format!(
            "failure: ABORTED after {:.2} s: {} (M = {:.2} N, max force {:.2} N)",
            done.elapsed, done.hold_reason, done.metric_m, fmax
        ));
    }
    if done.metric_m.is_nan() || done.metric_m > p.max_metric_m {
        return Err(format!(
            "M = {:.2} N above the bound {:.2} N",
            done.metric_m, p.max_metric_m
        ));
    }
    if !done.hold_reason.contains(&p.done_reason_contains) {
        return Err(format!(
            "DONE, but its reason '{}' does not mention '{}'",
            done.hold_reason, p.done_reason_contains
        ));
    }
    let fmax = max_force.lock().map(|m| *m).unwrap_or(f64::NAN);
    // How DONE was reached, when not plainly at the goal (see `crate::seated`).
    let note = if done.hold_reason.is_empty() {
        String::new()
    } else {
        format!("; {}", done.hold_reason)
    };
    Ok(format!(
        "success: DONE in {:.2} s (ROS time; {:.1} s wall), M = {:.2} N (paper-code scale {:.2}), max force {:.2} N, \
         tip {:.1} mm from the goal, latency trocar->command p50 {:.2} / p99 {:.2} ms, loop {:.1} Hz, {} steps{}",
        done.elapsed,
        t0.elapsed().as_secs_f64(),
        done.metric_m,
        done.metric_m_paper_scale,
        fmax,
        done.tip_to_goal * 1e3,
        done.latency_p50_ms,
        done.latency_p99_ms,
        done.loop_rate_hz,
        done.steps,
        note
    ))
}

/// Start the controller, wait for HOLD with a reason containing the expected text (the
/// launch makes the trocar pose stop), then check that the command stays still.
pub fn stale_hold(p: &CheckParams) -> Result<String, String> {
    let (status, _sub) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let (command, _sub2) = subscribe_latest::<trajectory_msgs::JointTrajectory>(&p.command_topic)?;
    wait_for(p.startup_timeout, || status.get()).ok_or("no status message")?;
    if p.call_start {
        trigger(&format!("{}/start", p.controller), p.startup_timeout)?;
    }
    // A short hold right after start (no pose received yet) is not the hold under test:
    // first see the arm moving, then wait for the hold.
    wait_for(p.time_limit, || {
        status.get().filter(|s| s.phase == "APPROACH" || s.phase == "INSERT")
    })
    .ok_or_else(|| format!("never moved; last phase {}", status.get().unwrap_or_default().phase))?;
    let held = wait_for(p.time_limit, || status.get().filter(|s| s.phase == "HOLD"))
        .ok_or_else(|| format!("never held; last phase {}", status.get().unwrap_or_default().phase))?;
    if !held.hold_reason.contains(&p.hold_reason_contains) {
        return Err(format!(
            "hold reason '{}' does not mention '{}'",
            held.hold_reason, p.hold_reason_contains
        ));
    }
    let before = command
        .get()
        .and_then(|c| c.points.first().map(|pt| pt.positions.clone()));
    std::thread::sleep(Duration::from_secs_f64(p.hold_observe));
    let after = command
        .get()
        .and_then(|c| c.points.first().map(|pt| pt.positions.clone()));
    if let (Some(a), Some(b)) = (&before, &after) {
        let moved = a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
        if moved > 1e-9 {
            return Err(format!("the command moved {moved:.2e} rad while holding"));
        }
    }
    let s = status.get().unwrap_or_default();
    if s.phase != "HOLD" {
        return Err(format!("left HOLD on its own: phase {}", s.phase));
    }
    Ok(format!("HOLD: {}", held.hold_reason))
}

/// Recorded topics are replayed into the nodes: the controller must publish status in the
/// allowed phases, and the estimator a trocar pose within `max_position_error` of the
/// recorded truth.
pub fn replay(p: &CheckParams) -> Result<String, String> {
    use super::msgs::geometry_msgs::PoseStamped;
    let (status, _s1) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let (pose, _s2) = subscribe_latest::<PoseStamped>(&p.pose_topic)?;
    let (truth, _s3) = subscribe_latest::<PoseStamped>(&p.true_pose_topic)?;
    wait_for(p.time_limit, || {
        (status.count() >= p.min_status && pose.count() >= p.min_poses.max(1) && truth.count() > 0).then_some(())
    })
    .ok_or_else(|| {
        format!(
            "got {} status, {} estimated and {} true poses",
            status.count(),
            pose.count(),
            truth.count()
        )
    })?;
    let s = status.get().unwrap_or_default();
    let allowed_hold =
        !p.allowed_hold_reason.is_empty() && s.phase == "HOLD" && s.hold_reason.contains(&p.allowed_hold_reason);
    if !(p.allowed_phases.contains(&s.phase) || allowed_hold) {
        return Err(format!(
            "phase {} ({}) not among {:?}",
            s.phase, s.hold_reason, p.allowed_phases
        ));
    }
    let est = convert::pose("estimate", &pose.get().unwrap_or_default().pose).map_err(|e| e.to_string())?;
    let tru = convert::pose("truth", &truth.get().unwrap_or_default().pose).map_err(|e| e.to_string())?;
    let err = (est.translation.vector - tru.translation.vector).norm();
    if err.is_nan() || err > p.max_position_error {
        return Err(format!("trocar estimate {:.1} mm from the truth", err * 1e3));
    }
    Ok(format!(
        "{} status (phase {}), {} trocar estimates, {:.2} mm from the truth",
        status.count(),
        s.phase,
        pose.count(),
        err * 1e3
    ))
}

/// Append a line to `$ROS_HOME/rostest_summary.txt`, which scripts/run-rostest prints
/// (rostest keeps a test node's stdout in its logs only).
fn append_summary(line: &str) {
    use std::io::Write as _;
    let Some(home) = std::env::var_os("ROS_HOME") else {
        return;
    };
    let path = std::path::Path::new(&home).join("rostest_summary.txt");
    if let Ok(mut f) = std::fs::OpenOptions::new().create(true).append(true).open(path) {
        let _ = writeln!(f, "{line}");
    }
}

/// Run the check named `name`, write the JUnit XML to `out` if given; true if it passed.
pub fn run(name: &str, out: Option<&std::path::Path>) -> bool {
    let mut report = TestReport::new(&format!("trocar_docking_{name}"));
    let params = params::load_private::<CheckParams>();
    report.check(name, || {
        let p = params.map_err(|e| e.to_string())?;
        let summary = match name {
            "roundtrip" => roundtrip(&p).map(|()| "round trip ok".to_string()),
            "docking" => docking(&p),
            "stale_hold" => stale_hold(&p),
            "replay" => replay(&p),
            "bad_input" => super::fault_injection::bad_input(&p),
            "latency" => super::camera_checks::latency(&p),
            "bad_images" => super::camera_checks::bad_images(&p),
            other => Err(format!("unknown check {other}")),
        }?;
        rosrust::ros_info!("{name}: {summary}");
        println!("{name}: {summary}");
        append_summary(&format!("{name}: {summary}"));
        Ok(())
    });
    if let Some(c) = report.cases().iter().find(|c| c.failure.is_some()) {
        let why = c.failure.clone().unwrap_or_default();
        eprintln!("{name} FAILED: {why}");
        append_summary(&format!("{name} FAILED: {why}"));
    }
    if let Some(path) = out {
        if let Err(e) = report.write(path) {
            eprintln!("cannot write {}: {e}", path.display());
            return false;
        }
    }
    report.passed()
}
