"""Run time against error — the central figure: scenes x spp x methods, torchgi and its peers.

    python scripts/bench_quality.py --out out/bench                    # the judged set, 1 and 4 spp, 256²
    python scripts/bench_quality.py --set tuning --out out/bench-tuning  # the scenes the defaults were chosen on
    python scripts/bench_quality.py --scenes cornell --spp 1 --size 64 --ref-spp 256 --out out/bench

Scenes: the judged set of ``configs/scenes/sets.yaml`` by default (never used for a default, a
design choice or training; docs/calibration.md), ``--set`` for another set.

For each scene and spp: a noisy torchgi render, a ``--ref-spp`` reference, and every method →
relMSE, PSNR (Reinhard-tone-mapped), SSIM, HDR-FLIP, wall ms of the denoiser (median of 3, this
process, 2 threads) and the seconds its input took to render. torchgi: ``Denoiser`` guided /
atrous / bilateral, À-Trous with SVGF variance guidance, the adaptive variants (same budget
through ``adaptive_render``, then guided / À-Trous) and, for spp > 1, supersampling with guide
rays (``render_guide_rays`` with spp eye rays, one indirect path per pixel, then
``Denoiser.supersample``). Classical peers, each twice: on the full colour and inside torchgi's
own light steps (light sources kept, demodulation, firefly clamp, remodulation; the better counts):
kornia ``guided_blur`` (normal as guide), kornia ``joint_bilateral_blur`` (normal as guide),
scikit-image ``denoise_nl_means`` (on the tone-mapped image, mapped back); Intel Open Image Denoise through pyoidn (colour + albedo +
normal, HDR) when installed. Writes ``quality.csv/json/md`` and ``quality_<scene>.png`` (log-log
Pareto plot: ms against relMSE), and checks two claims per scene and spp: the ordering of
Bauszat et al.'s Fig. 8 (guided below À-Trous and cross-bilateral in error) and torchgi's best
method against the classical peers and OIDN (relMSE, and OIDN's ms over its ms).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import available_scenes, markdown_table, metadata, oidn, scene_sets, write_results

import torchgi
from torchgi import light, metrics
from torchgi.denoise import Denoiser
from torchgi.filters import atrous, box
from torchgi.sampling import adaptive_render, sigma_position_rule
from torchgi.settings import BILATERAL, GUIDED


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


def classical() -> dict:
    """The classical peers as ``(image (1,3,H,W), GBuffer) -> image`` with the firefly factor of
    torchgi's nearest method (used when they run inside torchgi's light steps)."""
    out = {}
    try:
        import kornia

        out["kornia guided_blur"] = (lambda x, gb: kornia.filters.guided_blur(gb.normal, x, 9, 0.01), GUIDED.firefly)
        out["kornia joint_bilateral"] = (lambda x, gb: kornia.filters.joint_bilateral_blur(
            x, gb.normal, 9, 0.2, (3.0, 3.0)), BILATERAL.firefly)
    except ImportError:
        pass
    try:
        import numpy as np
        from skimage.restoration import denoise_nl_means

        def nl_means(x, gb):
            t = metrics.tonemap(x)[0].permute(1, 2, 0).double().numpy()
            # noise σ from the median absolute horizontal difference (robust; no PyWavelets needed)
            sigma = float(np.median(np.abs(np.diff(t, axis=1))) / (0.6745 * np.sqrt(2))) + 1e-6
            y = denoise_nl_means(t, h=0.8 * sigma, sigma=sigma, patch_size=5, patch_distance=6, channel_axis=-1,
                                 fast_mode=True)
            y = torch.from_numpy(y).permute(2, 0, 1)[None].to(x.dtype).clamp(0, 0.999)
            return y / (1 - y)  # inverse Reinhard

        out["skimage nl_means"] = (nl_means, GUIDED.firefly)
    except ImportError:
        pass
    return out


def in_light_steps(fn, firefly: float):
    """``fn`` run where torchgi's own filters run: inside the Denoiser's light steps (light sources
    kept whole, the rest demodulated by the albedo, fireflies clamped, filtered, remodulated;
    :func:`torchgi.light.restore`), so a peer is judged on the same input as torchgi's filters."""
    def run(gb):
        surface = light.surface_mask(gb.hit, gb.albedo)
        return light.restore(gb.color, gb.emission, None, gb.albedo, surface, lambda x: fn(x, gb), firefly, box)
    return run


