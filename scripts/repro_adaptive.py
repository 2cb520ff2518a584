"""Reproduce Bauszat et al. 2011's adaptive sampling: equal budget, uniform vs adaptive, with
À-Trous and with the guided filter; and the importance + allocation overhead (their Table 1).

    python scripts/repro_adaptive.py --out out/bench                  # grass + dragon, ~3 min
    python scripts/repro_adaptive.py --scenes grass --size 128 --ref-spp 128 --out out/bench  # quick

Protocol: each pixel on geometry gets ``rate`` samples on average (exact budget, minimum 1, none
on background; each sample traces the pixel's whole light). The filters work on the demodulated
indirect light (indirect / albedo) and the result is remodulated; errors are those of the indirect
light (the part the paper samples adaptively and filters) against a
``--ref-spp`` render. Importance and filter share their geometry weights, as in the paper:
σ_n = 0.1 and σ_x = (k · pixel footprint)², k = 2 by default; ``--k 2 8`` also reports k = 8
(a stronger filter). Writes ``adaptive.csv/json/md``, ``adaptive_timing.csv`` and ``adaptive.png``.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import (
    SIZES,
    available_scenes,
    load_scene,
    markdown_table,
    metadata,
    time_ms,
    write_results,
)

import torchgi
from torchgi import backends, metrics
from torchgi.filters import atrous, guide_from_gbuffer, guided
from torchgi.render import render_guides
from torchgi.sampling import adaptive_render, allocate, importance_map, pixel_footprint


def filtered_indirect(gb, method: str, sigma_x: float) -> torch.Tensor:
    albedo = gb.albedo.clamp_min(1e-3)
    demod = torch.where(gb.hit, gb.indirect / albedo, torch.zeros(()))
    if method == "atrous":
        out = atrous(demod, gb.normal, gb.position, iterations=5, sigma_normal=0.1, sigma_position=sigma_x)
    else:
        out = guided(demod, guide_from_gbuffer(gb), radius=4, eps=1e-3)
    return torch.where(gb.hit, out * albedo, torch.zeros(()))


def quality(args, rows: list[dict], images: dict) -> None:
    for name, scene in available_scenes(args.scenes, args.size):
        t0 = time.perf_counter()
        ref = torchgi.render(scene, spp=args.ref_spp, bounces=args.bounces, seed=99)
        print(f"{name}: reference {args.ref_spp} spp in {time.perf_counter() - t0:.1f} s", flush=True)
        hit = ref.hit
        foot = pixel_footprint(ref.position, hit)
        for k in args.k:
            sigma_x = (k * foot) ** 2
            uniform = torch.where(hit, round(args.rate), 0).to(torch.int64)
            variants = {"uniform": torchgi.render(scene, uniform, args.bounces, args.seed)}
            for label, share in (("adaptive", 0.0), ("adaptive+variance", 0.5)):
                variants[label], counts = adaptive_render(scene, args.rate, args.bounces, args.seed,
                                                          sigma_position=sigma_x, variance_share=share)
                if label == "adaptive":
                    images.setdefault(name, {})["counts"] = counts
            for label, gb in variants.items():
                spent = int(gb.spp[hit].sum())
                for method in ("atrous", "guided", "none"):
                    out = gb.indirect if method == "none" else filtered_indirect(gb, method, sigma_x)
                    rows.append({
                        "scene": name, "size": args.size, "k": k, "sampling": label, "filter": method,
                        "indirect_spp": spent / int(hit.sum()),
                        "mse": float(metrics.mse(out, ref.indirect)),
                        "relmse": float(metrics.relmse(out, ref.indirect)),
                    })
                    if k == args.k[0] and method != "none" and label in ("uniform", "adaptive"):
                        images[name][f"{label} + {method}"] = out
            images[name]["reference"] = ref.indirect
            for method in ("atrous", "guided"):
                sel = {r["sampling"]: r for r in rows if r["scene"] == name and r["k"] == k and r["filter"] == method}
                for label in ("adaptive", "adaptive+variance"):
                    sel[label]["mse_over_uniform"] = sel[label]["mse"] / sel["uniform"]["mse"]
            print(markdown_table([r for r in rows if r["scene"] == name and r["k"] == k],
                                 ["sampling", "filter", "indirect_spp", "mse", "relmse", "mse_over_uniform"]),
                  flush=True)


def timing(args, rows: list[dict]) -> None:
    """Importance + allocation at 1024x768 on grass guides: the default call (the compiled CPU
    kernels where they build) and the torch code compiled with ``fused=True``."""
    H, W = SIZES["1024x768"]
    g = render_guides(load_scene("grass", 1024).with_resolution(W, H))
    foot = pixel_footprint(g.position, g.hit)
    budget = 4 * int(g.hit.sum())
    for mode in ("kernel", "torch fused"):
        for window in (2, 4, 6, 8, 10):
            def importance():
                return importance_map(g.normal, g.position, window=window, sigma_position=(2 * foot) ** 2, hit=g.hit,
                                      fused=mode == "torch fused")

            with backends.use("torch") if mode != "kernel" else contextlib.nullcontext():
                t_all = time_ms(lambda: allocate(importance(), budget, min_samples=1, mask=g.hit),
                                min_run_time=args.min_time)["median_ms"]
                imp = importance()
                t_alloc = time_ms(lambda: allocate(imp, budget, min_samples=1, mask=g.hit),
                                  min_run_time=args.min_time)["median_ms"]
            rows.append({"size": "1024x768", "window": window, "mode": mode, "importance_plus_allocate_ms": t_all,
                         "allocate_ms": t_alloc, "paper_ms": {2: 8.3, 4: 26.2, 10: 128.7}.get(window)})
            print(rows[-1], flush=True)


def plot(images: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchgi.metrics import tonemap

    names = list(images)
    cols = ["counts", "uniform + atrous", "adaptive + atrous", "uniform + guided", "adaptive + guided", "reference"]
    fig, axes = plt.subplots(len(names), len(cols), figsize=(2.6 * len(cols), 2.7 * len(names)), squeeze=False)
    for row, name in zip(axes, names):
        for ax, col in zip(row, cols):
            img = images[name].get(col)
            if img is None:
                ax.axis("off")
                continue
            if col == "counts":
                im = ax.imshow(img[0, 0].numpy(), cmap="magma")
                fig.colorbar(im, ax=ax, fraction=0.046)
            else:
                ax.imshow(tonemap(img[0] * 4).clamp(0, 1).permute(1, 2, 0).numpy())
            ax.set_title(f"{name}: {col}", fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench")
    ap.add_argument("--scenes", nargs="+", default=["grass", "dragon"])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--rate", type=float, default=4.0)
    ap.add_argument("--bounces", type=int, default=2)
    ap.add_argument("--ref-spp", type=int, default=512)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--k", type=float, nargs="+", default=[2.0], help="σ_x = (k · footprint)², first one plotted")
    ap.add_argument("--min-time", type=float, default=1.0)
    ap.add_argument("--no-timing", action="store_true")
    ap.add_argument("--timing-only", action="store_true", help="only the importance + allocation table")
    args = ap.parse_args()
    rows: list[dict] = []
    images: dict = {}
    if not args.timing_only:
        quality(args, rows, images)
    timing_rows: list[dict] = []
    if not args.no_timing:
        timing(args, timing_rows)
    meta = metadata(torch.get_num_threads())
    out = Path(args.out)
    if rows:
        write_results(rows, meta, out, "adaptive")
    write_results(timing_rows, meta, out, "adaptive_timing")
    md = markdown_table([r for r in rows if r["filter"] != "none" or r["sampling"] == "uniform"],
                        ["scene", "k", "sampling", "filter", "indirect_spp", "mse", "relmse", "mse_over_uniform"])
    if timing_rows:
        md += "\n\n" + markdown_table(timing_rows, ["size", "window", "mode", "importance_plus_allocate_ms",
                                                    "allocate_ms", "paper_ms"])
    (out / ("adaptive_timing.md" if args.timing_only else "adaptive.md")).write_text(md + "\n")
    if images:
        plot(images, out / "adaptive.png")
    print(md)


if __name__ == "__main__":
    main()
