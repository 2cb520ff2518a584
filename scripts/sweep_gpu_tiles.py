"""Tile shapes of the Triton kernels (torchgi.filters.gpu) on the current CUDA device, one knob
at a time around the defaults: À-Trous at 1080p, 3 weights, 5 levels (tile rows x columns,
warps, taps unrolled per loop step) and the guided filter at 1080p, 4-channel guide, r = 32
(column-pass width and rows per program, row-pass tile, pixels per solve / apply program).
Prints the median ms of each setting, the fastest first per filter.

    python scripts/sweep_gpu_tiles.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_device import inputs
from benchmark_utils import SIZES, time_ms

from torchgi.filters import Guided, atrous, gpu

ATROUS = [dict(_BH=bh, _BW=bw, _WARPS=w, _UNROLL=u) for bh, bw, w, u in (
    (4, 64, 4, 1), (2, 64, 4, 1), (2, 128, 4, 1), (4, 64, 4, 2), (4, 64, 4, 5), (8, 64, 8, 1), (4, 32, 4, 1),
    (1, 128, 4, 1), (4, 64, 4, 25))]
GUIDED = [{}] + [{k: v} for k, vs in (("_COL_BW", (64, 256)), ("_COL_ROWS", (32, 128, 256)),
                                      ("_ROW_BW", (64, 256)), ("_ROW_BH", (1, 2, 8)), ("_PIX", (128, 512, 1024)))
                 for v in vs]


def sweep(name: str, settings: list[dict], fn) -> None:
    defaults = {k: getattr(gpu, k) for s in settings for k in s}
    results = []
    for setting in settings:
        for k, v in {**defaults, **setting}.items():
            setattr(gpu, k, v)
        t = time_ms(fn, min_run_time=0.5, device="cuda")
        results.append((t["median_ms"], setting))
        print(f"{name} {setting or 'defaults'}: {t['median_ms']:.3f} ms", flush=True)
    for k, v in defaults.items():
        setattr(gpu, k, v)
    for ms, setting in sorted(results, key=lambda r: r[0]):
        print(f"  {ms:.3f} ms  {setting or 'defaults'}")


def main() -> None:
    c, n, x = inputs(*SIZES["1080p"], torch.device("cuda"))
    sweep("atrous", ATROUS, lambda: atrous(c, n, x, iterations=5))
    guide = torch.cat([n, x[:, :1]], 1).contiguous()
    module = Guided(radius=32, eps=0.01).cuda()
    sweep("guided", GUIDED, lambda: module(c, guide))


if __name__ == "__main__":
    main()