def peers() -> dict:
    """Every peer: each classical filter on the full colour and inside torchgi's light steps (the
    better of the two counts as that peer in the claims), and OIDN's two protocols."""
    out = {}
    for name, (fn, firefly) in classical().items():
        out[f"{name} (full colour)"] = lambda gb, fn=fn: fn(gb.color, gb)
        out[f"{name} (light steps)"] = in_light_steps(fn, firefly)
    try:
        import pyoidn  # noqa: F401

        for q in ("fast", "high"):
            out[f"OIDN {q}"] = lambda gb, q=q: oidn(gb, q, False)
            out[f"OIDN {q}, emission added back"] = lambda gb, q=q: oidn(gb, q, True)
    except ImportError:
        pass
    return out


def rendered(fn):
    """``fn()`` and the seconds it took."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


MITSUBA_CORNELL = "mitsuba_cornell"  # Mitsuba 3's own Cornell box, rendered by Mitsuba (box pixel filter)
MITSUBA = "mitsuba:"  # "mitsuba:<scene>": that torchgi scene converted and rendered by Mitsuba 3


def _mitsuba_case(name, scene_dict, args):
    from torchgi.render import mitsuba

    render = lambda spp, seed: mitsuba.render_gbuffer(scene_dict, spp=spp, bounces=args.bounces, seed=seed)
    return name, render(args.ref_spp, 999).color, (lambda spp: render(spp, 1)), None


def cases(args):
    """``(name, reference colour, noisy(spp) -> GBuffer, torchgi scene or None)`` per scene: a
    torchgi scene rendered by torchgi, Mitsuba's Cornell box, or ``mitsuba:<scene>`` (a torchgi
    scene rendered by Mitsuba; only the guided-by-GBuffer methods run on those)."""
    import tempfile

    for entry in args.scenes:
        if entry == MITSUBA_CORNELL:
            from torchgi.render import mitsuba

            yield _mitsuba_case(entry, mitsuba.cornell_box(args.size), args)
        elif entry.startswith(MITSUBA):
            from torchgi.render import mitsuba

            for name, scene in available_scenes([entry.removeprefix(MITSUBA)], args.size):
                with tempfile.TemporaryDirectory() as tmp:  # the PLY files live while Mitsuba renders
                    case = _mitsuba_case(f"{Path(name).name} (Mitsuba)",
                                         mitsuba.to_mitsuba(scene, tmp, bounces=args.bounces), args)
                    yield case
        else:
            for name, scene in available_scenes([entry], args.size):
                ref = torchgi.render(scene, spp=args.ref_spp, bounces=args.bounces, seed=999).color
                yield (Path(name).name, ref,
                       (lambda spp, s=scene: torchgi.render(s, spp=spp, bounces=args.bounces, seed=1)), scene)


def methods_for(scene, noisy, t_noisy, spp, args, peer_fns) -> dict:
    """Every method's ``(fn, seconds its input took to render)`` for one noisy render."""
    methods = {
        "noisy": (lambda gb=noisy: gb.color, t_noisy),
        "torchgi pyramid": (lambda gb=noisy, d=Denoiser("pyramid"): d(gb), t_noisy),
        "torchgi blend": (lambda gb=noisy, d=Denoiser("blend"): d(gb), t_noisy),
        "torchgi kpn": (lambda gb=noisy, d=Denoiser("kpn"): d(gb), t_noisy),
        "torchgi guided": (lambda gb=noisy, d=Denoiser("guided"): d(gb), t_noisy),
        "torchgi atrous": (lambda gb=noisy: Denoiser("atrous")(gb), t_noisy),
        "torchgi atrous+variance": ((lambda gb=noisy: svgf_atrous(gb)) if noisy.variance is not None and spp > 1
                                    else None, t_noisy),
        "torchgi bilateral": (lambda gb=noisy: Denoiser("bilateral")(gb), t_noisy),
    }
    if scene is not None and chosen("torchgi adaptive", args):  # the methods that render: torchgi scenes only
        (adaptive, _), t_adaptive = rendered(
            lambda: adaptive_render(scene, rate=float(spp), bounces=args.bounces, seed=1))
        methods["torchgi adaptive+guided"] = (lambda gb=adaptive, d=Denoiser("guided"): d(gb), t_adaptive)
        methods["torchgi adaptive+atrous"] = (lambda gb=adaptive: Denoiser("atrous")(gb), t_adaptive)
        if spp > 1 and chosen("torchgi guided+guide rays", args):
            (guide, eye), t_guide = rendered(
                lambda: torchgi.render.render_guide_rays(scene, spp=spp, bounces=args.bounces, seed=1))
            methods["torchgi guided+guide rays"] = (
                lambda g=guide, e=eye, d=Denoiser("guided"): d.supersample(g, e), t_guide)
    methods.update({k: (lambda gb=noisy, f=f: f(gb), t_noisy) for k, f in peer_fns.items()})
    return {k: v for k, v in methods.items() if chosen(k, args)}


