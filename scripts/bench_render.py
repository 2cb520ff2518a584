"""Render benchmark: samples/s of torchgi and of Mitsuba 3 ``scalar_rgb`` on the same scenes,
bounces and spp, side by side in one run, plus the time with and without each skip of DESIGN §4.

    python scripts/bench_render.py --out out/bench                 # full run (a few minutes)
    python scripts/bench_render.py --quick --out out/bench         # smoke run

Both renderers use every core of this machine (torchgi: one process per core; Mitsuba: its
thread pool). Each configuration runs ``--repeats`` times, alternating torchgi and Mitsuba so
that load from elsewhere hits both alike; the table gives medians and their ratio. Scene
loading / BVH builds are excluded for both (Mitsuba's ``load_dict``, torchgi's first render).
Writes ``render.csv``, ``render.json``, ``render.md`` and ``render.png`` under ``--out``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import markdown_table, metadata, write_results

import torchgi
from torchgi.render import scenes
from torchgi.render.engine import SKIPS
from torchgi.render.mitsuba import load_mitsuba, to_mitsuba


def seconds(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def peers(name: str, size: int, bounces: int, spp: int, repeats: int, mi) -> dict:
    scene = scenes.BUILTINS[name](size)
    with tempfile.TemporaryDirectory() as tmp:
        mscene = mi.load_dict(to_mitsuba(scene, tmp, bounces=bounces))
    torchgi.render(scene.with_resolution(32, 32), spp=1, bounces=bounces)  # BVH, worker pool
    samples = size * size * spp
    ours, theirs = [], []
    for r in range(repeats):
        theirs.append(seconds(lambda: mi.render(mscene, spp=spp, seed=r)))
        ours.append(seconds(lambda: torchgi.render(scene, spp=spp, bounces=bounces, seed=r)))
    t_ours, t_theirs = statistics.median(ours), statistics.median(theirs)
    return {
        "scene": name, "size": f"{size}x{size}", "bounces": bounces, "spp": spp, "repeats": repeats,
        "torchgi_msps": samples / t_ours / 1e6, "mitsuba_msps": samples / t_theirs / 1e6,
        "ratio": t_theirs / t_ours, "torchgi_s": t_ours, "mitsuba_s": t_theirs,
        "torchgi_min_max_s": f"{min(ours):.3f}-{max(ours):.3f}",
        "mitsuba_min_max_s": f"{min(theirs):.3f}-{max(theirs):.3f}",
    }


SKIP_CASES = [
    # (skip of DESIGN §4, scene, bounces): timed with every skip on, and with all but this one
    ("absent_lights", "cornell", 1),
    ("dead_paths", "sky", 1),
    ("dead_paths", "grass", 1),
    ("last_vertex_rays", "cornell", 1),
    ("last_vertex_rays", "cornell", 0),
]


def skips(size: int, spp: int, repeats: int) -> list[dict]:
    rows = []
    for skip, name, bounces in SKIP_CASES:
        scene = scenes.BUILTINS[name](size)
        torchgi.render(scene.with_resolution(32, 32), spp=1, bounces=bounces)
        others = set(SKIPS) - {skip}
        on, off = [], []
        for r in range(repeats):
            off.append(seconds(lambda: torchgi.render(scene, spp=spp, bounces=bounces, seed=r, skip_unneeded=others)))
            on.append(seconds(lambda: torchgi.render(scene, spp=spp, bounces=bounces, seed=r)))
        rows.append({
            "skip": skip, "what": SKIPS[skip], "scene": name, "bounces": bounces, "size": f"{size}x{size}",
            "spp": spp, "with_skip_s": statistics.median(on), "without_skip_s": statistics.median(off),
            "speedup": statistics.median(off) / statistics.median(on),
        })
    return rows


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{r['scene']}\nb={r['bounces']}" for r in rows]
    x = range(len(rows))
    fig, ax = plt.subplots(figsize=(1.4 * len(rows) + 2, 3.5))
    ax.bar([i - 0.2 for i in x], [r["torchgi_msps"] for r in rows], 0.4, label="torchgi")
    ax.bar([i + 0.2 for i in x], [r["mitsuba_msps"] for r in rows], 0.4, label="Mitsuba 3 scalar_rgb")
    ax.set_xticks(list(x), labels)
    ax.set_ylabel("M samples / s (median)")
    ax.set_title(f"{rows[0]['size']}, {rows[0]['spp']} spp, {os.cpu_count()} cores")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/bench")
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="128x128, 2 spp, 2 repeats, cornell only")
    args = parser.parse_args()
    if args.quick:
        args.size, args.spp, args.repeats = 128, 2, 2
    mi = load_mitsuba()
    names = ["cornell"] if args.quick else ["cornell", "cornell_glossy", "sky", "grass"]
    rows = [peers(n, args.size, b, args.spp, args.repeats, mi) for n in names for b in (1, 3)]
    skip_rows = skips(args.size, args.spp, args.repeats) if not args.quick else []
    meta = metadata(torch.get_num_threads())
    meta["cores"] = len(os.sched_getaffinity(0))
    meta["mitsuba"] = mi.__version__
    out = Path(args.out)
    write_results(rows, meta, out, "render")
    write_results(skip_rows, meta, out, "render_skips")
    table = markdown_table(rows, ["scene", "size", "bounces", "spp", "torchgi_msps", "mitsuba_msps", "ratio"])
    skip_table = markdown_table(skip_rows, ["skip", "what", "scene", "bounces", "with_skip_s", "without_skip_s",
                                            "speedup"])
    (out / "render.md").write_text(table + "\n\n" + skip_table + "\n")
    plot(rows, out / "render.png")
    print(table)
    print()
    print(skip_table)
    print(f"\nwrote {out}/render.csv, render_skips.csv, render.json, render.md, render.png ({meta['commit']})")


if __name__ == "__main__":
    main()
