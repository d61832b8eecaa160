#!/usr/bin/env bash
# One-step set-up: create .venv, install the right torch and the project, then run
#   ./setup.sh train [train.py flags]   the main job on this machine's default backend
#   ./setup.sh test  [pytest flags]     the test suite
#   ./setup.sh install                  only install
#   ./setup.sh unitree                  also install the Go2 adapter's SDK (Unitree's unitree-sdk2
#                                       and CycloneDDS 0.10.2, built against the C library
#                                       cyclonedds-dev, installed with apt-get where it is missing)
# Environment: PYTHON (default python3), VENV (default .venv).
set -euo pipefail
cd "$(dirname "$0")"

usage="usage: ./setup.sh [install|train|test|unitree] [args...]   (default: install; env: PYTHON, VENV)"
task=${1-install}
[ $# -gt 0 ] && shift
case "$task" in
  install|train|test|unitree) ;;
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

if [ "$task" = unitree ]; then
  # CycloneDDS for Python 0.10.2 (the SDK's pin) has no wheel for this Python: it builds
  # against the C library 0.10.x, which Debian/Ubuntu package as cyclonedds-dev.
  case "${CYCLONEDDS_HOME:-/}" in
    /*) ;;
    *) echo "[setup] CYCLONEDDS_HOME must be an absolute path (pip builds cyclonedds in a temporary" \
            "folder), got '$CYCLONEDDS_HOME'" >&2; exit 1 ;;
  esac
  if [ -z "${CYCLONEDDS_HOME:-}" ] && [ ! -f /usr/include/dds/dds.h ]; then
    if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
      echo "[setup] installing the CycloneDDS C library (apt-get install cyclonedds-dev)"
      apt-get install -y -q cyclonedds-dev >/dev/null || { apt-get update -q >/dev/null && apt-get install -y -q cyclonedds-dev >/dev/null; }
    else
      echo "[setup] the CycloneDDS 0.10 C library is missing: 'sudo apt-get install cyclonedds-dev', or build" \
           "CycloneDDS 0.10.x and set CYCLONEDDS_HOME to its install prefix; then run ./setup.sh unitree again" >&2
      exit 1
    fi
  fi
  if [ -z "${CYCLONEDDS_HOME:-}" ]; then
    # Debian installs the library under lib/<multiarch>; the Python package's build looks
    # in <prefix>/lib and <prefix>/include, so give it a prefix of links.
    # The path must be absolute: pip builds cyclonedds in a temporary folder, where a
    # relative CYCLONEDDS_HOME (such as .venv/...) points nowhere.
    libdir=$(dirname "$(find /usr/lib /usr/lib64 -name 'libddsc.so' 2>/dev/null | head -n 1)")
    CYCLONEDDS_HOME="$(cd "$VENV" && pwd)/cyclonedds-prefix"
    mkdir -p "$CYCLONEDDS_HOME"
    ln -sfn /usr/include "$CYCLONEDDS_HOME/include"
    ln -sfn "$libdir" "$CYCLONEDDS_HOME/lib"
    ln -sfn /usr/bin "$CYCLONEDDS_HOME/bin"
  fi
  if ! "$PY" -c 'from legged_casters.deploy import unitree; unitree.load_sdk()' 2>/dev/null; then
    echo "[setup] installing unitree-sdk2 and cyclonedds (CYCLONEDDS_HOME=$CYCLONEDDS_HOME)"
    CYCLONEDDS_HOME="$CYCLONEDDS_HOME" pip_install -e ".[dev,unitree]"
  fi
  "$PY" -c 'from legged_casters.deploy import unitree; unitree.load_sdk(); print("[setup] unitree_sdk2py imports")'
fi

case "$task" in
  unitree) ;;
  install) echo "[setup] done: activate with 'source $VENV/bin/activate'" ;;
  train)
    # --procs auto: 2 training processes, one per core, on the CPU backend with 2+ usable
    # cores (docs/training.md). A --procs of yours comes later and wins.
    exec "$PY" train.py --procs auto "$@" ;;
  test) exec "$PY" -m pytest "$@" ;;
esac
