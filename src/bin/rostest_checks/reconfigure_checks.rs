//! Live tuning through `dynamic_reconfigure`'s own tool, `dynparam`: a change shows in
//! `dynparam get`, in `~parameter_updates` and in the controller's behaviour; a change the
//! phase forbids is refused and changes nothing.

use std::process::Command;
use std::sync::{Arc, Mutex};

use ::trocar_docking::kinematics::lbr::{LbrModel, ToolParams};
use ::trocar_docking::kinematics::{joint_names, Kinematics, LbrKinematics};
use ::trocar_docking::ros::convert;
use ::trocar_docking::ros::msgs::{dynamic_reconfigure as dr, sensor_msgs, trocar_docking};

use crate::common::{subscribe_latest, trigger, wait_for, CheckParams, Latest};
use crate::docking_checks::wait_for_end_accepting;

/// Run `rosrun dynamic_reconfigure dynparam ARGS`: its exit status and its output (stdout
/// then stderr).
fn dynparam(args: &[&str]) -> Result<(bool, String), String> {
    let out = Command::new("rosrun")
        .args(["dynamic_reconfigure", "dynparam"])
        .args(args)
        .output()
        .map_err(|e| format!("cannot run dynparam: {e}"))?;
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    Ok((out.status.success(), text))
}

/// The value of `name` in the newest `~parameter_updates`.
fn updated(updates: &Latest<dr::Config>, name: &str) -> Option<f64> {
    updates.get()?.doubles.iter().find(|d| d.name == name).map(|d| d.value)
}

/// Lower the force stop to `reconfigure_force_stop` with `dynparam set` while IDLE, see it in
/// `dynparam get` and `~parameter_updates`, start, and see the docking hold on it
/// (FORCE_LIMIT at that limit); then a raise while held is refused (the updates unchanged);
/// then a first docking at reduced speed ([`reduced_speed`]) and, in DONE, a weight changes
/// live.
pub fn reconfigure(p: &CheckParams) -> Result<String, String> {
    let node = p.controller.as_str();
    let (status, _s1) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    let (updates, _s2) = subscribe_latest::<dr::Config>(&format!("{node}/parameter_updates"))?;
    wait_for(p.startup_timeout, || status.get()).ok_or("no status message")?;
    let shipped = wait_for(p.startup_timeout, || updated(&updates, "force_stop_n")).ok_or("no parameter_updates")?;
    let retract = updated(&updates, "retract_force_stop_n").ok_or("no retract_force_stop_n")?;
    let (ok, got) = dynparam(&["get", node])?;
    if !ok || !got.contains(&format!("'force_stop_n': {shipped:?}")) {
        return Err(format!("dynparam get does not show force_stop_n {shipped}: {got}"));
    }
    let stop = p.reconfigure_force_stop;
    let (ok, out) = dynparam(&[
        "set",
        node,
        &format!("{{force_stop_n: {stop}, retract_force_stop_n: {stop}}}"),
    ])?;
    if !ok {
        return Err(format!("dynparam set refused in IDLE: {out}"));
    }
    wait_for(5.0, || updated(&updates, "force_stop_n").filter(|v| *v == stop))
        .ok_or_else(|| format!("parameter_updates does not show force_stop_n {stop}"))?;
    let (_, got) = dynparam(&["get", node])?;
    if !got.contains(&format!("'force_stop_n': {stop:?}")) {
        return Err(format!("dynparam get does not show the new force_stop_n {stop}: {got}"));
    }
    trigger(&format!("{node}/start"), p.startup_timeout)?;
    let held = wait_for(p.time_limit, || status.get().filter(|s| s.phase == "HOLD")).ok_or_else(|| {
        format!(
            "never held on the lowered stop; phase {}",
            status.get().unwrap_or_default().phase
        )
    })?;
    let limit = format!("over the {stop:.1} N limit");
    if held.hold_code != "FORCE_LIMIT" || !held.hold_reason.contains(&limit) {
        return Err(format!(
            "held with {} ({}), not FORCE_LIMIT {limit}",
            held.hold_code, held.hold_reason
        ));
    }
    let (ok, out) = dynparam(&["set", node, "force_stop_n", "30.0"])?;
    if ok || !out.contains("force_stop_n may only be lowered") {
        return Err(format!("raising the force stop while held was not refused: {out}"));
    }
    if updated(&updates, "force_stop_n") != Some(stop) {
        return Err("a refused change reached parameter_updates".into());
    }
    let stops = format!("{{force_stop_n: {shipped}, retract_force_stop_n: {retract}}}");
    let slow = reduced_speed(p, &status, &stops)?;
    let (ok, out) = dynparam(&["set", node, "insert_w_axis", "500.0"])?;
    if !ok {
        return Err(format!("a weight was refused in DONE: {out}"));
    }
    wait_for(5.0, || updated(&updates, "insert_w_axis").filter(|v| *v == 500.0))
        .ok_or("parameter_updates does not show insert_w_axis 500")?;
    Ok(format!(
        "dynparam set force_stop_n {shipped} -> {stop} N in IDLE; the docking held: {} ({}); \
         raising it while held refused; {slow}; insert_w_axis 500 applied live in DONE",
        held.hold_code, held.hold_reason
    ))
}

