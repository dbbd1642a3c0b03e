#!/usr/bin/env bash
# The one call a session with a lent GPU makes (see scripts/gpu_session.py for what it does):
#
#   bash scripts/prepare_gpu_session.sh        # here, first: wheels and stills into .gpu/
#   device run:  bash scripts/gpu_session.sh [MINUTES]   with carry [".gpu"], timeout_s about 60 * MINUTES + 90
#
# The device machine has torch with CUDA, OpenCV, numpy, scipy, typer, rich, safetensors and
# pytest, but not kornia: its wheels travel in .gpu/wheels.  Nothing there decodes or encodes
# video: the flights are rendered as folders of frames.
set -uo pipefail
cd "$(dirname "$0")/.."
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/wheels/*.whl || exit 1
export PYTHONPATH="/tmp/site:$PWD" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
python3 scripts/gpu_session.py --out "${OUT:-gpu-out}" --minutes "${1:-7}"
