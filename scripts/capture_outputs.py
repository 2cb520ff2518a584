"""Every Denoiser method and every filter on the benchmark scenes, saved for a bit-for-bit comparison
of two trees (e.g. before and after a refactor):

    python scripts/capture_outputs.py --out out/capture-after.pt
    python scripts/capture_outputs.py --compare out/capture-before.pt out/capture-after.pt

Renders cornell, cornell_glossy, sky, grass (and bunny where its mesh loads) at 1 and 4 spp
on the CPU, then runs: ``Denoiser`` guided / atrous / bilateral / none at every quality (and
guided with subsample 2), its deployed guided and À-Trous modules, ``supersample``; renders at
5 bounces (Russian roulette) and with the basic integrator;
the filters ``box``, ``guided`` (guides of 1, 3 and 4 channels, subsample 2, float64), ``atrous``
(1-3 weights, variance, subsample, energy, float64), ``cross_bilateral``; the sampling
``importance_map``, ``allocate``, ``adaptive_counts``. Each once with the default back ends and
once with the torch code only. Then the learned methods (pyramid untiled and tiled, with their
weights; blend), the deployed guided (from a frame, without emission) and pyramid modules, the
TemporalDenoiser (guided, pyramid, without the short pass, and at 256 px), ``DeployedTemporal``,
and the exported guided and temporal graphs in onnxruntime. ``--compare`` prints the cases that differ (``torch.equal``) and
exits 1 if any does.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchmark_utils import available_scenes

from torchgi.denoise import Denoiser
from torchgi.filters import atrous, box, cross_bilateral, guide_from_gbuffer, guided
from torchgi.render import render, render_guide_rays
from torchgi.sampling import adaptive_counts, allocate, importance_map, pixel_footprint


def torch_only():
    """The torch code paths only (``torchgi.backends.use("torch")``, in every tree since the
    back ends moved there)."""
    from torchgi import backends

    return backends.use("torch")


def cases(gb, size: int):
    """(name, thunk) pairs over one GBuffer."""
    surface = gb.hit
    guide = guide_from_gbuffer(gb)
    light = torch.where(surface, (gb.color - gb.emission) / gb.albedo.clamp_min(1e-3), 0.0)
    sx = (4 * pixel_footprint(gb.position, surface)) ** 2
    for method in ("guided", "atrous", "bilateral", "none"):
        for quality in ("fast", "balanced", "high"):
            yield f"denoiser-{method}-{quality}", lambda m=method, q=quality: Denoiser(m, q)(gb)
    yield "denoiser-guided-sub2", lambda: Denoiser("guided", subsample=2)(gb)
    yield "denoiser-blend", lambda: Denoiser("blend")(gb)
    yield "denoiser-pyramid", lambda: Denoiser("pyramid")(gb)
    yield "denoiser-pyramid-weights", lambda: Denoiser("pyramid").weights(gb)
    yield "denoiser-spp4", lambda: Denoiser("guided")(gb.replace(spp=None), spp=4)
    yield "denoiser-sanitize", lambda: Denoiser("atrous", sanitize=True, input_scale=2.0, iterations=3)(gb)
    yield "deployed-pyramid", lambda: Denoiser("pyramid").deploy(spp=1)(gb.color, gb.emission, gb.albedo, gb.normal,
                                                                       gb.depth)
    yield "deployed-guided-frame", lambda: Denoiser("guided").deploy(frame=gb)(
        *(getattr(gb, k) for k in Denoiser("guided").deploy(frame=gb).input_names))
    yield "deployed-guided-noemission", lambda: Denoiser("guided").deploy(spp=2, emission=False)(
        gb.color, gb.albedo, gb.normal, gb.depth)
    yield "denoiser-blend-weights", lambda: Denoiser("blend").weights(gb)
    yield "denoiser-guided-tiled", lambda: Denoiser("guided", max_memory_mb=4)(gb)
    yield "denoiser-guided-split", lambda: Denoiser("guided", filter_direct=False)(gb)
    yield "denoiser-no-emission", lambda: Denoiser("guided")(color=gb.color, albedo=gb.albedo, normal=gb.normal,
                                                               depth=gb.depth)
    yield "deployed-blend", lambda: Denoiser("blend").deploy(spp=1)(gb.color, gb.emission, gb.albedo, gb.normal,
                                                                   gb.depth)
    yield "deployed-guided", lambda: Denoiser("guided").deploy(spp=1)(gb.color, gb.emission, gb.albedo, gb.normal,
                                                                     gb.depth)
    yield "deployed-atrous", lambda: Denoiser("atrous").deploy(spp=1, sigma_position=sx)(
        gb.color, gb.emission, gb.albedo, gb.normal, gb.position)
    yield "box-r3", lambda: box(light, 3)
    yield "box-r40", lambda: box(light, 40)
    for k in (1, 3, 4):
        yield f"guided-g{k}", lambda k=k: guided(light, guide[:, :k], radius=6, eps=1e-3)
    yield "guided-sub2", lambda: guided(light, guide, radius=8, eps=1e-3, subsample=2)
    yield "guided-f64", lambda: guided(light.double(), guide.double(), radius=5, eps=1e-3)
    yield "guided-eps-tensor", lambda: guided(light, guide, radius=4, eps=torch.tensor([1e-3] * guide.shape[1]))
    yield "atrous-3w", lambda: atrous(light, gb.normal, gb.position, iterations=5, sigma_position=sx)
    yield "atrous-n", lambda: atrous(light, gb.normal, iterations=3, color_weight=False)
    yield "atrous-c", lambda: atrous(light, iterations=4, sigma_color=0.5)
    var = torch.where(surface, gb.variance / gb.albedo.clamp_min(1e-3) ** 2, 0.0).mean(1, keepdim=True) + 1e-8
    yield "atrous-var", lambda: atrous(light, gb.normal, gb.position, iterations=4, sigma_position=sx, variance=var,
                                       sigma_color=4.0)
    yield "atrous-sub2-energy", lambda: atrous(light, gb.normal, gb.position, iterations=4, sigma_position=sx,
                                               subsample=2, energy=True)
    yield "atrous-f64", lambda: atrous(light.double(), gb.normal.double(), gb.position.double(), iterations=3,
                                       sigma_position=sx)
    yield "bilateral", lambda: cross_bilateral(light, [gb.normal], radius=4, sigma_space=2.0, sigma_color=1.0,
                                               sigma_guides=[0.2])
    yield "importance", lambda: importance_map(gb.normal, gb.position, sigma_position=sx, hit=surface)
    q = importance_map(gb.normal, gb.position, sigma_position=sx, hit=surface)
    yield "allocate", lambda: allocate(q, 4 * size * size, min_samples=1, mask=surface)
    yield "allocate-f64", lambda: allocate(q.double(), 3 * size * size + 17)
    yield "adaptive-counts", lambda: adaptive_counts(gb, 4.0)


def capture(size: int) -> dict[str, torch.Tensor]:
    torch.manual_seed(0)
    out: dict[str, torch.Tensor] = {}
    for name, scene in available_scenes(["cornell", "cornell_glossy", "sky", "grass", "bunny"], size):
        for spp in (1, 4):
            gb = render(scene, spp=spp, bounces=1, seed=3)
            for mode in ("default", "torch"):
                ctx = torch_only() if mode == "torch" else contextlib.nullcontext()
                with ctx:
                    for case, fn in cases(gb, size):
                        out[f"{name}/{spp}spp/{mode}/{case}"] = fn()
            if spp == 4:
                out[f"{name}/render-b5"] = render(scene, spp=2, bounces=5, seed=1).color
                out[f"{name}/render-basic"] = render(scene, spp=2, bounces=2, seed=1, integrator="basic").color
                gr, eye = render_guide_rays(scene, spp=4, seed=3)
                out[f"{name}/supersample"] = Denoiser("guided", filter_direct=False).supersample(gr, eye)
                for k in ("color", "direct", "indirect", "emission", "albedo", "normal", "depth", "position"):
                    out[f"{name}/guide-rays/{k}"] = getattr(gr, k)
                with torch_only():
                    out[f"{name}/render-torch"] = render(scene, spp=2, bounces=2, seed=1).color
                out[f"{name}/render-adaptive"] = render(scene, spp=adaptive_counts(gb, 2.0), bounces=1, seed=5).color
        print(name, flush=True)
    out.update(temporal(size))
    out.update(onnx(size))
    return out


def temporal(size: int) -> dict[str, torch.Tensor]:
    """A camera path's frames (motion included) and the TemporalDenoiser over them, both back ends."""
    from torchgi import TemporalDenoiser, load_scene, render_sequence

    root = Path(__file__).resolve().parents[1]
    seq = load_scene(root / "configs/scenes/sequences/cornell_slide.yaml").with_resolution(size, size)
    frames = render_sequence(seq, 5, spp=1, seed=2)
    out = {f"sequence/{k}/{name}": getattr(f, name) for k, f in enumerate(frames) for name in ("color", "motion")}
    for mode in ("default", "torch"):
        with torch_only() if mode == "torch" else contextlib.nullcontext():
            for label, den in (("", TemporalDenoiser()), ("-pyramid", TemporalDenoiser(spatial="pyramid")),
                               ("-noshort", TemporalDenoiser(short_pass=False))):
                for k, f in enumerate(frames):
                    out[f"temporal{label}/{mode}/{k}"] = den(f)
    big = render_sequence(seq.with_resolution(256, 256), 3, spp=1, seed=2)  # above 256 px: the short pass runs
    den = TemporalDenoiser()
    for k, f in enumerate(big):
        out[f"temporal-256/{k}"] = den(f)
    from torchgi.temporal import DeployedTemporal, TemporalState

    m, state = DeployedTemporal(), None
    for k, f in enumerate(frames):
        state = state or TemporalState.empty(f.color).tensors()
        y = m(f.color, f.emission, f.albedo, f.normal, f.depth, f.motion, *state)
        out[f"deployed-temporal/{k}"] = y[0]
        state = (*y[1:4], y[4], f.normal, f.depth, y[5])
    return out


