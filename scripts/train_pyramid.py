"""Train the learned guided pyramid of ``torchgi.filters.pyramid`` (issue 28) on project-rendered data.

    torchgi datagen configs/data_gen/learned.yaml --out out/datagen-learned --workers 2
    python scripts/train_pyramid.py --data out/datagen-learned --out torchgi/filters/pyramid_weights.json

The data are the shards of ``configs/data_gen/learned.yaml``: ten scenes that are never benchmark
scenes. ``--holdout`` scenes (default: two of them) are never trained on: they are the validation
set, evaluated on whole images every ``--every`` steps and at the end beside
``Denoiser("guided")``, ``Denoiser("blend")`` and OIDN high, so that the design is chosen without
the judged scenes (docs/pyramid.md: 351 s for the shipped 4000 steps on 2 cores). Each noisy
shard goes through the Denoiser's own pipeline up to its filter (``train_blend.filter_input``'s
recording filter: demodulation, light sources, firefly clamp),
then :func:`~torchgi.filters.pyramid.pyramid_inputs` once per shard (features and candidate
coefficients, no gradient: they do not depend on the weights); training runs the network and
:func:`~torchgi.filters.pyramid.pyramid_mix` on random crops (offsets on the 1/4 grid, so the crops
of every level line up), Adam with a cosine schedule, the loss the benchmark's relMSE of the
remodulated image. Fixed seeds throughout. Writes the weights with their config, the training
arguments, the commit, the data's SHA-256 and the validation curve; ``--curve`` a PNG of it.
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

import torch
from benchmark_utils import without_back_off
from tqdm.auto import tqdm
from train_blend import FEATURES, data_sha256, filter_input, git_state, oidn_high

from torchgi import metrics
from torchgi.data import ShardDataset
from torchgi.filters.pyramid import FEATURE_SCALE, PyramidNet, pyramid_inputs, pyramid_mix

HOLDOUT = ("mirror_lamps", "lucy_sun_glossy")


def scene_of(name: str) -> str:
    """The scene of a shard name (``<scene>_v<view>s<seed>_<spp>spp``)."""
    return re.match(r"(.*)_v\d+s\d+_", name).group(1)


def prepared(sample: dict, net: PyramidNet) -> dict:
    """One shard through the Denoiser's pipeline up to the filter, then the pyramid's inputs."""
    d = filter_input(sample, "pyramid")
    with torch.no_grad():
        feats, coeffs, rest = pyramid_inputs(d["x"], d["guide"], max(d["spp"], 1.0), net, d["raw"])
    return {"feats": feats, "coeffs": coeffs, "x": d["x"], "rest": rest, "demod": d["demod"], "kept": d["kept"],
            "target": d["target"], "name": d["name"], "spp": d["shard_spp"], "gbuffer": d["gbuffer"]}


def output(net: PyramidNet, d: dict) -> torch.Tensor:
    """The remodulated image of ``d`` (a :func:`prepared` entry or a batch of crops)."""
    out = pyramid_mix(net, net(d["feats"]), d["coeffs"], d["x"], d["rest"])
    return out.clamp_min(0) * d["demod"] + d["kept"]


def crops(data: list[dict], size: int, count: int, g: torch.Generator) -> dict:
    """``count`` random ``size²`` crops (offsets on the 1/4 grid) from random shards, stacked."""
    out: dict[str, list] = {}
    q = FEATURE_SCALE
    for _ in range(count):
        d = data[int(torch.randint(len(data), (1,), generator=g))]
        H, W = d["target"].shape[-2:]
        y, x = (q * int(torch.randint((n - size) // q + 1, (1,), generator=g)) for n in (H, W))
        cut = lambda t, s: t[..., y // s : (y + size) // s, x // s : (x + size) // s]
        parts = {k: cut(d[k], 1) for k in ("x", "demod", "kept", "target")}
        parts["feats"] = cut(d["feats"], q)
        for k, ts in d["coeffs"].items():  # "<group>@<scale>": each candidate's cut at that scale
            for j, t in enumerate(ts):
                parts[f"coeffs.{k}#{j}"] = cut(t, int(k.split("@")[1]))
        parts["rest.mean"] = d["rest"]["mean"]
        if "removed4" in d["rest"]:
            parts["rest.removed4"] = cut(d["rest"]["removed4"], q)
        for k in ("guide", "colour"):  # full resolution (no colour channel without colour candidates)
            if k in d["rest"]:
                parts["rest." + k] = cut(d["rest"][k], 1)
        for k, t in parts.items():
            out.setdefault(k, []).append(t)
    batch = {k: torch.cat(v) for k, v in out.items()}
    batch["rest"] = {k[5:]: batch.pop(k) for k in list(batch) if k.startswith("rest.")}
    coeffs: dict[str, dict[int, torch.Tensor]] = {}
    for k in [k for k in batch if k.startswith("coeffs.")]:
        group, j = k[7:].split("#")
        coeffs.setdefault(group, {})[int(j)] = batch.pop(k)
    batch["coeffs"] = {g: [c[j] for j in sorted(c)] for g, c in coeffs.items()}
    return batch


def validate(net: PyramidNet, data: list[dict]) -> dict[int, float]:
    """Mean relMSE per spp over ``data``'s whole images."""
    sums: dict[int, list[float]] = {}
    with torch.no_grad():
        for d in data:
            sums.setdefault(d["spp"], []).append(float(metrics.relmse(output(net, d), d["target"])))
    return {s: sum(v) / len(v) for s, v in sorted(sums.items())}


