"""The training chain of the multi-resolution kernel-predicting Denoiser (``torchgi/filters/kpn.py``)
on procedural scenes, resumable: each call renders or checks the data, packs it once, then trains
from the last checkpoint for ``--minutes`` and validates every ``--val-every`` steps.

    python scripts/train_kpn.py --minutes 140                 # one run of the chain (resumes)
    python scripts/train_kpn.py --data-only                   # render / check the data and pack it
    python scripts/train_kpn.py --minutes 140 --fraction 0.25 --run quarter   # a data-size curve point
    python scripts/train_kpn.py --minutes 140 --widths 32 48 64 --run wide    # a capacity curve point

Data (``configs/data_gen/procedural*.yaml``, rendered by :func:`torchgi.data.run_job` into
``out/data-procedural*``; a job resumes and skips what its manifest says is complete):
training: 1000 procedural scenes rendered by torchgi and 160 of them by Mitsuba 3 (without
textures), 128², 2 bounces, 1-64 spp (powers of two), each against an independent 256 spp render
(Noise2Noise-style: an unbiased target); validation: 48 other procedural scenes (seeds from
100000) against 1024 spp references. The data hash is the SHA-256 of the three ``index.json``
files (each lists every shard's SHA-256).

Training: Adam (its step size from ``--lr`` to ``--lr-end`` by a cosine over the run's minutes),
random 64² crops (flips, 90° turns, an exposure of 2^U(-2, 2)), batch 8; the loss is the mean
squared difference of ``log(colour + 0.1)`` between the remodulated prediction and the 256 spp
target (:func:`loss_fn`; the target's own noise biases its optimum by about half its
relative variance, a fraction of a percent at 256 spp). Validation: mean relMSE per spp on the
48 validation frames against their references, beside the noisy input's and OIDN 2 "high"'s
(computed once). The checkpoint (``checkpoints/kpn/<run>.pt``: weights, Adam state, step, curves,
provenance; under 2 MB) is written every ``--save-every`` steps and at the end; the curve is
``out/kpn/<run>/curve.jsonl`` and ``curve.png``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
from benchmark_utils import cpu_model

import torchgi
from torchgi.data import run_job
from torchgi.filters.kpn import WEIGHTS, KPNet, kpn

JOBS = {  # name: (config, data folder)
    "val": ("configs/data_gen/procedural_val.yaml", "out/data-procedural-val"),
    "train": ("configs/data_gen/procedural.yaml", "out/data-procedural"),
    "mitsuba": ("configs/data_gen/procedural_mitsuba.yaml", "out/data-procedural-mitsuba"),
}
CACHE = ROOT / "out" / "kpn-cache"
CHECKPOINTS = ROOT / "checkpoints" / "kpn"
SPP = (1, 2, 4, 8, 16, 32, 64)
CROP, BATCH = 64, 8


def commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def render_data(workers: int, jobs: list[str]) -> str:
    """Run (or resume) the data jobs ``jobs`` (names of :data:`JOBS`); the data hash (of their index hashes)."""
    for name in jobs:
        config, out = JOBS[name]
        t0 = time.time()
        report = run_job(ROOT / config, ROOT / out, workers=workers, log=print)
        print(f"data {name}: rendered {len(report['rendered'])}, complete {len(report['skipped'])} "
              f"({time.time() - t0:.0f} s); index {index_hash(name)}", flush=True)
    return hashlib.sha256("".join(index_hash(name) for name in jobs).encode()).hexdigest()


def _load(path: Path):
    return torchgi.GBuffer.from_exr(path)


def index_hash(name: str) -> str:
    """The SHA-256 of a job's ``index.json`` (which lists every shard's SHA-256)."""
    return hashlib.sha256((ROOT / JOBS[name][1] / "index.json").read_bytes()).hexdigest()


def pack(name: str) -> dict:
    """The job's frames as tensors (float32), packed once into ``out/kpn-cache/<name>.pt``."""
    data_hash = index_hash(name)
    CACHE.mkdir(parents=True, exist_ok=True)
    cache = CACHE / f"{name}.pt"
    if cache.is_file():
        packed = torch.load(cache)
        if packed["data_hash"] == data_hash:
            return packed
    out = ROOT / JOBS[name][1]
    index = json.loads((out / "index.json").read_text())
    scenes = sorted({s["scene"] for s in index["shards"]}, key=lambda s: int(s.split("_")[-1]))
    guides, target, noisy = [], [], []
    t0 = time.time()
    for scene in scenes:
        ref = _load(out / f"{scene}_v00s0_ref.exr")
        guides.append(torch.cat([ref.albedo, ref.normal, ref.depth], 1)[0])
        target.append(ref.color[0])
        row = []
        for spp in SPP:
            gb = _load(out / f"{scene}_v00s0_{spp:04d}spp.exr")
            var = gb.variance if gb.variance is not None else torch.zeros_like(gb.color)
            row.append(torch.cat([gb.color, gb.emission, var.mean(1, keepdim=True)], 1)[0])
        noisy.append(torch.stack(row))
    packed = {"data_hash": data_hash, "scenes": scenes, "guides": torch.stack(guides), "target": torch.stack(target),
              "noisy": torch.stack(noisy)}
    torch.save(packed, cache)
    print(f"packed {name}: {len(scenes)} scenes in {time.time() - t0:.0f} s", flush=True)
    return packed