def chosen(method: str, args) -> bool:
    """Whether ``--only`` (substrings of method names; none: every method) takes ``method``."""
    return not args.only or any(o in method for o in args.only)


def scores(out, ref) -> dict:
    return {
        "relmse": float(metrics.relmse(out, ref)),
        "psnr_db": float(metrics.psnr(out, ref, tonemap_method="reinhard")),
        "ssim": float(metrics.ssim(metrics.tonemap(out), metrics.tonemap(ref), data_range=1.0)),
        "flip": float(metrics.flip(out.clamp_min(0), ref.clamp_min(0))),
    }


def run(args) -> list[dict]:
    rows = []
    peer_fns = peers()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, ref, noisy_fn, scene in cases(args):
        for spp in args.spp:
            noisy, t_noisy = rendered(lambda: noisy_fn(spp))
            if chosen("torchgi blend", args):
                choice_map(noisy, out_dir / f"blend_choice_{name}_{spp}spp.png")
            if chosen("torchgi pyramid", args):
                pyramid_map(noisy, out_dir / f"pyramid_choice_{name}_{spp}spp.png")
            for method, (fn, render_s) in methods_for(scene, noisy, t_noisy, spp, args, peer_fns).items():
                if fn is None:
                    continue  # SVGF needs a variance: none at 1 spp or from Mitsuba
                out, ms = timed(fn)
                row = {"scene": name, "size": args.size, "spp": spp, "method": method, "ms": ms,
                       "render_s": render_s, **scores(out, ref)}
                rows.append(row)
                print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
    return rows


def choice_map(gb, path: Path) -> None:
    """The blend's per-pixel choice as a picture: noisy | blend | the expected radius of its
    weights (``Denoiser.weights``; the noisy light counts 0 px, a colour-guided candidate its
    radius), 0 to the largest radius as black to yellow."""
    import matplotlib

    from torchgi.filters.blend import default_net
    from torchgi.io.png import write_png

    d = Denoiser("blend")
    out, w = d(gb), d.weights(gb)
    radii = torch.tensor(default_net().candidate_radii(), dtype=w.dtype).view(1, -1, 1, 1)
    radius = (w * radii).sum(1)[0] / radii.max()
    rgb = matplotlib.colormaps["inferno"](radius.clamp(0, 1).numpy())[..., :3]
    rad = torch.from_numpy(rgb).permute(2, 0, 1).float()
    tone = lambda x: metrics.tonemap(x)[0].clamp(0, 1) ** (1 / 2.2)
    row = torch.cat([tone(gb.color), tone(out), rad], -1)
    write_png(path, (row * 255).round().byte().permute(1, 2, 0).numpy(), overwrite=True)  # the run's own output


def pyramid_map(gb, path: Path) -> None:
    """The pyramid's per-pixel choice as a picture: noisy | pyramid | the expected log2 scale of
    its candidates (black: full resolution, yellow: scale 8) | the share of the full-resolution
    candidates (black 0 to yellow 1) | the gain of the residual's finest band (black 0 to yellow
    1); the three maps at 1/4 resolution, shown enlarged (``Denoiser.weights``)."""
    import matplotlib

    from torchgi.filters.pyramid import default_net
    from torchgi.io.png import write_png

    d, net = Denoiser("pyramid"), default_net()
    out, w = d(gb), d.weights(gb)
    K = len(net.candidates)
    scales = torch.tensor([math.log2(s) for s, _, _ in net.candidates], dtype=w.dtype).view(1, -1, 1, 1)
    full = [k for k, (s, _, _) in enumerate(net.candidates) if s == 1]
    maps = [(w[:, :K] * scales).sum(1) / 3, w[:, full].sum(1), w[:, K]]
    H, W = gb.color.shape[-2:]
    tone = lambda x: metrics.tonemap(x)[0].clamp(0, 1) ** (1 / 2.2)
    panels = [tone(gb.color), tone(out)]
    for m in maps:
        big = torch.nn.functional.interpolate(m[:, None], scale_factor=4, mode="nearest")[0, 0, :H, :W]
        rgb = matplotlib.colormaps["inferno"](big.clamp(0, 1).numpy())[..., :3]
        panels.append(torch.from_numpy(rgb).permute(2, 0, 1).float())
    row = torch.cat(panels, -1)
    write_png(path, (row * 255).round().byte().permute(1, 2, 0).numpy(), overwrite=True)  # the run's own output


