"""Error against the whole pipeline's time: torchgi's render plus each denoiser, against OIDN.

    python scripts/bench_equal_time.py --out out/bench-equal-time                   # the judged set, 256²
    python scripts/bench_equal_time.py --scenes cornell --spp 1 2 4 --size 64 --ref-spp 256 --out out/bet

For each torchgi scene of ``configs/scenes/sets.yaml``'s ``--set`` (judged by default: never used
for a default or for training) and each spp: one noisy torchgi render (seed 1; its time the median
of ``--repeats`` renders) against a ``--ref-spp`` reference (seed 999), denoised by every torchgi
method that filters and by Intel Open Image Denoise "fast" and "high" (pyoidn; colour + albedo +
normal, HDR, the better of its two protocols, as ``bench_quality.py``), each timed as the median
of ``--repeats`` calls after one warm-up, 2 threads. A point is (render + denoise seconds,
relMSE). Writes ``equal_time.csv/json/md`` and ``equal_time_<scene>.png`` (relMSE against time,
log-log, a curve per method, OIDN high's points marked) and, per OIDN high point (its 1, 4 and
16 spp renders), each torchgi method's lowest relMSE within the same total time: the equal-time
comparison.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_quality import MITSUBA, MITSUBA_CORNELL, case_args, cases, chosen, scores
from benchmark_utils import markdown_table, metadata, oidn, write_results

from torchgi import methods
from torchgi.denoise import Denoiser

OIDN_POINTS = (1, 4, 16)  # the spp of OIDN high's points the equal-time comparison is made at


def median_time(fn, repeats: int, warmup: int = 1) -> tuple[object, float]:
    """``fn()``'s last result and the median of ``repeats`` timed calls (seconds) after ``warmup``."""
    for _ in range(warmup):
        fn()
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def denoisers() -> dict:
    """name -> function of a GBuffer: every torchgi method that filters, OIDN fast and high."""
    out = {f"torchgi {m}": (lambda gb, d=Denoiser(m): d(gb)) for m in methods.names() if methods.get(m).filters}
    try:
        import pyoidn  # noqa: F401
    except ImportError:
        return out
    for quality in ("fast", "high"):
        out[f"OIDN {quality}"] = lambda gb, q=quality: oidn(gb, q, False)
        out[f"OIDN {quality}, emission added back"] = lambda gb, q=quality: oidn(gb, q, True)
    return out


def run(args) -> list[dict]:
    rows, fns = [], {k: f for k, f in denoisers().items() if chosen(k, args)}
    args.scenes = [s for s in args.scenes if not s.startswith(MITSUBA) and s != MITSUBA_CORNELL]  # torchgi renders
    for name, ref, noisy_fn, _scene in cases(args):
        for spp in args.spp:
            gb, render_s = median_time(lambda s=spp: noisy_fn(s), args.repeats)
            timed = {m: median_time(lambda f=f: f(gb), args.repeats) for m, f in fns.items()}
            for method, (out, denoise_s) in timed.items():  # (each timed before any metric runs)
                row = {"scene": name, "size": args.size, "spp": spp, "method": method, "render_s": render_s,
                       "denoise_s": denoise_s, "total_s": render_s + denoise_s, **scores(out, ref)}
                rows.append(row)
                print({k: (round(v, 5) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    return merged_oidn(rows)


def merged_oidn(rows: list[dict]) -> list[dict]:
    """OIDN's two protocols as one row per quality: the one of lower relMSE (named in ``protocol``)."""
    out, best = [], {}
    for r in rows:
        if not r["method"].startswith("OIDN"):
            out.append(r)
            continue
        quality = r["method"].split(",")[0]
        key = (r["scene"], r["spp"], quality)
        if key not in best or r["relmse"] < best[key]["relmse"]:
            best[key] = {**r, "method": quality, "protocol": r["method"]}
    return out + list(best.values())


def equal_time(rows: list[dict]) -> list[dict]:
    """Per scene and OIDN high point: each torchgi method's lowest relMSE at a total time no larger
    than OIDN's there (None where even its 1 spp point takes longer)."""
    table = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        here = [r for r in rows if r["scene"] == scene]
        for p in (r for r in here if r["method"] == "OIDN high" and r["spp"] in OIDN_POINTS):
            for method in dict.fromkeys(r["method"] for r in here if r["method"].startswith("torchgi")):
                within = [r for r in here if r["method"] == method and r["total_s"] <= p["total_s"]]
                b = min(within, key=lambda r: r["relmse"]) if within else None
                table.append({"scene": scene, "oidn_spp": p["spp"], "oidn_total_s": p["total_s"],
                              "oidn_relmse": p["relmse"], "method": method, "spp": b and b["spp"],
                              "total_s": b and b["total_s"], "relmse": b and b["relmse"],
                              "ratio": b and b["relmse"] / p["relmse"]})
    return table


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for scene in dict.fromkeys(r["scene"] for r in rows):
        fig, ax = plt.subplots(figsize=(6.4, 4.4))
        for method in dict.fromkeys(r["method"] for r in rows if r["scene"] == scene):
            pts = [(r["total_s"], r["relmse"], r["spp"]) for r in sorted(rows, key=lambda r: r["spp"])
                   if r["scene"] == scene and r["method"] == method]  # a curve in spp order
            style = "k*--" if method == "OIDN high" else ("k.:" if method.startswith("OIDN") else "-o")
            ax.plot([p[0] for p in pts], [p[1] for p in pts], style, label=method, markersize=4)
            if method == "OIDN high":
                for t, e, spp in pts:
                    ax.annotate(f"{spp} spp", (t, e), fontsize=6, textcoords="offset points", xytext=(3, 3))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("render + denoise (s, 2 threads)")
        ax.set_ylabel("relMSE")
        ax.set_title(f"{scene}: error at equal time")
        ax.legend(fontsize=6)
        fig.tight_layout()
        fig.savefig(out / f"equal_time_{scene}.png", dpi=100)
        plt.close(fig)


def main() -> None:
    args = case_args(__doc__, "out/bench-equal-time", [1, 2, 4, 8, 16, 32, 64], repeats=3)
    torch.set_num_threads(2)
    rows = run(args)
    out = Path(args.out)
    write_results(rows, metadata(torch.get_num_threads()), out, "equal_time")
    md = markdown_table(rows, ["scene", "spp", "method", "render_s", "denoise_s", "total_s", "relmse", "ssim", "flip"])
    eq = equal_time(rows)
    eq_md = markdown_table([{k: (round(v, 5) if isinstance(v, float) else v) for k, v in r.items()} for r in eq],
                           ["scene", "oidn_spp", "oidn_total_s", "oidn_relmse", "method", "spp", "total_s",
                            "relmse", "ratio"])
    (out / "equal_time.md").write_text(md + "\n\n## At OIDN high's points\n\n" + eq_md + "\n")
    plot(rows, out)
    print(eq_md)


if __name__ == "__main__":
    main()
