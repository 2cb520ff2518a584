"""Issue 17, a first measurement: can the guided filter's radius be chosen per pixel from the data
alone (no reference), and how much of the per-tile oracle's gain does that recover?

    python scripts/explore_per_pixel.py --size 128 --spp 1 4 --ref-spp 512 --out out/explore

Per scene and spp: a noisy torchgi render and a reference, then (all through the Denoiser's
pipeline: demodulation, lights, fireflies, remodulation)
* ``default``: ``Denoiser("guided")``;
* ``global best``: the best single radius of the candidates, chosen with the reference;
* ``oracle 8x8``: per 8x8 tile the candidate closest to the reference (an upper bound);
* ``sure``: per pixel the candidate of least SURE risk, ``box((y_k - x)² + 2 σ² d_k)``, where
  ``d_k = z · W_k z`` is a Monte Carlo estimate of the filter's own-pixel weight (``W_k`` is linear
  in the source: one extra filter call on a Rademacher probe ``z``) and ``σ²`` the local noise
  variance of the demodulated light ``x`` (the renderer's variance where it has one, >= 2 spp; else
  ``box((x - y_widest)²)``, which also counts the widest filter's bias);
* ``relative sure``: the risk weighted as relMSE weighs the image, ``albedo² / ((albedo y_4)² +
  0.01)`` with the radius-4 output standing in for the reference;
* ``sure, true noise level``: a diagnostic, the same with ``σ² = box((x - x_ref)²)`` from the
  reference's demodulated light: how well the selection rule does with a perfect noise estimate;
* ``OIDN high`` (pyoidn, colour + albedo + normal, HDR) where installed.
Candidates: the guided filter at radii 1, 2, 3, 4, 6, 8, 12, 16, eps 1e-4, on the Denoiser's
guide. Writes ``explore.csv`` / ``explore.md`` and, per case, ``radius_<scene>_<spp>.png`` (the
radius SURE chose). An exploration on the project's tuning scenes, not a judged result.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import available_scenes, markdown_table, metadata, write_results

import torchgi
from torchgi import metrics
from torchgi.denoise import Denoiser
from torchgi.filters import box, guide_from_gbuffer, guided
from torchgi.io import write_png

RADII = (1, 2, 3, 4, 6, 8, 12, 16)
EPS = 1e-4


class _Chooser(Denoiser):
    """The guided Denoiser's pipeline around a per-pixel choice among the candidate radii."""

    def __init__(self, smooth: int, probes: int = 1, seed: int = 0, true_light: torch.Tensor | None = None,
                 relative: bool = False) -> None:
        super().__init__("guided")
        self.smooth, self.probes, self.seed, self.choice, self.relative = smooth, probes, seed, None, relative
        self.true_light = true_light  # diagnostic: the reference's demodulated light gives the true noise level

    def _filter(self, x: torch.Tensor, gb, surface: torch.Tensor) -> torch.Tensor:
        guide = guide_from_gbuffer(gb)
        ys = torch.stack([guided(x, guide, radius=r, eps=EPS) for r in RADII])  # (K, B, C, H, W)
        gen = torch.Generator().manual_seed(self.seed)
        d = 0
        for _ in range(self.probes):  # own-pixel weight: E[z · W z] = diag(W) for a Rademacher z
            z = torch.randint(0, 2, x.shape, generator=gen).to(x.dtype) * 2 - 1
            d = d + torch.stack([z * guided(z, guide, radius=r, eps=EPS) for r in RADII]) / self.probes
        if self.true_light is not None:
            s2 = box((x - self.true_light).square(), 4)
        elif gb.variance is not None and gb.spp is not None and bool((gb.spp >= 2).all()):
            albedo = torch.where(surface, gb.albedo.clamp_min(1e-3), 1.0)
            s2 = gb.variance / albedo.square()  # variance of the pixel mean of x
        else:
            s2 = box((x - ys[-1]).square(), 4)
        weight = 1.0
        if self.relative:  # the risk of relMSE in the image: albedo² / (image² + 0.01), the image from radius 4
            albedo = torch.where(surface, gb.albedo.clamp_min(1e-3), 1.0)
            weight = albedo.square() / ((albedo * ys[RADII.index(4)]).square() + 1e-2)
        risk = torch.stack([box(weight * ((y - x).square() + 2 * s2 * dk), self.smooth).sum(1, keepdim=True)
                            for y, dk in zip(ys, d)])  # (K, B, 1, H, W)
        self.choice = risk.argmin(0)  # (B, 1, H, W)
        idx = self.choice.expand_as(x)[None]
        return ys.gather(0, idx)[0]


