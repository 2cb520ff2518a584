"""Tile shapes of the Triton kernels (torchgi.backends.triton_kernels) on the current CUDA device, around
the defaults: À-Trous at 1080p, 3 weights, 5 levels (tile rows x columns, warps, taps per loop
step) and the guided filter at 1080p, 4-channel guide, r = 32 (column pass: width, rows per
program, rows per loop step, warps; row-pass tile; pixels per solve / apply program).

Each setting gets the median time of a call, the GPU's busy time per call (the kernels alone,
torch.profiler: what the tiles change, without the host's noise) and its largest difference to
the torch code. Prints the settings by busy time and, with ``--out``, writes the fastest of each
filter to ``knobs.json`` (``bench_device.py --knobs`` applies it).

    python scripts/sweep_gpu_tiles.py --out out/device
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_device import device_busy, inputs
from benchmark_utils import SIZES, time_ms, triton_knob

from torchgi import backends
from torchgi.filters import atrous, guided

ATROUS = [{"_BH": bh, "_BW": bw, "_WARPS": w, "_UNROLL": u} for bh, bw, w, u in (
    (4, 64, 4, 1), (4, 64, 4, 2), (2, 64, 2, 2), (2, 64, 2, 1), (2, 128, 4, 1), (2, 128, 4, 2), (8, 64, 8, 2),
    (1, 128, 4, 2), (1, 128, 4, 1), (2, 128, 8, 2), (1, 256, 8, 2), (1, 64, 2, 2))]
_BASE = {"_ROW_BH": 8, "_COL_ROWS": 128}
GUIDED = [{}, _BASE] + [{**_BASE, **v} for v in (
    {"_COL_UNROLL": 2}, {"_COL_UNROLL": 4}, {"_COL_UNROLL": 8}, {"_COL_UNROLL": 4, "_COL_WARPS": 2},
    {"_COL_UNROLL": 4, "_COL_WARPS": 1}, {"_COL_UNROLL": 4, "_COL_ROWS": 64}, {"_COL_UNROLL": 4, "_COL_ROWS": 256},
    {"_COL_UNROLL": 4, "_COL_BW": 256}, {"_COL_UNROLL": 4, "_COL_BW": 64, "_COL_WARPS": 2}, {"_COL_UNROLL": 4, "_ROW_BH": 4},
    {"_COL_UNROLL": 4, "_ROW_BW": 64}, {"_COL_UNROLL": 4, "_PIX": 512}, {"_COL_UNROLL": 4, "_PIX": 128})]


def sweep(name: str, settings: list[dict], fn) -> dict:
    """Times ``fn`` under each setting of the Triton tile knobs; returns the fastest setting
    by GPU busy time (defaults restored)."""
    defaults = {k: getattr(triton_knob(k), k) for s in settings for k in s}
    with backends.use("torch"):
        want = fn()
    results = []
    for setting in settings:
        for k, v in {**defaults, **setting}.items():
            setattr(triton_knob(k), k, v)
        try:
            err = float((fn() - want).abs().max())
            t = time_ms(fn, min_run_time=0.3, device="cuda")
            busy = device_busy(fn, torch.device("cuda"))["gpu_busy_ms"]
        except Exception as e:  # noqa: BLE001 - a setting that does not compile or run: report, go on
            print(f"{name} {setting}: failed: {type(e).__name__}: {str(e)[:200]}", flush=True)
            continue
        results.append((busy, t["median_ms"], err, setting))
        print(f"{name} {setting or 'defaults'}: busy {busy:.3f} ms, call {t['median_ms']:.3f} ms, "
              f"max abs diff to torch {err:.1e}", flush=True)
    for k, v in defaults.items():
        setattr(triton_knob(k), k, v)
    results.sort(key=lambda r: r[0])
    for busy, call, err, setting in results:
        print(f"  {name}: busy {busy:.3f} ms  call {call:.3f} ms  diff {err:.1e}  {setting or 'defaults'}")
    return {**defaults, **results[0][3]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="folder for knobs.json (the fastest settings)")
    args = ap.parse_args()
    c, n, x = inputs(*SIZES["1080p"], torch.device("cuda"))
    best = sweep("atrous", ATROUS, lambda: atrous(c, n, x, iterations=5))
    guide = torch.cat([n, x[:, :1]], 1).contiguous()
    best.update(sweep("guided", GUIDED, lambda: guided(c, guide, radius=32, eps=0.01)))
    print("fastest:", best)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "knobs.json").write_text(json.dumps(best, indent=1))


if __name__ == "__main__":
    main()
