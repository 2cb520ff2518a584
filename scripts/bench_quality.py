"""Run time against error — the central figure: scenes x spp x methods, torchgi and its peers.

    python scripts/bench_quality.py --out out/bench                    # 5 scenes, 1 and 4 spp, 256²
    python scripts/bench_quality.py --scenes cornell --spp 1 --size 64 --ref-spp 256 --out out/bench

For each scene and spp: a noisy torchgi render, a ``--ref-spp`` reference, and every method →
relMSE, PSNR (Reinhard-tone-mapped), SSIM, HDR-FLIP, wall ms of the denoiser (median of 3, this
process, 2 threads) and the seconds its input took to render. torchgi: ``Denoiser`` guided /
atrous / bilateral, À-Trous with SVGF variance guidance, the adaptive variants (same budget
through ``adaptive_render``, then guided / À-Trous) and, for spp > 1, supersampling with guide
rays (``render_guide_rays`` with spp eye rays, one indirect path per pixel, then
``Denoiser.supersample``). Peers on the full colour: kornia ``guided_blur`` (normal as guide), kornia
``joint_bilateral_blur`` (normal as guide), scikit-image ``denoise_nl_means`` (on the
tone-mapped image, mapped back), Intel Open Image Denoise through pyoidn (colour + albedo +
normal, HDR) when installed. Writes ``quality.csv/json/md`` and ``quality_<scene>.png`` (log-log
Pareto plot: ms against relMSE), and checks two claims per scene and spp: the ordering of
Bauszat et al.'s Fig. 8 (guided below À-Trous and cross-bilateral in error) and torchgi's best
method against the classical peers and OIDN (relMSE, and OIDN's ms over its ms).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import available_scenes, markdown_table, metadata, write_results

import torchgi
from torchgi import metrics
from torchgi.denoise import Denoiser
from torchgi.filters import atrous
from torchgi.sampling import adaptive_render, sigma_position_rule


def timed(fn):
    out, times = None, []
    for _ in range(3):
        t0 = time.perf_counter()
        out = fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return out, statistics.median(times)


def svgf_atrous(gb):
    """À-Trous on the demodulated noisy light with the SVGF variance-guided colour weight."""
    surface = gb.hit
    albedo = gb.albedo.clamp_min(1e-3)
    noisy = gb.color - gb.emission
    demod = torch.where(surface, noisy / albedo, torch.zeros(()))
    var = torch.where(surface, gb.variance / albedo**2, torch.zeros(())).mean(1, keepdim=True) + 1e-8
    sigma_x = sigma_position_rule(gb.position, surface, 4.0)
    out = atrous(demod, gb.normal, gb.position, iterations=5, sigma_position=sigma_x, variance=var, sigma_color=4.0)
    return torch.where(surface, out * albedo, noisy) + gb.emission


def peers() -> dict:
    out = {}
    try:
        import kornia

        out["kornia guided_blur"] = lambda gb: kornia.filters.guided_blur(gb.normal, gb.color, 9, 0.01)
        out["kornia joint_bilateral"] = lambda gb: kornia.filters.joint_bilateral_blur(
            gb.color, gb.normal, 9, 0.2, (3.0, 3.0))
    except ImportError:
        pass
    try:
        import numpy as np
        from skimage.restoration import denoise_nl_means

        def nl_means(gb):
            x = metrics.tonemap(gb.color)[0].permute(1, 2, 0).double().numpy()
            # noise σ from the median absolute horizontal difference (robust; no PyWavelets needed)
            sigma = float(np.median(np.abs(np.diff(x, axis=1))) / (0.6745 * np.sqrt(2))) + 1e-6
            y = denoise_nl_means(x, h=0.8 * sigma, sigma=sigma, patch_size=5, patch_distance=6, channel_axis=-1,
                                 fast_mode=True)
            y = torch.from_numpy(y).permute(2, 0, 1)[None].float().clamp(0, 0.999)
            return y / (1 - y)  # inverse Reinhard

        out["skimage nl_means"] = nl_means
    except ImportError:
        pass
    try:
        import pyoidn

        def oidn(gb):
            hwc = lambda t: t[0].permute(1, 2, 0).contiguous()
            y = pyoidn.denoise(hwc(gb.color), hwc(gb.albedo), hwc(gb.normal), hdr=True, quality="high")
            return y.permute(2, 0, 1)[None]

        out["OIDN (pyoidn)"] = oidn
    except ImportError:
        pass
    return out


def rendered(fn):
    """``fn()`` and the seconds it took."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def run(args) -> list[dict]:
    rows = []
    peer_fns = peers()
    for name, scene in available_scenes(args.scenes, args.size):
        ref = torchgi.render(scene, spp=args.ref_spp, bounces=args.bounces, seed=999)
        for spp in args.spp:
            noisy, t_noisy = rendered(lambda: torchgi.render(scene, spp=spp, bounces=args.bounces, seed=1))
            methods = {
                "noisy": (lambda gb=noisy: gb.color, t_noisy),
                "torchgi guided": (lambda gb=noisy, d=Denoiser("guided"): d(gb), t_noisy),
                "torchgi atrous": (lambda gb=noisy: Denoiser("atrous")(gb), t_noisy),
                "torchgi atrous+variance": ((lambda gb=noisy: svgf_atrous(gb)) if spp > 1 else None, t_noisy),
                "torchgi bilateral": (lambda gb=noisy: Denoiser("bilateral")(gb), t_noisy),
            }
            (adaptive, _), t_adaptive = rendered(
                lambda: adaptive_render(scene, rate=float(spp), bounces=args.bounces, seed=1))
            methods["torchgi adaptive+guided"] = (lambda gb=adaptive, d=Denoiser("guided"): d(gb), t_adaptive)
            methods["torchgi adaptive+atrous"] = (lambda gb=adaptive: Denoiser("atrous")(gb), t_adaptive)
            if spp > 1:
                (guide, eye), t_guide = rendered(
                    lambda: torchgi.render.render_guide_rays(scene, spp=spp, bounces=args.bounces, seed=1))
                methods["torchgi guided+guide rays"] = (
                    lambda g=guide, e=eye, d=Denoiser("guided"): d.supersample(g, e), t_guide)
            methods.update({k: (lambda gb=noisy, f=f: f(gb), t_noisy) for k, f in peer_fns.items()})
            for method, (fn, render_s) in methods.items():
                if fn is None:
                    continue  # SVGF needs a variance: none at 1 spp
                out, ms = timed(fn)
                row = {
                    "scene": name, "spp": spp, "method": method, "ms": ms, "render_s": render_s,
                    "relmse": float(metrics.relmse(out, ref.color)),
                    "psnr_db": float(metrics.psnr(out, ref.color, tonemap_method="reinhard")),
                    "ssim": float(metrics.ssim(metrics.tonemap(out), metrics.tonemap(ref.color), data_range=1.0)),
                    "flip": float(metrics.flip(out.clamp_min(0), ref.color.clamp_min(0))),
                }
                rows.append(row)
                print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    return rows


