"""Render benchmark: samples/s of torchgi and of Mitsuba 3 ``scalar_rgb`` on the same scenes,
bounces and spp, side by side in one run; a 1080p case; the whole call (start-up included) of a
96x96 256 spp render of a scene with a Stanford mesh; where the time goes; and the time with and
without each skip of docs/design.md (Skips).

    python scripts/bench_render.py --out out/bench                 # full run (about 15 minutes)
    python scripts/bench_render.py --quick --out out/bench         # smoke run

Both renderers use every core of this machine (torchgi: the compiled tracer's threads, or the
torch wavefronts' worker processes; Mitsuba: its thread pool). Each configuration runs
``--repeats`` times, alternating the renderers so that load from elsewhere hits them alike; the
tables give medians and their ratios. In ``render.csv`` scene loading and BVH builds are
excluded for both (Mitsuba's ``load_dict``, torchgi's first render); ``render_call.csv`` times a
fresh process's load + render for each (imports excluded). Writes ``render.csv``,
``render_call.csv``, ``render_profile.csv``, ``render_skips.csv``, ``render.json`` (commit,
versions), ``render.md`` and ``render.png`` under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import CONFIG_SCENES, available_scenes, load_scene, markdown_table, metadata, write_results

import torchgi
from torchgi import backends
from torchgi.render.engine import SKIPS
from torchgi.render.mitsuba import load_mitsuba, to_mitsuba

SCENES = ["cornell", "cornell_glossy", "sky", "grass", "bunny_box"]


def seconds(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def peers(name: str, scene, bounces: int, spp: int, repeats: int, mi, torch_code: bool) -> dict:
    """torchgi (compiled tracer), Mitsuba and (``torch_code``) torchgi's torch wavefronts, alternating."""
    width, height = scene.camera.resolution
    with tempfile.TemporaryDirectory() as tmp:
        mscene = mi.load_dict(to_mitsuba(scene, tmp, bounces=bounces))
    torchgi.render(scene.with_resolution(32, 32), spp=1, bounces=bounces)  # BVH, library
    samples = width * height * spp
    ours, theirs, wave = [], [], []
    for r in range(repeats):
        theirs.append(seconds(lambda: mi.render(mscene, spp=spp, seed=r)))
        ours.append(seconds(lambda: torchgi.render(scene, spp=spp, bounces=bounces, seed=r)))
        if torch_code:
            with backends.use("torch"):
                wave.append(seconds(lambda: torchgi.render(scene, spp=spp, bounces=bounces, seed=r)))
    t_ours, t_theirs = statistics.median(ours), statistics.median(theirs)
    row = {
        "scene": name, "size": f"{width}x{height}", "bounces": bounces, "spp": spp, "repeats": repeats,
        "torchgi_msps": samples / t_ours / 1e6, "mitsuba_msps": samples / t_theirs / 1e6,
        "ratio": t_theirs / t_ours, "torchgi_s": t_ours, "mitsuba_s": t_theirs,
        "torchgi_min_max_s": f"{min(ours):.3f}-{max(ours):.3f}",
        "mitsuba_min_max_s": f"{min(theirs):.3f}-{max(theirs):.3f}",
        "tracer": backends.status()["last"]["path"]["ran"],
    }
    if torch_code:
        row["torch_code_msps"] = samples / statistics.median(wave) / 1e6
        row["ratio_torch_code"] = t_theirs / statistics.median(wave)
    return row


_CALL = {
    "torchgi": (
        "import sys, time, torchgi\n"
        "t = time.perf_counter()\n"
        "scene = torchgi.load_scene(sys.argv[1])\n"
        "torchgi.render(scene, spp=int(sys.argv[2]), bounces=1, seed=int(sys.argv[3]))\n"
        "print(time.perf_counter() - t)\n"
    ),
    "mitsuba": (
        "import sys, tempfile, time, torchgi\n"
        "from torchgi.render.mitsuba import load_mitsuba, to_mitsuba\n"
        "mi = load_mitsuba()\n"
        "with tempfile.TemporaryDirectory() as tmp:\n"
        "    d = to_mitsuba(torchgi.load_scene(sys.argv[1]), tmp, bounces=1)  # PLY files, before the clock\n"
        "    t = time.perf_counter()\n"
        "    mi.render(mi.load_dict(d), spp=int(sys.argv[2]), seed=int(sys.argv[3]))\n"
        "    print(time.perf_counter() - t)\n"
    ),
}


