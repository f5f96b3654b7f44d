#!/usr/bin/env bash
# The GPU path on a machine with CUDA, as one short run: the environment, the CUDA tests
# (test/test_cuda.py), the network and pipeline benchmarks on the device, and seconds per
# training step of the shipped architecture (docs/experiments/timing_recipe.json).
# Usage: bash scripts/gpu_check.sh [OUT_DIR] [DEVICE]   (DEVICE cuda by default; cpu for comparison)
set -u
OUT=${1:-gpu_check_out}
DEV=${2:-cuda}
PY=${PYTHON:-python3}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 SHAPE_DETECTOR_CACHE=${SHAPE_DETECTOR_CACHE:-/tmp/shape_detector_cache}
section() { echo "== $1 ($(date +%T))"; }

section environment
nvidia-smi -L 2>/dev/null || echo "no nvidia-smi"
$PY -c "import torch, onnxruntime as o, os; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '-', '| onnxruntime', o.__version__, o.get_available_providers(), '| cpus', os.cpu_count())"

section "tests on the device"
timeout 300 $PY -m pytest -q -p no:cacheprovider test/test_cuda.py 2>&1 | tail -15

section "network on $DEV"
timeout 180 $PY -m shape_detector bench network --device "$DEV" --backend torch --json "$OUT/network.json" 2>&1 | grep -v Warning

section "training steps on $DEV"
rm -rf /tmp/gpu_timing
timeout 400 $PY -m shape_detector train --recipe docs/experiments/timing_recipe.json --phase joint \
  --data-root /tmp/gpu_timing/data --out /tmp/gpu_timing/run --device "$DEV" 2>&1 | grep -E "s/it|epoch [0-9]|generat|frustum|phase|Error" | tail -20
cp /tmp/gpu_timing/run/joint/log.csv "$OUT/train_log.csv" 2>/dev/null

section "pipeline on $DEV"
timeout 300 $PY -m shape_detector bench pipeline --device "$DEV" --frames 10 --no-peer --processes 0 \
  --json "$OUT/pipeline.json" 2>&1 | grep -v Warning
section done
