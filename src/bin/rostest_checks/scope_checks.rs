//! The rostest check of steering after docking, against `sim.launch`:
//! `scope_pivot` docks, then drives `/docking/scope_command` as a surgeon would (pan, tilt,
//! the same back, in and out, then silence) and judges the pivot from outside the
//! controller: the shaft from the measured joints through the URDF's KDL chain, the true
//! port from the simulator's truth, interpolated to each joint stamp: the fulcrum where the
//! abdominal wall holds the trocar at rest, breathing (`/trocar/fulcrum_true`; a shaft that
//! pivots elsewhere drags the wall), and, reported beside, the trocar's own face port
//! (`/trocar/pose_true`, which a rigid bore keeps within its clearance of the shaft however
//! far the wall is dragged).
//!
//! Asserted: the shaft's line within `max_shaft_distance` (p95) of the true port while
//! commanded, sweeping at least `min_sweep_deg`; the controller's estimate of the force
//! across the shaft (the status `lateral_force`, what levers the wall) averaging at most
//! `max_mean_force` while commanded (the whole `f_ext_norm`, which adds the seal's friction
//! along the shaft while zooming, is reported beside); the phase DONE throughout (no HOLD);
//! the dead-man: after the last command (a zoom out, never followed by a stop) the tip
//! travels at most the zoom speed times `scope.command_timeout_s + dead_man_margin_s`, and from
//! then on stays within `max_still_motion` over `still_window_s`; bad commands (a pan in
//! the base frame, then a NaN pan, 0.5 s each) turn the shaft by no more than
//! `max_bad_turn_deg` (obeyed, the pan turns it by about 4 deg), move the tip by no more
//! than `max_still_motion` in the base frame or beyond the true port's motion, whichever
//! is smaller (the ignoring scope holds still, so it moves with the port only when the
//! port pushes it past the still dead-band; judged beyond the port alone, the breathing
//! in the window took 0.07-0.45 mm of the 0.5), and leave it DONE; and `~retract` leads
//! through RETRACT to IDLE
//! within `retract_timeout`.
//!
//! "Still" and the dead-man's travel are judged beyond the true port's motion across the
//! shaft ([`beyond_port`]):
//! the port breathes (config/sim.yaml: 1 mm across the axis, 4 mm along it) and the
//! controller's fulcrum follows it, as the pivot's targets ask, which carries the scope across its
//! shaft by up to the port's excursion; a scope that drifts, or keeps moving after its
//! commands stop, moves beyond that. The tip's motion in the base frame is reported beside.
//!
//! `scope_joy` checks the joystick node alone: the test node plays a joystick (Joy at
//! 20 Hz) and reads `/docking/scope_command`. Held: commands at the node's rate, each the
//! pure mapping's ([`::trocar_docking::ros::joy`]) of the played Joy under the same YAML, in
//! the tip's frame, stamped; released: one zero command, then silence; a joystick that stops
//! while held: one zero command within `joy_timeout_s` and a tick, then silence.

use std::sync::{Arc, Mutex};

use nalgebra::{Isometry3, Point3, Vector3};

use crate::common::{subscribe_latest, trigger, wait_for, CheckParams};
use ::trocar_docking::control::docking::geometry::distance_to_line;
use ::trocar_docking::control::ScopeCommand;
use ::trocar_docking::kinematics::lbr::LbrModel;
use ::trocar_docking::kinematics::{JointVector, Kinematics, LbrKinematics, TIP_LINK};
use ::trocar_docking::ros::convert;
use ::trocar_docking::ros::joy::JoyParams;
use ::trocar_docking::ros::msgs::{geometry_msgs, sensor_msgs, trocar_docking};
use ::trocar_docking::ros::node::lock;
use ::trocar_docking::ros::params;
use ::trocar_docking::stats::finite_quantile;

/// A time series recorded from a topic: (stamp s, value).
type Series<T> = Arc<Mutex<Vec<(f64, T)>>>;

/// A status as the check keeps it.
#[derive(Debug, Clone)]
struct StatusSample {
    phase: String,
    hold_code: String,
    f_ext_norm: f64,
    lateral_force: f64,
    shaft_to_fulcrum: f64,
}