def whole_call(path: Path, spp: int, repeats: int) -> dict:
    """A fresh process per call (imports excluded): torchgi's load_scene + render, against
    Mitsuba's load_dict + render of the same scene (its PLY files written before the clock)."""
    times: dict[str, list[float]] = {"torchgi": [], "mitsuba": []}
    for r in range(repeats + 1):  # the first pair warms the file cache (and builds the C library)
        for who, code in _CALL.items():
            out = subprocess.run([sys.executable, "-c", code, str(path), str(spp), str(r)], capture_output=True,
                                 text=True, check=True)
            if r:
                times[who].append(float(out.stdout.split()[-1]))
    scene = torchgi.load_scene(path)
    width, height = scene.camera.resolution
    ours, theirs = statistics.median(times["torchgi"]), statistics.median(times["mitsuba"])
    return {"scene": path.stem, "size": f"{width}x{height}", "triangles": int(scene.arrays().triangles.shape[0]),
            "spp": spp, "bounces": 1, "repeats": repeats, "torchgi_s": ours, "mitsuba_s": theirs,
            "ratio": theirs / ours, "torchgi_all_s": " ".join(f"{t:.3f}" for t in times["torchgi"]),
            "mitsuba_all_s": " ".join(f"{t:.3f}" for t in times["mitsuba"])}


def profile(name: str, size: int, bounces: int, spp: int) -> dict:
    """Where one render's time goes, the compiled tracer on one thread (so the shares are of one
    core): scene loading, the tables, the BVH build, the guide rays, and the samples split into
    embree's closest-hit and occlusion queries and the rest (sampling, BSDFs, lights, film)."""
    from torchgi.backends import c_kernels
    from torchgi.render.lights import Tables
    from torchgi.render.tiles import guide_rays_op, path_op

    t0 = time.perf_counter()
    scene = load_scene(name, size)  # a fresh scene: its files read, its arrays built
    arrays = scene.arrays()
    t_load = time.perf_counter() - t0
    t_tables = seconds(lambda: Tables.from_arrays(arrays))
    guides = guide_rays_op(arrays, scene.camera, threads=1)
    if backends.select(guides)[0] != "c":
        raise RuntimeError(f"no compiled tracer: {backends.status()['last']['guide_rays']}")
    lib = c_kernels.library()
    tri = torch.from_numpy(arrays.triangles).contiguous()
    t0 = time.perf_counter()
    handle = lib.torchgi_scene_new(tri.data_ptr(), tri.shape[0])
    t_bvh = time.perf_counter() - t0
    lib.torchgi_scene_free(handle)
    width, height = scene.camera.resolution
    backends.run(guides)  # this scene's BVH, built once
    t_guides = seconds(lambda: backends.run(guides))
    prof = torch.zeros(1, 4, dtype=torch.float64)
    op = path_op(arrays, scene.camera, np.full(width * height, spp), bounces=bounces, seed=0, profile=prof)
    t_trace = seconds(lambda: backends.run(op))
    t_plain = seconds(lambda: backends.run(path_op(arrays, scene.camera, np.full(width * height, spp),
                                                   bounces=bounces, seed=1)))
    samples = width * height * spp
    hit_s, occ_s, hit_n, occ_n = prof[0].tolist()
    return {
        "scene": name, "triangles": int(arrays.triangles.shape[0]), "size": f"{width}x{height}", "bounces": bounces,
        "spp": spp, "load_s": t_load, "tables_s": t_tables, "bvh_s": t_bvh, "guides_s": t_guides,
        "trace_s": t_plain, "trace_profiled_s": t_trace, "msps_one_core": samples / t_plain / 1e6,
        # shares of the run without timers; embree's seconds come from the run with them (their
        # clock reads counted in: an upper bound), the rest is sampling, BSDFs, lights and film
        "embree_closest_share": hit_s / t_plain, "embree_occluded_share": occ_s / t_plain,
        "shading_film_share": 1 - (hit_s + occ_s) / t_plain,
        "closest_rays_per_sample": hit_n / samples, "shadow_rays_per_sample": occ_n / samples,
        "ns_per_ray": 1e9 * (hit_s + occ_s) / max(hit_n + occ_n, 1),
    }


SKIP_CASES = [
    # (skip of docs/design.md Skips, scene, bounces): timed with every skip on, and with all but this one
    ("absent_lights", "cornell", 1),
    ("dead_paths", "sky", 1),
    ("dead_paths", "grass", 1),
    ("last_vertex_rays", "cornell", 1),
    ("last_vertex_rays", "cornell", 0),
]


