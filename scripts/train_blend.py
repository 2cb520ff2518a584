"""Train the learned blend of ``torchgi.filters.blend`` (issue 17) on project-rendered data.

    torchgi datagen configs/data_gen/blend.yaml --out out/datagen-blend --workers 2
    python scripts/train_blend.py --data out/datagen-blend --out torchgi/filters/blend_weights.json
    python scripts/train_blend.py --data out/datagen-blend --holdout dragon --out out/blend-val.json  # design runs

The data are the shards of ``configs/data_gen/blend.yaml``: four scenes that are never benchmark
scenes. Each noisy shard goes through the Denoiser's own pipeline up to its filter (demodulation,
light sources, firefly clamp: :func:`torchgi.light.restore` with a recording filter), so the
network sees exactly what ``Denoiser("blend")`` hands it; the candidates and features are computed
once per shard, then the per-pixel MLP is trained on random crops with Adam, the loss the
benchmark's relMSE of the remodulated image against the reference. Fixed seeds throughout; with
``--holdout SCENE`` that scene's shards are left out of training and reported as validation
(how the design was chosen without the benchmark scenes). Writes the weights with their config,
the training config, the git commit (and whether the tree had uncommitted changes) and the SHA-256
of the data's content (:func:`data_sha256`).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import time
from pathlib import Path

import torch

from torchgi import light, methods, metrics
from torchgi.buffers import GBuffer
from torchgi.data import ShardDataset
from torchgi.denoise import Denoiser
from torchgi.filters import box, guide_from
from torchgi.filters.blend import BlendNet, blend_candidates, blend_features
from torchgi.methods.base import noise_spp
from torchgi.settings import DEFAULTS

FEATURES = ("color", "albedo", "normal", "depth", "emission", "variance")


def filter_input(sample: dict, method: str) -> dict:
    """One shard through the Denoiser's pipeline up to its filter (a recording filter: light
    sources kept, demodulation, firefly clamp): the filter's input ``x`` (and ``raw``, the
    same before the firefly clamp), its guide (as
    ``Denoiser(method)`` builds it), the sample count it sees, the demodulator and the light
    added back, the target, the GBuffer, the shard's name and spp; tensors ``(1, ., H, W)``."""
    t = {k: sample[k][None] for k in FEATURES}
    H, W = t["color"].shape[-2:]
    gb = GBuffer(**t, spp=torch.full((1, 1, H, W), int(sample["spp"]), dtype=torch.int32))
    surface = light.surface_mask(gb.hit, gb.albedo)
    seen = {}

    def record(x, raw):
        seen["x"], seen["raw"] = x, raw
        return torch.zeros_like(x)

    kept = light.restore(gb.color, gb.emission, None, gb.albedo, surface, record, methods.get(method).firefly(), box,
                         unclamped=True)
    return {"x": seen["x"], "raw": seen["raw"], "guide": guide_from(gb.normal, gb.depth, depth_scale="image"),
            "spp": noise_spp(gb, surface, DEFAULTS), "demod": light.demodulator(gb.albedo, surface),
            "kept": kept, "target": sample["target"][None], "gbuffer": gb, "name": sample["name"],
            "shard_spp": int(sample["spp"])}


def prepared(sample: dict, net: BlendNet) -> dict:
    """One shard through the Denoiser's pipeline: candidates, features, the demodulator and the
    light added back, and the target, all ``(1, ., H, W)``."""
    d = filter_input(sample, "blend")
    cands = blend_candidates(d["x"], d["guide"], radii=net.radii, eps=net.eps, colour_radii=net.colour_radii,
                             colour_scale=net.colour_scale, fine_radii=net.fine_radii,
                             fine_eps=net.fine_eps)
    return {"cands": torch.stack(cands, 1), "feats": blend_features(cands, d["guide"], d["spp"], net.reference),
            "demod": d["demod"], "kept": d["kept"], "target": d["target"], "name": d["name"],
            "spp": d["shard_spp"], "gbuffer": d["gbuffer"]}


def output(net: BlendNet, d: dict) -> torch.Tensor:
    """The remodulated image of ``d`` (crops of :func:`prepared` entries) under ``net``."""
    w = torch.softmax(net(d["feats"]), 1)
    light = (w[:, :, None] * d["cands"]).sum(1).clamp_min(0)
    return light * d["demod"] + d["kept"]


def crops(data: list[dict], size: int, count: int, g: torch.Generator) -> dict:
    """``count`` random ``size²`` crops from random shards, stacked."""
    keys = ("cands", "feats", "demod", "kept", "target")
    out = {k: [] for k in keys}
    for _ in range(count):
        d = data[int(torch.randint(len(data), (1,), generator=g))]
        H, W = d["target"].shape[-2:]
        y, x = (int(torch.randint(n - size + 1, (1,), generator=g)) for n in (H, W))
        for k in keys:
            out[k].append(d[k][..., y : y + size, x : x + size])
    return {k: torch.cat(v) for k, v in out.items()}


