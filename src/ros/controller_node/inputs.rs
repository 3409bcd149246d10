//! The controller node's inputs, handed to the control loop lock-free: each subscriber
//! callback checks its message and writes the newest valid value (or `None` and the fault)
//! into a latest-value slot ([`crate::ros::handover::latest`]), which the loop reads
//! without a lock. A clock that goes back (a bag that loops, a simulator restart) bumps
//! an epoch that tells each callback to start its stamp order afresh.
//!
//! The external torques also reach the loop as a stream: every LBRState message's raw
//! torques go into a bounded lock-free queue (`crossbeam_queue::ArrayQueue`, the oldest
//! dropped when the loop falls behind, with a throttled warning), which the loop empties
//! into its [`ControlInput::torque_samples`] each step; the controller low-passes them
//! itself (`torque_filter_time_constant_s`). The queue is emptied before the torque slot is
//! read and the callback writes the slot before it queues the sample, so the slot's
//! newest sample is never older than the newest sample the loop took.
//!
//! The driver's two streams (joint states, LBRState) may restart under the controller: a
//! stamp that goes back there starts the stamp order afresh instead of rejecting every
//! message until the old stamps are passed, and the joint-state stream's restarts (stamps
//! back, a gap longer than `driver_restart_gap_s`, the names in another order; [`JointStream`])
//! reach the loop as [`Restart`] events, which hold the controller until a new start.
//! Joint values are always picked by name. A message with the same stamp as the last one
//! (a duplicate) is dropped without clearing the input.
//!
//! The surgeon's scope command (`/docking/scope_command`, a TwistStamped) is a fourth
//! latest-value input, stamped with its header stamp (a zero stamp: its arrival on the
//! node's clock). A bad one (NaN, a frame other than '' or the tip's, a stamp that goes
//! back) clears it, so the scope holds still, with a throttled warning; it is no fault of
//! the docking and never holds the controller. The controller's dead-man
//! ([`crate::control::scope::pivot::live_command`]) drops a command older than
//! `scope.command_timeout_s`, and ignores one stamped further ahead of its clock (a clock that
//! went back).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use crossbeam_queue::ArrayQueue;
use nalgebra::Isometry3;

use super::ControllerNodeParams;
use crate::control::io::TORQUE_SAMPLES;
use crate::control::{ControlInput, ScopeCommand, Stamped, TorqueSamples};
use crate::kinematics::JointVector;
use crate::ros::convert::{self, InputError, StampOrder};
use crate::ros::handover::{latest, FaultText, SlotReader, SlotWriter};
use crate::ros::msgs::{geometry_msgs, lbr_msgs, sensor_msgs};
use crate::ros::node::{lock, ros_err, NodeError, Throttle};

/// One input as the loop sees it: the newest valid value and the last fault.
type Slot<T> = Option<Stamped<T>>;

/// The loop's end of the inputs.
pub struct InputReaders {
    joints: SlotReader<Slot<JointVector>>,
    tau_ext: SlotReader<Slot<JointVector>>,
    /// Every raw torque sample since the last step, stamped, oldest first.
    torque_queue: Arc<ArrayQueue<(f64, JointVector)>>,
    trocar: SlotReader<Slot<Isometry3<f64>>>,
    scope: SlotReader<Slot<ScopeCommand>>,
    faults: [SlotReader<Option<FaultText>>; 3],
    restarts: SlotReader<Option<Restart>>,
    last_restart: u64,
    epoch: Arc<AtomicU64>,
}

/// A restart of the joint-state stream, as the loop receives it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Restart {
    /// Counts the restarts seen (a new value is a new restart).
    pub seq: u64,
    /// Change of the stamp across the restart, s (negative: back).
    pub stamp_jump_s: f64,
    /// Whether the joint names arrived in another order.
    pub names_reordered: bool,
}

/// Watches the joint-state stream for a driver restart: a stamp that goes back, a gap
/// longer than `max_gap` between consecutive messages, or the names in another order.
#[derive(Debug, Clone, Default)]
pub struct JointStream {
    last_stamp: Option<f64>,
    names: Vec<String>,
    max_gap: f64,
    restarts: u64,
}

