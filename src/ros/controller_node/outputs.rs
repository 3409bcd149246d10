//! The controller node's outputs, published off the control loop: the loop pushes one
//! [`StepRecord`] per step into a lock-free queue ([`crate::ros::handover::outputs`]) and
//! a publisher thread turns it into messages (rosrust's publish serialises and allocates):
//! the joint command every step, `/docking/status` and `/docking/f_ext` at the status rate,
//! markers and tf at the markers rate. The trajectory command's stamp is 0 as shipped
//! (`command_stamp: next_update`: the driver's trajectory controller starts it at its own next
//! update, [`crate::ros::node::CommandStamp`]). A scope command the controller ignored (not finite,
//! stamped in the future) is logged here, throttled. In a dry run the command goes to the
//! preview topic instead, with the ghost's joints, the ghost's base frame and the tip's path.

use std::collections::VecDeque;
use std::time::Duration;

use nalgebra::{Isometry3, Point3};

use super::ControllerNodeParams;
use crate::control::docking::depth::DepthReport;
use crate::control::ControlOutput;
use crate::kinematics::JointVector;
use crate::ros::convert;
use crate::ros::handover::{FaultText, OutputReceiver, RecvError};
use crate::ros::markers::{self, Scene};
use crate::ros::msgs::{geometry_msgs, sensor_msgs, std_msgs, tf2_msgs, trocar_docking, visualization_msgs};
use crate::ros::node::{ros_err, CommandStamp, CommandType, NodeError, Throttle};
use crate::ros::stats::Percentiles;

/// What the loop hands the publisher after a step.
#[derive(Debug, Clone)]
pub struct StepRecord {
    /// The step's time.
    pub stamp: rosrust::Time,
    /// The controller's output.
    pub out: ControlOutput,
    /// The trocar pose the step used.
    pub trocar: Option<Isometry3<f64>>,
    /// The tip's depth as the controller knows it (None before INSERT).
    pub depth: Option<DepthReport>,
    /// The first input fault at this step.
    pub fault: Option<FaultText>,
    /// Seconds since start.
    pub elapsed: f64,
    /// Ages of the trocar pose and the joint state, ms.
    pub ages_ms: (f64, f64),
    /// Loop statistics when the status is due this step (`None`: not due).
    pub status: Option<LoopSnapshot>,
    /// Whether markers and tf are due this step.
    pub markers: bool,
}

/// The loop statistics a status carries.
#[derive(Debug, Clone, Copy, Default)]
pub struct LoopSnapshot {
    /// Control steps since start.
    pub steps: u64,
    /// Measured loop rate, Hz.
    pub rate_hz: f64,
    /// Trocar measurement -> command latency, ms.
    pub latency: Percentiles,
}

/// Publishers of the node.
struct Outputs {
    trajectory: Option<rosrust::Publisher<convert::AsStamped>>,
    multiarray: Option<rosrust::Publisher<std_msgs::Float64MultiArray>>,
    /// Each command again, stamped with its step's time (`None` in a dry run).
    command_joints: Option<rosrust::Publisher<sensor_msgs::JointState>>,
    status: rosrust::Publisher<trocar_docking::DockingStatus>,
    f_ext: rosrust::Publisher<geometry_msgs::WrenchStamped>,
    markers: rosrust::Publisher<visualization_msgs::MarkerArray>,
    tf: rosrust::Publisher<tf2_msgs::TFMessage>,
    ignored_log: Throttle,
    /// Dry run only: the ghost's joints and the tip's path so far.
    preview: Option<Preview>,
}

/// A dry run's extra outputs.
struct Preview {
    joints: rosrust::Publisher<sensor_msgs::JointState>,
    /// The tip's positions at the markers rate, newest last, at most [`TIP_PATH_POINTS`].
    tip_path: VecDeque<Point3<f64>>,
    /// The ghost's base frame (`ghost/` + the base frame, robot_state_publisher's prefix).
    base_frame: String,
}

/// Points of the drawn tip path: 60 s at the default 20 Hz markers rate.
const TIP_PATH_POINTS: usize = 1200;

