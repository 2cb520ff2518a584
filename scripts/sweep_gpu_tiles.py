"""Tile shapes of the Triton À-Trous kernel (torchgi.filters.gpu) at 1080p, 3 weights, 5 levels:
median ms per shape on the current CUDA device, the fastest first.

    python scripts/sweep_gpu_tiles.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_device import inputs
from benchmark_utils import SIZES, time_ms

from torchgi.filters import atrous, gpu


def main() -> None:
    c, n, x = inputs(*SIZES["1080p"], torch.device("cuda"))
    results = []
    for bh, bw, warps in ((8, 32, 4), (4, 64, 4), (16, 32, 4), (8, 64, 4), (8, 64, 8), (2, 128, 4), (16, 64, 8)):
        gpu._BH, gpu._BW, gpu._WARPS = bh, bw, warps
        t = time_ms(lambda: atrous(c, n, x, iterations=5), min_run_time=0.5, device="cuda")
        results.append((t["median_ms"], bh, bw, warps))
        print(f"{bh}x{bw}, {warps} warps: {t['median_ms']:.3f} ms", flush=True)
    print("fastest:", min(results))


if __name__ == "__main__":
    main()