impl JointStream {
    /// A watch that calls a gap longer than `max_gap` (s) a restart.
    pub fn new(max_gap: f64) -> Self {
        Self {
            max_gap,
            ..Self::default()
        }
    }

    /// A valid message with `stamp` and `names` arrived: the restart it reveals, if any.
    pub fn observe(&mut self, stamp: f64, names: &[String]) -> Option<Restart> {
        let reordered = !self.names.is_empty() && self.names.as_slice() != names;
        if self.names.as_slice() != names {
            self.names = names.to_vec();
        }
        let jump = self.last_stamp.map_or(0.0, |t| stamp - t);
        let gap = self.last_stamp.is_some() && (jump < 0.0 || jump > self.max_gap);
        self.last_stamp = Some(stamp);
        (gap || reordered).then(|| {
            self.restarts += 1;
            Restart {
                seq: self.restarts,
                stamp_jump_s: jump,
                names_reordered: reordered,
            }
        })
    }
}

impl InputReaders {
    /// The inputs of a control step at `now`, and the first input fault, if any.
    pub fn read(&mut self, now: f64) -> (ControlInput, Option<FaultText>) {
        // The queue first, then the slot (see the module doc).
        let mut torque_samples = TorqueSamples::default();
        while let Some((stamp, tau)) = self.torque_queue.pop() {
            torque_samples.push(stamp, tau);
        }
        let input = ControlInput {
            scope: self.scope.read(),
            now,
            joints: self.joints.read(),
            tau_ext: self.tau_ext.read(),
            torque_samples,
            trocar: self.trocar.read(),
        };
        let fault = self.faults.iter_mut().find_map(SlotReader::read);
        (input, fault)
    }

    /// A restart of the joint-state stream since the last call, if any.
    pub fn restart(&mut self) -> Option<Restart> {
        let r = self.restarts.read().filter(|r| r.seq != self.last_restart)?;
        self.last_restart = r.seq;
        Some(r)
    }

    /// The clock went back: the callbacks start their stamp orders afresh.
    pub fn clock_went_back(&self) {
        self.epoch.fetch_add(1, Ordering::Release);
    }
}

/// What a rejected message does besides clearing its input.
enum OnReject {
    /// The docking inputs: the reason goes to the loop (the hold's cause), logged each time.
    Fault(SlotWriter<Option<FaultText>>),
    /// The scope command: logged at most once per period of the throttle.
    Log(Throttle),
}

/// A subscriber's end: its slot, what a rejection does, and its stamp order (touched only
/// by the subscriber's own thread).
struct Feed<T: Send> {
    value: SlotWriter<Slot<T>>,
    on_reject: OnReject,
    order: Mutex<(StampOrder, u64)>,
    epoch: Arc<AtomicU64>,
    topic: String,
    /// A stamp that goes back restarts the stream (the driver's topics) instead of being
    /// rejected.
    restartable: bool,
}

impl<T: Copy + Send> Feed<T> {
    /// Check `value`'s stamp order; `Ok(false)`: a duplicate, dropped.
    fn in_order(&self, stamp: f64) -> Result<bool, InputError> {
        let epoch = self.epoch.load(Ordering::Acquire);
        let mut order = lock(&self.order);
        if order.1 != epoch {
            *order = (StampOrder::default(), epoch);
        }
        match order.0.accept(&self.topic, stamp) {
            Ok(()) => Ok(true),
            Err(InputError::OutOfOrder { previous, got, .. }) if got == previous => Ok(false),
            Err(InputError::OutOfOrder { .. }) if self.restartable => {
                order.0.reset();
                order.0.accept(&self.topic, stamp).map(|()| true)
            }
            Err(e) => Err(e),
        }
    }

    /// Take a converted message; `true` when it was accepted as the newest value. A
    /// rejected one is logged (throttled for the scope command).
    fn accept(&self, stamp: f64, value: Result<T, InputError>) -> bool {
        match self.take(stamp, value) {
            Ok(fresh) => fresh,
            Err(e) => {
                match &self.on_reject {
                    OnReject::Fault(_) => {
                        rosrust::ros_warn!("input rejected, holding: {e}");
                    }
                    OnReject::Log(t) => {
                        if t.ready() {
                            rosrust::ros_warn!("scope command rejected, the scope holds still: {e}");
                        }
                    }
                }
                false
            }
        }
    }

