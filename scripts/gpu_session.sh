#!/usr/bin/env bash
# The one call a session with a lent GPU makes (see benchmarks/gpu.py, `python -m benchmarks gpu`, for what it does):
#
#   bash scripts/prepare_gpu_session.sh        # here, first: wheels, stills and footage into .gpu/
#   device run:  MOSAIC_COMMIT=<sha> bash scripts/gpu_session.sh [MINUTES] [STAGES]
#     STAGES training (default):  carry [".gpu/wheels", ".gpu/wheels-rs", ".gpu/stills"]
#     STAGES throughput:          carry [".gpu/wheels", ".gpu/av", ".gpu/footage"], with models/cnn.safetensors
#                                 moved out of the tree for the call (PyAV's 36 MB wheel and the tree must
#                                 fit the call's 64 MiB; those runs read lstm alone)
#   timeout_s about 60 * MINUTES + 90
#
# The device machine has torch with CUDA, OpenCV, numpy, scipy, typer, rich, safetensors and
# pytest, but not kornia nor PyAV nor any ffmpeg binary: their wheels travel in .gpu/.  Where
# kornia_rs does not travel (the throughput call), a stand-in module lets kornia import: mosaic's
# estimator uses kornia's geometry alone, which never calls it.
set -uo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/*/*.whl || exit 1
if [ ! -d /tmp/site/kornia_rs ]; then
  mkdir -p /tmp/site/kornia_rs
  cat > /tmp/site/kornia_rs/__init__.py <<'PY'
"""A stand-in for kornia_rs (kornia's image I/O), which this device call does not carry: kornia's
package imports it, mosaic's use of kornia (its geometry) never calls it."""
import sys
import types


class _Missing(types.ModuleType):
    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        module = _Missing(f"{self.__name__}.{name}")
        sys.modules[module.__name__] = module
        return module

    def __call__(self, *args, **kwargs):
        raise RuntimeError("kornia_rs did not travel to this machine")


sys.modules[__name__].__class__ = _Missing
PY
fi
export PYTHONPATH="/tmp/site:$PWD" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
python3 -m benchmarks gpu --out "${OUT:-gpu-out}" --minutes "${1:-7}" --stages "${2:-training}"
