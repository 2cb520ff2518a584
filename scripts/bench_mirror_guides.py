"""Whether guides through mirrors pay: each Denoiser and OIDN with the first hit's guides and with
``render(mirror_guides=R)``'s (the albedo and normal of what a mirror reflects).

    python scripts/bench_mirror_guides.py --out out/bench-mirror-guides
    python scripts/bench_mirror_guides.py --scenes judged/mirror_floor_cubes --out out/bench-mirror-judged

Per scene (sets.yaml syntax; default: the training set's two near-mirror scenes, and
``mirror_lamps`` with its floor's roughness set to ``--sharp``, a sharper mirror than any tuning or
training scene has) and spp: one noisy render (seed 1) with each kind of guides, against a
``--ref-spp`` reference (seed 999); relMSE of ``Denoiser("guided")``, ``("pyramid")``,
``("blend")`` and OIDN "high" (colour + albedo + normal, HDR). Writes ``mirror_guides.csv/json/md``
with the ratio of each method's error with the mirror guides to its error without.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmark_utils import available_scenes, markdown_table, metadata, oidn, write_results

import torchgi
from torchgi import metrics

METHODS = ("guided", "pyramid", "blend")
SHARP = "sharp:"  # "sharp:<entry>": that scene with its first mesh's roughness set to --sharp


def scenes(args) -> list[tuple[str, torchgi.Scene]]:
    """``(name, scene)`` per ``--scenes`` entry at ``--size``²."""
    out = []
    for entry in args.scenes:
        for name, scene in available_scenes([entry.removeprefix(SHARP)], args.size):
            if entry.startswith(SHARP):
                m0 = scene.meshes[0]
                m0 = dataclasses.replace(m0, material=dataclasses.replace(m0.material, roughness=args.sharp))
                scene = dataclasses.replace(scene, meshes=[m0, *scene.meshes[1:]])
                name = f"{Path(name).name} (floor roughness {args.sharp})"
            out.append((Path(name).name, scene))
    return out


def run(args) -> list[dict]:
    rows = []
    for name, scene in scenes(args):
        ref = torchgi.render(scene, spp=args.ref_spp, bounces=args.bounces, seed=999).color
        for spp in args.spp:
            errors = {}
            for guides in ("first hit", "mirror"):
                gb = torchgi.render(scene, spp=spp, bounces=args.bounces, seed=1,
                                    mirror_guides=args.roughness if guides == "mirror" else None)
                outs = {m: torchgi.Denoiser(m)(gb) for m in METHODS}
                try:
                    outs["OIDN high"] = oidn(gb, "high", False)
                except ImportError:
                    pass
                for method, out in outs.items():
                    errors[method, guides] = float(metrics.relmse(out, ref))
            for method in dict.fromkeys(m for m, _ in errors):
                first, mirror = errors[method, "first hit"], errors[method, "mirror"]
                row = {"scene": name, "spp": spp, "method": method, "relmse_first_hit": first,
                       "relmse_mirror_guides": mirror, "ratio": mirror / first}
                rows.append(row)
                print({k: (round(v, 5) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench-mirror-guides")
    ap.add_argument("--scenes", nargs="+", default=["train/mirror_lamps", "train/armadillo_glossy_room",
                                                    f"{SHARP}train/mirror_lamps"])
    ap.add_argument("--spp", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--bounces", type=int, default=2)
    ap.add_argument("--roughness", type=float, default=0.1, help="render(mirror_guides=...): mirrors below it")
    ap.add_argument("--sharp", type=float, default=0.01, help="the floor roughness of the sharp: scenes")
    args = ap.parse_args()
    torch.set_num_threads(2)
    rows = run(args)
    out = Path(args.out)
    write_results(rows, metadata(torch.get_num_threads()), out, "mirror_guides")
    md = markdown_table([{k: (round(v, 5) if isinstance(v, float) else v) for k, v in r.items()} for r in rows],
                        ["scene", "spp", "method", "relmse_first_hit", "relmse_mirror_guides", "ratio"])
    (out / "mirror_guides.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
