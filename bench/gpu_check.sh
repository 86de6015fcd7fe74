#!/usr/bin/env bash
# The GPU check (bench/gpu_check.py): stage one on hopper-m-r, then TD3+BC with 10 stacked seeds
# for what fits the budget. `--dry-run` runs the same path on CPU in seconds.
#   bench/gpu_check.sh [--dry-run] [--budget-s 450] [--root DIR] [--json-out FILE]
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-.venv/bin/python}"
export MUJOCO_GL="${MUJOCO_GL:-egl}" PYTHONUNBUFFERED=1 OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
exec "$PYTHON" bench/gpu_check.py "$@"