def onnx(size: int) -> dict[str, torch.Tensor]:
    """The pyramid and guided Denoisers in tiles on a 520x470 render; exported graphs (guided,
    temporal) run in onnxruntime on a render."""
    import tempfile

    from torchgi import load_scene
    from torchgi.export import OrtDenoiser, OrtSession, export_denoiser, export_temporal
    from torchgi.temporal import TemporalState

    root = Path(__file__).resolve().parents[1]
    gb = render(load_scene(root / "configs/scenes/cornell.yaml").with_resolution(size, size), spp=4, bounces=1, seed=3)
    out: dict[str, torch.Tensor] = {}
    big = render(load_scene(root / "configs/scenes/cornell.yaml").with_resolution(520, 470), spp=4, bounces=1, seed=3)
    out["pyramid-tiled"] = Denoiser("pyramid", max_memory_mb=200)(big)
    out["pyramid-tiled-weights"] = Denoiser("pyramid", max_memory_mb=200).weights(big)
    out["guided-tiled-big"] = Denoiser("guided", max_memory_mb=20)(big)
    with tempfile.TemporaryDirectory() as d:
        p = export_denoiser("guided", Path(d) / "guided.onnx", frame=gb)
        out["onnx/guided-frame"] = OrtDenoiser(p)(gb)
        p = export_temporal(Path(d) / "temporal.onnx")
        s = TemporalState.empty(gb.color)
        y = OrtSession(p)(color=gb.color, emission=gb.emission, albedo=gb.albedo, normal=gb.normal, depth=gb.depth,
                          motion=torch.zeros_like(gb.color[:, :2]), light=s.light, history=s.output,
                          moments=s.moments, length=s.length, prev_normal=s.normal, prev_depth=s.depth,
                          prev_surface=s.surface)
        out["onnx/temporal"] = y[0]
    return out


def compare(a: Path, b: Path) -> int:
    x, y = torch.load(a), torch.load(b)
    bad = sorted(k for k in x.keys() & y.keys() if not torch.equal(x[k], y[k]))
    missing = sorted(x.keys() ^ y.keys())
    for k in bad:
        d = (x[k].double() - y[k].double()).abs().max().item()
        print(f"differs: {k} (max abs diff {d:.3g})")
    for k in missing:
        print(f"in one only: {k}")
    print(f"{len(x.keys() & y.keys()) - len(bad)} of {len(x.keys() | y.keys())} cases bit-identical")
    return 1 if bad or missing else 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/capture.pt"))
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--compare", nargs=2, type=Path, default=None)
    args = ap.parse_args()
    if args.compare:
        sys.exit(compare(*args.compare))
    torch.set_num_threads(2)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(capture(args.size), args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