    /// Store a converted message: `Ok(true)` the newest value, `Ok(false)` a duplicate
    /// (dropped), `Err` rejected: the input is cleared (and the fault set, for a docking input).
    fn take(&self, stamp: f64, value: Result<T, InputError>) -> Result<bool, InputError> {
        let checked = value.and_then(|v| self.in_order(stamp).map(|fresh| fresh.then_some(v)));
        let fault = match &self.on_reject {
            OnReject::Fault(f) => Some(f),
            OnReject::Log(_) => None,
        };
        match checked {
            Ok(None) => Ok(false),
            Ok(Some(value)) => {
                self.value.write(Some(Stamped { stamp, value }));
                fault.inspect(|f| f.write(None));
                Ok(true)
            }
            Err(e) => {
                self.value.write(None);
                fault.inspect(|f| f.write(Some(FaultText::from_display(&e))));
                Err(e)
            }
        }
    }
}

fn feed_with<T: Copy + Send>(
    topic: &str,
    epoch: &Arc<AtomicU64>,
    restartable: bool,
    on_reject: OnReject,
) -> (Feed<T>, SlotReader<Slot<T>>) {
    let (value, value_r) = latest(None);
    let feed = Feed {
        value,
        on_reject,
        order: Mutex::new((StampOrder::default(), epoch.load(Ordering::Acquire))),
        epoch: epoch.clone(),
        topic: topic.to_string(),
        restartable,
    };
    (feed, value_r)
}

fn feed<T: Copy + Send>(
    topic: &str,
    epoch: &Arc<AtomicU64>,
    restartable: bool,
) -> (Feed<T>, SlotReader<Slot<T>>, SlotReader<Option<FaultText>>) {
    let (fault, fault_r) = latest(None);
    let (feed, value_r) = feed_with(topic, epoch, restartable, OnReject::Fault(fault));
    (feed, value_r, fault_r)
}

/// How often a rejected scope command is logged at most.
const SCOPE_LOG_PERIOD: std::time::Duration = std::time::Duration::from_secs(2);