/// What the check records while it runs.
#[derive(Default)]
struct Records {
    joints: Series<JointVector>,
    truth: Series<Point3<f64>>,
    fulcrum: Series<Point3<f64>>,
    status: Series<StatusSample>,
}

/// Record `topic` into `into` with `f` (messages `f` maps to `None` are skipped).
fn record<T: rosrust::Message, V: Send + 'static>(
    topic: &str,
    into: &Series<V>,
    f: impl Fn(&T) -> Option<(f64, V)> + Send + 'static,
) -> Result<rosrust::Subscriber, String> {
    let into = into.clone();
    rosrust::subscribe(topic, 1000, move |m: T| {
        if let Some(v) = f(&m) {
            lock(&into).push(v);
        }
    })
    .map_err(|e| format!("subscribe {topic}: {e}"))
}

impl Records {
    fn subscribe(p: &CheckParams) -> Result<(Self, Vec<rosrust::Subscriber>), String> {
        let r = Self::default();
        let names = ::trocar_docking::kinematics::joint_names();
        let subs = vec![
            record(&p.joint_states_topic, &r.joints, move |m: &sensor_msgs::JointState| {
                let q = convert::joint_positions("joints", m, &names).ok()?;
                Some((convert::seconds(m.header.stamp), q))
            })?,
            record(&p.true_pose_topic, &r.truth, |m: &geometry_msgs::PoseStamped| {
                let t = convert::pose("truth", &m.pose).ok()?;
                Some((convert::seconds(m.header.stamp), Point3::from(t.translation.vector)))
            })?,
            record(&p.true_fulcrum_topic, &r.fulcrum, |m: &geometry_msgs::PointStamped| {
                let q = Point3::new(m.point.x, m.point.y, m.point.z);
                q.coords
                    .iter()
                    .all(|x| x.is_finite())
                    .then(|| (convert::seconds(m.header.stamp), q))
            })?,
            record(&p.status_topic, &r.status, |s: &trocar_docking::DockingStatus| {
                let v = StatusSample {
                    phase: s.phase.clone(),
                    hold_code: s.hold_code.clone(),
                    f_ext_norm: s.f_ext_norm,
                    lateral_force: s.lateral_force,
                    shaft_to_fulcrum: s.shaft_to_fulcrum,
                };
                Some((convert::seconds(s.header.stamp), v))
            })?,
        ];
        Ok((r, subs))
    }
}

/// The surgeon's sequence: (command, duration s), then silence.
fn sequence(p: &CheckParams) -> Vec<(ScopeCommand, f64)> {
    let (w, v) = (p.pan_speed, p.zoom_speed);
    let c = |pan, tilt, zoom| ScopeCommand {
        pan,
        tilt,
        roll: 0.0,
        zoom,
    };
    vec![
        (c(w, 0.0, 0.0), p.pan_time),
        (c(0.0, w, 0.0), p.pan_time),
        (c(-w, 0.0, 0.0), p.pan_time),
        (c(0.0, -w, 0.0), p.pan_time),
        (c(0.0, 0.0, v), p.zoom_time),
        (c(0.0, 0.0, -v), p.zoom_time),
    ]
}

/// Publish `steps` in `frame` at `scope_rate_hz`, stamped with the ROS clock; returns
/// their start and end (ROS time, s). The schedule runs on the ROS clock (the simulator's).
fn drive(p: &CheckParams, steps: &[(ScopeCommand, f64)], frame: &str) -> Result<(f64, f64), String> {
    let publ = rosrust::publish::<geometry_msgs::TwistStamped>(&p.scope_command_topic, 10)
        .map_err(|e| format!("publish {}: {e}", p.scope_command_topic))?;
    let total: f64 = steps.iter().map(|s| s.1).sum();
    let t0 = convert::seconds(rosrust::now());
    let period = std::time::Duration::from_secs_f64(1.0 / p.scope_rate_hz);
    loop {
        let now = rosrust::now();
        let t = convert::seconds(now) - t0;
        if t >= total || !rosrust::is_ok() {
            return Ok((t0, t0 + total));
        }
        let mut left = t;
        let cmd = steps
            .iter()
            .find(|(_, d)| {
                left -= d;
                left < 0.0
            })
            .map_or(ScopeCommand::default(), |s| s.0);
        let _ = publ.send(convert::scope_twist(now, frame, &cmd));
        std::thread::sleep(period);
    }
}

