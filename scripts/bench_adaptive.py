"""Adaptive sampling with the product's Denoiser: relMSE against wall time (issue 56).

    python scripts/bench_adaptive.py --out out/bench-adaptive                    # judged set + cornell, 256²
    python scripts/bench_adaptive.py --set tuning --size 128 --ref-spp 256 --out out/ba-tuning
    python scripts/bench_adaptive.py --calibrate --set tuning --no-cornell --spp 4 8 16 32 --out out/ba-calibration

For each torchgi scene of ``--set`` (judged by default; ``--cornell`` adds the Cornell box, a
tuning scene), ``--bounces`` bounces, against a ``--ref-spp`` reference (seed 999; kept under
``--out``/refs and reused when present), every pipeline ends in ``Denoiser()`` (2 threads):

- ``uniform``: ``render(spp)`` for each ``--spp``; time: the median of ``--repeats`` renders
  plus denoises;
- ``adaptive_render``: the paper's single round at rates ``--rates`` (honest counts: each pixel's
  whole light gets its samples);
- ``render_to seconds``: ``render_to(seconds=T)`` at T = the uniform pipeline's time at 4 and
  16 spp (the median time and relMSE of ``--repeats`` runs after a warm-up), and the same with
  ``adaptive=False`` (uniform rounds);
- ``render_to target``: ``render_to(target=E)`` at E = the uniform pipeline's relMSE at 4 and 16 spp
  (``max_spp=--max-spp``: a run whose estimate never reaches E stops there);
- ``OIDN high``: pyoidn on the uniform renders (the better of its two protocols), its render
  and its own time.

``--calibrate`` measures ``render_to``'s ``HALF_TO_WHOLE`` instead (on the tuning set: a half's
denoised relMSE over the whole's, and the estimate against the truth), ``render_to_calibration.*``.

Writes ``adaptive_bench.csv/json/md`` and ``adaptive_<scene>.png`` (relMSE against time, log-log)
and prints the issue's checks: relMSE falling with the rate, render_to at T at most 0.85x
uniform's, render_to(target) within 1.25 E in less time than uniform's.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_equal_time import merged_oidn
from benchmark_utils import available_scenes, markdown_table, metadata, oidn, scene_sets, write_results

import torchgi
from torchgi import metrics, render_to
from torchgi.denoise import Denoiser
from torchgi.sampling import adaptive_render

POINTS = (4, 16)  # the uniform spp whose time and relMSE render_to is given


def timed(fn, repeats: int, warmup: int = 1) -> tuple[list, float]:
    """``fn()``'s results of ``repeats`` timed calls after ``warmup`` and their median time (s)."""
    for _ in range(warmup):
        fn()
    outs, times = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        outs.append(fn())
        times.append(time.perf_counter() - t0)
    return outs, statistics.median(times)


def reference(scene, name: str, args) -> torch.Tensor:
    """The ``--ref-spp`` reference colour, read from ``--out``/refs when a run left it there."""
    path = Path(args.out) / "refs" / f"{name}_{args.size}_{args.ref_spp}spp_b{args.bounces}.pt"
    if path.is_file():
        return torch.load(path)
    ref = torchgi.render(scene, spp=args.ref_spp, bounces=args.bounces, seed=999).color
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(ref, path)
    return ref


