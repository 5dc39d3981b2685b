#!/usr/bin/env bash
# Create or update the project's virtual environment (.venv by default):
#   1. system libraries the wheels need (libusb-1.0 for open3d),
#   2. python3 -m venv, the pinned requirements, this package in editable mode,
#   3. orchard_mapping_msgs built with CMake and installed into the venv prefix
#      (the ros-jazzy-* wheels install their CMake packages there too).
# Normally called by `make setup`, which skips it when nothing changed.
# Environment: VENV (default .venv), PYTHON (default python3), BUILD_DIR
# (default build/orchard_mapping_msgs), JOBS (default: number of CPUs).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

VENV="${VENV:-.venv}"
PYTHON="${PYTHON:-python3}"
BUILD_DIR="${BUILD_DIR:-build/orchard_mapping_msgs}"
JOBS="${JOBS:-$(nproc 2>/dev/null || echo 2)}"
export PIP_DISABLE_PIP_VERSION_CHECK=1
export DEBIAN_FRONTEND=noninteractive

log() { printf '[setup] %s\n' "$*" >&2; }
# Run a noisy command with its output in a log file, shown only on failure.
quiet() {
  local logfile="$1"; shift
  if ! "$@" >"$logfile" 2>&1; then
    log "FAILED: $* (last lines of $logfile follow)"
    tail -n 60 "$logfile" >&2
    return 1
  fi
}

# --- 1. system packages -------------------------------------------------------
APT_UPDATED=0
apt_install() {
  local sudo=()
  if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1; then
      sudo=(sudo -n)
    else
      log "need root or sudo to install: $*"
      return 1
    fi
  fi
  if ! command -v apt-get >/dev/null 2>&1; then
    log "no apt-get; install these system packages by hand: $*"
    return 1
  fi
  if [ "$APT_UPDATED" -eq 0 ]; then
    "${sudo[@]}" apt-get update -qq </dev/null
    APT_UPDATED=1
  fi
  log "apt-get install -y $*"
  "${sudo[@]}" apt-get install -y -qq --no-install-recommends "$@" </dev/null
}

missing_pkgs=()
LDCONFIG="$(command -v ldconfig || echo /sbin/ldconfig)"   # /sbin is not on every PATH
ld_cache="$("$LDCONFIG" -p 2>/dev/null || true)"   # no `| grep -q`: SIGPIPE under pipefail
if ! grep -q 'libusb-1\.0\.so' <<<"$ld_cache"; then
  missing_pkgs+=(libusb-1.0-0)          # open3d imports fail without it
fi
if ! command -v cc >/dev/null 2>&1 || ! command -v c++ >/dev/null 2>&1; then
  missing_pkgs+=(gcc g++)               # the message package compiles C/C++
fi
if ! command -v make >/dev/null 2>&1; then
  missing_pkgs+=(make)
fi
# A Debian system Python needs the venv module and its headers (a pyenv or
# python.org build ships both).
if ! "$PYTHON" -c 'import ensurepip, venv' >/dev/null 2>&1; then
  missing_pkgs+=(python3-venv)
fi
if ! "$PYTHON" -c 'import os, sysconfig, sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' >/dev/null 2>&1; then
  missing_pkgs+=(python3-dev)
fi
if [ "${#missing_pkgs[@]}" -gt 0 ]; then
  apt_install "${missing_pkgs[@]}"
fi

# --- 2. virtual environment ---------------------------------------------------
if [ ! -x "$VENV/bin/python" ]; then
  log "creating $VENV with $("$PYTHON" -c 'import sys; print(sys.executable, sys.version.split()[0])')"
  "$PYTHON" -m venv "$VENV"
fi
VENV="$(cd "$VENV" && pwd)"
PY="$VENV/bin/python"
# pip, without the "Location 'file:///...' is ignored" lines that this
# machine's pip configuration (index folders that may not exist) prints per package.
pip_install() {
  "$PY" -m pip install -q "$@" 2>&1 | { grep -v "is ignored: it is neither a file nor a directory" || true; }
}