/// Sleep `seconds` of ROS time (bounded by 10 times as long on the wall clock).
fn sleep_ros(seconds: f64) {
    let until = convert::seconds(rosrust::now()) + seconds;
    wait_for(seconds * 10.0 + 1.0, || {
        (convert::seconds(rosrust::now()) >= until).then_some(())
    });
}

/// The port at `t`, linearly interpolated between the true poses around it.
fn port_at(truth: &[(f64, Point3<f64>)], t: f64) -> Option<Point3<f64>> {
    let k = truth.partition_point(|(s, _)| *s <= t);
    let (a, b) = (truth.get(k.checked_sub(1)?)?, truth.get(k)?);
    let w = if b.0 > a.0 { (t - a.0) / (b.0 - a.0) } else { 0.0 };
    Some(a.1 + (b.1 - a.1) * w)
}

/// Distance of the shaft (the line through the tip along its z axis) from `port`, m.
fn shaft_distance(tip: &Isometry3<f64>, port: &Point3<f64>) -> f64 {
    distance_to_line(
        port,
        &Point3::from(tip.translation.vector),
        &(tip.rotation * Vector3::z()),
    )
}

/// The pivot as measured over the commanded window: shaft distances from the true port, and
/// the largest angle of the shaft from its first direction (rad).
fn pivot_figures(tips: &[(f64, Isometry3<f64>)], truth: &[(f64, Point3<f64>)]) -> (Vec<f64>, f64) {
    let z0 = tips.first().map_or(Vector3::z(), |(_, t)| t.rotation * Vector3::z());
    let distances = tips
        .iter()
        .filter_map(|(s, tip)| port_at(truth, *s).map(|port| shaft_distance(tip, &port)))
        .collect();
    let sweep = tips
        .iter()
        .map(|(_, t)| (t.rotation * Vector3::z()).angle(&z0))
        .fold(0.0, f64::max);
    (distances, sweep)
}

/// The largest distance of a tip in `tips` from the first one, m.
fn spread(tips: &[(f64, Isometry3<f64>)]) -> f64 {
    let Some((_, first)) = tips.first() else {
        return f64::NAN;
    };
    tips.iter()
        .map(|(_, t)| (t.translation.vector - first.translation.vector).norm())
        .fold(0.0, f64::max)
}

/// The largest motion of a tip in `tips` from the first one beyond the true port's motion
/// across the shaft over the same time: |d tip - (d port - z (z . d port))|, with z the
/// first shaft direction, m (NaN if the port is unknown).
fn beyond_port(tips: &[(f64, Isometry3<f64>)], truth: &[(f64, Point3<f64>)]) -> f64 {
    let Some((s0, first)) = tips.first() else {
        return f64::NAN;
    };
    let (Some(port0), z) = (port_at(truth, *s0), first.rotation * Vector3::z()) else {
        return f64::NAN;
    };
    tips.iter()
        .map(|(s, t)| {
            let Some(port) = port_at(truth, *s) else {
                return f64::NAN;
            };
            let d_port = port - port0;
            let across = d_port - z * z.dot(&d_port);
            (t.translation.vector - first.translation.vector - across).norm()
        })
        .fold(
            0.0,
            |m: f64, x| if x.is_nan() || m.is_nan() { f64::NAN } else { m.max(x) },
        )
}

/// Tips (FK of the measured joints) between `from` and `to` (ROS time, s).
fn tips_between(
    kin: &LbrKinematics,
    joints: &[(f64, JointVector)],
    from: f64,
    to: f64,
) -> Result<Vec<(f64, Isometry3<f64>)>, String> {
    joints
        .iter()
        .filter(|(s, _)| *s >= from && *s <= to)
        .map(|(s, q)| kin.fk(q).map(|t| (*s, t)).map_err(|e| e.to_string()))
        .collect()
}