def scene_rows(name: str, scene, ref: torch.Tensor, args) -> list[dict]:
    d = Denoiser()
    b = args.bounces
    rows = []

    def row(method: str, x: float, relmse: float, seconds: float, spp: float) -> None:
        r = {"scene": name, "method": method, "x": x, "spp": round(spp, 3), "seconds": seconds, "relmse": relmse}
        rows.append(r)
        print({k: (round(v, 5) if isinstance(v, float) else v) for k, v in r.items()}, flush=True)

    for spp in args.spp:
        outs, t = timed(lambda s=spp: (gb := torchgi.render(scene, spp=s, bounces=b, seed=1), d(gb)), args.repeats)
        gb, out = outs[-1]
        row("uniform", spp, float(metrics.relmse(out, ref)), t, spp)
        if args.oidn:
            t_render = timed(lambda s=spp: torchgi.render(scene, spp=s, bounces=b, seed=1), 1, 0)[1]
            for split in (False, True):
                outs, t = timed(lambda s=split: oidn(gb, "high", s), args.repeats)
                row(f"OIDN high{', emission added back' if split else ''}", spp,
                    float(metrics.relmse(outs[-1], ref)), t_render + t, spp)
    for rate in args.rates:
        outs, t = timed(lambda r=rate: (gb := adaptive_render(scene, rate=float(r), bounces=b, seed=1)[0], d(gb)),
                        1, 0)
        gb, out = outs[-1]
        row("adaptive_render", rate, float(metrics.relmse(out, ref)), t, float(gb.spp.float().mean()))
    uniform = {r["x"]: r for r in rows if r["method"] == "uniform"}
    for spp in (p for p in POINTS if p in uniform):
        for mode, value, placed in (("seconds", uniform[spp]["seconds"], True), ("target", uniform[spp]["relmse"], True),
                                    ("seconds", uniform[spp]["seconds"], False)):
            kw = {mode: value, "adaptive": placed}
            runs = []
            for _ in range(1 if mode == "target" else args.repeats):
                outs, t = timed(lambda kw=kw: (gb := render_to(scene, bounces=b, seed=1, denoiser=d,
                                                                  max_spp=args.max_spp, **kw), d(gb)),
                                1, 1 if not runs else 0)
                gb, out = outs[-1]
                runs.append((t, float(metrics.relmse(out, ref)), float(gb.spp.float().mean())))
            t, e, s = (statistics.median(v) for v in zip(*runs))
            row(f"render_to {mode}" + ("" if placed else ", uniform rounds"), spp, e, t, s)
    return rows


