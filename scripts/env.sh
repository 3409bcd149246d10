# Source this file (bash): the one place that sets the environment every tool needs.
#   source scripts/env.sh
# ROS master, the package path (the checkout, whatever its folder is called), the message
# search path for rosrust, and a PATH on which ROS's Python tools work even where `python3`
# is a pyenv build that cannot import rospy.
TD_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export TD_ROOT
export ROS_MASTER_URI="${ROS_MASTER_URI:-http://127.0.0.1:11311}"
export ROS_IP="${ROS_IP:-127.0.0.1}"
export ROS_HOME="${ROS_HOME:-$TD_ROOT/target/ros_home}"
export ROS_LOG_DIR="${ROS_LOG_DIR:-$ROS_HOME/log}"
# The ROS view of the package (scripts/ros-package): target/ros_pkg/trocar_docking links to
# package.xml, launch/, config/, ... of the checkout and to ONE build profile's node binaries.
# roslaunch/rostest find a node by walking the package folder (following links) for an
# executable named `type` and take the first: walking the checkout would meet target/debug
# and target/release (and cxx's symlink loop under target/), so it walks this view instead.
case ":${ROS_PACKAGE_PATH:-}:" in
  *":$TD_ROOT/target/ros_pkg:"*) ;;
  *) export ROS_PACKAGE_PATH="$TD_ROOT/target/ros_pkg${ROS_PACKAGE_PATH:+:$ROS_PACKAGE_PATH}" ;;
esac
export ROS_DISTRO="${ROS_DISTRO:-noetic}"
export ROS_PYTHON_VERSION=3
export CMAKE_PREFIX_PATH="${CMAKE_PREFIX_PATH:-/usr}"
# Debian's ROS tools are /usr/bin python scripts; keep /usr/bin ahead of pyenv shims.
export PATH="/usr/bin:/bin:$PATH"
# Python modules of our own messages (scripts/gen-python-msgs), so rostopic/rosbag read them.
case ":${PYTHONPATH:-}:" in
  *":$TD_ROOT/target/ros_py:"*) ;;
  *) export PYTHONPATH="$TD_ROOT/target/ros_py${PYTHONPATH:+:$PYTHONPATH}" ;;
esac