/// Dock: start (unless the launch does) and wait for DONE.
fn dock(p: &CheckParams) -> Result<(), String> {
    let (status, _sub) = subscribe_latest::<trocar_docking::DockingStatus>(&p.status_topic)?;
    wait_for(p.startup_timeout, || status.get()).ok_or("no status message")?;
    if p.call_start {
        trigger(&format!("{}/start", p.controller), p.startup_timeout)?;
    }
    let s = crate::docking_checks::wait_for_end(p, &status)?;
    if s.phase != "DONE" {
        return Err(format!("docking ABORTED: {}", s.hold_reason));
    }
    Ok(())
}

/// `~retract`: RETRACT, then IDLE within `retract_timeout`.
fn retract(p: &CheckParams, status: &Series<StatusSample>) -> Result<f64, String> {
    let from = lock(status).len();
    let t0 = convert::seconds(rosrust::now());
    trigger(&format!("{}/retract", p.controller), p.startup_timeout)?;
    let phases = || -> Vec<String> { lock(status)[from..].iter().map(|s| s.1.phase.clone()).collect() };
    wait_for(p.retract_timeout, || {
        let ph = phases();
        let retracting = ph.iter().position(|s| s == "RETRACT")?;
        ph[retracting..].iter().any(|s| s == "IDLE").then_some(())
    })
    .ok_or_else(|| {
        let mut ph = phases();
        ph.dedup();
        format!(
            "~retract: phases {ph:?}, not RETRACT then IDLE within {} s",
            p.retract_timeout
        )
    })?;
    Ok(convert::seconds(rosrust::now()) - t0)
}

/// The mean of the finite values, NaN if there is none.
fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = v.filter(|x| x.is_finite()).fold((0.0, 0), |(s, n), x| (s + x, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        sum / f64::from(n)
    }
}

/// The means of the status over a window (NaN: none).
#[derive(Debug, Clone, Copy, Default)]
struct StatusMeans {
    /// The force estimate, N.
    f_ext_n: f64,
    /// The force across the shaft, N.
    lateral_n: f64,
    /// The shaft's distance from the controller's own fulcrum, m.
    shaft_to_fulcrum_m: f64,
}

/// The status over a window of time.
#[derive(Debug, Clone)]
struct StatusFigures {
    /// How many status messages.
    count: usize,
    /// The phases other than DONE, with their codes, each change once.
    others: Vec<String>,
    /// The means.
    means: StatusMeans,
}

/// Status over [from, to]: how many, the phases other than DONE (with their codes), and
/// the means of the force estimate, the lateral force and the shaft's distance from the
/// controller's own fulcrum (NaN: none).
fn status_figures(status: &[(f64, StatusSample)], from: f64, to: f64) -> StatusFigures {
    let window: Vec<_> = status.iter().filter(|(s, _)| *s >= from && *s <= to).collect();
    let mut others: Vec<String> = window
        .iter()
        .filter(|(_, s)| s.phase != "DONE")
        .map(|(_, s)| format!("{} {}", s.phase, s.hold_code))
        .collect();
    others.dedup();
    let means = StatusMeans {
        f_ext_n: mean(window.iter().map(|(_, s)| s.f_ext_norm)),
        lateral_n: mean(window.iter().map(|(_, s)| s.lateral_force)),
        shaft_to_fulcrum_m: mean(window.iter().map(|(_, s)| s.shaft_to_fulcrum)),
    };
    StatusFigures {
        count: window.len(),
        others,
        means,
    }
}

/// What `scope_pivot` measured.
#[derive(Debug, Clone, Default)]
struct Figures {
    /// Joint states and status while commanded.
    counts: (usize, usize),
    /// p95 distance of the shaft from the true port (the true fulcrum, where the wall
    /// holds the trocar) while commanded, m, and from the trocar's own face port.
    p95: (f64, f64),
    /// Largest angle of the shaft from its first direction, rad.
    sweep: f64,
    /// Means while commanded: force estimate and lateral force, the shaft's distance from
    /// the controller's fulcrum.
    status: StatusMeans,
    /// Phases other than DONE while commanded.
    others: Vec<String>,
    /// Tip travel from the last command to the start of the still window, beyond the true
    /// port's motion across the shaft, m.
    travel: f64,
    /// Tip motion over the still window in the base frame, and beyond the true port's
    /// motion across the shaft (what following a breathing port explains), m.
    still: (f64, f64),
}

