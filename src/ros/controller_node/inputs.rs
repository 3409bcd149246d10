//! The controller node's inputs, handed to the control loop lock-free: each subscriber
//! callback checks its message and writes the newest valid value (or `None` and the fault)
//! into a latest-value slot ([`crate::ros::handover::latest`]), which the loop reads
//! without a lock. A clock that goes back (a bag that loops, a simulator restart) bumps
//! an epoch that tells each callback to start its stamp order afresh.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use nalgebra::Isometry3;

use super::ControllerNodeParams;
use crate::control::{ControlInput, Stamped};
use crate::kinematics::JointVector;
use crate::ros::convert::{self, InputError, StampOrder};
use crate::ros::handover::{latest, FaultText, SlotReader, SlotWriter};
use crate::ros::msgs::{geometry_msgs, lbr_msgs, sensor_msgs};
use crate::ros::node::{lock, ros_err, NodeError};

/// One input as the loop sees it: the newest valid value and the last fault.
type Slot<T> = Option<Stamped<T>>;

/// The loop's end of the inputs.
pub struct InputReaders {
    joints: SlotReader<Slot<JointVector>>,
    tau_ext: SlotReader<Slot<JointVector>>,
    trocar: SlotReader<Slot<Isometry3<f64>>>,
    faults: [SlotReader<Option<FaultText>>; 3],
    epoch: Arc<AtomicU64>,
}

impl InputReaders {
    /// The inputs of a control step at `now`, and the first input fault, if any.
    pub fn read(&mut self, now: f64) -> (ControlInput, Option<FaultText>) {
        let input = ControlInput {
            now,
            joints: self.joints.read(),
            tau_ext: self.tau_ext.read(),
            trocar: self.trocar.read(),
        };
        let fault = self.faults.iter_mut().find_map(SlotReader::read);
        (input, fault)
    }

    /// The clock went back: the callbacks start their stamp orders afresh.
    pub fn clock_went_back(&self) {
        self.epoch.fetch_add(1, Ordering::Release);
    }
}

/// A subscriber's end: its slot, its fault slot, and its stamp order (touched only by the
/// subscriber's own thread).
struct Feed<T: Send> {
    value: SlotWriter<Slot<T>>,
    fault: SlotWriter<Option<FaultText>>,
    order: Mutex<(StampOrder, u64)>,
    epoch: Arc<AtomicU64>,
    topic: String,
}

impl<T: Copy + Send> Feed<T> {
    fn accept(&self, stamp: f64, value: Result<T, InputError>) {
        let epoch = self.epoch.load(Ordering::Acquire);
        let checked = value.and_then(|v| {
            let mut order = lock(&self.order);
            if order.1 != epoch {
                *order = (StampOrder::default(), epoch);
            }
            order.0.accept(&self.topic, stamp).map(|()| v)
        });
        match checked {
            Ok(value) => {
                self.value.write(Some(Stamped { stamp, value }));
                self.fault.write(None);
            }
            Err(e) => {
                rosrust::ros_warn!("input rejected, holding: {e}");
                self.value.write(None);
                self.fault.write(Some(FaultText::from_display(&e)));
            }
        }
    }
}

fn feed<T: Copy + Send>(
    topic: &str,
    epoch: &Arc<AtomicU64>,
) -> (Feed<T>, SlotReader<Slot<T>>, SlotReader<Option<FaultText>>) {
    let (value, value_r) = latest(None);
    let (fault, fault_r) = latest(None);
    let feed = Feed {
        value,
        fault,
        order: Mutex::new((StampOrder::default(), epoch.load(Ordering::Acquire))),
        epoch: epoch.clone(),
        topic: topic.to_string(),
    };
    (feed, value_r, fault_r)
}

/// Subscribe the three inputs; the subscribers live as long as the returned handles.
pub fn subscribe(p: &ControllerNodeParams) -> Result<(InputReaders, Vec<rosrust::Subscriber>), NodeError> {
    let epoch = Arc::new(AtomicU64::new(0));
    let (jf, joints, jfault) = feed::<JointVector>(&p.joint_states_topic, &epoch);
    let (tf, tau_ext, tfault) = feed::<JointVector>(&p.lbr_state_topic, &epoch);
    let (pf, trocar, pfault) = feed::<Isometry3<f64>>(&p.trocar_pose_topic, &epoch);
    let names = p.joint_names.clone();
    let frame = p.base_frame.clone();
    let subs = vec![
        rosrust::subscribe(&p.joint_states_topic, 2, move |m: sensor_msgs::JointState| {
            let q = convert::joint_positions(&jf.topic, &m, &names);
            jf.accept(convert::seconds(m.header.stamp), q);
        })
        .map_err(ros_err)?,
        rosrust::subscribe(&p.lbr_state_topic, 2, move |m: lbr_msgs::LBRState| {
            let t = convert::external_torques(&tf.topic, &m);
            tf.accept(convert::seconds(m.stamp.data), t);
        })
        .map_err(ros_err)?,
        rosrust::subscribe(&p.trocar_pose_topic, 2, move |m: geometry_msgs::PoseStamped| {
            let pose = convert::pose_in_frame(&pf.topic, &m, &frame);
            pf.accept(convert::seconds(m.header.stamp), pose);
        })
        .map_err(ros_err)?,
    ];
    let readers = InputReaders {
        joints,
        tau_ext,
        trocar,
        faults: [jfault, tfault, pfault],
        epoch,
    };
    Ok((readers, subs))
}