CLASSICAL = tuple(f"{p} ({where})" for p in ("kornia guided_blur", "kornia joint_bilateral", "skimage nl_means")
                  for where in ("full colour", "light steps"))
OIDN_HIGH = ("OIDN high", "OIDN high, emission added back")


def claims(rows: list[dict], default: str) -> list[str]:
    """Per scene and spp: Bauszat Fig. 8's ordering, torchgi's best against the peers, and
    issue 17's lines for the default Denoiser (``default``: its method's row)."""
    lines = []
    for scene, spp in dict.fromkeys((r["scene"], r["spp"]) for r in rows):
        by = {r["method"]: r for r in rows if r["scene"] == scene and r["spp"] == spp}
        fig8 = [f"torchgi {m}" for m in ("guided", "atrous", "bilateral")]
        if all(m in by for m in fig8):  # (not where --only left them out)
            g, a, b = (by[m]["relmse"] for m in fig8)
            lines.append(f"{scene} {spp} spp: Fig. 8 ordering (guided below À-Trous and cross-bilateral): "
                         f"{'holds' if g < a and g < b else 'does not hold'} ({g:.4g} / {a:.4g} / {b:.4g})")
        ours = min((r for m, r in by.items() if m.startswith("torchgi")), key=lambda r: r["relmse"])
        peers_ = [by[m] for m in CLASSICAL if m in by]
        best_peer = min(peers_, key=lambda r: r["relmse"]) if peers_ else None
        line = f"{scene} {spp} spp: torchgi best = {ours['method']} {ours['relmse']:.4g} in {ours['ms']:.3g} ms"
        if best_peer is not None:
            line += (f"; best classical peer {best_peer['method']} {best_peer['relmse']:.4g} "
                     f"({'beaten' if ours['relmse'] < best_peer['relmse'] else 'NOT beaten'})")
        lines.append(line)
        highs = [by[m] for m in OIDN_HIGH if m in by]
        if highs and default in by:
            o, d = min(highs, key=lambda r: r["relmse"]), by[default]
            bound = 1.0 if spp == 1 else 1.3
            ok = d["relmse"] <= bound * o["relmse"]
            lines.append(
                f"{scene} {spp} spp: default Denoiser ({default}) {d['relmse']:.4g} / OIDN high (best protocol: "
                f"{o['method']}) {o['relmse']:.4g} = {d['relmse'] / o['relmse']:.2f}x (issue 17 bound {bound}x: "
                f"{'met' if ok else 'NOT met'}); OIDN high {by['OIDN high']['ms']:.3g} ms = "
                f"{by['OIDN high']['ms'] / d['ms']:.1f}x the default's {d['ms']:.3g} ms (bound 10x)")
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


def case_args(doc: str, out: str, spp: list[int], repeats: int | None = None) -> argparse.Namespace:
    """The command line of a benchmark over :func:`cases` (``--out``, ``--set`` / ``--scenes``,
    ``--spp``, ``--size``, ``--ref-spp``, ``--bounces``, and ``--repeats`` with that default where
    ``repeats`` is given) parsed, ``scenes`` resolved from the set."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--out", default=out)
    ap.add_argument("--set", default="judged", choices=("judged", "tuning", "training"),
                    help="the scene set of configs/scenes/sets.yaml to run (default: judged)")
    ap.add_argument("--scenes", nargs="+", help="these entries instead of --set's (sets.yaml's syntax)")
    ap.add_argument("--spp", type=int, nargs="+", default=spp)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--bounces", type=int, default=2)
    ap.add_argument("--only", nargs="+", default=None,
                    help="run only the methods whose names contain one of these (e.g. 'pyramid' 'OIDN')")
    if repeats is not None:
        ap.add_argument("--repeats", type=int, default=repeats, help="timed calls per measurement (median)")
    args = ap.parse_args()
    args.scenes = args.scenes or scene_sets()[args.set]
    return args


def main() -> None:
    args = case_args(__doc__, "out/bench", [1, 4])
    torch.set_num_threads(2)
    rows = run(args)
    meta = metadata(torch.get_num_threads())
    out = Path(args.out)
    write_results(rows, meta, out, "quality")
    md = markdown_table(rows, ["scene", "size", "spp", "method", "ms", "render_s", "relmse", "psnr_db", "ssim", "flip"])
    checks = claims(rows, f"torchgi {Denoiser().method}")
    (out / "quality.md").write_text(md + "\n\n" + "\n".join(f"- {c}" for c in checks) + "\n")
    plot(rows, out)
    print(md)
    print("\n".join(checks))


if __name__ == "__main__":
    main()
