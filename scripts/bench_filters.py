"""Filter benchmark: run time against size, radius and guide dimension, peers side by side,
and accuracy against a float64 oracle. Writes CSV/JSON/Markdown and a PNG plot.

    python scripts/bench_filters.py --out out/bench            # full run (several minutes)
    python scripts/bench_filters.py --quick --out out/bench    # smoke run
    python scripts/bench_filters.py --only atrous --out out/bench

Sections: guided (docs/design.md, Guided filter; issue 5) at 1024x768 / 1080p / 4K, guide dims 1/3/4, r = 8..64,
the compiled kernels (the default on the CPU, ``torchgi.backends``) and the torch code
side by side, kornia guided_blur(separable=True) at the same window, flatness in r, accuracy
with offset guides; À-Trous (docs/design.md, À-Trous; issue 4) with the compiled kernel, torch eager and
``torch.compile`` (fused), 512² / 1024x768 / 1080p, 1/5/10 iterations, 0-3 weights (the shape
of the paper's Table 2), the time of the bare exponentials side by side, the first-call cost of
both compiled forms, peak extra memory, and the brute-force cross-bilateral and kornia
joint_bilateral_blur at the footprint of 3 levels.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# Fresh caches, so the first calls show the real build / compile costs.
os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", tempfile.mkdtemp(prefix="torchgi-inductor-"))
os.environ.setdefault("TORCHGI_CACHE", tempfile.mkdtemp(prefix="torchgi-native-"))

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from benchmark_utils import SIZES, markdown_table, metadata, time_ms, write_results

from torchgi import backends
from torchgi.backends import c_kernels
from torchgi.filters import Guided, atrous, guided


def make_inputs(H: int, W: int, n: int, seed: int = 0, offset: float = 0.0):
    from oracles import scene

    p, I = scene(1, H, W, n, seed=seed)
    return p.contiguous(), (I + offset).contiguous()


def bench_guided(args, rows: list[dict]) -> None:
    import kornia

    cases = []
    if args.quick:
        cases += [("1024x768", n, r) for n in (1, 4) for r in (8, 32, 64)]
    else:
        cases += [("1024x768", n, r) for n in (1, 3, 4) for r in (8, 16, 32, 64)]
        cases += [("1080p", n, r) for n in (1, 3, 4) for r in (24, 32)]
        cases += [("4K", 4, 32)]
    for size, n, r in cases:
        H, W = SIZES[size]
        p, I = make_inputs(H, W, n)
        module = Guided(radius=r, eps=0.01)
        t_fn = time_ms(lambda: guided(p, I, radius=r, eps=0.01), min_run_time=args.min_time)
        t_mod = time_ms(lambda: module(p, I), min_run_time=args.min_time)
        module.release()
        with backends.use("torch"):
            t_torch = time_ms(lambda: module(p, I), min_run_time=args.min_time)
        module.release()
        row = {"filter": "guided", "impl": "torchgi", "size": size, "guide_dim": n, "radius": r,
               "fn_ms": t_fn["median_ms"], "fn_iqr_ms": t_fn["iqr_ms"],
               "module_ms": t_mod["median_ms"], "module_iqr_ms": t_mod["iqr_ms"], "torch_module_ms": t_torch["median_ms"]}
        if size == "1024x768" and r == 32 and n in (3, 4) or (args.quick and r == 32):
            # kornia at the same (2r+1)² window, separable box, same eps; its border mode is
            # reflect (ours shrinks the window), which does not change the cost.
            try:
                t_k = time_ms(lambda: kornia.filters.guided_blur(I, p, 2 * r + 1, 0.01, separable=True),
                              min_run_time=args.min_time)
                row["kornia_ms"] = t_k["median_ms"]
                row["kornia_over_module"] = t_k["median_ms"] / t_mod["median_ms"]
            except Exception as exc:  # noqa: BLE001 - report the peer's failure, do not hide it
                row["kornia_ms"] = None
                row["kornia_error"] = f"{type(exc).__name__}: {exc}"[:120]
        rows.append(row)
        print({k: (round(v, 2) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)


def accuracy(args, rows: list[dict]) -> None:
    """Max error relative to the output range against the float64 oracle and NaN count, for the
    compiled kernels and the torch code; for the latter also the number of negative variances
    before the clamp (from the module's kept workspace)."""
    from oracles import guided_oracle

    H, W = (540, 960) if args.quick else SIZES["1080p"]
    for offset in (0.0, 1e3, 1e4):
        p, I = make_inputs(H, W, 4, seed=3, offset=offset)
        ref = guided_oracle(p, I, 24, 0.01)
        for impl in ("compiled", "torch"):
            module = Guided(radius=24, eps=0.01)
            with backends.use("torch") if impl == "torch" else contextlib.nullcontext():
                out = module(p, I)
            negative = None
            if impl == "torch":
                ws = module._workspace["ws"]
                negative = sum(int((ws.mII[k] - ws.mI[i] * ws.mI[i] < 0).sum())
                               for k, i in ((0, 0), (2, 1), (5, 2), (9, 3)))
            err = float((out.double() - ref).abs().max() / (ref.max() - ref.min()))
            row = {"filter": "guided-accuracy", "impl": impl, "size": f"{W}x{H}", "guide_dim": 4, "radius": 24,
                   "offset": offset, "max_rel_err": err, "nan": int(torch.isnan(out).sum()),
                   "neg_var_before_clamp": negative}
            rows.append(row)
            print(row, flush=True)


def atrous_inputs(H: int, W: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    c = torch.rand(1, 3, H, W, generator=g) * 2
    n = torch.nn.functional.normalize(torch.randn(1, 3, H, W, generator=g), dim=1)
    x = torch.rand(1, 3, H, W, generator=g) * 5
    return c, n, x


WEIGHTS = {0: {"color_weight": False, "normal": False, "position": False}, 1: {"color_weight": True, "normal": False,
           "position": False}, 2: {"color_weight": True, "normal": True, "position": False},
           3: {"color_weight": True, "normal": True, "position": True}}


def run_atrous(c, n, x, iterations: int, weights: int, mode: str = "compiled"):
    """``mode``: "compiled" (the default call: the compiled CPU kernel), "eager" (torch code),
    "fused" (torch code under ``torch.compile``)."""
    w = WEIGHTS[weights]
    with backends.use("torch") if mode != "compiled" else contextlib.nullcontext():
        return atrous(c, n if w["normal"] else None, x if w["position"] else None, iterations=iterations,
                      color_weight=w["color_weight"], fused=mode == "fused")


_PEAK_CHILD = """
import os, sys, threading, time, torch
sys.path.insert(0, "scripts")
torch.set_num_threads(2)
from bench_filters import atrous_inputs, run_atrous
page = os.sysconf("SC_PAGE_SIZE")
def rss():
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * page
H, W, mode = {H}, {W}, {mode!r}
c, n, x = atrous_inputs(H, W)
run_atrous(c, n, x, 5, 3, mode)  # warm-up (builds or compiles)
base, peak, stop = rss(), [0], [False]
def poll():
    while not stop[0]:
        peak[0] = max(peak[0], rss())
        time.sleep(0.0005)
t = threading.Thread(target=poll); t.start()
run_atrous(c, n, x, 5, 3, mode)
stop[0] = True; t.join()
print(peak[0] - base, c.numel() * 4)
"""


def peak_memory(size: str, mode: str) -> dict:
    """Peak resident memory of one 5-level, 3-weight call above the resident memory just
    before it, in a fresh process whose allocator returns freed blocks to the OS at once
    (``MALLOC_MMAP_THRESHOLD_``), so the resident size tracks live buffers; RSS is polled
    every 0.5 ms from a thread while the call runs."""
    H, W = SIZES[size]
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="131072")
    out = subprocess.run([sys.executable, "-c", _PEAK_CHILD.format(H=H, W=W, mode=mode)], capture_output=True,
                         text=True, check=True, env=env, cwd=Path(__file__).resolve().parents[1]).stdout.split()
    extra, color_bytes = int(out[-2]), int(out[-1])
    return {"peak_extra_MB": extra / 2**20, "extra_over_color": extra / color_bytes,
            "extra_over_inputs": extra / (3 * color_bytes)}


def bench_atrous(args, rows: list[dict]) -> None:
    from torchgi.filters import cross_bilateral

    # first-call cost of both compiled forms at one size, then a new size and step (the C kernels
    # were built in main: metadata native_build_s)
    c, n, x = atrous_inputs(*SIZES["1024x768"])
    c2, n2, x2 = atrous_inputs(*SIZES["512²"])
    for mode in ("compiled", "fused"):
        t0 = time.perf_counter()
        run_atrous(c, n, x, 5, 3, mode)
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        run_atrous(c2, n2, x2, 5, 3, mode)
        new_size = time.perf_counter() - t0
        rows.append({"filter": "atrous-first-call", "impl": mode, "size": "1024x768", "first_call_s": first,
                     "new_size_first_call_s": new_size})
        print(rows[-1], flush=True)

    cases = [("1024x768", 5, w) for w in (0, 1, 2, 3)] + [("1024x768", it, 3) for it in (1, 10)]
    if not args.quick:
        cases += [("512²", it, 3) for it in (1, 5, 10)] + [("1080p", it, 3) for it in (1, 5, 10)]
    for size, iterations, weights in cases:
        H, W = SIZES[size]
        c, n, x = atrous_inputs(H, W)
        e = torch.rand(25 * iterations * H * W // 8)
        buf = torch.empty_like(e)

        def exps():
            for _ in range(8):
                torch.exp(e, out=buf)

        t_exp = time_ms(exps, min_run_time=args.min_time)
        t_c = time_ms(lambda: run_atrous(c, n, x, iterations, weights, "compiled"), min_run_time=args.min_time)
        torch_too = size == "1024x768" or iterations == 5
        t_fused = time_ms(lambda: run_atrous(c, n, x, iterations, weights, "fused"), min_run_time=args.min_time) \
            if torch_too else None
        t_eager = time_ms(lambda: run_atrous(c, n, x, iterations, weights, "eager"), min_run_time=args.min_time) \
            if torch_too else None
        row = {"filter": "atrous", "size": size, "iterations": iterations, "weights": weights,
               "exp_ms": t_exp["median_ms"], "compiled_ms": t_c["median_ms"], "compiled_iqr_ms": t_c["iqr_ms"],
               "compiled_over_exp": t_c["median_ms"] / t_exp["median_ms"],
               "fused_ms": t_fused["median_ms"] if t_fused else None,
               "eager_ms": t_eager["median_ms"] if t_eager else None}
        if size == "1024x768" and iterations == 5 and weights == 3:
            for mode in ("compiled", "eager"):
                row.update({f"{k}_{mode}": v for k, v in peak_memory(size, mode).items()})
        rows.append(row)
        print({k: (round(v, 2) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)

    # peers at the footprint of 3 levels: taps reach 2·(1+2+4) = 14 px, a 29x29 window
    import kornia

    c, n, x = atrous_inputs(*SIZES["512²"])
    r = 14
    t_a = time_ms(lambda: run_atrous(c, n, x, 3, 3), min_run_time=args.min_time)
    t_b = time_ms(lambda: cross_bilateral(c, [n, x], radius=r, sigma_space=r / 2, sigma_color=0.5,
                                          sigma_guides=[0.3, 0.3]), min_run_time=args.min_time)
    t_k = time_ms(lambda: kornia.filters.joint_bilateral_blur(c, n, 2 * r + 1, 0.3, (r / 2, r / 2)),
                  min_run_time=args.min_time)
    row = {"filter": "footprint-29", "size": "512²", "atrous_3it_ms": t_a["median_ms"],
           "cross_bilateral_r14_ms": t_b["median_ms"], "kornia_joint_bilateral_k29_ms": t_k["median_ms"]}
    rows.append(row)
    print(row, flush=True)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for n in (1, 3, 4):
        sel = [r for r in rows if r.get("filter") == "guided" and r["size"] == "1024x768" and r["guide_dim"] == n]
        if sel:
            ax.plot([r["radius"] for r in sel], [r["module_ms"] for r in sel], "o-", label=f"torchgi guide dim {n}")
    kor = [r for r in rows if r.get("kornia_ms")]
    for r in kor:
        ax.plot([r["radius"]], [r["kornia_ms"]], "x", color="k")
    if kor:
        ax.plot([], [], "x", color="k", label="kornia guided_blur (separable)")
    ax.axhline(80, ls="--", color="gray", label="paper, GTX 285, dim 4 (80 ms)")
    ax.set_yscale("log")
    ax.set_xlabel("radius r (px)")
    ax.set_ylabel("ms (median)")
    ax.set_title("Guided filter, 1024x768, CPU")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--min-time", type=float, default=1.0, help="seconds of timing per case")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", choices=["guided", "atrous"], default=None)
    args = ap.parse_args()
    torch.manual_seed(0)
    torch.set_num_threads(args.threads)
    meta = metadata(args.threads)
    t0 = time.perf_counter()
    c_kernels.library()  # build the C kernels into the empty cache
    meta.update(native_build_s=time.perf_counter() - t0, native=c_kernels.describe())
    print(meta, flush=True)
    rows: list[dict] = []
    if args.only in (None, "guided"):
        bench_guided(args, rows)
        accuracy(args, rows)
    if args.only in (None, "atrous"):
        bench_atrous(args, rows)
    out = Path(args.out)
    stem = "filters" if args.only is None else f"filters_{args.only}"
    write_results(rows, meta, out, stem)
    md = ""
    if args.only in (None, "guided"):
        speed = [r for r in rows if r.get("filter") == "guided"]
        md += markdown_table(speed, ["size", "guide_dim", "radius", "fn_ms", "module_ms", "torch_module_ms",
                                     "kornia_ms", "kornia_over_module"])
        md += "\n\n" + markdown_table([r for r in rows if r.get("filter") == "guided-accuracy"],
                                      ["impl", "size", "offset", "max_rel_err", "nan", "neg_var_before_clamp"])
        plot(rows, out / f"{stem}.png")
    if args.only in (None, "atrous"):
        md += "\n\n" + markdown_table([r for r in rows if r.get("filter") == "atrous"],
                                      ["size", "iterations", "weights", "exp_ms", "compiled_ms",
                                       "compiled_over_exp", "fused_ms", "eager_ms"])
        for kind in ("atrous-first-call", "footprint-29"):
            sel = [r for r in rows if r.get("filter") == kind]
            md += "\n\n" + markdown_table(sel, [k for k in sel[0] if k != "filter"])
        mem = [r for r in rows if "peak_extra_MB_compiled" in r]
        md += "\n\n" + markdown_table(mem, [k for k in mem[0] if k.startswith(("peak", "extra"))])
    (out / f"{stem}.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