def evaluate(net: BlendNet, data: list[dict], peers: bool) -> list[dict]:
    """relMSE per shard of the blend, the best single candidate (chosen with the reference) and,
    with ``peers``, ``Denoiser("guided")`` and OIDN "high" (colour + albedo + normal, HDR)."""
    rows = []
    with torch.no_grad():
        for d in data:
            row = {"name": d["name"], "spp": d["spp"], "blend": float(metrics.relmse(output(net, d), d["target"])),
                   "best single": min(float(metrics.relmse(d["cands"][:, k].clamp_min(0) * d["demod"] + d["kept"],
                                                           d["target"])) for k in range(d["cands"].shape[1]))}
            if peers:
                gb = d["gbuffer"]
                row["guided"] = float(metrics.relmse(Denoiser("guided")(gb), d["target"]))
                row["oidn"] = float(metrics.relmse(oidn_high(gb), d["target"]))
            rows.append(row)
    return rows


def oidn_high(gb: GBuffer) -> torch.Tensor:
    import pyoidn

    hwc = lambda t: t[0].permute(1, 2, 0).contiguous()
    return pyoidn.denoise(hwc(gb.color), hwc(gb.albedo), hwc(gb.normal), hdr=True, quality="high").permute(2, 0, 1)[None]


def report(rows: list[dict], part: str) -> None:
    """Per shard, then the mean per spp."""
    for r in rows:
        print(part, r["name"], r["spp"], " ".join(f"{k} {v:.5f}" for k, v in r.items() if isinstance(v, float)))
    for spp in sorted({r["spp"] for r in rows}):
        sel = [r for r in rows if r["spp"] == spp]
        keys = [k for k, v in sel[0].items() if isinstance(v, float)]
        print(f"{part} mean at {spp} spp over {len(sel)} shards:",
              " ".join(f"{k} {sum(r[k] for r in sel) / len(sel):.5f}" for k in keys))


def data_sha256(folder: Path) -> str:
    """SHA-256 of the training data's content: the index's config, then each shard and reference
    file the index names (sorted by name) with the SHA-256 of its bytes. Recomputed by
    ``tests/filters/test_blend.py`` from the files themselves when they are present."""
    index = json.loads((folder / "index.json").read_text())
    h = hashlib.sha256(json.dumps(index["config"], sort_keys=True).encode())
    names = sorted({s["file"] for s in index["shards"]} | {s["reference_file"] for s in index["shards"]})
    for name in names:
        h.update(f"{name}:{hashlib.sha256((folder / name).read_bytes()).hexdigest()}\n".encode())
    return h.hexdigest()


def git_state() -> tuple[str, bool]:
    """The commit the script runs from and whether tracked files differ from it (dirty)."""
    run = lambda *a: subprocess.run(["git", *a], capture_output=True, text=True, check=False).stdout.strip()
    return run("rev-parse", "HEAD"), bool(run("status", "--porcelain", "--untracked-files=no"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="out/datagen-blend")
    ap.add_argument("--out", default="torchgi/filters/blend_weights.json")
    ap.add_argument("--holdout", default=None, help="a scene name left out of training and reported")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--crop", type=int, default=48)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--hidden", type=int, default=32)
    ap.add_argument("--context", type=int, nargs="*", default=[2, 8])
    ap.add_argument("--radii", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--colour-radii", type=int, nargs="*", default=[4, 8])
    ap.add_argument("--eps", type=float, default=1e-5)
    ap.add_argument("--fine-radii", type=int, nargs="*", default=[2, 4])
    ap.add_argument("--fine-eps", type=float, default=1e-6)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(2)
    torch.manual_seed(args.seed)
    t0 = time.perf_counter()
    commit, dirty = git_state()  # before training: the code that trained
    net = BlendNet(hidden=args.hidden, context=args.context, radii=args.radii, colour_radii=args.colour_radii,
                   fine_radii=args.fine_radii, fine_eps=args.fine_eps, eps=args.eps)
    ds = ShardDataset(args.data, features=FEATURES)
    data = [prepared(ds[i], net) for i in range(len(ds))]
    held = [re.match(r"(.*)_v\d+s\d+_", d["name"]).group(1) == args.holdout for d in data]
    train = [d for d, h in zip(data, held) if not h]
    val = [d for d, h in zip(data, held) if h]
    print(f"{len(train)} training shards, {len(val)} held out; prepared in {time.perf_counter() - t0:.0f} s", flush=True)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.steps)
    g = torch.Generator().manual_seed(args.seed)
    for step in range(args.steps):
        b = crops(train, args.crop, args.batch, g)
        loss = metrics.relmse(output(net, b), b["target"])
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 250 == 0 or step == args.steps - 1:
            print(f"step {step} loss {float(loss):.5f} ({time.perf_counter() - t0:.0f} s)", flush=True)
    report(evaluate(net, train, False), "train")
    if val:
        report(evaluate(net, val, True), "held out")
    index = Path(args.data) / "index.json"
    provenance = {
        "script": "scripts/train_blend.py", "args": vars(args), "commit": commit, "dirty": dirty,
        "data_sha256": data_sha256(Path(args.data)),
        "data_config": json.loads(index.read_text())["config"], "training_shards": [d["name"] for d in train],
        "held_out_scene": args.holdout,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    net.save(args.out, provenance)
    print(f"wrote {args.out} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
