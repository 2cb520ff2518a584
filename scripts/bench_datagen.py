"""Data-generation throughput: shards per minute and samples per second, 1 and 2 local workers.

    python scripts/bench_datagen.py --out out/bench            # about a minute on 2 cores
    python scripts/bench_datagen.py --config configs/data_gen/default.yaml --out out/bench

Each run starts from an empty folder (fresh renders, EXR writes, manifests, index). Samples
count every path traced (ladder + reference, all pixels). Writes ``datagen.csv/json/md``.
"""

from __future__ import annotations

import argparse
import shutil
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=None, help="a data-generation YAML (default: 3 scenes at 128x128)")
    ap.add_argument("--out", default="out/bench")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()
    config = load_config(args.config) if args.config else config_from_dict(DEFAULT)
    tasks = plan(config)
    shards = len(tasks) * (len(config.spp) + 1)
    samples = 0
    for task in tasks:
        w, h = task_scene(config, task).camera.resolution
        samples += w * h * (sum(config.spp) + config.reference_spp)
    rows = []
    for workers in args.workers:
        folder = Path(tempfile.mkdtemp(prefix="torchgi-datagen-"))
        try:
            t0 = time.perf_counter()
            run_job(config, folder, workers=workers, progress=False, log=lambda m: None)
            seconds = time.perf_counter() - t0
        finally:
            shutil.rmtree(folder)
        rows.append({"config": args.config or "3 scenes 128x128", "workers": workers, "tasks": len(tasks),
                     "shards": shards, "seconds": seconds, "shards_per_min": shards / seconds * 60,
                     "samples_per_s": samples / seconds})
        print(rows[-1], flush=True)
    meta = metadata(torch.get_num_threads())
    out = Path(args.out)
    write_results(rows, meta, out, "datagen")
    md = markdown_table(rows, ["workers", "tasks", "shards", "seconds", "shards_per_min", "samples_per_s"])
    (out / "datagen.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
