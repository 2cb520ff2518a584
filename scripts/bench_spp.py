"""Error against the sample count (issue 33): does each method's error fall as samples rise?

    python scripts/bench_spp.py --out out/bench-spp                     # the judged set, 1-64 spp, 256²
    python scripts/bench_spp.py --set tuning --out out/bench-spp-tuning   # the scenes the back-off was tuned on
    python scripts/bench_spp.py --scenes cornell --spp 1 2 4 --size 64 --ref-spp 256 --out out/bench-spp

For each scene of ``configs/scenes/sets.yaml``'s ``--set`` (judged by default: never used for a
default) and each spp: one noisy render (seed 1) against a ``--ref-spp`` reference (seed 999),
denoised by the default ``Denoiser()``, the same without its back-off toward the input
(``settings.pipeline.back_off=False``: the filter at its one radius, as it was before issue 33), ``Denoiser("atrous")``, ``Denoiser("blend")``, ``Denoiser("kpn")`` and Intel Open Image Denoise high
(pyoidn, both protocols of ``bench_quality.py``; the better counts) → relMSE, PSNR, SSIM, FLIP.
Writes ``spp.csv/json/md`` and ``spp_<scene>.png`` (relMSE against spp, log-log, per method beside
the noisy input), and checks issue 33's lines for the default Denoiser: below the noisy input's
relMSE at every spp, never above 1.05x its value at half the samples, and, on scenes with a glossy
material, within 2x OIDN high's at 8 spp.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_quality import MITSUBA, case_args, cases, chosen, rendered, scores
from benchmark_utils import available_scenes, markdown_table, metadata, oidn, without_back_off, write_results

from torchgi.denoise import Denoiser

DEFAULT = "torchgi default"
OIDN = ("OIDN high", "OIDN high, emission added back")


def methods() -> dict:
    out = {
        "noisy": lambda gb: gb.color,
        DEFAULT: lambda gb: Denoiser()(gb),
        "torchgi default, no back-off": without_back_off,
        "torchgi atrous": lambda gb: Denoiser("atrous")(gb),
        "torchgi blend": lambda gb: Denoiser("blend")(gb),
        "torchgi kpn": lambda gb: Denoiser("kpn")(gb),
    }
    try:
        import pyoidn  # noqa: F401

        out[OIDN[0]] = lambda gb: oidn(gb, "high", False)
        out[OIDN[1]] = lambda gb: oidn(gb, "high", True)
        out["OIDN fast"] = lambda gb: oidn(gb, "fast", False)
    except ImportError:
        pass
    return out


def glossy_scenes(entries: list[str], size: int) -> set[str]:
    """The case names (as :func:`bench_quality.cases` gives them) of entries with a glossy material."""
    out = set()
    for entry in entries:
        for name, scene in available_scenes([entry.removeprefix(MITSUBA)], size):
            if any(m.material.type == "glossy" for m in scene.meshes):
                out.add(f"{Path(name).name} (Mitsuba)" if entry.startswith(MITSUBA) else Path(name).name)
    return out


def run(args) -> list[dict]:
    rows, fns = [], {k: f for k, f in methods().items() if k == "noisy" or chosen(k, args)}
    for name, ref, noisy_fn, _scene in cases(args):
        for spp in args.spp:
            gb, render_s = rendered(lambda: noisy_fn(spp))
            for method, fn in fns.items():
                row = {"scene": name, "size": args.size, "spp": spp, "method": method, "render_s": render_s,
                       **scores(fn(gb), ref)}
                rows.append(row)
                print({k: (round(v, 5) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    return rows


def claims(rows: list[dict], glossy: set[str]) -> list[str]:
    """Issue 33's lines for the default Denoiser, per scene and spp."""
    lines = []
    at = {(r["scene"], r["spp"], r["method"]): r["relmse"] for r in rows}
    if not any(r["method"] == DEFAULT for r in rows):
        return lines
    for scene in dict.fromkeys(r["scene"] for r in rows):
        spps = sorted({r["spp"] for r in rows if r["scene"] == scene})
        for spp in spps:
            d, noisy = at[scene, spp, DEFAULT], at[scene, spp, "noisy"]
            line = f"{scene} {spp} spp: default {d:.4g} vs noisy {noisy:.4g} ({'below' if d < noisy else 'NOT below'})"
            if spp // 2 in spps and spp % 2 == 0:
                half = at[scene, spp // 2, DEFAULT]
                line += f"; {d / half:.3f}x its {spp // 2}-spp value ({'met' if d <= 1.05 * half else 'NOT met'}: <= 1.05x)"
            highs = [at[k] for k in ((scene, spp, m) for m in OIDN) if k in at]
            if highs:
                o = min(highs)
                line += f"; {d / o:.2f}x OIDN high {o:.4g}"
                if spp == 8 and scene in glossy:
                    line += f" (glossy scene, bound 2x: {'met' if d <= 2 * o else 'NOT met'})"
            lines.append(line)
    return lines


def kpn_claims(rows: list[dict]) -> list[str]:
    """The learned method's lines (issue 67) against OIDN high (the better protocol) per scene:
    its ratio at each spp, at most 1.2x on every case at 1, 4 and 16 spp, at most 1.0x on half of
    them, and its 16-spp ratio at most 1.15x its 1-spp ratio."""
    at = {(r["scene"], r["spp"], r["method"]): r["relmse"] for r in rows}
    if not any(r["method"] == "torchgi kpn" for r in rows):
        return []
    lines, ratios = [], {}
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for spp in sorted({r["spp"] for r in rows if r["scene"] == scene}):
            highs = [at[k] for k in ((scene, spp, m) for m in OIDN) if k in at]
            if highs and (scene, spp, "torchgi kpn") in at:
                ratios[scene, spp] = at[scene, spp, "torchgi kpn"] / min(highs)
        line = f"{scene}: kpn / OIDN high " + ", ".join(f"{spp} spp {r:.2f}x" for (sc, spp), r in ratios.items()
                                                        if sc == scene)
        if (scene, 1) in ratios and (scene, 16) in ratios:
            slope = ratios[scene, 16] / ratios[scene, 1]
            line += f"; 16/1 spp {slope:.2f} ({'met' if slope <= 1.15 else 'NOT met'}: <= 1.15)"
        lines.append(line)
    judged = [r for (sc, spp), r in ratios.items() if spp in (1, 4, 16)]
    if judged:
        lines.append(f"kpn at 1, 4, 16 spp: {sum(r <= 1.2 for r in judged)}/{len(judged)} cases within 1.2x OIDN high "
                     f"(all needed), {sum(r <= 1.0 for r in judged)}/{len(judged)} at or below 1.0x (half needed)")
    return lines


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for scene in dict.fromkeys(r["scene"] for r in rows):
        fig, ax = plt.subplots(figsize=(6, 4.2))
        for method in dict.fromkeys(r["method"] for r in rows):
            pts = sorted((r["spp"], r["relmse"]) for r in rows if r["scene"] == scene and r["method"] == method)
            style = {"noisy": "k--", DEFAULT: "C0-o"}.get(method, "-.")
            ax.plot(*zip(*pts), style, label=method, markersize=4)
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("samples per pixel")
        ax.set_ylabel("relMSE")
        ax.set_title(f"{scene}: error against spp")
        ax.legend(fontsize=6)
        fig.tight_layout()
        fig.savefig(out / f"spp_{scene}.png", dpi=100)
        plt.close(fig)


def main() -> None:
    args = case_args(__doc__, "out/bench-spp", [1, 2, 4, 8, 16, 32, 64])
    torch.set_num_threads(2)
    rows = run(args)
    out = Path(args.out)
    write_results(rows, metadata(torch.get_num_threads()), out, "spp")
    md = markdown_table(rows, ["scene", "size", "spp", "method", "render_s", "relmse", "psnr_db", "ssim", "flip"])
    checks = claims(rows, glossy_scenes(args.scenes, args.size)) + kpn_claims(rows)
    (out / "spp.md").write_text(md + "\n\n" + "\n".join(f"- {c}" for c in checks) + "\n")
    plot(rows, out)
    print("\n".join(checks))


if __name__ == "__main__":
    main()
