# shellcheck shell=bash
# Source this (bash) to get the environment every fluxdrive process runs in:
#     source tools/env.sh
# The ./fluxdrive launcher sources it, and tests and subprocesses inherit it unchanged.
# It does not build anything: run tools/bootstrap.sh (or ./fluxdrive) first.
#
# How `import rclpy` works in the venv
# ------------------------------------
# The ROS 2 wheels are plain pip packages: Python modules in site-packages, C/C++ shared
# libraries in .venv/lib and in site-packages/ros_*.libs, CMake/ament resources in
# .venv/share. The dependency ros-wheels-bootstrapper installs ros_wheels_bootstrapper.pth;
# at every interpreter start it runs `import ros_wheels_bootstrapper`, which, unless
# _ROS_WHEELS_BOOTSTRAP_COMPLETE is set, puts .venv/lib and every site-packages/ros_*.libs
# on LD_LIBRARY_PATH and re-execs the interpreter (os.execve, same argv) so the dynamic
# loader sees them. The installed ament index (.venv/share/ament_index) is found without
# AMENT_PREFIX_PATH, so bare `.venv/bin/python -c "import rclpy"` works.
#
# What this file adds:
#   * the same LD_LIBRARY_PATH computed here plus _ROS_WHEELS_BOOTSTRAP_COMPLETE=1, which
#     saves the re-exec (about 30 ms per python start) and makes the variables explicit, so
#     a child process started with this environment works even if it is not the venv
#     python. A child given a reduced environment (no LD_LIBRARY_PATH, no guard) still
#     works through the .pth; one with the guard but without LD_LIBRARY_PATH does not:
#     pass os.environ on, whole;
#   * the colcon workspace .ws/install (our interface package flux_drive_msgs and the
#     ament_python node packages), through colcon's own .ws/install/local_setup.bash:
#     AMENT_PREFIX_PATH (rosidl typesupport and rmw find libraries through the ament index),
#     PYTHONPATH (.ws/install/lib/python3.11/site-packages, plus .ws/build/<pkg> for the
#     symlink-installed ament_python packages), LD_LIBRARY_PATH (.ws/install/lib),
#     CMAKE_PREFIX_PATH. The venv prefix is appended to AMENT_PREFIX_PATH and
#     CMAKE_PREFIX_PATH so the wheels' packages stay visible next to ours;
#   * VIRTUAL_ENV and PATH (.venv/bin first), ROS_VERSION/ROS_DISTRO/ROS_PYTHON_VERSION;
#   * ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless already set (keep DDS on this machine),
#     RMW_IMPLEMENTATION=rmw_fastrtps_cpp unless already set (the only rmw installed).
# Sourcing it twice does not grow the path variables.

# Root of the checkout: the parent of the directory holding this file. Bash only.
if [ -z "${BASH_VERSION:-}" ]; then
  echo "tools/env.sh: source it from bash" >&2
  return 1 2>/dev/null || exit 1
fi
FLUXDRIVE_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export FLUXDRIVE_ROOT
# colcon's setup scripts do not survive `set -u`: lift it while this file runs.
case $- in *u*) _fd_nounset=1; set +u ;; *) _fd_nounset= ;; esac

_fd_venv="$FLUXDRIVE_ROOT/.venv"
_fd_ws="$FLUXDRIVE_ROOT/.ws/install"

# _fd_prepend VAR DIR: put DIR first in the colon list VAR, once; drop empty entries.
_fd_prepend() {
  local _var="$1" _dir="$2" _out="$2" _item _old
  _old="${!_var:-}"
  local IFS=:
  for _item in $_old; do
    [ -n "$_item" ] && [ "$_item" != "$_dir" ] && _out="$_out:$_item"
  done
  export "$_var=$_out"
}
# _fd_append VAR DIR: put DIR last in VAR unless it is already there.
_fd_append() {
  local _var="$1" _dir="$2" _old
  _old="${!_var:-}"
  case ":$_old:" in
    *":$_dir:"*) ;;
    *) export "$_var=${_old:+$_old:}$_dir" ;;
  esac
}
# _fd_clean VAR: drop empty entries (an empty entry in LD_LIBRARY_PATH means the cwd).
_fd_clean() {
  local _var="$1" _out="" _item
  local IFS=:
  for _item in ${!_var:-}; do
    [ -n "$_item" ] && _out="${_out:+$_out:}$_item"
  done
  if [ -n "$_out" ]; then export "$_var=$_out"; else unset "$_var"; fi
}

export VIRTUAL_ENV="$_fd_venv"
_fd_prepend PATH "$_fd_venv/bin"

# Libraries of the ROS wheels (what ros_wheels_bootstrapper would add), then the guard.
for _fd_site in "$_fd_venv"/lib/python3.*/site-packages; do
  for _fd_libs in "$_fd_site"/ros_*.libs; do
    [ -d "$_fd_libs" ] && _fd_prepend LD_LIBRARY_PATH "$_fd_libs"
  done
done
_fd_prepend LD_LIBRARY_PATH "$_fd_venv/lib"
export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1

# The colcon workspace, with colcon's own script (it knows the symlink-installed packages).
if [ -f "$_fd_ws/local_setup.bash" ]; then
  _fd_cpe="${COLCON_PYTHON_EXECUTABLE-__unset__}"
  export COLCON_PYTHON_EXECUTABLE="$_fd_venv/bin/python3"
  # shellcheck disable=SC1091
  . "$_fd_ws/local_setup.bash"
  if [ "$_fd_cpe" = __unset__ ]; then unset COLCON_PYTHON_EXECUTABLE; else export COLCON_PYTHON_EXECUTABLE="$_fd_cpe"; fi
fi
[ -d "$_fd_ws/lib" ] && _fd_prepend LD_LIBRARY_PATH "$_fd_ws/lib" # overlay before the venv
_fd_append AMENT_PREFIX_PATH "$_fd_venv"
_fd_append CMAKE_PREFIX_PATH "$_fd_venv"
for _fd_v in LD_LIBRARY_PATH PYTHONPATH AMENT_PREFIX_PATH CMAKE_PREFIX_PATH PATH; do
  _fd_clean "$_fd_v"
done

export ROS_VERSION=2
export ROS_DISTRO=jazzy
export ROS_PYTHON_VERSION=3
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"

unset _fd_venv _fd_ws _fd_site _fd_libs _fd_v _fd_cpe
unset -f _fd_prepend _fd_append _fd_clean
if [ -n "$_fd_nounset" ]; then set -u; fi
unset _fd_nounset
