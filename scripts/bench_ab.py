"""Two trees of torchgi side by side: the same cases timed in alternating fresh processes (before,
after, before, after, ...), for a refactor that must not move the timings.

    git worktree add /tmp/before <commit>
    python scripts/bench_ab.py --before /tmp/before --after . --rounds 4 --out out/bench-ab

Cases, on 2 threads: the Denoiser (guided, À-Trous, blend, pyramid) on a 512² Cornell box at 1 spp
and guided at 4 spp (its back-off and choice among radii), eight
TemporalDenoiser frames at 256², a 256² render at 16 spp, importance + allocation at 1024x768.
Each process imports torchgi from its tree (checked), warms each case up once and reports the
median of its repeats; the table gives, per case, the median over rounds of each side and the
ratio after / before. Writes ``ab.csv``, ``ab.json`` and ``ab.png``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import markdown_table, metadata, write_results

CHILD = r"""
import json, statistics, sys, time
tree = sys.argv[1]
sys.path.insert(0, tree)
import torch
import torchgi
assert torchgi.__file__.startswith(tree), (torchgi.__file__, tree)
torch.set_num_threads(2)
from torchgi.render import render, scenes
from torchgi.sampling import allocate, importance_map

gb = render(scenes.cornell(512), spp=1, bounces=1, seed=1)
gb4 = render(scenes.cornell(512), spp=4, bounces=1, seed=1)
seq = [render(scenes.cornell(256), spp=1, bounces=1, seed=k).replace(motion=torch.zeros(1, 2, 256, 256))
       for k in range(8)]
guides = render(scenes.grass(256).with_resolution(1024, 768), spp=1, bounces=0, seed=2)
den = {m: torchgi.Denoiser(m) for m in ("guided", "atrous", "blend", "pyramid")}

def temporal():
    t = torchgi.TemporalDenoiser()
    for f in seq:
        t(f)

def importance():
    q = importance_map(guides.normal, guides.position, window=4, sigma_position=1.0, hit=guides.hit)
    allocate(q, 4 * int(guides.hit.sum()), mask=guides.hit)

cases = {
    "Denoiser guided 512²": lambda: den["guided"](gb),
    "Denoiser atrous 512²": lambda: den["atrous"](gb),
    "Denoiser blend 512²": lambda: den["blend"](gb),
    "Denoiser pyramid 512²": lambda: den["pyramid"](gb),
    "Denoiser guided 512² 4 spp": lambda: den["guided"](gb4),
    "TemporalDenoiser 8 frames 256²": temporal,
    "render cornell 256² 16 spp": lambda: render(scenes.cornell(256), spp=16, bounces=1, seed=3),
    "importance + allocate 1024x768": importance,
}
out = {}
for name, fn in cases.items():
    fn()
    times = []
    for _ in range(int(sys.argv[2])):
        t0 = time.perf_counter(); fn(); times.append(time.perf_counter() - t0)
    out[name] = statistics.median(times) * 1e3
print(json.dumps(out))
"""


def run(tree: Path, repeats: int) -> dict[str, float]:
    proc = subprocess.run([sys.executable, "-c", CHILD, str(tree.resolve()), str(repeats)], capture_output=True,
                          text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{tree}: {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True)
    ap.add_argument("--after", type=Path, default=Path("."))
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path("out/bench-ab"))
    args = ap.parse_args()
    runs: dict[str, list[dict[str, float]]] = {"before": [], "after": []}
    for r in range(args.rounds):
        for side in (("before", "after") if r % 2 == 0 else ("after", "before")):
            runs[side].append(run(getattr(args, side), args.repeats))
            print(f"round {r + 1} {side}: " + ", ".join(f"{k} {v:.1f}" for k, v in runs[side][-1].items()), flush=True)
    rows = []
    for case in runs["before"][0]:
        b = statistics.median(x[case] for x in runs["before"])
        a = statistics.median(x[case] for x in runs["after"])
        spread = [x[case] for x in runs["before"] + runs["after"]]
        rows.append({"case": case, "before_ms": round(b, 2), "after_ms": round(a, 2), "after / before": round(a / b, 3),
                     "min_ms": round(min(spread), 2), "max_ms": round(max(spread), 2)})
    meta = metadata(2) | {"before": str(args.before), "after": str(args.after), "rounds": args.rounds,
                          "repeats": args.repeats}
    write_results(rows, meta, args.out, "ab")
    print(markdown_table(rows, list(rows[0])))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.barh([r["case"] for r in rows], [r["after / before"] for r in rows])
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_xlabel("after / before (median time)")
    fig.tight_layout()
    fig.savefig(args.out / "ab.png", dpi=120)


if __name__ == "__main__":
    main()
