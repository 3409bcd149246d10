//! The `docking_controller` node: subscribes the joint states, the driver's LBRState
//! (external torques) and the trocar pose; runs the guarded [`Controller`] at a fixed rate;
//! publishes the joint command, `/docking/status`, `/docking/f_ext`, `/docking/markers` and
//! tf frames of the trocar and the goal; serves `~preflight`, `~start`, `~abort`, `~reset` and
//! `~retract`, and the live parameters through `dynamic_reconfigure`
//! ([`crate::ros::reconfigure`]: `~set_parameters`, applied between two steps). `~start` runs the preflight first ([`crate::ros::preflight`], on the service's
//! thread, never the loop's) and refuses, naming the failed check, when a check fails; the
//! loop then never hears of the start.
//! After DONE it takes the surgeon's scope commands (`/docking/scope_command`) and
//! reports the pivot (fulcrum, shaft distance, lateral force, limit) in the status and
//! the markers. Every topic and frame name is a parameter (see [`ControllerNodeParams`]).
//!
//! Nothing moves before `~start`. A bad message (wrong joints, NaN, wrong frame, a stamp
//! that goes back) is dropped with a logged reason and clears that input, so the controller
//! holds; a driver or camera that stops makes the input stale, and the controller holds.
//!
//! **Real time.** The control loop ([`control_loop`]) takes no lock that another thread
//! holds and allocates nothing per step: the subscribers hand it their inputs through
//! latest-value slots ([`inputs`]), the services their requests through a lock-free queue
//! with a reply, and the loop hands each step's record to a publisher thread ([`outputs`]),
//! which builds and sends the messages. (Under `/use_sim_time` rosrust's simulated clock
//! is itself a mutex shared with the `/clock` subscriber: that is the simulator's, not the
//! robot's, where the loop reads the wall clock.)

mod ghost;
mod inputs;
pub mod node_params;
mod outputs;

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::control::live::LiveValues;
use crate::control::{Controller, HoldReason, Phase};
use crate::kinematics::{Kinematics, LbrKinematics, TIP_LINK};
use crate::ros::convert;
use crate::ros::handover::{self, OutputSender, RequestClient, RequestServer};
use crate::ros::node::{reply_service, NodeError, Reply};
use crate::ros::pacer::Pacer;
use crate::ros::params;
use crate::ros::preflight;
use crate::ros::reconfigure;
use crate::ros::stats::LoopStats;
use inputs::InputReaders;
pub use node_params::ControllerNodeParams;
use outputs::{LoopSnapshot, StepRecord};

/// A supervision request from a service thread to the loop.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Request {
    Start,
    Abort,
    Reset,
    Retract,
    /// Live-tuned values ([`crate::ros::reconfigure`]), applied between two steps.
    Reconfigure(LiveValues),
    /// The controller's phase (`Ok`, its code), for `~start` to know a fresh docking.
    Phase,
}

/// How long a service waits for the loop to take its request.
const SERVICE_TIMEOUT: Duration = Duration::from_secs(1);

/// A `std_srvs/Trigger` service that sends `request` to the loop and returns its reply.
fn trigger_service(
    name: &str,
    client: &RequestClient<Request, Reply>,
    request: Request,
) -> Result<rosrust::Service, NodeError> {
    let client = client.clone();
    reply_service(name, move || {
        client
            .call(request, SERVICE_TIMEOUT)
            .unwrap_or_else(|e| Err(e.to_string()))
    })
}

/// The preflight's outcome as a Trigger reply: `Ok(report)` when every check passed, else
/// `Err` naming the first failed check, its finding and the fix, then every failed code.
fn preflight_reply(p: &ControllerNodeParams, kin: &dyn Kinematics) -> Reply {
    let report = preflight::run(&p.preflight, p, kin).map_err(|e| format!("preflight could not run: {e}"))?;
    match report.first_failure() {
        None => Ok(report.to_string()),
        Some(c) => Err(format!(
            "preflight failed: {}: {} (fix: {}); failed: {}",
            c.code,
            c.detail,
            c.fix,
            report.failed_codes().join(", ")
        )),
    }
}

