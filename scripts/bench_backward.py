"""Training-step benchmark of the filters as layers: the no-grad forward, forward + backward
with autograd, and the peak memory each adds, side by side in one run (issue 57).

    python scripts/bench_backward.py --out out/bench            # ~1 minute
    python scripts/bench_backward.py --size 512 --out out/bench

Cases at ``size``² (float32, 2 threads unless ``--threads``): the box filter (r 4, 3 channels),
the guided filter (r 4, a 4-channel guide, 3-channel source; gradients to source and guide),
kornia's ``guided_blur`` on the same inputs (its 9x9 window), À-Trous (5 iterations, normal
and position weights; gradient to the colour), ``apply_kernels`` at three scales (5 x 5
normalised kernels at dilations 1, 2, 4; gradients to the image and the three weight tensors). Memory: the peak resident size a call adds
above the resident size just before it, in a fresh process whose allocator returns freed
blocks to the OS at once (``MALLOC_MMAP_THRESHOLD_``), read from ``VmHWM`` after resetting it;
"working" memory is a step's less the gradients it returns (as large as the differentiated inputs).
Writes ``backward.csv`` / ``.json`` and ``backward.png`` under ``--out``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import markdown_table, metadata, time_ms, write_results

CASES = ("box", "guided", "kornia guided_blur", "atrous", "apply_kernels")


def inputs(case: str, size: int, grad: bool) -> tuple[torch.Tensor, ...]:
    """The case's tensors at ``size``² (fixed seed); the differentiated ones require grad."""
    g = torch.Generator().manual_seed(0)
    color = torch.rand(1, 3, size, size, generator=g)
    if case == "box":
        return (color.requires_grad_(grad),)
    if case == "apply_kernels":  # three scales of 5 x 5 kernels
        weights = [torch.rand(1, 25, size, size, generator=g) + 0.01 for _ in range(3)]
        return (color.requires_grad_(grad), *(w.requires_grad_(grad) for w in weights))
    if case == "atrous":
        normal = torch.nn.functional.normalize(torch.randn(1, 3, size, size, generator=g), dim=1)
        position = torch.rand(1, 3, size, size, generator=g)
        return color.requires_grad_(grad), normal, position
    guide = torch.rand(1, 4, size, size, generator=g)
    return color.requires_grad_(grad), guide.requires_grad_(grad)


def call(case: str, t: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """One forward of ``case`` on ``t``."""
    from kornia.filters import guided_blur

    from torchgi.filters import apply_kernels, atrous, box, guided

    if case == "box":
        return box(t[0], 4)
    if case == "guided":
        return guided(t[0], t[1], radius=4, eps=0.01)
    if case == "kornia guided_blur":
        return guided_blur(t[1], t[0], 9, 0.01)
    if case == "apply_kernels":
        y = t[0]
        for d, w in zip((1, 2, 4), t[1:]):
            y = apply_kernels(y, w, dilation=d, normalize=True)
        return y
    return atrous(t[0], t[1], t[2], iterations=5)


def step(case: str, t: tuple[torch.Tensor, ...]) -> None:
    """Forward, a scalar loss, backward; gradients cleared."""
    call(case, t).square().mean().backward()
    for x in t:
        x.grad = None


_CHILD = """
import sys, torch
sys.path.insert(0, {scripts!r})
from bench_backward import inputs, call, step
torch.set_num_threads({threads})
case, size, grad = {case!r}, {size}, {grad}
t = inputs(case, size, grad)
run = (lambda: step(case, t)) if grad else (lambda: call(case, t))
def status(key):
    return next(int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith(key))
with torch.no_grad() if not grad else torch.enable_grad():
    run(); run()
    before = status("VmRSS:")
    open("/proc/self/clear_refs", "w").write("5")
    run()
    print(status("VmHWM:") - before)
"""


def peak_extra_mb(case: str, size: int, grad: bool, threads: int) -> float:
    """The peak resident memory one call (``grad``: a training step) adds, in MB (see the module doc)."""
    code = _CHILD.format(scripts=str(Path(__file__).resolve().parent), threads=threads, case=case, size=size, grad=grad)
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="131072")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env,
                         cwd=Path(__file__).resolve().parents[1]).stdout.split()
    return int(out[-1]) / 2**20


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("out/bench"))
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--min-time", type=float, default=1.0, help="seconds per timing")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from torchgi import backends

    rows = []
    for case in CASES:
        row: dict = {"case": case, "size": args.size}
        t = inputs(case, args.size, False)
        with torch.no_grad():
            row["forward_ms"] = time_ms(lambda: call(case, t), min_run_time=args.min_time)["median_ms"]
        op = {"box": "box", "guided": "guided", "atrous": "atrous", "apply_kernels": "apply_kernels"}.get(case)
        row["forward_ran"] = backends.status()["last"][op]["ran"] if op else "kornia"
        t = inputs(case, args.size, True)
        row["step_ms"] = time_ms(lambda: step(case, t), min_run_time=args.min_time)["median_ms"]
        row["step_over_forward"] = row["step_ms"] / row["forward_ms"]
        grad_op = {"guided": "guided_grad", "atrous": "atrous_level_grad", "apply_kernels": "apply_kernels_grad"}.get(
            case, op)  # the op computing the gradients (the box's backward is a box)
        row["step_ran"] = backends.status()["last"][grad_op]["ran"] if op else "kornia"
        row["forward_MB"] = peak_extra_mb(case, args.size, False, args.threads)
        row["step_MB"] = peak_extra_mb(case, args.size, True, args.threads)
        row["step_MB_over_forward"] = row["step_MB"] / max(row["forward_MB"], 1e-9)
        # the gradients themselves (as large as the differentiated inputs) are the step's result:
        # what it holds beyond them is its working memory
        row["grads_MB"] = sum(x.numel() * x.element_size() for x in t if x.requires_grad) / 2**20
        row["working_MB_over_forward"] = (row["step_MB"] - row["grads_MB"]) / max(row["forward_MB"], 1e-9)
        rows.append(row)
        print(row, flush=True)
    by_case = {r["case"]: r for r in rows}
    for r in rows:
        r["kornia_step_over_this"] = by_case["kornia guided_blur"]["step_ms"] / r["step_ms"]
    meta = metadata(args.threads) | {"command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:])}
    write_results(rows, meta, args.out, "backward")
    print(markdown_table(rows, ["case", "forward_ms", "step_ms", "step_over_forward", "forward_MB", "step_MB",
                                "grads_MB", "step_MB_over_forward", "working_MB_over_forward",
                                "kornia_step_over_this"]))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    x = range(len(rows))
    ax.bar([i - 0.2 for i in x], [r["forward_ms"] for r in rows], 0.4, label="forward, no grad")
    ax.bar([i + 0.2 for i in x], [r["step_ms"] for r in rows], 0.4, label="forward + backward")
    ax.set_xticks(list(x), [r["case"] for r in rows])
    ax.set_ylabel(f"ms at {args.size}², {args.threads} threads (median)")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "backward.png", dpi=120)


if __name__ == "__main__":
    main()
