#!/usr/bin/env bash
# The prepared GPU check on a lent CUDA machine (the device tool's `run`), in two parts that fit
# separate calls: `tune` (about 2 min) and `check` (about 3 min); no argument runs both.
#
#   bash scripts/device_check.sh tune     # the tile sweep -> $OUT/knobs.json, a profile with those tiles
#   bash scripts/device_check.sh check    # CUDA tests, profile and bench_device with the defaults
#
# tune: sweep_gpu_tiles.py (each setting's call time, GPU busy time and difference to the torch
#   code; the fastest to knobs.json), then where the time of a 1080p call goes with them.
# check: the CUDA tests of the Triton kernels and of the importance map / allocation against the
#   float64 oracles (the interpreter and the offline compile checks already ran on the CPU:
#   skipped here), where the time of a 1080p call goes (host, Python, kernels), and
#   bench_device (kernels vs torch code, GPU busy time, kernels and host syncs per call), the
#   pipeline tests on CUDA and bench_pipeline at 1080p and 4K (the Denoiser end to end vs OIDN).
set -uo pipefail  # a step fails when its python does, whatever it is piped through
failed=()
OUT=${OUT:-out/device}
mkdir -p "$OUT"
export PYTHONPATH=$PWD
part=${1:-all}
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee "$OUT/gpu.txt" || failed+=(nvidia-smi)
python -c "import torch, triton; print('torch', torch.__version__, 'triton', triton.__version__)" | tee -a "$OUT/gpu.txt" \
    || failed+=(versions)
if [ "$part" != check ]; then
    timeout 100 python scripts/sweep_gpu_tiles.py --out "$OUT" > "$OUT/sweep.txt" 2>&1 || failed+=(sweep)
    grep "^  \|fastest\|failed" "$OUT/sweep.txt" || true
    knobs=$OUT/knobs.json; [ -f "$knobs" ] || knobs=
    timeout 30 python scripts/profile_gpu_call.py ${knobs:+--knobs "$knobs"} > "$OUT/profile_tuned.txt" 2>&1 \
        || failed+=(profile_tuned)
    grep "^==" "$OUT/profile_tuned.txt" || true
fi
if [ "$part" != tune ]; then
    timeout 60 python -m pytest -q -n 0 tests/backends/test_gpu.py tests/sampling/test_sampling.py --device cuda \
        -k "not interpreter and not spills and (gpu or importance_matches or hamilton)" 2>&1 | tail -25 \
        | tee "$OUT/test_gpu.txt" || failed+=(test_gpu)
    timeout 30 python scripts/profile_gpu_call.py > "$OUT/profile.txt" 2>&1 || failed+=(profile)
    grep "^==" "$OUT/profile.txt" || true
    timeout 90 python scripts/bench_device.py --device cuda --no-fused --min-time 0.3 --out "$OUT" 2>&1 | tail -22 \
        || failed+=(bench_device)
    # issue 18's GPU line: the whole Denoiser at 1080p against OIDN (pyoidn) on the same CUDA tensors
    timeout 120 python -m pytest -q -n 0 tests/methods/test_pipeline.py tests/methods/test_denoise.py --device cuda 2>&1 | tail -5 \
        || failed+=(test_pipeline)
    timeout 150 python scripts/bench_pipeline.py --sizes 1080p 4K --no-memory --rounds 5 --out "$OUT/pipeline" \
        > "$OUT/pipeline.txt" 2>&1 || failed+=(bench_pipeline)
    grep "cuda\|^1080p\|^4K" "$OUT/pipeline.txt" || true
fi
if [ ${#failed[@]} -gt 0 ]; then
    echo "device_check: FAILED: ${failed[*]}" >&2
    exit 1
fi
echo "device_check: every step passed"
