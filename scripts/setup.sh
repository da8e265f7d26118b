#!/usr/bin/env bash
# Set up a fresh machine for genreg: Debian libs, a venv in .venv, Python deps, ROS 2 Kilted wheels.
# Idempotent: a second run only checks. Usage: bash scripts/setup.sh
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then
  if command -v apt-get >/dev/null; then
    (apt-get update -qq && apt-get install -y -qq libusb-1.0-0 libgl1 libgomp1) >/dev/null
  fi
fi
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
. .venv/bin/activate
STAMP=.venv/.genreg-deps
REQ_HASH=$( (cat scripts/setup.sh setup.py 2>/dev/null || true) | sha256sum | cut -c1-16)
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$REQ_HASH" ]; then
  pip install -q --upgrade pip
  # torch pinned: the CPU wheel on local disk (a bare 'torch' pulls a multi-GB CUDA build).
  pip install -q torch==2.13.0
  pip install -q numpy scipy numba open3d small_gicp kiss-matcher rosbags mcap tqdm matplotlib pytest ruff pyyaml pillow \
    hypothesis scikit-learn \
    colcon-common-extensions
  pip install -q ros-kilted-rclpy ros-kilted-rmw-fastrtps-cpp ros-kilted-sensor-msgs \
    ros-kilted-geometry-msgs ros-kilted-diagnostic-msgs ros-kilted-lifecycle-msgs ros-kilted-rcl-lifecycle \
    ros-kilted-std-srvs ros-kilted-nav-msgs
  [ -f setup.py ] && pip install -q --no-deps -e .
  echo "$REQ_HASH" > "$STAMP"
fi
# Compile genreg's numba kernels once into their cache (about half a minute cold, a second when cached).
python -m genreg_core.kernels