def peers(net: PyramidNet, data: list[dict]) -> list[dict]:
    """relMSE per shard: the pyramid, ``Denoiser("guided")``, ``Denoiser("blend")``, OIDN high
    (colour + albedo + normal, HDR), all on the same shard (filters only: no back-off)."""
    rows = []
    with torch.no_grad():
        for d in data:
            gb = d["gbuffer"]
            rows.append({"name": d["name"], "spp": d["spp"],
                         "pyramid": float(metrics.relmse(output(net, d), d["target"])),
                         "guided": float(metrics.relmse(without_back_off(gb, "guided"), d["target"])),
                         "blend": float(metrics.relmse(without_back_off(gb, "blend"), d["target"])),
                         "oidn": float(metrics.relmse(oidn_high(gb), d["target"]))})
    return rows


def plot_curve(curve: list[dict], path: Path) -> None:
    """The training loss and the validation relMSE per spp against the step, log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    steps = [c["step"] for c in curve]
    ax.plot(steps, [c["train"] for c in curve], "k-", label="train loss (mean of the last steps)")
    for spp in curve[0]["val"]:
        ax.plot(steps, [c["val"][spp] for c in curve], "o-", label=f"held out, {spp} spp")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("relMSE")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def report(rows: list[dict], holdout: list[str]) -> None:
    """Print :func:`peers`' mean relMSE per spp, then per held-out scene and spp."""
    names = ("pyramid", "guided", "blend", "oidn")
    mean = lambda sel, k: sum(r[k] for r in sel) / len(sel)
    for spp in sorted({r["spp"] for r in rows}):
        sel = [r for r in rows if r["spp"] == spp]
        print(f"held out, {spp} spp, mean of {len(sel)}: " + " ".join(f"{k} {mean(sel, k):.5f}" for k in names))
    for scene in holdout:
        for spp in sorted({r["spp"] for r in rows}):
            sel = [r for r in rows if r["spp"] == spp and scene_of(r["name"]) == scene]
            if sel:
                print(f"  {scene} {spp} spp: " + " ".join(f"{k} {mean(sel, k):.5f}" for k in names))


