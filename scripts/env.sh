# Source this file (bash): the one place that sets the environment every tool needs.
#   source scripts/env.sh
# The catkin devel space that make build makes (scripts/catkin-devel: target/catkin_ws), so
# that ROS tools find the package, its nodes and the Python modules of its messages; the ROS
# master; and a PATH on which ROS's Python tools work even where `python3` is a pyenv build
# that cannot import rospy. Before the first make build there is no devel space yet; the
# cargo commands need none.
TD_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export TD_ROOT
export TD_CATKIN_WS="$TD_ROOT/target/catkin_ws"
if [ -f "$TD_CATKIN_WS/devel/setup.bash" ]; then
  # catkin's setup script reads unset variables: relax `set -u` while it runs.
  case $- in *u*) set +u; source "$TD_CATKIN_WS/devel/setup.bash"; set -u ;;
    *) source "$TD_CATKIN_WS/devel/setup.bash" ;; esac
fi
export ROS_MASTER_URI="${ROS_MASTER_URI:-http://127.0.0.1:11311}"
export ROS_IP="${ROS_IP:-127.0.0.1}"
export ROS_HOME="${ROS_HOME:-$TD_ROOT/target/ros_home}"
export ROS_LOG_DIR="${ROS_LOG_DIR:-$ROS_HOME/log}"
export ROS_DISTRO="${ROS_DISTRO:-noetic}"
export ROS_PYTHON_VERSION=3
export CMAKE_PREFIX_PATH="${CMAKE_PREFIX_PATH:-/usr}"
# Debian's ROS tools are /usr/bin python scripts; keep /usr/bin ahead of pyenv shims.
export PATH="/usr/bin:/bin:$PATH"

# td_node NAME: the path of one of the package's executables in the devel space (what rosrun
# and roslaunch run), or a clear error when make build has not made it.
td_node() {
  local path
  path=$(catkin_find --first-only --libexec trocar_docking "$1" 2>/dev/null || true)
  if [ -z "$path" ] || [ ! -x "$path" ]; then
    echo "$1 is not in a catkin devel space on CMAKE_PREFIX_PATH: run make build" >&2
    return 1
  fi
  echo "$path"
}