def skips(size: int, spp: int, repeats: int) -> list[dict]:
    """Each skip in the torch wavefronts, where it is a switch (the compiled tracer has every skip
    built in: a path that misses or dies simply ends there)."""
    rows = []
    for skip, name, bounces in SKIP_CASES:
        scene = torchgi.scenes.BUILTINS[name](size)
        others = set(SKIPS) - {skip}
        on, off = [], []
        with backends.use("torch"):
            torchgi.render(scene.with_resolution(32, 32), spp=1, bounces=bounces)
            for r in range(repeats):
                off.append(seconds(lambda: torchgi.render(scene, spp=spp, bounces=bounces, seed=r,
                                                          skip_unneeded=others)))
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

    labels = [f"{r['scene']}\n{r['size']} b={r['bounces']}" for r in rows]
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(1.5 * len(rows) + 2, 3.8))
    has_torch = all("torch_code_msps" in r for r in rows)
    w = 0.27 if has_torch else 0.4
    ax.bar(x - w, [r["torchgi_msps"] for r in rows], w, label="torchgi (compiled tracer)")
    ax.bar(x, [r["mitsuba_msps"] for r in rows], w, label="Mitsuba 3 scalar_rgb")
    if has_torch:
        ax.bar(x + w, [r["torch_code_msps"] for r in rows], w, label="torchgi torch wavefronts")
    ax.set_xticks(list(x), labels, fontsize=7)
    ax.set_ylabel("M samples / s (median)")
    ax.set_title(f"{rows[0]['spp']} spp, {os.cpu_count()} cores")
    ax.legend(fontsize=8)
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
    names = ["cornell"] if args.quick else SCENES
    found = list(available_scenes(names, args.size))
    rows = [peers(n, s, b, args.spp, args.repeats, mi, True) for n, s in found for b in (1, 3)]
    if not args.quick:  # 1080p
        hd = torchgi.scenes.cornell(512).with_resolution(1920, 1080)
        rows.append(peers("cornell", hd, 1, 16, 3, mi, False))
    call_rows = []
    if any(n == "bunny_box" for n in dict(available_scenes(["bunny_box"], 8))):  # its meshes are under the mesh root
        call_rows.append(whole_call(CONFIG_SCENES / "bunny_box.yaml", 32 if args.quick else 256,
                                    1 if args.quick else 5))
    profile_rows = [profile(n, 128 if args.quick else 256, b, args.spp) for n, _ in found for b in (1, 3)]
    skip_rows = skips(args.size, args.spp, args.repeats) if not args.quick else []
    meta = metadata(torch.get_num_threads())
    meta["cores"] = len(os.sched_getaffinity(0))
    meta["mitsuba"] = mi.__version__
    meta["backends"] = {k: v for k, v in backends.status().items() if k != "last"}
    out = Path(args.out)
    write_results(rows, meta, out, "render")
    write_results(call_rows, meta, out, "render_call")
    write_results(profile_rows, meta, out, "render_profile")
    write_results(skip_rows, meta, out, "render_skips")
    tables = [
        markdown_table(rows, ["scene", "size", "bounces", "spp", "torchgi_msps", "mitsuba_msps", "ratio",
                              "torch_code_msps", "ratio_torch_code"]),
        markdown_table(call_rows, ["scene", "size", "triangles", "spp", "bounces", "torchgi_s", "mitsuba_s",
                                   "ratio"]),
        markdown_table(profile_rows, ["scene", "triangles", "bounces", "load_s", "tables_s", "bvh_s", "guides_s",
                                      "trace_s", "msps_one_core", "embree_closest_share", "embree_occluded_share",
                                      "shading_film_share", "closest_rays_per_sample", "shadow_rays_per_sample",
                                      "ns_per_ray"]),
        markdown_table(skip_rows, ["skip", "what", "scene", "bounces", "with_skip_s", "without_skip_s", "speedup"]),
    ]
    (out / "render.md").write_text("\n\n".join(tables) + "\n")
    plot(rows, out / "render.png")
    print("\n\n".join(tables))
    print(json.dumps(meta["backends"]))
    print(f"\nwrote {out}/render*.csv, render.json, render.md, render.png ({meta['commit']})")


if __name__ == "__main__":
    main()