def parse() -> argparse.Namespace:
    """The command line."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="out/datagen-learned")
    ap.add_argument("--out", default="torchgi/filters/pyramid_weights.json")
    ap.add_argument("--curve", default=None, help="PNG of the loss curve (default: beside --out in out/)")
    ap.add_argument("--holdout", nargs="*", default=list(HOLDOUT), help="scenes left out of training")
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--clip", type=float, default=1.0, help="gradient norm clip")
    ap.add_argument("--widths", type=int, nargs=3, default=[16, 24, 32])
    ap.add_argument("--direct", action=argparse.BooleanOptionalAction, default=True,
                    help="the low-frequency correction and the gains of the clamped-away light (PyramidNet's direct)")
    ap.add_argument("--colour", type=float, nargs="*", default=None,
                    help="scale radius eps triples of the colour-guided candidates (none: no colour candidates)")
    ap.add_argument("--candidates", type=float, nargs="+", default=None,
                    help="scale radius eps triples (default: PyramidNet's)")
    ap.add_argument("--every", type=int, default=500, help="steps between validations")
    ap.add_argument("--no-peers", action="store_true", help="skip the final comparison with OIDN")
    ap.add_argument("--seed", type=int, default=0)
    return ap.parse_args()


def main() -> None:
    args = parse()
    torch.set_num_threads(2)
    torch.manual_seed(args.seed)
    t0 = time.perf_counter()
    commit, dirty = git_state()  # before training: the code that trained
    triples = lambda v: [v[i : i + 3] for i in range(0, len(v), 3)]
    kw = {} if args.candidates is None else {"candidates": triples(args.candidates)}
    if args.colour is not None:
        kw["colour"] = triples(args.colour)
    net = PyramidNet(widths=args.widths, direct=args.direct, **kw)
    ds = ShardDataset(args.data, features=FEATURES)
    data = [prepared(ds[i], net) for i in tqdm(range(len(ds)), desc="prepare", unit="shard", mininterval=30)]
    train = [d for d in data if scene_of(d["name"]) not in args.holdout]
    val = [d for d in data if scene_of(d["name"]) in args.holdout]
    print(f"{len(train)} training shards, {len(val)} held out ({', '.join(args.holdout)}); "
          f"prepared in {time.perf_counter() - t0:.0f} s; {sum(p.numel() for p in net.parameters())} weights",
          flush=True)
    with torch.no_grad():  # standardise the features over the training shards
        f = torch.cat([d["feats"].flatten(2) for d in train], 2)
        net.shift.copy_(f.mean((0, 2)))
        sd = f.std((0, 2))
        net.scale.copy_(torch.where(sd > 1e-3, 1 / sd, torch.ones_like(sd)))  # constant features unscaled
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.steps)
    g = torch.Generator().manual_seed(args.seed)
    curve, recent = [], []
    t_train = time.perf_counter()
    bar = tqdm(range(args.steps), desc="train", unit="step", mininterval=30)
    for step in bar:
        b = crops(train, args.crop, args.batch, g)
        loss = metrics.relmse(output(net, b), b["target"])
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), args.clip)
        opt.step()
        sched.step()
        recent.append(loss.item())
        if val and ((step + 1) % args.every == 0 or step + 1 == args.steps):
            v = validate(net, val)
            curve.append({"step": step + 1, "train": sum(recent) / len(recent), "val": v})
            recent = []
            bar.write(f"step {step + 1}: train {curve[-1]['train']:.5f}, held out "
                      + " ".join(f"{s} spp {x:.5f}" for s, x in v.items()))
    train_s = time.perf_counter() - t_train
    provenance = {
        "script": "scripts/train_pyramid.py", "args": vars(args), "commit": commit, "dirty": dirty,
        "data_sha256": data_sha256(Path(args.data)),
        "data_config": json.loads((Path(args.data) / "index.json").read_text())["config"],
        "training_shards": [d["name"] for d in train], "held_out_scenes": list(args.holdout),
        "curve": curve, "training_seconds": round(train_s, 1),
    }
    net.save(args.out, provenance)
    print(f"wrote {args.out}; training {train_s:.0f} s, all {time.perf_counter() - t0:.0f} s", flush=True)
    if curve:
        curve_path = Path(args.curve) if args.curve else Path("out") / (Path(args.out).stem + "_curve.png")
        curve_path.parent.mkdir(parents=True, exist_ok=True)
        plot_curve(curve, curve_path)
        print(f"wrote {curve_path}")
    if val and not args.no_peers:
        report(peers(net, val), args.holdout)

if __name__ == "__main__":
    main()
