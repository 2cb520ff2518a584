"""Data-generation throughput: shards per minute and samples per second, per worker count and per
tracer (the compiled one, and the torch wavefronts as before it), side by side in one run.

    python scripts/bench_datagen.py --out out/bench            # 3 scenes at 128x128: a few minutes
    python scripts/bench_datagen.py --config configs/data_gen/default.yaml --views 1 --seeds 0 --out out/bench

Each run is a fresh process (``TORCHGI_NATIVE=0`` for the torch code, which switches the
compiled back ends off there and in its worker processes) writing into an empty folder: renders,
EXR writes, manifests, index. ``--views`` / ``--seeds`` cut the config's plan to fewer tasks
(same scenes, resolution, ladder, reference and bounces). Samples count every path traced
(ladder + reference, all pixels). Runs alternate tracers; ``--repeats`` of each, medians.
Writes ``datagen.csv/json/md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import markdown_table, metadata, write_results

from torchgi.data import config_from_dict, load_config, plan, run_job, task_scene

DEFAULT = {"scenes": ["cornell", "sky", "grass"], "resolution": [128, 128], "views": 2, "spp": [1, 2, 4, 8],
           "reference_spp": 256, "bounces": 2, "seeds": [0]}


def _config(args):
    config = load_config(args.config) if args.config else config_from_dict(DEFAULT)
    if args.views is not None:
        config = dataclasses.replace(config, views=args.views)
    if args.seeds is not None:
        config = dataclasses.replace(config, seeds=tuple(args.seeds))
    return config


def _one(args) -> None:
    """The child: one run_job into an empty folder; prints its seconds as JSON."""
    folder = Path(tempfile.mkdtemp(prefix="torchgi-datagen-"))
    try:
        t0 = time.perf_counter()
        run_job(_config(args), folder, workers=args.workers[0], progress=False, log=lambda m: None)
        print(json.dumps({"seconds": time.perf_counter() - t0}))
    finally:
        shutil.rmtree(folder)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=None, help="a data-generation YAML (default: 3 scenes at 128x128)")
    ap.add_argument("--views", type=int, default=None, help="views per scene instead of the config's")
    ap.add_argument("--seeds", type=int, nargs="+", default=None, help="seeds instead of the config's")
    ap.add_argument("--out", default="out/bench")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--tracers", nargs="+", default=["c", "torch"], choices=["c", "torch"])
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _one(args)
        return
    config = _config(args)
    tasks = plan(config)
    shards = len(tasks) * (len(config.spp) + 1)
    samples = 0
    for task in tasks:
        w, h = task_scene(config, task).camera.resolution
        samples += w * h * (sum(config.spp) + config.reference_spp)
    child = [sys.executable, __file__, "--child"] + (["--config", args.config] if args.config else []) + \
        (["--views", str(args.views)] if args.views is not None else []) + \
        (["--seeds", *map(str, args.seeds)] if args.seeds is not None else [])
    times: dict[tuple[str, int], list[float]] = {}
    for _ in range(args.repeats):
        for workers in args.workers:
            for tracer in args.tracers:
                env = dict(os.environ, TORCHGI_NATIVE="0" if tracer == "torch" else "1")
                out = subprocess.run([*child, "--workers", str(workers)], env=env, capture_output=True, text=True,
                                     check=True)
                times.setdefault((tracer, workers), []).append(json.loads(out.stdout.splitlines()[-1])["seconds"])
                print(tracer, workers, times[tracer, workers][-1], flush=True)
    rows = []
    for (tracer, workers), ts in times.items():
        seconds = statistics.median(ts)
        base = times.get(("torch", workers))
        rows.append({"config": args.config or "3 scenes 128x128", "views": config.views, "seeds": len(config.seeds),
                     "tracer": "compiled" if tracer == "c" else "torch code", "workers": workers, "tasks": len(tasks),
                     "shards": shards, "samples": samples, "seconds": seconds, "shards_per_min": shards / seconds * 60,
                     "samples_per_s": samples / seconds,
                     "speedup_vs_torch_code": statistics.median(base) / seconds if base else None})
    meta = metadata(torch.get_num_threads())
    out = Path(args.out)
    write_results(rows, meta, out, "datagen")
    md = markdown_table(rows, ["tracer", "workers", "tasks", "shards", "seconds", "shards_per_min", "samples_per_s",
                               "speedup_vs_torch_code"])
    (out / "datagen.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