# requirements.lock is a pip freeze. The ros-* wheels also install an egg-info
# for the ROS package they carry (ros-action-msgs -> action_msgs, ros-rclpy ->
# rclpy, ...), so the freeze lists names that no index serves. Drop every
# `X==v` whose `ros-X` is pinned too: each comes with its ros-X wheel.
mkdir -p build
REQS=build/requirements.install.txt
"$PY" - requirements.lock "$REQS" <<'PYEOF'
import re, sys
src, dst = sys.argv[1], sys.argv[2]
pat = re.compile(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*==")
norm = lambda n: re.sub(r"[-_.]+", "-", n).lower()
lines = open(src).read().splitlines()
pinned = {norm(m.group(1)) for l in lines if (m := pat.match(l))}
out, dropped = [], 0
for l in lines:
    m = pat.match(l)
    if m and not norm(m.group(1)).startswith("ros-") and "ros-" + norm(m.group(1)) in pinned:
        dropped += 1
        continue
    out.append(l)
open(dst, "w").write("\n".join(out) + "\n")
print(f"[setup] requirements.lock: {dropped} egg-info names of ros-* wheels left to those wheels", file=sys.stderr)
PYEOF
# Each pip step is skipped while its inputs are unchanged (hash kept in the venv).
step_hash() { cat "$@" | sha256sum | cut -d' ' -f1; }
h="$(step_hash "$REQS")"
if [ "$(cat "$VENV/.reqs-hash" 2>/dev/null)" != "$h" ]; then
  log "pip install -r $REQS"
  pip_install -r "$REQS"
  echo "$h" >"$VENV/.reqs-hash"
fi
h="$(step_hash setup.py setup.cfg)"
if [ "$(cat "$VENV/.editable-hash" 2>/dev/null)" != "$h" ] || [ ! -x "$VENV/bin/orchard-map" ]; then
  log "pip install --no-deps -e ."
  pip_install --no-deps -e .
  echo "$h" >"$VENV/.editable-hash"
fi

# --- 3. message packages into the venv prefix ------------------------------------
# The ros-jazzy-* wheels install share/<pkg>/cmake, lib/ and include/ under the
# venv root ($VENV), so $VENV is both the CMake prefix and the install prefix.
# vendor/tf2_msgs: TFMessage for /tf and /tf_static (the tf2 packages are not on
# PyPI); skipped where a tf2_msgs is already importable (a sourced ROS 2 install).
CMAKE="$VENV/bin/cmake"                 # cmake from requirements.lock
export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
build_msgs() {
  local src="$1" dir="$2"
  log "building $(basename "$src") in $dir"
  mkdir -p "$dir"
  quiet "$dir/configure.log" "$CMAKE" -S "$src" -B "$dir" \
    -DCMAKE_PREFIX_PATH="$VENV" \
    -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$PY" \
    -DBUILD_TESTING=OFF \
    -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_PROJECT_INCLUDE="$ROOT/cmake/fix_wheel_includes.cmake"
  quiet "$dir/build.log" "$CMAKE" --build "$dir" -j "$JOBS"
  quiet "$dir/install.log" "$CMAKE" --install "$dir"
}
if [ -f "$VENV/share/tf2_msgs/vendored-by-orchard-mapping" ] || \
   ! "$PY" -c 'import tf2_msgs.msg' >/dev/null 2>&1; then
  build_msgs vendor/tf2_msgs "$(dirname "$BUILD_DIR")/tf2_msgs"
  touch "$VENV/share/tf2_msgs/vendored-by-orchard-mapping"
fi
build_msgs orchard_mapping_msgs "$BUILD_DIR"

# --- 4. check ------------------------------------------------------------------
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST "$PY" - <<'EOF'
import rclpy
from orchard_mapping_msgs.msg import TrunkCylinder, TrunkCylinderArray  # noqa: F401
from tf2_msgs.msg import TFMessage  # noqa: F401

rclpy.init()
try:
    node = rclpy.create_node("orchard_setup_check")
    node.create_publisher(TrunkCylinderArray, "setup_check", 1)
    node.destroy_node()
finally:
    rclpy.try_shutdown()
EOF
log "ok: $VENV ready (orchard_mapping_msgs importable, rclpy publisher created)"