impl Figures {
    /// Measure the run: commanded over [t0, t1], then silence.
    fn measure(p: &CheckParams, kin: &LbrKinematics, rec: &Records, t0: f64, t1: f64) -> Result<Self, String> {
        let joints = lock(&rec.joints).clone();
        let truth = lock(&rec.truth).clone();
        let tips = tips_between(kin, &joints, t0, t1)?;
        let (distances, sweep) = pivot_figures(&tips, &lock(&rec.fulcrum));
        let (face, _) = pivot_figures(&tips, &truth);
        let n = distances.len();
        let StatusFigures {
            count: n_status,
            others,
            means: status,
        } = status_figures(&lock(&rec.status), t0, t1);
        let still_from = t1 + p.command_timeout + p.dead_man_margin_s;
        let still = tips_between(kin, &joints, still_from, still_from + p.still_window_s)?;
        Ok(Self {
            counts: (n, n_status),
            p95: (finite_quantile(&distances, 0.95), finite_quantile(&face, 0.95)),
            sweep,
            status,
            others,
            travel: beyond_port(&tips_between(kin, &joints, t1, still_from)?, &truth),
            still: (spread(&still), beyond_port(&still, &truth)),
        })
    }

    fn text(&self, p: &CheckParams) -> String {
        format!(
            "shaft to the true port (the wall's fulcrum) p95 {:.3} mm over {} joint states (to the trocar's face port: {:.3} mm; \
             to the controller's fulcrum: mean {:.3} mm), \
             sweep {:.1} deg, mean force estimate across the shaft {:.2} N (whole |f_ext| {:.2} N), travel after the last command {:.2} mm, then still within {:.3} mm \
             beyond the true port's motion across the shaft over {} s ({:.3} mm in the base frame)",
            self.p95.0 * 1e3,
            self.counts.0,
            self.p95.1 * 1e3,
            self.status.shaft_to_fulcrum_m * 1e3,
            self.sweep.to_degrees(),
            self.status.lateral_n,
            self.status.f_ext_n,
            self.travel * 1e3,
            self.still.1 * 1e3,
            p.still_window_s,
            self.still.0 * 1e3
        )
    }

    /// Every bound the figures break, in words.
    fn failures(&self, p: &CheckParams) -> Vec<String> {
        let (n, n_status) = self.counts;
        let max_travel = p.zoom_speed * (p.command_timeout + p.dead_man_margin_s);
        let over = |v: f64, bound: f64| v.is_nan() || v > bound;
        [
            (n < 100 || n_status < 100).then(|| {
                format!(
                    "only {n} joint states with a true fulcrum ({}) and {n_status} status while commanded",
                    p.true_fulcrum_topic
                )
            }),
            over(self.p95.0, p.max_shaft_distance)
                .then(|| format!("shaft p95 above {} mm", p.max_shaft_distance * 1e3)),
            (self.sweep.to_degrees() < p.min_sweep_deg).then(|| format!("swept less than {} deg", p.min_sweep_deg)),
            over(self.status.lateral_n, p.max_mean_force)
                .then(|| format!("mean lateral force above {} N", p.max_mean_force)),
            (!self.others.is_empty()).then(|| format!("left DONE while commanded: {:?}", self.others)),
            over(self.travel, max_travel).then(|| format!("dead-man: moved more than {:.2} mm", max_travel * 1e3)),
            over(self.still.1, p.max_still_motion).then(|| format!("not still: above {} mm", p.max_still_motion * 1e3)),
        ]
        .into_iter()
        .flatten()
        .collect()
    }
}