/// `~preflight` (the checks, their report) and `~start` (the checks first, unless
/// `preflight_on_start` is false, then the start request to the loop). Both block their
/// own service thread for the preflight's window, never the loop.
fn preflight_services(
    p: &ControllerNodeParams,
    kin: &Arc<LbrKinematics>,
    client: &RequestClient<Request, Reply>,
) -> Result<[rosrust::Service; 2], NodeError> {
    let (pc, kc) = (p.clone(), kin.clone());
    let check = reply_service("~preflight", move || preflight_reply(&pc, kc.as_ref()))?;
    let (ps, ks, client) = (p.clone(), kin.clone(), client.clone());
    let start = reply_service("~start", move || {
        // Only a docking that begins from IDLE, with the arm at rest: a start that resumes a
        // hold or accepts the depth finds the scope in the trocar, touched by it and moved by
        // the breathing, where the at-rest checks cannot pass (the loop checks the resume).
        if ps.preflight_on_start && fresh_start(&client) {
            preflight_reply(&ps, ks.as_ref())?;
        }
        client
            .call(Request::Start, SERVICE_TIMEOUT)
            .unwrap_or_else(|e| Err(e.to_string()))
    })?;
    Ok([check, start])
}

/// Whether a `~start` now begins a docking (the controller IDLE, or its phase unknown: the
/// preflight then runs), rather than resuming one.
fn fresh_start(client: &RequestClient<Request, Reply>) -> bool {
    client
        .call(Request::Phase, SERVICE_TIMEOUT)
        .map_or(true, |r| r.map_or(true, |phase| phase == Phase::Idle.as_str()))
}

/// The loop's own state besides the controller.
struct LoopState {
    stats: LoopStats,
    start_time: Option<f64>,
    last_now: f64,
    last_latency_stamp: f64,
    last_status: f64,
    last_markers: f64,
    status_period: f64,
    markers_period: f64,
    /// The arm the controller steers in a dry run (`None`: the real one).
    ghost: Option<ghost::Ghost>,
}

impl LoopState {
    fn new(p: &ControllerNodeParams) -> Self {
        let period = |hz: f64, never: f64| if hz > 0.0 { 1.0 / hz } else { never };
        Self {
            stats: LoopStats::new(1.0, p.latency_samples)
                .with_nominal_period(Duration::from_secs_f64(p.controller.dt_s)),
            start_time: None,
            last_now: f64::NEG_INFINITY,
            last_latency_stamp: f64::NEG_INFINITY,
            last_status: f64::NEG_INFINITY,
            last_markers: f64::NEG_INFINITY,
            status_period: period(p.status_rate_hz, 0.0),
            markers_period: period(p.markers_rate_hz, f64::INFINITY),
            ghost: p.dry_run.then(ghost::Ghost::default),
        }
    }

    /// Carry out a supervision request at `now`.
    fn handle(&mut self, controller: &mut Controller, request: Request, now: f64) -> Reply {
        match request {
            Request::Start => {
                controller.start()?;
                self.start_time = Some(now);
                self.stats.clear();
                Ok("docking started".into())
            }
            Request::Abort => {
                controller.abort("operator abort (~abort)");
                Ok("aborted: holding".into())
            }
            Request::Reset => {
                controller.reset();
                self.start_time = None;
                if let Some(g) = self.ghost.as_mut() {
                    g.clear();
                }
                Ok("reset to IDLE".into())
            }
            Request::Retract => {
                controller.retract()?;
                Ok("retracting along the shaft to the stand-off point, then IDLE".into())
            }
            Request::Reconfigure(values) => {
                controller.set_live(&values)?;
                Ok(format!("applied in {}", controller.phase()))
            }
            Request::Phase => Ok(controller.phase().as_str().into()),
        }
    }
}

