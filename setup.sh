#!/usr/bin/env bash
# One-step set-up: create .venv, install the right torch and the project, then run
#   ./setup.sh train [train.py flags]   the main job on this machine's default backend
#   ./setup.sh test  [pytest flags]     the test suite
#   ./setup.sh install                  only install
# Environment: PYTHON (default python3), VENV (default .venv).
set -euo pipefail
cd "$(dirname "$0")"

usage="usage: ./setup.sh [install|train|test] [args...]   (default: install; env: PYTHON, VENV)"
task=${1-install}
[ $# -gt 0 ] && shift
case "$task" in
  install|train|test) ;;
  *) echo "$usage  (got '$task')" >&2; exit 2 ;;
esac

PYTHON=${PYTHON:-python3}
VENV=${VENV:-.venv}
"$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 10))' || {
  echo "legged_casters needs Python >= 3.10; set PYTHON=/path/to/python3.x" >&2; exit 1; }
[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
PY="$VENV/bin/python"
pip_install() { "$PY" -m pip install --disable-pip-version-check -q "$@"; }

# torch first: a CUDA build only where there is an NVIDIA GPU. On a CPU-only machine
# a plain "torch" from PyPI is a multi-GB CUDA build, so ask for the CPU build
# (torch 2.13.0+cpu): from a local wheel or index if pip has one configured, else
# from PyTorch's CPU index.
if ! "$PY" -c 'import torch' 2>/dev/null; then
  if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    echo "[setup] NVIDIA GPU found: installing a CUDA build of torch"
    pip_install "torch>=2.6"
  else
    echo "[setup] no NVIDIA GPU: installing the CPU build of torch"
    pip_install "torch==2.13.0+cpu" 2>/dev/null \
      || pip_install "torch==2.13.0+cpu" --extra-index-url https://download.pytorch.org/whl/cpu
  fi
fi
# Reinstall only when the declared dependencies changed.
stamp="$VENV/.legged_casters-installed"
want=$(cat pyproject.toml | cksum)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ] || ! "$PY" -c 'import legged_casters' 2>/dev/null; then
  echo "[setup] installing legged_casters and its dependencies into $VENV"
  pip_install -e ".[dev]"
  echo "$want" > "$stamp"
fi

case "$task" in
  install) echo "[setup] done: activate with 'source $VENV/bin/activate'" ;;
  train)
    if [ -f train.py ]; then
      exec "$PY" train.py "$@"
    else
      # Until train.py lands (issue 5), the main job is the caster-physics check.
      exec "$PY" scripts/plot_caster_force.py "$@"
    fi ;;
  test) exec "$PY" -m pytest "$@" ;;
esac