impl Outputs {
    fn new(p: &ControllerNodeParams) -> Result<Self, NodeError> {
        let topic = if p.dry_run { &p.preview_topic } else { &p.command_topic };
        let (trajectory, multiarray) = match p.command_type {
            CommandType::Trajectory => (Some(rosrust::publish(topic, 1).map_err(ros_err)?), None),
            CommandType::Float64MultiArray => (None, Some(rosrust::publish(topic, 1).map_err(ros_err)?)),
        };
        let preview = if p.dry_run {
            Some(Preview {
                joints: rosrust::publish(&p.preview_joint_states_topic, 10).map_err(ros_err)?,
                tip_path: VecDeque::with_capacity(TIP_PATH_POINTS),
                base_frame: ghost_frame(&p.base_frame),
            })
        } else {
            None
        };
        Ok(Self {
            trajectory,
            multiarray,
            command_joints: if p.dry_run {
                None
            } else {
                Some(rosrust::publish(&p.command_joints_topic, 100).map_err(ros_err)?)
            },
            status: rosrust::publish(&p.status_topic, 10).map_err(ros_err)?,
            f_ext: rosrust::publish(&p.f_ext_topic, 10).map_err(ros_err)?,
            markers: rosrust::publish(&p.markers_topic, 2).map_err(ros_err)?,
            tf: rosrust::publish(crate::ros::topics::TF, 10).map_err(ros_err)?,
            ignored_log: Throttle::new(Duration::from_secs(2)),
            preview,
        })
    }

    fn command(&self, p: &ControllerNodeParams, stamp: rosrust::Time, q: &JointVector) {
        let r = match (&self.trajectory, &self.multiarray) {
            (Some(t), _) => t.send(convert::trajectory_command(
                match p.command_stamp {
                    CommandStamp::NextUpdate => rosrust::Time::default(),
                    CommandStamp::Step => stamp,
                },
                &p.joint_names,
                q,
                p.command_lookahead_periods * p.controller.dt_s,
            )),
            (_, Some(m)) => m.send(convert::multiarray_command(q)),
            _ => Ok(()),
        };
        if let Err(e) = r {
            rosrust::ros_err!("cannot publish the command: {e}");
        }
        if let Some(c) = &self.command_joints {
            // Numbered by its own publisher in step with the command's (one each per command).
            let mut m = convert::joint_state(stamp, &p.joint_names, q, &JointVector::zeros());
            m.effort.clear();
            let _ = c.send(m);
        }
    }

    fn publish(&mut self, p: &ControllerNodeParams, r: &StepRecord) {
        if let Some(why) = r.out.pivot.and_then(|v| v.ignored) {
            if self.ignored_log.ready() {
                rosrust::ros_warn!("{why}");
            }
        }
        if let Some(q) = &r.out.command {
            self.command(p, r.stamp, q);
            if let Some(v) = &self.preview {
                let _ = v
                    .joints
                    .send(convert::joint_state(r.stamp, &p.joint_names, q, &JointVector::zeros()));
            }
        }
        if let Some(snapshot) = &r.status {
            let _ = self.status.send(status_msg(&p.base_frame, r, snapshot));
            let _ = self.f_ext.send(geometry_msgs::WrenchStamped {
                header: convert::header(r.stamp, &p.base_frame),
                wrench: geometry_msgs::Wrench {
                    force: convert::vector_msg(&r.out.f_ext),
                    torque: geometry_msgs::Vector3::default(),
                },
            });
        }
        if r.markers {
            self.scene(p, r);
        }
    }

    fn scene(&mut self, p: &ControllerNodeParams, r: &StepRecord) {
        let out = &r.out;
        let scene = Scene {
            trocar: r.trocar,
            goal: out.goal,
            tip: out.tip,
            f_ext: out.f_ext,
            reference: out.reference,
            pivot: out.pivot,
        };
        let mut array = markers::docking_markers(r.stamp, &p.base_frame, &scene, &p.markers);
        let mut transforms = Vec::new();
        if let Some(v) = self.preview.as_mut() {
            if out.phase == crate::control::Phase::Idle {
                v.tip_path.clear();
            } else if let Some(tip) = out.tip {
                if v.tip_path.len() == TIP_PATH_POINTS {
                    v.tip_path.pop_front();
                }
                v.tip_path.push_back(Point3::from(tip.translation.vector));
            }
            array
                .markers
                .push(markers::tip_path(r.stamp, &p.base_frame, v.tip_path.iter(), &p.markers));
            transforms.push(convert::transform_stamped(
                r.stamp,
                &p.base_frame,
                &v.base_frame,
                &Isometry3::identity(),
            ));
        }
        let _ = self.markers.send(array);
        if let (Some(t), Some(g)) = (&r.trocar, out.goal) {
            let goal = Isometry3::from_parts(g.coords.into(), t.rotation);
            transforms.push(convert::transform_stamped(r.stamp, &p.base_frame, &p.trocar_frame, t));
            transforms.push(convert::transform_stamped(r.stamp, &p.base_frame, &p.goal_frame, &goal));
        }
        if !transforms.is_empty() {
            let _ = self.tf.send(tf2_msgs::TFMessage { transforms });
        }
    }
}