/// Subscribe the four inputs; the subscribers live as long as the returned handles.
pub fn subscribe(p: &ControllerNodeParams) -> Result<(InputReaders, Vec<rosrust::Subscriber>), NodeError> {
    let epoch = Arc::new(AtomicU64::new(0));
    let (jf, joints, jfault) = feed::<JointVector>(&p.joint_states_topic, &epoch, true);
    let (tf, tau_ext, tfault) = feed::<JointVector>(&p.lbr_state_topic, &epoch, true);
    let (pf, trocar, pfault) = feed::<Isometry3<f64>>(&p.trocar_pose_topic, &epoch, false);
    let (sf, scope) = feed_with::<ScopeCommand>(
        &p.scope_command_topic,
        &epoch,
        false,
        OnReject::Log(Throttle::new(SCOPE_LOG_PERIOD)),
    );
    let tip_frame = p.tip_frame.clone();
    let (restart_w, restarts) = latest(None);
    let stream = Mutex::new(JointStream::new(p.driver_restart_gap_s));
    let names = p.joint_names.clone();
    let torque_queue = Arc::new(ArrayQueue::new(TORQUE_SAMPLES));
    let torque_feed = torque_queue.clone();
    let behind = Throttle::new(SCOPE_LOG_PERIOD);
    let dropped = AtomicU64::new(0);
    let frame = p.base_frame.clone();
    // Queues of one: the loop only ever wants the newest message, and a flood is dropped
    // in the transport instead of queued.
    let subs = vec![
        rosrust::subscribe(&p.joint_states_topic, 1, move |m: sensor_msgs::JointState| {
            let stamp = convert::seconds(m.header.stamp);
            let q = convert::joint_positions(&jf.topic, &m, &names);
            if jf.accept(stamp, q) {
                let restart = lock(&stream).observe(stamp, &m.name);
                if let Some(r) = restart {
                    rosrust::ros_warn!(
                        "{}: the joint states restarted (stamps {:+.3} s, names reordered: {}): holding until a new start",
                        jf.topic,
                        r.stamp_jump_s,
                        r.names_reordered
                    );
                    restart_w.write(Some(r));
                }
            }
        })
        .map_err(ros_err)?,
        // Every FRI cycle's raw torques go to the controller's low-pass, in order: the
        // newest (or the rejection) into the slot first, then the sample into the queue.
        rosrust::subscribe(&p.lbr_state_topic, 1, move |m: lbr_msgs::LBRState| {
            let stamp = convert::seconds(m.stamp.data);
            let t = convert::external_torques(&tf.topic, &m);
            let sample = t.as_ref().ok().copied();
            tf.accept(stamp, t);
            if let Some(tau) = sample {
                if torque_feed.force_push((stamp, tau)).is_some() {
                    let n = dropped.fetch_add(1, Ordering::Relaxed) + 1;
                    if behind.ready() {
                        rosrust::ros_warn!("{}: the control loop fell behind, {n} torque samples dropped", tf.topic);
                    }
                }
            }
        })
        .map_err(ros_err)?,
        rosrust::subscribe(&p.trocar_pose_topic, 1, move |m: geometry_msgs::PoseStamped| {
            let pose = convert::pose_in_frame(&pf.topic, &m, &frame);
            pf.accept(convert::seconds(m.header.stamp), pose);
        })
        .map_err(ros_err)?,
        rosrust::subscribe(&p.scope_command_topic, 1, move |m: geometry_msgs::TwistStamped| {
            let stamp = convert::scope_stamp(&m, convert::seconds(rosrust::now()));
            sf.accept(stamp, convert::scope_command(&sf.topic, &m, &tip_frame));
        })
        .map_err(ros_err)?,
    ];
    let readers = InputReaders {
        joints,
        tau_ext,
        torque_queue,
        trocar,
        scope,
        faults: [jfault, tfault, pfault],
        restarts,
        last_restart: 0,
        epoch,
    };
    Ok((readers, subs))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_joint_stream_restart_is_stamps_back_a_gap_or_reordered_names() {
        let names = crate::kinematics::joint_names();
        let mut reversed = names.clone();
        reversed.reverse();
        let mut s = JointStream::new(0.1);
        assert_eq!(s.observe(10.0, &names), None, "the first message is no restart");
        assert_eq!(s.observe(10.002, &names), None);
        assert_eq!(s.observe(10.05, &names), None, "a gap under the timeout is none");
        let back = s.observe(0.5, &names).expect("stamps restarted");
        assert!(back.stamp_jump_s < -9.0 && !back.names_reordered && back.seq == 1);
        assert_eq!(s.observe(0.502, &names), None, "the new stream goes on");
        let gap = s.observe(3.0, &names).expect("resumed after an interruption");
        assert!(gap.stamp_jump_s > 2.0 && gap.seq == 2);
        let order = s.observe(3.002, &reversed).expect("names in another order");
        assert!(order.names_reordered && order.seq == 3);
        assert_eq!(s.observe(3.004, &reversed), None, "the new order is now the stream's");
    }

    #[test]
    fn a_bad_scope_command_clears_the_input_and_holds_no_fault() {
        let epoch = Arc::new(AtomicU64::new(0));
        let throttle = Throttle::new(SCOPE_LOG_PERIOD);
        let (f, mut r) = feed_with::<ScopeCommand>("/docking/scope_command", &epoch, false, OnReject::Log(throttle));
        let pan = ScopeCommand {
            pan: 0.1,
            ..ScopeCommand::default()
        };
        assert_eq!(f.take(1.0, Ok(pan)), Ok(true));
        assert_eq!(r.read().map(|c| (c.stamp, c.value)), Some((1.0, pan)));
        let bad = convert::scope_command(
            "t",
            &convert::scope_twist(convert::ros_time(1.1), "lbr_link_0", &pan),
            "endoscope_tip",
        );
        assert!(matches!(f.take(1.1, bad), Err(InputError::WrongFrame { .. })));
        assert_eq!(r.read(), None, "a rejected command stops the scope");
        assert_eq!(f.take(1.2, Ok(pan)), Ok(true));
        assert!(f.take(1.15, Ok(pan)).is_err(), "a stamp that goes back is rejected");
        assert_eq!(r.read(), None);
        // A clock that went back starts the order afresh.
        epoch.fetch_add(1, Ordering::Release);
        assert_eq!(f.take(0.5, Ok(pan)), Ok(true));
        assert!(r.read().is_some());
    }
}