/// What bad commands did: the tip's motion (m) and the shaft's turn (deg) from their start
/// to 0.3 s after, and the phases other than DONE meanwhile.
struct BadCommands {
    /// The smaller of the tip's motion in the base frame and beyond the true port's motion
    /// across the shaft: a scope that holds still moves by neither, or (yielding to the
    /// breathing port, which it does only past the still dead-band) with the port.
    moved: f64,
    /// The largest angle of the shaft from its direction at the start, deg.
    turned_deg: f64,
    /// Phases other than DONE.
    others: Vec<String>,
}

/// Bad commands: a pan in the base frame, then a NaN pan, 0.5 s each.
fn bad_commands(p: &CheckParams, kin: &LbrKinematics, rec: &Records) -> Result<BadCommands, String> {
    let pan = ScopeCommand {
        pan: p.pan_speed,
        ..ScopeCommand::default()
    };
    let nan = ScopeCommand {
        pan: f64::NAN,
        ..ScopeCommand::default()
    };
    let (t0, _) = drive(p, &[(pan, 0.5)], ::trocar_docking::kinematics::BASE_LINK)?;
    let (_, t1) = drive(p, &[(nan, 0.5)], &p.tip_frame)?;
    sleep_ros(0.5);
    let joints = lock(&rec.joints).clone();
    let tips = tips_between(kin, &joints, t0, t1 + 0.3)?;
    let moved = spread(&tips).min(beyond_port(&tips, &lock(&rec.truth)));
    let turned_deg = tips.first().map_or(f64::NAN, |(_, first)| {
        let z0 = first.rotation * Vector3::z();
        tips.iter()
            .map(|(_, t)| (t.rotation * Vector3::z()).angle(&z0).to_degrees())
            .fold(0.0, f64::max)
    });
    let others = status_figures(&lock(&rec.status), t0, t1 + 0.3).others;
    Ok(BadCommands {
        moved,
        turned_deg,
        others,
    })
}

/// `scope_pivot`: see the module documentation.
pub fn scope_pivot(p: &CheckParams) -> Result<String, String> {
    let kin = LbrKinematics::from_model_or_file(LbrModel::Med7, &p.urdf_file, TIP_LINK).map_err(|e| e.to_string())?;
    let (rec, _subs) = Records::subscribe(p)?;
    dock(p)?;
    sleep_ros(p.settle_s);
    let (t0, t1) = drive(p, &sequence(p), &p.tip_frame)?;
    sleep_ros(p.command_timeout + p.dead_man_margin_s + p.still_window_s + 0.2);
    let figures = Figures::measure(p, &kin, &rec, t0, t1)?;
    let mut failures = figures.failures(p);
    let bad = bad_commands(p, &kin, &rec)?;
    if bad.moved.is_nan()
        || bad.moved > p.max_still_motion
        || bad.turned_deg.is_nan()
        || bad.turned_deg > p.max_bad_turn_deg
        || !bad.others.is_empty()
    {
        failures.push(format!(
            "bad commands moved the scope {:.3} mm and turned it {:.2} deg (phases {:?})",
            bad.moved * 1e3,
            bad.turned_deg,
            bad.others
        ));
    }
    let retracted = retract(p, &rec.status).unwrap_or_else(|e| {
        failures.push(e);
        f64::NAN
    });
    let text = figures.text(p);
    if failures.is_empty() {
        Ok(format!(
            "{text}; bad commands (base frame, NaN) moved it {:.3} mm, turned it {:.2} deg; ~retract: RETRACT then IDLE in {retracted:.1} s",
            bad.moved * 1e3,
            bad.turned_deg
        ))
    } else {
        Err(format!("{}: {text}", failures.join("; ")))
    }
}