/// The dry run's ghost frame for `frame`: robot_state_publisher's `tf_prefix` `ghost`.
fn ghost_frame(frame: &str) -> String {
    format!("ghost/{}", frame.trim_start_matches('/'))
}

/// Tip distance to the insertion axis of `trocar` (m).
fn distance_to_axis(tip: &Isometry3<f64>, trocar: &Isometry3<f64>) -> f64 {
    let local = trocar.inverse_transform_point(&Point3::from(tip.translation.vector));
    local.x.hypot(local.y)
}

/// The hold reason text and code of a step: the controller's, with an input fault (a
/// message the node dropped) as the cause when there is one.
fn hold_text_and_code(out: &ControlOutput, fault: Option<&FaultText>) -> (String, &'static str) {
    match (fault.map(FaultText::as_str), out.reason_text()) {
        (Some(f), Some(r)) if !r.contains(f) => (format!("{r}; input: {f}"), "INPUT_REJECTED"),
        (Some(_), Some(r)) => (r, "INPUT_REJECTED"),
        (Some(f), None) => (f.to_string(), "INPUT_REJECTED"),
        (None, Some(r)) => (r, out.reason_code()),
        (None, None) => (String::new(), ""),
    }
}

/// Fill a DockingStatus from a step record.
fn status_msg(frame: &str, r: &StepRecord, s: &LoopSnapshot) -> trocar_docking::DockingStatus {
    let out = &r.out;
    let (hold_reason, hold_code) = hold_text_and_code(out, r.fault.as_ref());
    let costs = out.solve.as_ref().map_or([f64::NAN; 5], |s| s.costs);
    let tip_point = out.tip.map(|t| Point3::from(t.translation.vector));
    let pivot = out.pivot.as_ref();
    trocar_docking::DockingStatus {
        header: convert::header(r.stamp, frame),
        phase: out.phase.to_string(),
        hold_reason,
        hold_code: hold_code.to_string(),
        cost_axis: costs[0],
        cost_goal: costs[1],
        cost_alignment: costs[2],
        cost_joint_step: costs[3],
        cost_admittance: costs[4],
        iterations: out
            .solve
            .as_ref()
            .map_or(0, |s| u32::try_from(s.iterations).unwrap_or(u32::MAX)),
        solve_time_us: out.solve.as_ref().map_or(0.0, |s| s.solve_time_us),
        solver_status: out.solve.as_ref().map_or("not_run", |s| s.status.as_text()).to_string(),
        f_ext: convert::vector_msg(&out.f_ext),
        f_ext_norm: out.f_ext.norm(),
        metric_m: out.metric_m,
        metric_m_paper_scale: crate::control::docking::metrics::PAPER_CODE_SCALE * out.metric_m,
        elapsed: r.elapsed,
        tip_to_goal: match (tip_point, out.goal) {
            (Some(t), Some(g)) => (t - g).norm(),
            _ => f64::NAN,
        },
        tip_to_axis: match (&out.tip, &r.trocar) {
            (Some(tip), Some(t)) => distance_to_axis(tip, t),
            _ => f64::NAN,
        },
        steps: s.steps,
        loop_rate_hz: s.rate_hz,
        latency_p50_ms: s.latency.p50,
        latency_p99_ms: s.latency.p99,
        latency_max_ms: s.latency.max,
        trocar_age_ms: r.ages_ms.0,
        joints_age_ms: r.ages_ms.1,
        fulcrum: convert::point_msg(&pivot.map_or(Point3::new(f64::NAN, f64::NAN, f64::NAN), |p| p.fulcrum)),
        shaft_to_fulcrum: pivot.map_or(f64::NAN, |p| p.shaft_distance),
        lateral_force: pivot.map_or(f64::NAN, |p| p.lateral_force),
        scope_limit: pivot
            .and_then(|p| p.limit)
            .map_or_else(String::new, |l| l.code().to_string()),
        depth_correction: r.depth.map_or(0.0, |d| d.correction),
        depth_uncertainty: r.depth.map_or(f64::NAN, |d| d.uncertainty),
        depth_basis: r.depth.map_or("", |d| d.basis.code()).to_string(),
    }
}