/// The control loop: read, step, write, until shutdown.
fn control_loop(
    p: &ControllerNodeParams,
    kin: &dyn Kinematics,
    mut controller: Controller,
    mut inputs: InputReaders,
    requests: &RequestServer<Request, Reply>,
    records: &OutputSender<StepRecord>,
    started_at: Option<f64>,
) {
    let mut pace = Pacer::new(1.0 / p.controller.dt_s);
    let mut st = LoopState::new(p);
    st.start_time = started_at;
    while rosrust::is_ok() {
        let started = Instant::now();
        let stamp = rosrust::now();
        let now = convert::seconds(stamp);
        st.stats.step_started(started);
        requests.serve(|r| st.handle(&mut controller, r, now));
        if now < st.last_now {
            // Time went back (a bag looped, the simulator restarted): stamp orders and the
            // publishing schedule afresh (the controller holds on it: CLOCK_BACK).
            inputs.clock_went_back();
            st.last_latency_stamp = f64::NEG_INFINITY;
            st.last_status = f64::NEG_INFINITY;
            st.last_markers = f64::NEG_INFINITY;
        }
        st.last_now = now;
        let (mut input, fault) = inputs.read(now);
        if let Some(g) = st.ghost.as_mut() {
            g.substitute(&mut input);
        }
        let out = controller.step(kin, &input);
        if let Some(g) = st.ghost.as_mut() {
            g.follow(out.command.as_ref());
        }
        if let Some(r) = inputs.restart() {
            // After the step, so that a clock jump the step saw stays the named cause; the
            // next step's status carries the hold.
            controller.interrupt(HoldReason::DriverRestart {
                stamp_jump_s: r.stamp_jump_s,
                names_reordered: r.names_reordered,
            });
        }
        st.stats.tick(now);
        if let (Some(_), Some(t)) = (&out.command, &input.trocar) {
            if t.stamp > st.last_latency_stamp {
                st.last_latency_stamp = t.stamp;
                st.stats.latency((convert::seconds(rosrust::now()) - t.stamp) * 1e3);
            }
        }
        let status = (now - st.last_status >= st.status_period).then(|| {
            st.last_status = now;
            LoopSnapshot {
                steps: st.stats.steps(),
                rate_hz: st.stats.rate_hz(),
                latency: st.stats.percentiles(),
            }
        });
        let markers = now - st.last_markers >= st.markers_period;
        if markers {
            st.last_markers = now;
        }
        let age = |s: Option<f64>| s.map_or(f64::INFINITY, |s| (now - s) * 1e3);
        records.push(StepRecord {
            stamp,
            trocar: input.trocar.map(|t| t.value),
            depth: controller.depth(),
            ages_ms: (age(input.trocar.map(|t| t.stamp)), age(input.joints.map(|j| j.stamp))),
            elapsed: st.start_time.map_or(0.0, |t0| now - t0),
            fault,
            status,
            markers,
            out,
        });
        st.stats.step_finished(Instant::now());
        pace.sleep();
    }
}

