"""Filter and importance-map timings on one device (CUDA or CPU), beside the papers' GPU figures.

    python scripts/bench_device.py --device cuda --out out/bench     # on a GPU machine
    python scripts/bench_device.py --device cpu --quick               # smoke run

Times (``torch.utils.benchmark`` medians, CUDA synchronised) the guided filter, r = 32, at
1024x768 with 1/3/4-channel guides (paper: 16/71/80 ms on a GTX 285) and at 1080p with a
4-channel guide, À-Trous with 3 weights at 512² and 1080p, 5 and 10 iterations (paper: 5.6 ms at
512²; 42.6/86.0 ms at 1080p) — each as the default call (the kernels: Triton on CUDA, compiled
C on the CPU) and as the torch code (À-Trous eager and fused) — and importance map + allocation
at 1024x768 with windows 2/4/10 (paper: 8.3/26.2/128.7 ms). On CUDA each row also gives the
GPU's busy time per call and the kernels it launches (torch.profiler), which separates the
kernels from the host's work (checks, launches), and both filters at 1080p are also captured in
a CUDA graph and replayed. Writes ``device_<name>.csv/json/md``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import SIZES, markdown_table, metadata, time_ms, triton_knob, write_results

from torchgi import backends
from torchgi.filters import Guided, atrous, guided
from torchgi.sampling import allocate, importance_map

PAPER = {
    ("guided", 1): 16.0, ("guided", 3): 71.0, ("guided", 4): 80.0,
    ("atrous", "512²", 5): 5.6, ("atrous", "1080p", 5): 42.6, ("atrous", "1080p", 10): 86.0,
    ("importance", 2): 8.3, ("importance", 4): 26.2, ("importance", 10): 128.7,
}


def inputs(H: int, W: int, device: torch.device, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    color = torch.rand(1, 3, H, W, generator=g) * 2
    normal = torch.nn.functional.normalize(torch.randn(1, 3, H, W, generator=g), dim=1)
    position = torch.rand(1, 3, H, W, generator=g) * 5
    return color.to(device), normal.to(device), position.to(device)


def compiled_variants(timed, device: torch.device) -> None:
    """The guided filter (dim 4, r 32) and À-Trous (3 weights, 5 levels) at 1080p, eager and as
    one ``torch.compile``'d graph with static shapes (``reduce-overhead``: CUDA graphs on CUDA),
    measured against the issues' 1 ms target. First calls (compiles) are timed separately."""
    import time

    from torchgi.backends.torch_code.filter_guided import _guided_reference
    from torchgi.filters.guided import _check_eps

    H, W = SIZES["1080p"]
    color, normal, position = inputs(H, W, device)
    guide = torch.cat([normal, position[:, :1]], 1).contiguous()
    eps, _ = _check_eps(0.01, 1, 4, guide, guide.dtype)

    def guided_graph(src: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        mg, mp = g.mean((2, 3), keepdim=True), src.mean((2, 3), keepdim=True)
        return _guided_reference(g - mg, src - mp, 32, eps) + mp

    def atrous_graph(c: torch.Tensor, n: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return atrous(c, n, x, iterations=5, sigma_color=1.0, sigma_normal=0.1, sigma_position=0.1)

    mode = "reduce-overhead" if device.type == "cuda" else "default"
    for name, fn, args in (("guided r=32 dim 4", guided_graph, (color, guide)),
                           ("atrous 3 weights 5 it", atrous_graph, (color, normal, position))):
        timed(f"{name} eager graph", lambda: fn(*args), size="1080p", param="eager")
        compiled = torch.compile(fn, mode=mode, dynamic=False)
        t0 = time.perf_counter()
        for _ in range(3):  # CUDA graphs record on the second or third call
            compiled(*args)
        if device.type == "cuda":
            torch.cuda.synchronize()
        print(f"{name}: first three compiled calls {time.perf_counter() - t0:.1f} s", flush=True)
        err = float((compiled(*args) - fn(*args)).abs().max())
        timed(f"{name} compiled", lambda: compiled(*args), size="1080p", param=f"{mode}, max abs diff {err:.1e}")


def device_busy(fn, device: torch.device, reps: int = 20) -> dict:
    """GPU time per call summed over the kernels ``fn`` launches, their number and the host's
    waits on the GPU (``torch.cuda.set_sync_debug_mode`` warnings) per call (CUDA only)."""
    if device.type != "cuda":
        return {}
    import warnings

    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fn()
    finally:
        torch.cuda.set_sync_debug_mode(0)
    syncs = sum("synchroniz" in str(w.message) for w in caught)
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(reps):
            fn()
        torch.cuda.synchronize()
    events = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    busy_us = sum(e.device_time for e in events)
    return {"gpu_busy_ms": busy_us / reps / 1000, "kernels_per_call": len(events) / reps, "syncs_per_call": syncs}


def graph_replays(timed, device: torch.device) -> None:
    """The default calls (Triton kernels) at 1080p captured once in a CUDA graph and replayed:
    the time without Python, checks and launch overhead, next to the same eager call."""
    H, W = SIZES["1080p"]
    c, n, x = inputs(H, W, device)
    guide = torch.cat([n, x[:, :1]], 1).contiguous()
    calls = {
        "atrous 3 weights 5 it": lambda: atrous(c, n, x, iterations=5, sigma_color=1.0),
        "guided r=32 dim 4": lambda: guided(c, guide, radius=32, eps=0.01),
    }
    for name, fn in calls.items():
        try:
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                for _ in range(2):
                    fn()
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                out = fn()
            graph.replay()
            err = float((out - fn()).abs().max())
        except RuntimeError as e:  # report and go on: the other rows still count
            print(f"{name}: CUDA graph capture failed: {e}", flush=True)
            continue
        timed(f"{name} eager (kernels)", fn, size="1080p", param="")
        timed(f"{name} CUDA graph replay", graph.replay, size="1080p", param=f"max abs diff {err:.1e}")


def apply_knobs(path: str | None) -> dict:
    """Sets the tile knobs of :mod:`torchgi.backends.triton_kernels` from a ``knobs.json`` of
    ``sweep_gpu_tiles.py`` (None: nothing); returns them."""
    knobs = json.loads(Path(path).read_text()) if path else {}
    for k, v in knobs.items():
        setattr(triton_knob(k), k, v)
    return knobs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", default="out/bench")
    ap.add_argument("--min-time", type=float, default=0.5)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-fused", action="store_true", help="skip torch.compile'd À-Trous")
    ap.add_argument("--compiled", action="store_true",
                    help="also time whole-filter torch.compile variants at 1080p (static shapes; CUDA graphs on CUDA)")
    ap.add_argument("--knobs", default=None,
                    help="a knobs.json of sweep_gpu_tiles.py: tile settings of the Triton kernels to time with")
    args = ap.parse_args()
    device = torch.device(args.device)
    knobs = apply_knobs(args.knobs)
    rows: list[dict] = []

    def timed(name: str, fn, **fields) -> None:
        t = time_ms(fn, min_run_time=args.min_time, device=device.type)
        row = {"what": name, **fields, "median_ms": t["median_ms"], "iqr_ms": t["iqr_ms"], **device_busy(fn, device)}
        rows.append(row)
        print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)

    H, W = SIZES["1024x768"]
    _, normal, position = inputs(H, W, device)
    for size, dims in (("1024x768", (1, 3, 4)), ("1080p", (4,))):
        c, n, x = inputs(*SIZES[size], device)
        for dim in dims:
            guide = torch.cat([n, x[:, :1]], 1)[:, :dim].contiguous()
            module = Guided(radius=32, eps=0.01).to(device)
            for mode in ("kernel", "torch"):
                def run(mode=mode, guide=guide, module=module, c=c):
                    with backends.use("torch") if mode != "kernel" else contextlib.nullcontext():
                        return module(c, guide)

                err = float((run() - run("torch")).abs().max()) if mode == "kernel" else None
                timed(f"guided r=32 {mode}", run, size=size, param=f"dim {dim}",
                      paper_ms=PAPER["guided", dim] if size == "1024x768" else None, max_abs_diff_to_torch=err)
    sizes = ("512²",) if args.quick else ("512²", "1080p")
    for size in sizes:
        c, n, x = inputs(*SIZES[size], device)
        for iterations in (5, 10):
            for mode in ("kernel", "eager") + (() if args.no_fused else ("fused",)):
                # kernel: the default call (Triton on CUDA, C on the CPU); eager / fused: the torch code
                def run(mode=mode, iterations=iterations):
                    with backends.use("torch") if mode != "kernel" else contextlib.nullcontext():
                        return atrous(c, n, x, iterations=iterations, fused=mode == "fused")

                err = float((run() - run("eager")).abs().max()) if mode == "kernel" else None
                timed(f"atrous 3 weights {mode}", run, size=size, param=f"{iterations} it",
                      paper_ms=PAPER.get(("atrous", size, iterations)), max_abs_diff_to_torch=err)
    if device.type == "cuda":
        graph_replays(timed, device)
    if args.compiled:
        compiled_variants(timed, device)
    for window in (2, 4, 10):
        def imp_alloc():
            imp = importance_map(normal, position, window=window, sigma_normal=0.1, sigma_position=0.1)
            return allocate(imp, 4 * H * W, min_samples=1)

        timed("importance + allocate", imp_alloc, size="1024x768", param=f"window {window}",
              paper_ms=PAPER["importance", window])
    meta = metadata(torch.get_num_threads())
    meta["device"] = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    meta["knobs"] = {k: getattr(triton_knob(k), k) for k in knobs}
    out = Path(args.out)
    stem = f"device_{device.type}"
    write_results(rows, meta, out, stem)
    md = markdown_table(rows, ["what", "size", "param", "median_ms", "iqr_ms", "gpu_busy_ms", "kernels_per_call",
                               "syncs_per_call", "paper_ms", "max_abs_diff_to_torch"])
    (out / f"{stem}.md").write_text(f"{meta['device']}, torch {meta['torch']}, commit {meta['commit']}, "
                                    f"tiles {meta['knobs'] or 'default'}\n\n{md}\n")
    print(md)


if __name__ == "__main__":
    main()