/// Start the publisher thread: it publishes every record until the loop closes the queue.
pub fn spawn_publisher(
    p: &ControllerNodeParams,
    records: OutputReceiver<StepRecord>,
) -> Result<std::thread::JoinHandle<()>, NodeError> {
    let mut outputs = Outputs::new(p)?;
    let p = p.clone();
    std::thread::Builder::new()
        .name("docking_publisher".into())
        .spawn(move || loop {
            match records.recv_timeout(Duration::from_millis(200)) {
                Ok(r) => outputs.publish(&p, &r),
                Err(RecvError::Timeout) => {}
                Err(RecvError::Closed) => break,
            }
        })
        .map_err(|e| NodeError::Invalid(format!("cannot start the publisher thread: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::{HoldReason, Phase};

    fn out(hold: Option<HoldReason>) -> ControlOutput {
        ControlOutput {
            hold,
            ..ControlOutput::empty(Phase::Hold)
        }
    }

    #[test]
    fn an_input_fault_is_the_code_and_joins_the_text() {
        let o = out(Some(HoldReason::NoTrocarPose));
        let f = FaultText::new("/trocar/pose: frame 'camera' is not 'lbr_link_0'");
        let (text, code) = hold_text_and_code(&o, Some(&f));
        assert_eq!(code, "INPUT_REJECTED");
        assert!(
            text.contains("no trocar pose") && text.contains("frame 'camera'"),
            "{text}"
        );
        assert_eq!(hold_text_and_code(&o, None).1, "NO_TROCAR_POSE");
        assert_eq!(hold_text_and_code(&out(None), None), (String::new(), ""));
    }

    fn record(out: ControlOutput) -> StepRecord {
        StepRecord {
            stamp: convert::ros_time(10.0),
            out,
            trocar: None,
            depth: None,
            fault: None,
            elapsed: 1.0,
            ages_ms: (0.0, 0.0),
            status: None,
            markers: false,
        }
    }

    #[test]
    fn the_status_carries_the_pivot_while_the_port_is_held() {
        use crate::control::{PivotReport, ScopeLimit};
        let pivot = PivotReport {
            fulcrum: Point3::new(0.6, -0.05, 0.25),
            shaft_distance: 3e-4,
            lateral_force: 0.4,
            depth: 0.03,
            cone_axis: nalgebra::Vector3::z(),
            cone_half_angle: 0.5,
            limit: Some(ScopeLimit::MaxDepth),
            ignored: None,
            fulcrum_depth: 0.02,
            breathing_offset: 0.0,
        };
        let held = ControlOutput {
            pivot: Some(pivot),
            ..ControlOutput::empty(Phase::Done)
        };
        let s = status_msg("lbr_link_0", &record(held), &LoopSnapshot::default());
        assert_eq!(s.phase, "DONE");
        assert_eq!((s.fulcrum.x, s.fulcrum.y, s.fulcrum.z), (0.6, -0.05, 0.25));
        assert_eq!(s.shaft_to_fulcrum, 3e-4);
        assert_eq!(s.lateral_force, 0.4);
        assert_eq!(s.scope_limit, "MAX_DEPTH");
        let free = ControlOutput {
            pivot: Some(PivotReport { limit: None, ..pivot }),
            ..ControlOutput::empty(Phase::Retract)
        };
        let s = status_msg("lbr_link_0", &record(free), &LoopSnapshot::default());
        assert_eq!((s.phase.as_str(), s.scope_limit.as_str()), ("RETRACT", ""));
        let s = status_msg("lbr_link_0", &record(out(None)), &LoopSnapshot::default());
        assert!(s.fulcrum.x.is_nan() && s.shaft_to_fulcrum.is_nan() && s.lateral_force.is_nan());
        assert_eq!(s.scope_limit, "");
    }

    #[test]
    fn the_status_carries_the_depth_and_what_it_rests_on() {
        use crate::control::docking::depth::DepthBasis;
        let s = status_msg("lbr_link_0", &record(out(None)), &LoopSnapshot::default());
        assert!(s.depth_uncertainty.is_nan() && s.depth_correction == 0.0 && s.depth_basis.is_empty());
        let mut r = record(ControlOutput::empty(Phase::Done));
        r.depth = Some(DepthReport {
            correction: 0.0031,
            uncertainty: 0.0015,
            basis: DepthBasis::Seal { correction: 0.0031 },
        });
        let s = status_msg("lbr_link_0", &r, &LoopSnapshot::default());
        assert_eq!((s.depth_correction, s.depth_uncertainty), (0.0031, 0.0015));
        assert_eq!(s.depth_basis, "SEAL");
        r.depth = Some(DepthReport {
            correction: 0.0,
            uncertainty: 0.0056,
            basis: DepthBasis::Refused {
                correction: 0.013,
                bound: 0.0072,
            },
        });
        let s = status_msg("lbr_link_0", &r, &LoopSnapshot::default());
        assert_eq!((s.depth_basis.as_str(), s.depth_correction), ("REFUSED", 0.0));
    }
}
