"""Where the time of one filter call at 1080p goes on a CUDA device: the host's time until the
call returns (the GPU idle before), the whole call, the Python functions that take the host's
time (cProfile) and the GPU kernels (torch.profiler), for À-Trous (3 weights, 5 levels) and the
guided filter (4-channel guide, r = 32) with the Triton kernels.

    python scripts/profile_gpu_call.py [--knobs out/device/knobs.json]     # prints; nothing written
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_device import apply_knobs, inputs
from benchmark_utils import SIZES

from torchgi.filters import atrous, guided


def profile(name: str, fn, reps: int = 30) -> None:
    for _ in range(3):
        fn()
    host, wall = [], []
    for _ in range(reps):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        t1 = time.perf_counter()
        torch.cuda.synchronize()
        host.append(t1 - t0)
        wall.append(time.perf_counter() - t0)
    print(f"== {name}: host until return {statistics.median(host) * 1e3:.3f} ms, "
          f"call + synchronise {statistics.median(wall) * 1e3:.3f} ms (medians of {reps})", flush=True)
    prof = cProfile.Profile()
    for _ in range(reps):
        torch.cuda.synchronize()
        prof.enable()
        fn()
        prof.disable()
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(18)
    print("\n".join(s.getvalue().splitlines()[6:]), flush=True)
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as tprofile

    with tprofile(activities=[ProfilerActivity.CUDA]) as p:
        for _ in range(reps):
            fn()
        torch.cuda.synchronize()
    print(p.key_averages().table(sort_by="cuda_time_total", row_limit=14, max_name_column_width=60), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--knobs", default=None, help="a knobs.json of sweep_gpu_tiles.py")
    print("tiles:", apply_knobs(ap.parse_args().knobs) or "default")
    c, n, x = inputs(*SIZES["1080p"], torch.device("cuda"))
    guide = torch.cat([n, x[:, :1]], 1).contiguous()
    profile("atrous 3 weights 5 it", lambda: atrous(c, n, x, iterations=5))
    profile("guided r=32 dim 4", lambda: guided(c, guide, radius=32, eps=0.01))


if __name__ == "__main__":
    main()
