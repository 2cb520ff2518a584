"""The Denoiser end to end against its kernel and OIDN: median ms and peak memory, 256² to 4K.

Per size one 1 spp render of a scene (Cornell box by default; ``--spp N`` for N, with its
``variance`` and ``spp`` as inputs too) and, timed side by side in alternating rounds on the same
inputs (``color, albedo, normal, depth, emission``):
``Denoiser("guided")`` end to end (and forced to full resolution), its guided kernel alone (same radius, eps and guide, full
resolution, on the colour), the default ``Denoiser()`` when it is another method, the guided
Denoiser tiled with ``max_memory_mb=256``, ``Denoiser("pyramid")`` (its default
``max_memory_mb="auto"``: in tiles within twice the inputs from about 4.4 Mpx) and untiled
(``max_memory_mb=None``), and Intel Open Image Denoise "fast" and "high"
(pyoidn: colour + albedo + normal, HDR). On CUDA (when a GPU is present) the same on CUDA tensors.
Peak memory is measured in a fresh process per size and method: the resident set's high-water
mark during the one call minus the resident set before it (the inputs already loaded).

    python scripts/bench_pipeline.py --out out/bench-pipeline

writes ``pipeline.csv`` / ``.json`` / ``.md`` (with the issue's claims checked) and
``pipeline.png`` (ms over pixels, log-log).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmark_utils import SIZES, markdown_table, metadata, write_results

import torchgi
from torchgi.denoise import Denoiser

INPUTS = ("color", "albedo", "normal", "depth", "emission")
TILED_MB = 256


def render_inputs(scene: str, H: int, W: int, cache: Path, spp: int = 1) -> dict[str, torch.Tensor]:
    """The named inputs of an ``spp`` render (seed 1), cached under ``cache``; from 2 spp with the
    measured ``variance`` and ``spp`` (the Denoiser then backs off toward its input)."""
    path = cache / (f"{scene}_{W}x{H}" + ("" if spp == 1 else f"_{spp}spp") + ".pt")
    if path.exists():
        return torch.load(path)
    base = torchgi.scenes.BUILTINS[scene](max(H, W)).with_resolution(W, H)
    gb = torchgi.render(base, spp=spp, bounces=1, seed=1)
    inputs = {k: getattr(gb, k).contiguous() for k in INPUTS + (("variance", "spp") if spp > 1 else ())}
    cache.mkdir(parents=True, exist_ok=True)
    torch.save(inputs, path)
    return inputs


def methods(inputs: dict[str, torch.Tensor], device: str) -> dict:
    """name -> zero-argument callable on ``inputs``."""
    from torchgi.filters import guide_from_gbuffer
    from torchgi.filters import guided as guided_filter
    from torchgi.settings import GUIDED

    guided = Denoiser("guided")
    gb = torchgi.GBuffer(**inputs)
    radius = guided.deploy(spp=float(inputs["spp"].double().mean()) if "spp" in inputs else 1.0).params["radius"]
    guide, x, ws = guide_from_gbuffer(gb), inputs["color"].clone(), {}
    full = Denoiser("guided", subsample=1)
    fns = {
        'Denoiser("guided")': lambda: guided(**inputs),
        'Denoiser("guided", subsample=1)': lambda: full(**inputs),
        f"guided kernel (r={radius})": lambda: guided_filter(x, guide, radius=radius, eps=GUIDED.eps, workspace=ws),
    }
    fns['Denoiser("pyramid")'] = lambda d=Denoiser("pyramid"): d(**inputs)
    fns["pyramid, max_memory_mb=None"] = lambda d=Denoiser("pyramid", max_memory_mb=None): d(**inputs)
    default = Denoiser()
    if default.method != "guided":
        fns[f'Denoiser() ("{default.method}")'] = lambda: default(**inputs)
    tiled = Denoiser("guided", max_memory_mb=TILED_MB)
    fns[f"guided, max_memory_mb={TILED_MB}"] = lambda: tiled(**inputs)
    try:
        import pyoidn

        hwc = {k: inputs[k][0].permute(1, 2, 0).contiguous() for k in ("color", "albedo", "normal")}
        for q in ("fast", "high"):
            fns[f"OIDN {q}"] = lambda q=q: pyoidn.denoise(hwc["color"], hwc["albedo"], hwc["normal"], hdr=True,
                                                          quality=q)
    except ImportError:
        print("pyoidn not installed: no OIDN columns", file=sys.stderr)
    return fns


def timed(fns: dict, rounds: int, device: str, settle: int = 0, pause: float = 0.0) -> dict[str, float]:
    """Median ms of each callable over ``rounds`` alternating rounds (after one warm-up call);
    each round starts one method later, so that every method follows every other equally often
    (OIDN's worker threads keep spinning for a while after its call). ``settle``: untimed calls
    of a method just before its timed one, so that it is timed after itself, not after another
    library whose threads still spin (onnxruntime's slow the next torch call down); ``pause``:
    seconds slept before those, for threads that spin longer than one call (onnxruntime's after
    an 8 ms torch call: docs/benchmarks/onnx.md)."""
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    times: dict[str, list[float]] = {k: [] for k in fns}
    for fn in fns.values():
        fn()
    names = list(fns)
    for i in range(rounds):
        for name in names[i % len(names):] + names[: i % len(names)]:
            fn = fns[name]
            time.sleep(pause)
            for _ in range(settle):
                fn()
            sync()
            t = time.perf_counter()
            fn()
            sync()
            times[name].append((time.perf_counter() - t) * 1e3)
    return {k: sorted(v)[len(v) // 2] for k, v in times.items()}


def _status_mb() -> dict[str, float]:
    text = Path("/proc/self/status").read_text()
    return {k: int(re.search(k + r":\s+(\d+)", text).group(1)) / 1024 for k in ("VmRSS", "VmHWM")}


def probe(args) -> None:
    """In a fresh process: the peak extra memory (MB) of one call of ``args.probe_method``."""
    torch.set_num_threads(args.threads)
    H, W = SIZES[args.probe_size]
    inputs = render_inputs(args.scene, H, W, Path(args.out) / "inputs", args.spp)
    fns = methods({k: v[..., :64, :64].contiguous() for k, v in inputs.items()}, "cpu")
    fns[args.probe_method]()  # libraries loaded, kernels built
    fn = methods(inputs, "cpu")[args.probe_method]
    Path("/proc/self/clear_refs").write_text("5")  # the high-water mark restarts at the current set
    before = _status_mb()["VmRSS"]
    out = fn()
    peak = _status_mb()["VmHWM"]
    result = {"extra_mb": peak - before, "output_mb": out.numel() * out.element_size() / 2**20}
    for method in ("guided", "pyramid"):  # tiled (or "auto") against the untiled call
        if args.probe_method in (f'Denoiser("{method}")', f"{method}, max_memory_mb={TILED_MB}"):
            whole = Denoiser(method, max_memory_mb=None)(**inputs)
            result["tiled_rel_diff"] = float(((out - whole).abs() / (whole.abs() + 1e-3)).max())
    print(json.dumps(result))


def memory(args, size: str, name: str) -> dict:
    cmd = [sys.executable, __file__, "--probe-size", size, "--probe-method", name, "--scene", args.scene,
           "--out", args.out, "--threads", str(args.threads), "--spp", str(args.spp)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode:
        print(proc.stderr[-2000:], file=sys.stderr)
        return {}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run(args) -> list[dict]:
    rows = []
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for size in args.sizes:
        H, W = SIZES[size]
        inputs = render_inputs(args.scene, H, W, Path(args.out) / "inputs", args.spp)
        in_mb = sum(t.numel() * t.element_size() for t in inputs.values()) / 2**20
        for device in devices:
            on = {k: v.to(device) for k, v in inputs.items()}
            # small images: more rounds (a call is milliseconds, the shared machine's noise is not)
            rounds = args.rounds * 5 if H * W < 1e6 else args.rounds if H * W < 4e6 else max(3, args.rounds // 2)
            ms = timed(methods(on, device), rounds, device)
            for name, t in ms.items():
                row = {"size": size, "pixels": H * W, "device": device, "method": name, "median_ms": t,
                       "inputs_mb": in_mb}
                if device == "cpu" and args.memory:
                    row.update(memory(args, size, name))
                rows.append(row)
                print(row, flush=True)
    return rows


def claims(rows: list[dict]) -> list[str]:
    """The issue's lines, per size, from this run."""
    lines = []
    for size in dict.fromkeys(r["size"] for r in rows):
        by = {r["method"]: r for r in rows if r["size"] == size and r["device"] == "cpu"}
        den = by['Denoiser("guided")']
        kernel = next(r for k, r in by.items() if k.startswith("guided kernel"))
        full = by['Denoiser("guided", subsample=1)']
        line = f"{size}: Denoiser(\"guided\") {den['median_ms']:.3g} ms = {den['median_ms'] / kernel['median_ms']:.2f}x " \
               f"its kernel (bound 1.3x); at full resolution {full['median_ms']:.3g} ms"
        if "OIDN high" in by:
            line += f"; OIDN high {by['OIDN high']['median_ms'] / den['median_ms']:.1f}x slower (bound 15x)"
            default = next((r for k, r in by.items() if k.startswith("Denoiser() (")), den)
            line += f"; default {by['OIDN high']['median_ms'] / default['median_ms']:.1f}x (bound 10x)"
        if "extra_mb" in den:
            line += f"; peak extra {den['extra_mb']:.0f} MB = {den['extra_mb'] / den['inputs_mb']:.2f}x inputs (bound 2x)"
        tiled = next((r for k, r in by.items() if k.startswith("guided, max_memory_mb")), None)
        if tiled is not None and "extra_mb" in tiled:
            line += f"; tiled: extra {tiled['extra_mb']:.0f} MB (bound {TILED_MB}), {tiled['median_ms']:.3g} ms, " \
                    f"max rel. diff {tiled['tiled_rel_diff']:.1e} (bound 1e-5)"
        lines.append(line)
        pyr, pyr_whole = by.get('Denoiser("pyramid")'), by.get("pyramid, max_memory_mb=None")
        if pyr is not None and "OIDN high" in by:  # issue 28's speed and memory lines
            line = f"{size}: Denoiser(\"pyramid\") {pyr['median_ms']:.3g} ms, OIDN high " \
                   f"{by['OIDN high']['median_ms'] / pyr['median_ms']:.2f}x slower (bound 5x)"
            for label, r in (('default ("auto")', pyr), ("untiled", pyr_whole)):
                if r is not None and "extra_mb" in r:
                    line += f"; {label}: peak extra {r['extra_mb']:.0f} MB = {r['extra_mb'] / r['inputs_mb']:.2f}x " \
                            f"inputs (bound 2x), {r['median_ms']:.3g} ms"
                    line += f", max rel. diff {r['tiled_rel_diff']:.1e}" if "tiled_rel_diff" in r else ""
            lines.append(line)
    return lines


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, (device, name) in enumerate(dict.fromkeys((r["device"], r["method"]) for r in rows)):
        pts = [(r["pixels"], r["median_ms"]) for r in rows if r["device"] == device and r["method"] == name]
        ax.plot(*zip(*pts, strict=True), marker="o", color=f"C{i}", label=f"{name} ({device})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("pixels")
    ax.set_ylabel("median ms")
    ax.legend(fontsize=7)
    ax.set_title("Denoiser end to end, its kernel and OIDN (same inputs, one run)")
    fig.tight_layout()
    fig.savefig(out / "pipeline.png", dpi=100)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench-pipeline")
    ap.add_argument("--scene", default="cornell")
    ap.add_argument("--sizes", nargs="+", default=["256²", "512²", "1080p", "4K"], choices=list(SIZES) + ["256²"])
    ap.add_argument("--spp", type=int, default=1, help="samples per pixel of the inputs (from 2: with variance)")
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-memory", dest="memory", action="store_false")
    ap.add_argument("--probe-size", help=argparse.SUPPRESS)
    ap.add_argument("--probe-method", help=argparse.SUPPRESS)
    args = ap.parse_args()
    SIZES.setdefault("256²", (256, 256))
    if args.probe_size:
        probe(args)
        return
    torch.set_num_threads(args.threads)
    rows = run(args)
    out = Path(args.out)
    write_results(rows, metadata(torch.get_num_threads()), out, "pipeline")
    md = markdown_table(rows, ["size", "device", "method", "median_ms", "extra_mb", "inputs_mb"])
    checks = claims(rows)
    (out / "pipeline.md").write_text(md + "\n\n" + "\n".join(f"- {c}" for c in checks) + "\n")
    plot(rows, out)
    print(md)
    print("\n".join(checks))


if __name__ == "__main__":
    main()
