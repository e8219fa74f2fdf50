#!/usr/bin/env bash
# Set up the rclpy environment (tests/ros/setup.sh) and run the interop test of `bom node`
# (tests/ros/interop.py) on loopback. Usage: tests/ros/run_interop.sh [VENV [WORKSPACE]]
set -euo pipefail
cd "$(dirname "$0")/../.."
VENV=${1:-target/ros-venv}
WS=${2:-target/ros-ws}
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-73}
tests/ros/setup.sh "$VENV" "$WS"
# shellcheck disable=SC1091
. "$VENV/bin/activate"
# colcon's setup scripts read unset variables.
set +u
# shellcheck disable=SC1091
. "$WS/install/setup.bash"
set -u
# Loopback only: capture this domain's DDS traffic (RTPS ports 7400 + 250 x domain onwards, and
# the SPDP multicast group) on every other interface while the test runs; it must stay empty.
BASE=$((7400 + 250 * ROS_DOMAIN_ID))
CAPS=()
if command -v tcpdump >/dev/null && [ "$(id -u)" = 0 ]; then
  for dev in $(ls /sys/class/net); do
    [ "$dev" = lo ] && continue
    [ "$(cat "/sys/class/net/$dev/operstate" 2>/dev/null)" = down ] && continue
    tcpdump -i "$dev" -n -q -w "target/interop-$dev.pcap" "udp and (portrange $BASE-$((BASE + 249)) or dst host 239.255.0.1)" 2>/dev/null &
    CAPS+=("$dev:$!")
  done
  sleep 1
else
  echo "note: tcpdump (as root) not available: the loopback-only check is skipped"
fi
status=0
python tests/ros/interop.py --bom target/release/bom --bag bags/mujoco/drawer_limit_undeclared.mcap || status=$?
# BOM-NUTS in the node (issue 26), on a real door track (kinematic mode: seconds of sampling).
printf 'bom:\n  ros__parameters:\n    nuts:\n      enabled: true\n' > target/interop-nuts.yaml
python tests/ros/interop.py --bom target/release/bom --bag bags/sturm/left_door_001.mcap \
  --params-file target/interop-nuts.yaml --log target/interop-node-nuts.log --expect-nuts || status=$?
for c in "${CAPS[@]}"; do
  dev=${c%%:*}; pid=${c##*:}
  kill -INT "$pid" 2>/dev/null || true
  wait "$pid" 2>/dev/null || true
  # An unreadable capture (tcpdump died, no file) proves nothing: that is a failure, not 0 packets.
  if ! out=$(tcpdump -r "target/interop-$dev.pcap" -n 2>/dev/null); then
    echo "FAIL  the capture on $dev could not be read (target/interop-$dev.pcap): loopback-only not shown"
    status=1
    continue
  fi
  n=$(printf '%s' "$out" | grep -c . || true)
  if [ "$n" = 0 ]; then
    echo "ok    no DDS packet of domain $ROS_DOMAIN_ID on $dev (loopback only)"
  else
    echo "FAIL  $n DDS packet(s) of domain $ROS_DOMAIN_ID left loopback on $dev"
    printf '%s\n' "$out" | head -5
    status=1
  fi
done
exit $status