/// A joystick played by the test node: publish `axes` with the dead-man `held` at 20 Hz for
/// `seconds` (wall time).
fn play_joy(publ: &rosrust::Publisher<sensor_msgs::Joy>, j: &JoyParams, axes: &[f32], held: bool, seconds: f64) {
    let mut buttons = vec![0; usize::try_from(j.deadman_button).unwrap_or(0) + 1];
    if let Some(b) = buttons.last_mut() {
        *b = i32::from(held);
    }
    let msg = sensor_msgs::Joy {
        axes: axes.to_vec(),
        buttons,
        ..Default::default()
    };
    let t0 = std::time::Instant::now();
    while t0.elapsed().as_secs_f64() < seconds {
        let _ = publ.send(msg.clone());
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

/// The commands that arrived since `from` (an index into the record): (count, zero ones).
fn arrived(got: &Series<ScopeCommand>, from: usize) -> (usize, usize) {
    let g = lock(got);
    let new = &g[from.min(g.len())..];
    (
        new.len(),
        new.iter().filter(|(_, c)| *c == ScopeCommand::default()).count(),
    )
}

/// Commands from `from` on equal to the held `held` command: the hold's tail still in
/// flight when the release began (published before the node saw the release).
fn in_flight(got: &Series<ScopeCommand>, from: usize, held: &ScopeCommand) -> usize {
    let g = lock(got);
    g[from.min(g.len())..].iter().take_while(|(_, c)| c == held).count()
}

/// `scope_joy`: see the module documentation.
pub fn scope_joy(p: &CheckParams) -> Result<String, String> {
    let j: JoyParams = params::from_yaml_file(std::path::Path::new(&p.joy_config)).map_err(|e| e.to_string())?;
    let got: Series<ScopeCommand> = Series::default();
    let frame = j.frame_id.clone();
    let bad: Arc<Mutex<Vec<String>>> = Arc::default();
    let bad_w = bad.clone();
    let _sub = record(&j.command_topic, &got, move |m: &geometry_msgs::TwistStamped| {
        let c = convert::scope_command("joy", m, &frame);
        if m.header.frame_id != frame || m.header.stamp.seconds() <= 0.0 || c.is_err() {
            lock(&bad_w).push(format!("{:?} {} {:?}", m.header.frame_id, m.header.stamp.seconds(), c));
        }
        Some((convert::seconds(rosrust::now()), c.ok()?))
    })?;
    let publ = rosrust::publish::<sensor_msgs::Joy>(&j.joy_topic, 10).map_err(|e| e.to_string())?;
    let axes = [0.8, -0.5, 0.0, 0.3, 1.0, 0.0];
    wait_for(p.startup_timeout, || (publ.subscriber_count() > 0).then_some(()))
        .ok_or("scope_joy never subscribed to the joystick")?;
    play_joy(&publ, &j, &axes, false, 0.5);
    let silent_released = arrived(&got, 0).0;
    let held_from = lock(&got).len();
    play_joy(&publ, &j, &axes, true, 2.0);
    let (n_held, _) = arrived(&got, held_from);
    let expected = j
        .command(&sensor_msgs::Joy {
            axes: axes.to_vec(),
            buttons: vec![1; usize::try_from(j.deadman_button).unwrap_or(0) + 1],
            ..Default::default()
        })
        .map_err(|e| e.to_string())?
        .ok_or("the mapping gave no command with the dead-man held")?;
    let last = lock(&got).last().map(|c| c.1);
    let released_from = lock(&got).len();
    play_joy(&publ, &j, &axes, false, 1.0);
    let released = arrived(&got, released_from + in_flight(&got, released_from, &expected));
    play_joy(&publ, &j, &axes, true, 0.5);
    let stopped_from = lock(&got).len();
    std::thread::sleep(std::time::Duration::from_secs_f64(j.joy_timeout_s + 1.0));
    let (n_after, zeros_after) = arrived(&got, stopped_from);
    let ticks_timeout = (j.joy_timeout_s * j.rate_hz).ceil() as usize + 2;
    let rate = n_held as f64 / 2.0;
    let mut failures = Vec::new();
    if silent_released != 0 {
        failures.push(format!("{silent_released} commands with the dead-man released"));
    }
    if (rate - j.rate_hz).abs() > 0.25 * j.rate_hz {
        failures.push(format!("{rate:.1} commands/s held, expected {} Hz", j.rate_hz));
    }
    if last
        .map(|c| {
            (c.pan - expected.pan).abs()
                + (c.tilt - expected.tilt).abs()
                + (c.roll - expected.roll).abs()
                + (c.zoom - expected.zoom).abs()
                > 1e-6
        })
        .unwrap_or(true)
    {
        failures.push(format!("held: sent {last:?}, the mapping gives {expected:?}"));
    }
    if released != (1, 1) {
        failures.push(format!(
            "released: {} commands ({} zero), expected one zero",
            released.0, released.1
        ));
    }
    if zeros_after != 1 || n_after > ticks_timeout {
        failures.push(format!("joystick stopped: {n_after} commands ({zeros_after} zero), expected at most {ticks_timeout} ending in one zero"));
    }
    if let Some(b) = lock(&bad).first() {
        failures.push(format!("a command off its frame, unstamped or malformed: {b}"));
    }
    let text = format!(
        "held: {rate:.1} commands/s, {expected:?}; released: one stop; joystick stopped: {n_after} commands then silence"
    );
    if failures.is_empty() {
        Ok(text)
    } else {
        Err(format!("{}: {text}", failures.join("; ")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_port_is_interpolated_between_true_poses() {
        let truth = vec![(1.0, Point3::new(0.0, 0.0, 0.0)), (1.1, Point3::new(0.0, 0.001, 0.0))];
        let p = port_at(&truth, 1.05).unwrap();
        assert!((p.y - 0.0005).abs() < 1e-12);
        assert!(
            port_at(&truth, 0.9).is_none() && port_at(&truth, 1.2).is_none(),
            "no extrapolation"
        );
    }

    #[test]
    fn the_shaft_distance_is_the_lines_not_the_tips() {
        // A tip 5 cm along z past a port 2 mm off its line.
        let tip = Isometry3::translation(0.0, 0.0, 0.05);
        assert!((shaft_distance(&tip, &Point3::new(0.002, 0.0, 0.0)) - 0.002).abs() < 1e-12);
        assert!(shaft_distance(&tip, &Point3::new(0.0, 0.0, -0.3)) < 1e-12);
    }

    #[test]
    fn pivot_figures_measure_sweep_and_spread() {
        let port = Point3::origin();
        let truth = vec![(0.0, port), (10.0, port)];
        // The shaft turns 20 deg about the port; the tip 3 cm past it.
        let tips: Vec<_> = (0..=20)
            .map(|k| {
                let r = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::x_axis(), f64::from(k).to_radians());
                let at = r * Vector3::new(0.0, 0.0, 0.03);
                (f64::from(k) * 0.1, Isometry3::from_parts(at.into(), r))
            })
            .collect();
        let (d, sweep) = pivot_figures(&tips, &truth);
        assert_eq!(d.len(), 21);
        assert!(finite_quantile(&d, 0.95) < 1e-12);
        assert!((sweep.to_degrees() - 20.0).abs() < 1e-9);
        assert!((spread(&tips) - 2.0 * 0.03 * 10f64.to_radians().sin()).abs() < 1e-9);
        // A scope carried across its shaft by a moving port has not moved beyond it; along
        // the shaft it has.
        let carried: Vec<_> = (0..3)
            .map(|k| (f64::from(k), Isometry3::translation(0.001 * f64::from(k), 0.0, 0.0)))
            .collect();
        let port = vec![(0.0, Point3::origin()), (2.5, Point3::new(0.0025, 0.0, 0.005))];
        assert!(beyond_port(&carried, &port) < 1e-12);
        let still: Vec<_> = (0..3).map(|k| (f64::from(k), Isometry3::identity())).collect();
        assert!((beyond_port(&still, &port) - 0.002).abs() < 1e-12);
        assert!(mean([1.0, f64::NAN, 3.0].into_iter()) == 2.0 && mean(std::iter::empty()).is_nan());
    }

    #[test]
    fn the_sequence_is_the_done_when_script() {
        let s = sequence(&CheckParams::default());
        assert_eq!(s.len(), 6);
        assert!((s.iter().map(|x| x.1).sum::<f64>() - 10.0).abs() < 1e-12);
        assert_eq!(s[0].0.pan, 0.17);
        assert_eq!(s[3].0.tilt, -0.17);
        assert_eq!(s[5].0.zoom, -0.01, "the last command moves: silence, no stop, follows");
    }
}