def predict(net: KPNet, noisy: torch.Tensor, guides: torch.Tensor, spp: torch.Tensor) -> torch.Tensor:
    """:func:`torchgi.filters.kpn.kpn` of packed rows: noisy ``(B, 7, H, W)`` (colour, emission,
    variance), guides ``(B, 7, H, W)`` (albedo, normal, depth), spp ``(B,)``."""
    return kpn(noisy[:, 0:3], guides[:, 0:3], guides[:, 3:6], guides[:, 6:7], emission=noisy[:, 3:6],
               variance=noisy[:, 6:7], spp=spp, net=net)


def batch(train: list[dict], rng: np.random.Generator):
    """BATCH random crops with augmentation: noisy, guides, target, spp."""
    rows = []
    for _ in range(BATCH):
        part = train[int(rng.choice(len(train), p=[len(t["scenes"]) for t in train] / np.sum(
            [len(t["scenes"]) for t in train])))]
        i, k = int(rng.integers(len(part["scenes"]))), int(rng.integers(len(SPP)))
        H, W = part["target"].shape[-2:]
        y, x = int(rng.integers(H - CROP + 1)), int(rng.integers(W - CROP + 1))
        sl = (slice(None), slice(y, y + CROP), slice(x, x + CROP))
        n, g, t = part["noisy"][i, k][sl], part["guides"][i][sl], part["target"][i][sl]
        scale = float(2.0 ** rng.uniform(-2, 2))
        n = torch.cat([n[:6] * scale, n[6:] * scale * scale])
        t = t * scale
        turns, flip = int(rng.integers(4)), bool(rng.integers(2))
        stack = [torch.rot90(a, turns, (1, 2)) for a in (n, g, t)]
        if flip:
            stack = [a.flip(2) for a in stack]
        rows.append((*stack, SPP[k]))
    return (torch.stack([r[0] for r in rows]), torch.stack([r[1] for r in rows]), torch.stack([r[2] for r in rows]),
            torch.tensor([float(r[3]) for r in rows]))