CLASSICAL = ("kornia guided_blur", "kornia joint_bilateral", "skimage nl_means")


def claims(rows: list[dict]) -> list[str]:
    """Per scene and spp: Bauszat Fig. 8's ordering, and torchgi's best against the peers."""
    lines = []
    for scene, spp in dict.fromkeys((r["scene"], r["spp"]) for r in rows):
        by = {r["method"]: r for r in rows if r["scene"] == scene and r["spp"] == spp}
        g, a, b = (by[f"torchgi {m}"]["relmse"] for m in ("guided", "atrous", "bilateral"))
        lines.append(f"{scene} {spp} spp: Fig. 8 ordering (guided below À-Trous and cross-bilateral): "
                     f"{'holds' if g < a and g < b else 'does not hold'} ({g:.4g} / {a:.4g} / {b:.4g})")
        ours = min((r for m, r in by.items() if m.startswith("torchgi")), key=lambda r: r["relmse"])
        peers_ = [by[m] for m in CLASSICAL if m in by]
        best_peer = min(peers_, key=lambda r: r["relmse"]) if peers_ else None
        line = f"{scene} {spp} spp: torchgi best = {ours['method']} {ours['relmse']:.4g} in {ours['ms']:.3g} ms"
        if best_peer is not None:
            line += (f"; best classical peer {best_peer['method']} {best_peer['relmse']:.4g} "
                     f"({'beaten' if ours['relmse'] < best_peer['relmse'] else 'NOT beaten'})")
        if "OIDN (pyoidn)" in by:
            o = by["OIDN (pyoidn)"]
            line += f"; OIDN {o['relmse']:.4g} in {o['ms']:.3g} ms = {o['ms'] / ours['ms']:.1f}x torchgi's time"
        lines.append(line)
    return lines


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for scene in dict.fromkeys(r["scene"] for r in rows):
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        for spp, marker in zip(sorted({r["spp"] for r in rows}), "os^"):
            for r in (r for r in rows if r["scene"] == scene and r["spp"] == spp and r["method"] != "noisy"):
                color = "C0" if r["method"].startswith("torchgi") else "C3"
                ax.scatter(r["ms"], r["relmse"], marker=marker, color=color)
                ax.annotate(f"{r['method'].replace('torchgi ', '')} ({spp})", (r["ms"], r["relmse"]), fontsize=6)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall ms (median of 3)")
        ax.set_ylabel("relMSE")
        ax.set_title(f"{scene}: torchgi (blue) and peers (red); marker = spp")
        fig.tight_layout()
        fig.savefig(out / f"quality_{scene}.png", dpi=100)
        plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench")
    ap.add_argument("--scenes", nargs="+", default=["cornell", "cornell_glossy", "sky", "grass", "bunny"])
    ap.add_argument("--spp", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--bounces", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(2)
    rows = run(args)
    meta = metadata(torch.get_num_threads())
    out = Path(args.out)
    write_results(rows, meta, out, "quality")
    md = markdown_table(rows, ["scene", "spp", "method", "ms", "render_s", "relmse", "psnr_db", "ssim", "flip"])
    checks = claims(rows)
    (out / "quality.md").write_text(md + "\n\n" + "\n".join(f"- {c}" for c in checks) + "\n")
    plot(rows, out)
    print(md)
    print("\n".join(checks))


if __name__ == "__main__":
    main()
