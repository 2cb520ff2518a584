"""The exported default Denoiser in onnxruntime against the eager one (issue 32): relMSE and ms.

    python scripts/bench_onnx.py --out out/bench-onnx [--sizes 512 1080p] [--spp 1 4] [--ref-spp 256]
        [--method guided|pyramid|blend]

For each judged scene (``configs/scenes/sets.yaml``; torchgi renders only), size and spp: a noisy
render and a ``--ref-spp`` reference; the default ``Denoiser()`` exported with the choices it
makes on that render (``export_denoiser(frame=...)``: from 2 spp on with its variance input, so
that it backs off toward the input as the eager call does) and with or without an emission input,
run in onnxruntime on the render (without its emission layer for the second) and beside it,
alternating, the eager default on the same inputs (the render with its variance). Each row:
relMSE against the reference, the median ms of
``--rounds`` alternating calls (``bench_pipeline.timed``: each round starts one method later; each
timed call follows a 0.2 s pause and an untimed call of the same method, as when one library runs
alone: onnxruntime's threads spin on past the next torch call), and
onnxruntime's largest difference from the eager call over the eager
output's largest value. Writes ``onnx.csv``, ``onnx.json``, ``onnx.md``. torch on 2 threads,
onnxruntime with its default (one per core: 2 on the project's benchmark machine).
``--method`` exports and runs another method than "guided" (the default Denoiser's) the same way.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch
from bench_pipeline import timed
from benchmark_utils import available_scenes, markdown_table, metadata, scene_sets, write_results

import torchgi
from torchgi import metrics
from torchgi.denoise import Denoiser
from torchgi.export import OrtDenoiser, export_denoiser

SIZES = {"256": (256, 256), "512": (512, 512), "1080p": (1080, 1920)}


def run(args) -> list[dict]:
    rows, graphs = [], {}
    tmp = Path(tempfile.mkdtemp())
    for size in args.sizes:
        H, W = SIZES[size]
        for name, scene in available_scenes([s for s in args.scenes if ":" not in s], W):
            scene = scene.with_resolution(W, H)
            ref = torchgi.render(scene, spp=args.ref_spp, bounces=args.bounces, seed=999).color
            for spp in args.spp:
                gb = torchgi.render(scene, spp=spp, bounces=args.bounces, seed=1)
                for emission in (True, False):
                    same = gb if emission else gb.replace(emission=None)  # what both are fed
                    key = (repr(Denoiser(args.method).deploy(frame=same, emission=emission)), emission)
                    if key not in graphs:  # one export per distinct set of fixed choices
                        graphs[key] = OrtDenoiser(export_denoiser(
                            args.method, tmp / f"g{len(graphs)}.onnx", frame=same, emission=emission))
                    d, ort = Denoiser(args.method), graphs[key]
                    fns = {"eager": lambda d=d, g=same: d(g), "onnxruntime": lambda o=ort, g=same: o(g)}
                    outs = {k: f() for k, f in fns.items()}
                    eager = outs["eager"]
                    for method, ms in timed(fns, args.rounds, "cpu", settle=1, pause=0.2).items():
                        out = outs[method]
                        rows.append({"scene": Path(name).name, "size": size, "spp": spp,
                                     "emission layer": emission, "method": method,
                                     "relmse": float(metrics.relmse(out, ref)), "ms": ms,
                                     "rel_diff_vs_eager": float((out - eager).abs().max() / eager.abs().max()),
                                     "graph": key[0] if method == "onnxruntime" else ""})
                    print({k: rows[-2][k] for k in ("scene", "size", "spp", "emission layer")},
                          {r["method"]: (round(r["relmse"], 6), round(r["ms"], 1)) for r in rows[-2:]}, flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench-onnx")
    ap.add_argument("--set", default="judged", choices=("judged", "tuning", "training"))
    ap.add_argument("--scenes", nargs="+", help="these entries instead of --set's")
    ap.add_argument("--sizes", nargs="+", default=["512", "1080p"], choices=list(SIZES))
    ap.add_argument("--spp", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--ref-spp", type=int, default=256)
    ap.add_argument("--bounces", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--method", default="guided", choices=("guided", "pyramid", "blend"),
                    help="the Denoiser method exported and compared (default: guided, the default Denoiser's)")
    args = ap.parse_args()
    args.scenes = args.scenes or scene_sets()[args.set]
    torch.set_num_threads(2)
    rows = run(args)
    out = Path(args.out)
    write_results(rows, metadata(torch.get_num_threads()), out, "onnx")
    md = markdown_table(rows, ["scene", "size", "spp", "emission layer", "method", "relmse", "ms",
                               "rel_diff_vs_eager", "graph"])
    (out / "onnx.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