/// The tip's speed as the joint states come in.
#[derive(Debug, Default)]
struct SpeedState {
    /// The last sample kept: its stamp (s) and the tip's position (m).
    last: Option<(f64, nalgebra::Vector3<f64>)>,
    /// The largest speed so far, m/s.
    max: f64,
}

/// The largest speed of the tip between joint states 50-100 ms apart (FK of the measured
/// joints), m/s, from the moment `start` is called.
struct TipSpeed {
    max: Arc<Mutex<SpeedState>>,
    _sub: rosrust::Subscriber,
}

impl TipSpeed {
    fn subscribe(topic: &str) -> Result<Self, String> {
        let kin = LbrKinematics::from_model(LbrModel::Med7, &ToolParams::default()).map_err(|e| e.to_string())?;
        let max: Arc<Mutex<SpeedState>> = Arc::new(Mutex::new(SpeedState::default()));
        let (m, names) = (max.clone(), joint_names());
        let sub = rosrust::subscribe(topic, 100, move |js: sensor_msgs::JointState| {
            let (Ok(q), Ok(mut m)) = (convert::joint_positions("", &js, &names), m.lock()) else {
                return;
            };
            let Ok(tip) = kin.fk(&q) else { return };
            let (t, p) = (convert::seconds(js.header.stamp), tip.translation.vector);
            match m.last {
                Some((t0, p0)) if t - t0 >= 0.05 => {
                    if t - t0 <= 0.1 {
                        m.max = f64::max(m.max, (p - p0).norm() / (t - t0));
                    }
                    m.last = Some((t, p));
                }
                Some(_) => {}
                None => m.last = Some((t, p)),
            }
        })
        .map_err(|e| e.to_string())?;
        Ok(Self { max, _sub: sub })
    }

    fn max(&self) -> f64 {
        self.max.lock().map_or(f64::NAN, |m| m.max)
    }
}

/// A lab's first docking at reduced speed: `~reset`, the force stops back to `stops` (the
/// shipped values), the speeds down with the `dynparam set` of docs/lab.md, start, DONE; the tip's measured
/// speed stays within the reduced `max_tip_speed_m_s` (+10 % for the speed's estimate over 50 ms
/// of joint states).
fn reduced_speed(
    p: &CheckParams,
    status: &Latest<trocar_docking::DockingStatus>,
    stops: &str,
) -> Result<String, String> {
    let node = p.controller.as_str();
    trigger(&format!("{node}/reset"), p.startup_timeout)?;
    let (ok, out) = dynparam(&["set", node, stops])?;
    if !ok {
        return Err(format!("the force stops could not be raised back in IDLE: {out}"));
    }
    let (ok, out) = dynparam(&["set", node, REDUCED])?;
    if !ok {
        return Err(format!("the reduced speeds were refused in IDLE: {out}"));
    }
    let speed = TipSpeed::subscribe(&p.joint_states_topic)?;
    trigger(&format!("{node}/start"), p.startup_timeout)?;
    let (done, accepted) = wait_for_end_accepting(p, status)?;
    if done.phase != "DONE" {
        return Err(format!("the reduced-speed docking ABORTED: {}", done.hold_reason));
    }
    let v = speed.max();
    if v.is_nan() || v > REDUCED_TIP_SPEED * 1.1 {
        return Err(format!(
            "the tip moved at {:.1} mm/s with max_tip_speed_m_s {:.0} mm/s",
            v * 1e3,
            REDUCED_TIP_SPEED * 1e3
        ));
    }
    Ok(format!(
        "at reduced speed DONE in {:.1} s, the tip at most {:.1} mm/s (max_tip_speed_m_s {:.0} mm/s){accepted}",
        done.elapsed,
        v * 1e3,
        REDUCED_TIP_SPEED * 1e3
    ))
}

/// The reduced speeds of a first docking (docs/lab.md), and its tip speed limit, m/s.
const REDUCED: &str =
    "{force_stop_n: 20.0, retract_force_stop_n: 12.0, approach_speed_m_s: 0.02, insert_speed_m_s: 0.01, max_tip_speed_m_s: 0.03}";
const REDUCED_TIP_SPEED: f64 = 0.03;
