//! Default topic names of the stack, one constant each: the LBR driver's (`lbr_fri_ros`,
//! namespace `/lbr`), the ZED mini camera's, and ours. Every node takes its topics as
//! parameters; these are the defaults the parameter structs, the simulator and the rostest
//! checks share (`config/*.yaml` spell the same names for the launch files).

/// Joint states of the arm (sensor_msgs/JointState), from the driver or the simulator.
pub const JOINT_STATES: &str = "/lbr/joint_states";
/// The driver's LBRState (external torques), once per FRI cycle.
pub const LBR_STATE: &str = "/lbr/states";
/// Messages a driver topic may hold, at the publisher and at a subscriber, before it drops
/// (2 s of a 500 Hz FRI stream). The preflight counts rates from the stamps of what arrives,
/// so a thread that the scheduler holds back (the simulator's publisher under load, the
/// preflight's subscriber) must delay messages, not drop them and read a slow driver.
pub const DRIVER_QUEUE: usize = 1000;
/// The joint command (trajectory_msgs/JointTrajectory, or Float64MultiArray).
pub const COMMAND: &str = "/lbr/PositionJointInterface_trajectory_controller/command";
/// The camera image (ZED mini, left, rectified).
pub const CAMERA_IMAGE: &str = "/zedm/zed_node/left/image_rect_color";
/// The camera's CameraInfo.
pub const CAMERA_INFO: &str = "/zedm/zed_node/left/camera_info";
/// The stereo pair's right image (ZED mini, right, rectified).
pub const CAMERA_RIGHT_IMAGE: &str = "/zedm/zed_node/right/image_rect_color";
/// The right camera's CameraInfo (its projection's Tx gives the baseline).
pub const CAMERA_RIGHT_INFO: &str = "/zedm/zed_node/right/camera_info";
/// The simulated camera's image: what a camera driver publishes, the raw (distorted) image
/// in image_pipeline's names (`image_raw` beside its `camera_info`).
pub const SIM_CAMERA_IMAGE: &str = "/sim_camera/left/image_raw";
/// The simulated camera's CameraInfo (K, D, R = identity, P = [K | 0]).
pub const SIM_CAMERA_INFO: &str = "/sim_camera/left/camera_info";
/// The simulated stereo pair's right raw image.
pub const SIM_CAMERA_RIGHT_IMAGE: &str = "/sim_camera/right/image_raw";
/// The simulated right camera's CameraInfo (P's Tx = -fx * baseline).
pub const SIM_CAMERA_RIGHT_INFO: &str = "/sim_camera/right/camera_info";
/// The trocar pose in the base frame (geometry_msgs/PoseStamped).
pub const TROCAR_POSE: &str = "/trocar/pose";
/// The simulator's true trocar pose.
pub const TROCAR_POSE_TRUE: &str = "/trocar/pose_true";
/// The simulator's true fulcrum: where the abdominal wall holds the trocar at rest, moving
/// with the breathing (geometry_msgs/PointStamped); what the scope should pivot about.
pub const TROCAR_FULCRUM_TRUE: &str = "/trocar/fulcrum_true";
/// The controller's status (trocar_docking/DockingStatus).
pub const DOCKING_STATUS: &str = "/docking/status";
/// Each joint command again (sensor_msgs/JointState), stamped with its control step's time.
pub const DOCKING_COMMAND_JOINTS: &str = "/docking/command_joints";
/// The estimated external force at the tip (geometry_msgs/WrenchStamped).
pub const DOCKING_F_EXT: &str = "/docking/f_ext";
/// RViz markers (visualization_msgs/MarkerArray).
pub const DOCKING_MARKERS: &str = "/docking/markers";
/// The surgeon's scope commands after docking (geometry_msgs/TwistStamped, `endoscope_tip`).
pub const SCOPE_COMMAND: &str = "/docking/scope_command";
/// A joystick (sensor_msgs/Joy, the `joy` package's `joy_node`).
pub const JOY: &str = "/joy";
/// tf.
pub const TF: &str = "/tf";
/// The simulated clock (with `/use_sim_time`).
pub const CLOCK: &str = "/clock";