def oracle_tiles(outs: torch.Tensor, ref: torch.Tensor, tile: int) -> torch.Tensor:
    """Per ``tile x tile`` block the candidate (``outs (K, B, C, H, W)``) of least relative squared error."""
    err = ((outs - ref) ** 2 / (ref**2 + 1e-2)).sum(2, keepdim=True)  # (K, B, 1, H, W)
    K, B, _, H, W = err.shape
    pooled = torch.nn.functional.avg_pool2d(err.reshape(K * B, 1, H, W), tile, ceil_mode=True)
    best = pooled.reshape(K, B, 1, *pooled.shape[-2:]).argmin(0)
    best = best.repeat_interleave(tile, -2).repeat_interleave(tile, -1)[..., :H, :W]
    return outs.gather(0, best.expand_as(outs[0])[None])[0]


def oidn_fn():
    try:
        import pyoidn
    except ImportError:
        return None

    def run(gb):
        hwc = lambda t: t[0].permute(1, 2, 0).contiguous()
        return pyoidn.denoise(hwc(gb.color), hwc(gb.albedo), hwc(gb.normal), hdr=True, quality="high").permute(
            2, 0, 1)[None]

    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["cornell", "cornell_glossy", "sky", "grass", "bunny"])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", nargs="+", type=int, default=[1, 4])
    ap.add_argument("--ref-spp", type=int, default=512)
    ap.add_argument("--smooth", nargs="+", type=int, default=[2, 4])
    ap.add_argument("--probes", nargs="+", type=int, default=[1], help="Rademacher probes of the divergence")
    ap.add_argument("--out", type=Path, default=Path("out/explore"))
    args = ap.parse_args()
    torch.set_num_threads(2)
    args.out.mkdir(parents=True, exist_ok=True)
    oidn = oidn_fn()
    rows = []
    for name, scene in available_scenes(args.scenes, args.size):
        ref = torchgi.render(scene, spp=args.ref_spp, bounces=1, seed=99).color
        for spp in args.spp:
            gb = torchgi.render(scene, spp=spp, bounces=1, seed=1)
            err = {"scene": name, "spp": spp, "noisy": float(metrics.relmse(gb.color, ref))}
            err["default"] = float(metrics.relmse(Denoiser("guided")(gb), ref))
            outs = torch.stack([Denoiser("guided", radius=r, eps=EPS)(gb) for r in RADII])
            singles = [float(metrics.relmse(o, ref)) for o in outs]
            err["global best"] = min(singles)
            err["global best radius"] = RADII[int(np.argmin(singles))]
            err["oracle 8x8"] = float(metrics.relmse(oracle_tiles(outs, ref, 8), ref))
            for s in args.smooth:
                for probes in args.probes:
                    chooser = _Chooser(s, probes)
                    err[f"sure box{s} x{probes}"] = float(metrics.relmse(chooser(gb), ref))
            radius_map = torch.tensor(RADII, dtype=torch.float32)[chooser.choice[0, 0]]
            write_png(args.out / f"radius_{name}_{spp}.png",
                      (radius_map / max(RADII) * 255).round().to(torch.uint8).numpy(), overwrite=True)
            surface = gb.hit
            albedo = torch.where(surface, gb.albedo.clamp_min(1e-3), 1.0)
            true_light = (ref - gb.emission) / albedo
            err["relative sure box8 x8"] = float(metrics.relmse(_Chooser(8, 8, relative=True)(gb), ref))
            err["sure, true noise level"] = float(metrics.relmse(_Chooser(8, 8, true_light=true_light)(gb), ref))
            if oidn is not None:
                err["OIDN high"] = float(metrics.relmse(oidn(gb), ref))
            rows.append(err)
            print(err, flush=True)
    cols = list(rows[0])
    meta = metadata(2) | {"args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}}
    write_results(rows, meta, args.out, "explore")
    (args.out / "explore.md").write_text(markdown_table(rows, cols))


if __name__ == "__main__":
    main()