/// Run the node until shutdown. Call after `rosrust::init`.
pub fn run() -> Result<(), NodeError> {
    let p: ControllerNodeParams = params::load_private()?;
    p.validate()?;
    let kin = Arc::new(LbrKinematics::from_model_or_file(p.model, &p.urdf_file, TIP_LINK)?);
    let mut cp = p.controller.clone();
    cp.force_feedback = p.force_feedback;
    let mut controller = Controller::new(cp.clone(), kin.limits().clone())
        .map_err(|e| NodeError::Invalid(format!("controller: {e}")))?;
    controller.set_dry_run(p.dry_run);
    let (inputs, _subs) = inputs::subscribe(&p)?;
    let (client, server) = handover::requests::<Request, Reply>(8);
    let _preflight = preflight_services(&p, &kin, &client)?;
    let _services = [
        trigger_service("~abort", &client, Request::Abort)?,
        trigger_service("~reset", &client, Request::Reset)?,
        trigger_service("~retract", &client, Request::Retract)?,
    ];
    let reconfigure_client = client.clone();
    let _reconfigure = reconfigure::serve(&cp, move |values| {
        reconfigure_client
            .call(Request::Reconfigure(values), SERVICE_TIMEOUT)
            .unwrap_or_else(|e| Err(e.to_string()))
    })?;
    let (records, receiver) = handover::outputs::<StepRecord>(64);
    let publisher = outputs::spawn_publisher(&p, receiver)?;
    if p.autostart {
        controller
            .start()
            .map_err(|e| NodeError::Invalid(format!("autostart: {e}")))?;
    }
    if p.dry_run {
        rosrust::ros_warn!(
            "docking_controller: DRY RUN at {:.0} Hz: commands {:?} on {} (not {}), the controller steers a ghost arm \
             (joints on {}); waiting for ~start",
            1.0 / p.controller.dt_s,
            p.command_type,
            p.preview_topic,
            p.command_topic,
            p.preview_joint_states_topic
        );
    } else {
        rosrust::ros_info!(
            "docking_controller: {:.0} Hz, command {:?} on {}, waiting for ~start",
            1.0 / p.controller.dt_s,
            p.command_type,
            p.command_topic
        );
    }
    if p.realtime_priority != 0 {
        match crate::realtime::set_realtime_priority(p.realtime_priority) {
            Ok(()) => {
                rosrust::ros_info!("control loop runs at SCHED_FIFO {}", p.realtime_priority);
            }
            Err(e) => {
                rosrust::ros_warn!("control loop at normal priority: {e}");
            }
        }
    }
    let started_at = p.autostart.then(|| convert::seconds(rosrust::now()));
    control_loop(&p, kin.as_ref(), controller, inputs, &server, &records, started_at);
    drop(records);
    let _ = publisher.join();
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `~start` runs the preflight for a docking that begins from IDLE only: the loop's
    /// phase decides (a hold resumed or a depth accepted skips it), and a loop that does not
    /// answer runs it, as a fresh start would.
    #[test]
    fn the_preflight_runs_on_a_fresh_start_only() {
        let (client, mut server) = handover::requests::<Request, Reply>(8);
        for (phase, fresh) in [(Phase::Idle, true), (Phase::Hold, false), (Phase::Done, false)] {
            let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
            let loop_side = {
                let stop = stop.clone();
                std::thread::spawn(move || {
                    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                        server.serve(|r| match r {
                            Request::Phase => Ok(phase.as_str().to_string()),
                            _ => Err("unexpected".into()),
                        });
                        std::thread::sleep(Duration::from_millis(1));
                    }
                    server
                })
            };
            assert_eq!(fresh_start(&client), fresh, "{phase}");
            stop.store(true, std::sync::atomic::Ordering::Relaxed);
            server = loop_side.join().unwrap();
        }
        // No loop answering: the preflight runs.
        assert!(fresh_start(&client));
    }

    #[test]
    fn a_dry_run_must_not_preview_on_the_command_topic() {
        let text = include_str!("../../../config/docking_controller.yaml");
        let shipped: ControllerNodeParams = params::from_yaml_str("docking_controller.yaml", text).unwrap();
        assert!(
            !shipped.dry_run,
            "robot.launch commands the arm unless asked for a dry run"
        );
        let mut p = ControllerNodeParams {
            dry_run: true,
            ..shipped
        };
        assert!(p.validate().is_ok());
        p.preview_topic = p.command_topic.clone();
        let e = p.validate().unwrap_err().to_string();
        assert!(
            e.contains("preview_topic") && e.contains("never commands the driver"),
            "{e}"
        );
        p.preview_topic.clear();
        assert!(p.validate().is_err());
        p.dry_run = false;
        assert!(p.validate().is_ok(), "the preview topic matters only in a dry run");
    }
}
