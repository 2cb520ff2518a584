"""The labelled grid of procedural scenes in ``docs/procedural_grid.png``: 16 seeds of
:func:`torchgi.scenes.procedural`, each rendered by torchgi at 128², 2 bounces, 64 spp, denoised
by nothing, tonemapped to sRGB (exposure 1), with its seed, object count, lights and texture count.

    python scripts/procedural_grid.py --out docs/procedural_grid.png [--first 0] [--spp 64]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def _label(scene) -> str:
    a = scene.arrays()
    kinds = {"PointLight": "point", "Sky": "sky"}
    area = int(sum(1 for m in scene.meshes if m.material.emissive))
    lights = ([f"{area} area"] if area else []) + [kinds.get(type(li).__name__, type(li).__name__) for li in scene.lights]
    return (f"seed {scene.name.split('_')[-1]}: {len(scene.meshes)} meshes, {int((a.texture > 0).sum())} textured; "
            f"light: {', '.join(lights)}")


def main() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import torchgi
    from torchgi.io.png import to_srgb8

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args()
    if args.out.exists() and not args.overwrite:
        raise SystemExit(f"--out: {args.out} exists (pass --overwrite)")
    fig, axes = plt.subplots(4, 4, figsize=(12, 13))
    for ax, seed in zip(axes.flat, range(args.first, args.first + 16)):
        scene = torchgi.scenes.procedural(seed, 128)
        gb = torchgi.render(scene, spp=args.spp, bounces=2, seed=seed, progress=False)
        ax.imshow(np.asarray(to_srgb8(gb.color[0])))
        ax.set_title(_label(scene), fontsize=6.5)
        ax.axis("off")
    fig.suptitle(f"torchgi.scenes.procedural(seed, 128), seeds {args.first}-{args.first + 15}: "
                 f"{args.spp} spp, 2 bounces, no denoiser", fontsize=10)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)


if __name__ == "__main__":
    main()