def calibration_rows(name: str, scene, ref: torch.Tensor, args) -> list[dict]:
    """``render_to``'s constant :data:`~torchgi.progressive.HALF_TO_WHOLE`: uniform
    renders of two halves of ``spp`` (seeds 11, 12) and their merge, the denoised relMSE of a half
    and of the whole, and the estimate ``render_to`` makes from the halves (over the constant)
    against the whole's true relMSE."""
    from torchgi.progressive import _estimate
    from torchgi.sampling import merge_rounds

    d, rows = Denoiser(), []
    for spp in args.spp:
        if spp < 2:
            continue
        H, W = ref.shape[-2:]
        c = torch.full((1, 1, H, W), spp // 2)
        a, b = (torchgi.render(scene, c, bounces=args.bounces, seed=s) for s in (11, 12))
        whole = (merge_rounds(a, c, b, c), 2 * c)
        out = d(whole[0])
        true, half = float(metrics.relmse(out, ref)), float(metrics.relmse(d(a), ref))
        est = _estimate([(a, c), (b, c)], whole, out, d)
        rows.append({"scene": name, "spp": spp, "whole": true, "half": half, "half_over_whole": half / true,
                     "estimate": est, "estimate_over_whole": est / true})
        print({k: (round(v, 5) if isinstance(v, float) else v) for k, v in rows[-1].items()}, flush=True)
    return rows


def checks(rows: list[dict]) -> list[str]:
    """The issue's lines, per scene."""
    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        here = {(r["method"], r["x"]): r for r in rows if r["scene"] == scene}
        rates = [here[k]["relmse"] for k in sorted(k for k in here if k[0] == "adaptive_render")]
        falls = all(a > b for a, b in itertools.pairwise(rates))
        out.append(f"{scene}: adaptive_render relMSE {' > '.join(f'{e:.5f}' for e in rates)}: "
                   f"{'falls' if falls else 'does NOT fall'}")
        for spp in POINTS:
            u, s, t, su = (here.get((m, spp)) for m in ("uniform", "render_to seconds", "render_to target",
                                                         "render_to seconds, uniform rounds"))
            if u is None:
                continue
            if s is not None:
                ratio = s["relmse"] / u["relmse"]
                out.append(f"  T of {spp} spp ({u['seconds']:.3f} s): render_to {s['relmse']:.5f} in "
                           f"{s['seconds']:.3f} s, {ratio:.2f}x uniform's {u['relmse']:.5f} "
                           f"({'meets' if ratio <= 0.85 and s['seconds'] <= u['seconds'] * 1.05 else 'misses'} 0.85x)")
            if su is not None:
                out.append(f"  T of {spp} spp, uniform rounds: {su['relmse']:.5f} in {su['seconds']:.3f} s, "
                           f"{su['relmse'] / u['relmse']:.2f}x uniform's")
            if t is not None:
                ok = t["relmse"] <= 1.25 * u["relmse"] and t["seconds"] < u["seconds"]
                out.append(f"  E of {spp} spp ({u['relmse']:.5f}): render_to(target) {t['relmse']:.5f} "
                           f"({t['relmse'] / u['relmse']:.2f} E) in {t['seconds']:.3f} s against uniform's "
                           f"{u['seconds']:.3f} s ({'meets' if ok else 'misses'})")
    return out


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    styles = {"uniform": "o-", "adaptive_render": "s--", "render_to seconds": "D", "render_to target": "^",
              "render_to seconds, uniform rounds": "x", "OIDN high": "k*:"}
    for scene in dict.fromkeys(r["scene"] for r in rows):
        fig, ax = plt.subplots(figsize=(6.4, 4.4))
        for method, style in styles.items():
            pts = sorted((r["seconds"], r["relmse"], r["x"]) for r in rows
                         if r["scene"] == scene and r["method"] == method)
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], style, label=method, markersize=5)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("render + denoise (s, 2 threads)")
        ax.set_ylabel("relMSE against the reference")
        ax.set_title(f"{scene}: adaptive sampling at equal time")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / f"adaptive_{scene}.png", dpi=100)
        plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench-adaptive")
    ap.add_argument("--set", default="judged", choices=("judged", "tuning", "training"))
    ap.add_argument("--scenes", nargs="+", help="these scenes instead of --set's torchgi scenes")
    ap.add_argument("--cornell", action=argparse.BooleanOptionalAction, default=True,
                    help="add the Cornell box (a tuning scene)")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--bounces", type=int, default=2)
    ap.add_argument("--spp", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32, 64])
    ap.add_argument("--rates", type=int, nargs="+", default=[1, 4, 16, 64])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--max-spp", type=float, default=128.0, help="render_to's max_spp (bounds a run that misses)")
    ap.add_argument("--oidn", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--calibrate", action="store_true",
                    help="only the estimate's calibration (run it with --set tuning --no-cornell --spp 4 8 16 32)")
    args = ap.parse_args()
    torch.set_num_threads(2)
    names = args.scenes or [s for s in scene_sets()[args.set] if ":" not in s and not s.startswith("mitsuba")]
    names += ["cornell"] if args.cornell and "cornell" not in names else []
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for entry, scene in available_scenes(names, args.size):
        name = Path(entry).name
        rows += (calibration_rows if args.calibrate else scene_rows)(name, scene, reference(scene, name, args), args)
    if args.calibrate:
        write_results(rows, metadata(torch.get_num_threads()), out, "render_to_calibration")
        cols = ["scene", "spp", "whole", "half", "half_over_whole", "estimate", "estimate_over_whole"]
        (out / "render_to_calibration.md").write_text(markdown_table(rows, cols) + "\n")
        print(f"median half / whole: {statistics.median(r['half_over_whole'] for r in rows):.3f}")
        return
    rows = merged_oidn(rows)
    write_results(rows, metadata(torch.get_num_threads()), out, "adaptive_bench")
    lines = checks(rows)
    (out / "adaptive_bench.md").write_text(
        markdown_table(rows, ["scene", "method", "x", "spp", "seconds", "relmse"]) + "\n\n" + "\n".join(lines) + "\n")
    plot(rows, out)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
