"""The training example of docs/training.md: a small network predicts the guided filter's ``eps``
per pixel, trained end to end through the filter on shards from ``torchgi datagen``, against the
same filter with one learned ``eps`` (fixed parameters), reported on held-out judged scenes.

    python scripts/train_example.py --out out/example-train        # renders its data first if missing

Data: ``configs/data_gen/example.yaml`` (four training-set scenes, 128², 1-16 spp, 256 spp
references) into ``--data``, ``configs/data_gen/example_heldout.yaml`` (three judged scenes) into
``--heldout``; rendered by :func:`torchgi.data.run_job` when the folder has no index. The filter
runs on the irradiance (colour less emission over the albedo where it is above 0.02; remodulated
and the emission added back after), guided by normal and depth
(:func:`torchgi.filters.guide_from`), radius 6. Both models are trained with Adam on the same
random 64² crops (fixed seeds), the loss the relMSE of the remodulated image against the
reference. Writes ``example.json`` (losses, held-out relMSE per spp, times, commit) and
``example_loss.png`` (both loss curves) under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import torch
from torch import nn

from torchgi import metrics
from torchgi.data import ShardDataset, load_config, run_job
from torchgi.filters import Guided, box, guide_from, guided

ROOT = Path(__file__).resolve().parents[1]
FEATURES = ("color", "albedo", "normal", "depth", "emission")
RADIUS = 6


class EpsNet(nn.Module):
    """Per-pixel ``eps (B, 1, H, W)`` (guide units squared, > 0) from the irradiance's log
    luminance and its local log variance, the log sample count and the guide: three 3x3
    convolutions (3.5k weights), ``eps = softplus(z + 1)`` times ``scale``."""

    def __init__(self, guide_channels: int = 4, width: int = 16, scale: float = 0.01) -> None:
        super().__init__()
        self.scale = scale
        self.net = nn.Sequential(
            nn.Conv2d(3 + guide_channels, width, 3, padding=1), nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=1), nn.ReLU(),
            nn.Conv2d(width, 1, 3, padding=1),
        )

    def forward(self, irr: torch.Tensor, guide: torch.Tensor, spp: torch.Tensor) -> torch.Tensor:
        lum = irr.mean(1, keepdim=True)
        log_lum = torch.log1p(lum)
        local_var = (box(log_lum.square(), 2) - box(log_lum, 2).square()).clamp_min(0)
        feats = torch.cat([log_lum, torch.log(local_var + 1e-6), torch.log(spp).expand_as(lum), guide], 1)
        return nn.functional.softplus(self.net(feats) + 1.0) * self.scale


def prepare(batch: dict) -> tuple[torch.Tensor, ...]:
    """Irradiance (emission left out), modulator (the albedo where above 0.02, else 1), guide,
    emission, spp plane and target of a collated batch."""
    mod = torch.where(batch["albedo"] > 0.02, batch["albedo"], torch.ones_like(batch["albedo"]))
    guide = guide_from(batch["normal"], batch["depth"], depth_scale="image")
    spp = batch["spp"].to(torch.float32).view(-1, 1, 1, 1)
    return (batch["color"] - batch["emission"]) / mod, mod, guide, batch["emission"], spp, batch["target"]


def denoise(model: nn.Module, irr, mod, guide, emission, spp) -> torch.Tensor:
    """The remodulated filter output of ``model`` (an :class:`EpsNet` or a learnable :class:`Guided`)
    with the emission added back."""
    if isinstance(model, EpsNet):
        return guided(irr, guide, radius=RADIUS, eps=model(irr, guide, spp)) * mod + emission
    return model(irr, guide) * mod + emission


def ensure_data(config: str, out: Path) -> None:
    """Render ``config`` into ``out`` unless it holds a finished job."""
    if not (out / "index.json").is_file():
        t0 = time.perf_counter()
        run_job(load_config(ROOT / config), out, workers=2, log=lambda m: None)
        print(f"rendered {config} into {out} in {time.perf_counter() - t0:.1f} s", flush=True)


def train(model: nn.Module, data: ShardDataset, steps: int, lr: float, batch: int, seed: int) -> list[float]:
    """Adam on relMSE over random crops; returns the loss of every step."""
    torch.manual_seed(seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    order = torch.Generator().manual_seed(seed)
    losses = []
    for step in range(steps):
        data.set_epoch(step)
        idx = torch.randint(0, len(data), (batch,), generator=order).tolist()
        b = torch.utils.data.default_collate([data[i] for i in idx])
        irr, mod, guide, emission, spp, target = prepare(b)
        loss = metrics.relmse(denoise(model, irr, mod, guide, emission, spp), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    return losses


@torch.no_grad()
def evaluate(models: dict[str, nn.Module], data: ShardDataset) -> dict[str, dict[int, float]]:
    """Mean relMSE per spp over the held-out images, for each model and for the noisy input."""
    sums: dict[str, dict[int, list[float]]] = {name: {} for name in ["noisy", *models]}
    for i in range(len(data)):
        b = torch.utils.data.default_collate([data[i]])
        irr, mod, guide, emission, spp, target = prepare(b)
        spp_i = int(b["spp"][0])
        sums["noisy"].setdefault(spp_i, []).append(float(metrics.relmse(b["color"], target)))
        for name, model in models.items():
            sums[name].setdefault(spp_i, []).append(float(metrics.relmse(denoise(model, irr, mod, guide, emission, spp), target)))
    return {name: {s: sum(v) / len(v) for s, v in sorted(per.items())} for name, per in sums.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("out/example-data"))
    ap.add_argument("--heldout", type=Path, default=Path("out/example-heldout"))
    ap.add_argument("--out", type=Path, default=Path("out/example-train"))
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    ensure_data("configs/data_gen/example.yaml", args.data)
    ensure_data("configs/data_gen/example_heldout.yaml", args.heldout)
    train_set = ShardDataset(args.data, crop=64, features=FEATURES, seed=args.seed)
    heldout = ShardDataset(args.heldout, features=FEATURES)
    torch.manual_seed(args.seed)
    models = {"fixed eps (one learned value)": Guided(radius=RADIUS, eps=0.01, learnable=True),
              "per-pixel eps (EpsNet)": EpsNet()}
    result: dict = {"command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:]), "threads": torch.get_num_threads(),
                    "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                             cwd=ROOT, check=False).stdout.strip(), "models": {}}
    for name, model in models.items():
        t0 = time.perf_counter()
        losses = train(model, train_set, args.steps, 1e-2 if isinstance(model, Guided) else 3e-3, args.batch,
                       args.seed)
        seconds = time.perf_counter() - t0
        result["models"][name] = {"train_s": seconds, "losses": losses,
                                  "parameters": sum(p.numel() for p in model.parameters())}
        print(f"{name}: {args.steps} steps in {seconds:.1f} s, last 50 steps' loss {sum(losses[-50:]) / 50:.5f}",
              flush=True)
    result["fixed_eps"] = models["fixed eps (one learned value)"].eps.detach().tolist()
    result["heldout_relmse"] = evaluate(models, heldout)
    for name, per in result["heldout_relmse"].items():
        print(f"held-out relMSE {name}: " + ", ".join(f"{s} spp {v:.5f}" for s, v in per.items()))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "example.json").write_text(json.dumps(result, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, m in result["models"].items():
        k = 20
        smooth = [sum(m["losses"][max(0, i - k) : i + 1]) / len(m["losses"][max(0, i - k) : i + 1])
                  for i in range(len(m["losses"]))]
        ax.plot(smooth, label=name)
    ax.set_xlabel("step (8 crops of 64²)")
    ax.set_ylabel("training relMSE (mean of 20 steps)")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "example_loss.png", dpi=120)


if __name__ == "__main__":
    main()