def loss_fn(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The squared difference of ``log(x + 0.1)``: relative where the light is above 0.1, as the
    judged relMSE is (its ``sqrt(ref² + 0.01)`` denominator), and unbounded for a spread firefly
    (a relMSE normalised by the detached prediction saturates at 1 there)."""
    return (torch.log(pred.clamp_min(0) + 0.1) - torch.log(target.clamp_min(0) + 0.1)).square().mean()


def relmse_per_image(x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    return ((x - ref).square() / (ref.square() + 0.01)).mean((1, 2, 3))


@torch.no_grad()
def validate(net: KPNet, val: dict) -> dict:
    """Mean relMSE per spp over the validation frames."""
    net.eval()
    out = {}
    for k, spp in enumerate(SPP):
        errs = []
        for a in range(0, len(val["scenes"]), 8):
            n, g, t = val["noisy"][a:a + 8, k], val["guides"][a:a + 8], val["target"][a:a + 8]
            errs.append(relmse_per_image(predict(net, n, g, torch.full((n.shape[0],), float(spp))), t))
        out[spp] = float(torch.cat(errs).mean())
    net.train()
    return out


def baselines(val: dict) -> dict:
    """The noisy input's and OIDN 2 "high"'s mean relMSE per spp on the validation frames (once)."""
    path = CACHE / "val_baselines.json"
    if path.is_file():
        data = json.loads(path.read_text())
        if data["data_hash"] == val["data_hash"]:
            return data
    import pyoidn

    hwc = lambda t: t.permute(1, 2, 0).contiguous()
    data = {"data_hash": val["data_hash"], "noisy": {}, "oidn_high": {}}
    for k, spp in enumerate(SPP):
        noisy, oidn = [], []
        for i in range(len(val["scenes"])):
            n, g, t = val["noisy"][i, k], val["guides"][i], val["target"][i]
            noisy.append(float(relmse_per_image(n[None, :3], t[None])))
            y = pyoidn.denoise(hwc(n[:3] - n[3:6]), hwc(g[0:3]), hwc(g[3:6]), hdr=True, quality="high")
            oidn.append(float(relmse_per_image(y.permute(2, 0, 1)[None] + n[None, 3:6], t[None])))
        data["noisy"][str(spp)], data["oidn_high"][str(spp)] = float(np.mean(noisy)), float(np.mean(oidn))
    path.write_text(json.dumps(data, indent=1))
    return data


def plot(curve: list[dict], base: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    steps = [c["step"] for c in curve if "val" in c]
    for spp in SPP:
        ratio = [c["val"][str(spp)] / base["oidn_high"][str(spp)] for c in curve if "val" in c]
        axes[0].plot(steps, ratio, label=f"{spp} spp")
    axes[0].axhline(1.0, color="k", lw=0.5)
    axes[0].set(xlabel="step", ylabel="validation relMSE / OIDN high's", title="validation (48 procedural scenes)",
                yscale="log", ylim=(0.8, 10))
    axes[0].legend(fontsize=7)
    train = [c for c in curve if "loss" in c]
    axes[1].plot([c["step"] for c in train], [c["loss"] for c in train])
    axes[1].set(xlabel="step", ylabel="training loss (noisy targets)", yscale="log", title="training loss")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=140.0, help="training time of this run")
    parser.add_argument("--run", default="main", help="the chain's name (its checkpoint and curve)")
    parser.add_argument("--fraction", type=float, default=1.0, help="the share of training scenes used")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam's step size at the start of this run")
    parser.add_argument("--lr-end", type=float, default=None,
                        help="the step size at the end of this run, reached by a cosine in time (default: --lr)")
    parser.add_argument("--val-every", type=int, default=500)
    parser.add_argument("--save-every", type=int, default=1000)
    parser.add_argument("--widths", type=int, nargs=3, default=None, metavar=("W2", "W4", "W8"),
                        help="a new chain's network widths at 1/2, 1/4, 1/8 resolution (default KPNet's); a "
                             "resumed chain keeps its checkpoint's")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--data-only", action="store_true")
    parser.add_argument("--train-jobs", nargs="+", default=["train", "mitsuba"], choices=["train", "mitsuba"],
                        help="the training data (JOBS) used; the data hash is over these and the validation job")
    return parser.parse_args()


def subset(train: list[dict], fraction: float) -> list[dict]:
    """The first share of each part's scenes (seeds in order), for the data-size curve."""
    if fraction >= 1:
        return train
    keys = ("noisy", "guides", "target", "scenes")
    return [{**t, **{k: t[k][:max(1, int(len(t["scenes"]) * fraction))] for k in keys}} for t in train]


class Chain:
    """One run of the chain: the network, Adam, and the state a checkpoint holds."""

    def __init__(self, args: argparse.Namespace, train: list[dict], data_hash: str) -> None:
        CHECKPOINTS.mkdir(parents=True, exist_ok=True)
        self.path = CHECKPOINTS / f"{args.run}.pt"
        self.dir = ROOT / "out" / "kpn" / args.run
        self.dir.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(0)
        saved = torch.load(self.path) if self.path.is_file() else None
        widths = saved["config"]["widths"] if saved is not None else args.widths
        if saved is not None and args.widths is not None and list(args.widths) != list(widths):
            raise SystemExit(f"--widths: the chain {args.run!r} has widths {widths}; start another --run for others")
        self.net = KPNet() if widths is None else KPNet(widths)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=args.lr)
        self.state = {"step": 0, "curve": [], "runs": []}
        if saved is not None:
            self.net.load_state_dict(saved["net"])
            self.opt.load_state_dict(saved["opt"])
            self.state = {k: saved[k] for k in ("step", "curve", "runs")}
            print(f"resumed {self.path} at step {self.state['step']}", flush=True)
        for group in self.opt.param_groups:
            group["lr"] = args.lr
        scenes = sum(len(t["scenes"]) for t in train)
        self.record = {"command": " ".join(sys.argv), "commit": commit(), "machine": f"{cpu_model()}, "
                       f"{platform.node()}", "threads": torch.get_num_threads(), "start_step": self.state["step"],
                       "lr": args.lr, "lr_end": args.lr_end, "train_scenes": scenes, "fraction": args.fraction, "examples": scenes * len(SPP),
                       "data_hash": data_hash, "started": time.strftime("%Y-%m-%d %H:%M:%S")}
        self.state["runs"].append(self.record)
        self.t0 = time.time()

    def save(self, base: dict) -> None:
        self.record.update(end_step=self.state["step"], seconds=round(time.time() - self.t0))
        torch.save({"net": self.net.state_dict(), "opt": self.opt.state_dict(), **self.state,
                    "config": self.net.config()}, self.path)
        with open(self.dir / "curve.jsonl", "w") as fh:
            fh.writelines(json.dumps(c) + "\n" for c in self.state["curve"])
        plot(self.state["curve"], base, self.dir / "curve.png")

    def export(self) -> None:
        """The weights into the package (``torchgi/filters/kpn_weights.json``) with their config,
        the chain's runs (command, commit, machine, steps, data hash) and the last validation."""
        last = [c for c in self.state["curve"] if "val" in c]
        self.net.save(WEIGHTS, {"script": "scripts/train_kpn.py", "config": self.net.config(),
                                "step": self.state["step"], "runs": self.state["runs"],
                                "validation": last[-1] if last else None})
        print(f"exported {WEIGHTS} ({WEIGHTS.stat().st_size / 1e6:.2f} MB)", flush=True)

    def step(self, train: list[dict], rng: np.random.Generator) -> float:
        n, g, t, spp = batch(train, rng)
        loss = loss_fn(predict(self.net, n, g, spp), t)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.net.parameters(), 1.0)
        self.opt.step()
        self.state["step"] += 1
        return loss.item()

    def validate(self, val: dict, base: dict) -> None:
        v = validate(self.net, val)
        self.state["curve"].append({"step": self.state["step"], "val": {str(k): x for k, x in v.items()},
                                    "seconds": round(time.time() - self.t0)})
        ratio = " ".join(f"{k}:{x / base['oidn_high'][str(k)]:.3f}" for k, x in v.items())
        print(f"step {self.state['step']} ({time.time() - self.t0:.0f} s) val/OIDN {ratio}", flush=True)


