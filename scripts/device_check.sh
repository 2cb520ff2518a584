#!/usr/bin/env bash
# The prepared GPU check, one call on a lent CUDA machine (the device tool's `run`); about 8 min.
#
#   bash scripts/device_check.sh            # writes test / benchmark / sweep output under $OUT
#
# 1. the CUDA tests of the Triton kernels against the float64 oracles (the interpreter and the
#    offline compile checks already ran on the CPU: skipped here), 2. bench_device (kernels vs
#    torch code, GPU busy time, kernels and host syncs per call), 3. the tile sweep.
set -u
OUT=${OUT:-out/device}
mkdir -p "$OUT"
export PYTHONPATH=$PWD
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
python -c "import torch, triton; print('torch', torch.__version__, 'triton', triton.__version__)" | tee -a "$OUT/gpu.txt"
timeout 300 python -m pytest -q -x tests/test_gpu.py --device cuda -k "not interpreter and not spills" 2>&1 \
    | tail -25 | tee "$OUT/test_gpu.txt"
timeout 150 python scripts/bench_device.py --device cuda --no-fused --min-time 0.3 --out "$OUT" 2>&1 | tail -30
timeout 120 python scripts/sweep_gpu_tiles.py 2>&1 | tee "$OUT/sweep.txt"
