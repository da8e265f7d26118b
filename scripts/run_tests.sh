#!/usr/bin/env bash
# Set up (idempotent) and run every test, plus ruff. Usage: bash scripts/run_tests.sh [pytest args]
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
# Every rclpy process stays on this machine and in its own DDS domain (tests pick their own ids too).
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# Idle OpenMP threads must not spin on this shared 2-core machine (Open3D, small_gicp, torch).
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-PASSIVE}
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 100 ))}
ruff check .
python -m pytest -q -p no:cacheprovider test/ "$@"