def main() -> None:
    args = parse_args()
    torch.set_num_threads(2)
    jobs = ["val", *args.train_jobs]
    data_hash = render_data(args.workers, jobs)
    val, train = pack("val"), [pack(name) for name in args.train_jobs]
    base = baselines(val)
    print("validation baselines: noisy", base["noisy"], "OIDN high", base["oidn_high"], flush=True)
    if args.data_only:
        return
    train = subset(train, args.fraction)
    chain = Chain(args, train, data_hash)
    rng = np.random.default_rng([chain.state["step"], len(chain.state["runs"])])
    losses = []
    lr_end = args.lr if args.lr_end is None else args.lr_end
    while (done := (time.time() - chain.t0) / (args.minutes * 60)) < 1:
        for group in chain.opt.param_groups:
            group["lr"] = lr_end + (args.lr - lr_end) * 0.5 * (1 + math.cos(math.pi * done))
        losses.append(chain.step(train, rng))
        step = chain.state["step"]
        if step % 100 == 0:
            chain.state["curve"].append({"step": step, "loss": float(np.mean(losses))})
            losses = []
        if step % args.val_every == 0:
            chain.validate(val, base)
        if step % args.save_every == 0:
            chain.save(base)
    chain.save(base)
    if args.run == "main":
        chain.export()
    print(f"run done: step {chain.state['step']}, {time.time() - chain.t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
