"""The Denoiser's fused guided pipeline (``backends.RestoreOp``) and its guide statistics
(``GuideStatsOp``, ``EdgeShareOp``): the compiled back end against the torch code run in float64
(the pipeline's maths with rounding out of the way), against a hand-computed case, across
threads, and its NaN/Inf checks naming the input."""

from __future__ import annotations

import pytest
import torch

import torchgi
from tests.helpers import last_backend, tile_budgets
from tests.oracles import box_oracle
from torchgi import backends
from torchgi.core import NonFiniteError
from torchgi.denoise import Denoiser
from torchgi.settings import DEFAULTS


@pytest.fixture(scope="module")
def render():
    pytest.importorskip("embreex", reason="the render extra is not installed")
    return torchgi.render(torchgi.scenes.cornell(64), spp=1, bounces=1, seed=3)


def _compiled(device: torch.device) -> str:
    name = "triton" if device.type == "cuda" else "c"
    why = backends.status()[name]
    if not why.startswith(("compiled kernels in use", "Triton ")) or (name == "triton" and "CUDA" not in why):
        pytest.skip(f"{name}: {why}")
    return name


def _variants(gb):
    """(name, Denoiser kwargs, call inputs) covering every branch of the pipeline."""
    full = {"color": gb.color, "albedo": gb.albedo, "normal": gb.normal, "depth": gb.depth, "emission": gb.emission}
    crop = {k: v[..., 3:, 5:].contiguous() for k, v in full.items()}  # odd sizes, the light off-centre
    two = {k: torch.cat([v, v.flip(-1) * (3.0 if k in ("color", "emission", "depth") else 1.0)]) for k, v in full.items()}
    no_emission = {k: v for k, v in full.items() if k != "emission"}
    no_depth = {k: v for k, v in full.items() if k != "depth"}
    split = {"direct": gb.direct, "indirect": gb.indirect, **{k: v for k, v in full.items() if k != "color"},
             "hit": gb.hit}
    conductor = {**full, "albedo": gb.albedo * torch.linspace(1, 8, gb.albedo.shape[-1])}  # "albedo" above 1
    return [
        ("default", {}, full), ("half", {"subsample": 2}, full), ("third", {"subsample": 3}, crop),
        ("odd", {}, crop), ("odd-half", {"subsample": 2}, crop), ("batch", {"subsample": 2}, two),
        ("no-emission", {}, no_emission), ("no-depth", {"radius": 3}, no_depth),
        ("split", {"filter_direct": False}, split), ("hit", {}, {**full, "hit": gb.hit}),
        ("eps", {"eps": 1e-3, "radius": 2}, full), ("conductor", {}, conductor),
        ("conductor-half", {"subsample": 2}, {**conductor, "hit": gb.hit}),
    ]


@pytest.mark.parametrize("case", range(13))
def test_compiled_pipeline_matches_the_float64_torch_code(render, case):
    name, params, inputs = _variants(render)[case]
    _compiled(torch.device("cpu"))
    d = Denoiser("guided", **params)
    with backends.use("c"):
        out = d(**inputs)
    assert last_backend("restore") == "c"
    with backends.use("torch"):
        ref = d(**{k: v.double() if v.is_floating_point() else v for k, v in inputs.items()})
    err = ((out.double() - ref).abs() / (ref.abs() + 1e-3)).max()
    # measured: up to 1.5e-4 at full resolution, 1.7e-3 at a third (the float32 torch code: 3e-3, 1e-2)
    assert float(err) < (5e-4 if params.get("subsample", 1) == 1 else 5e-3), name


def test_a_constant_guide_without_lights_is_two_box_filters():
    """Hand-computed: constant guide -> a = 0, b = box(x); output = box(box(x)) x albedo, no
    light source (no emission), no firefly (light within 2x of its neighbours)."""
    _compiled(torch.device("cpu"))
    g = torch.Generator().manual_seed(0)
    x = 1 + torch.rand(1, 3, 37, 45, generator=g, dtype=torch.float64)
    albedo = torch.full_like(x, 0.5)
    normal = torch.zeros_like(x)
    normal[:, 2] = 1
    with backends.use("c"):
        out = Denoiser("guided", radius=3, subsample=1)(color=(x * albedo).float(), albedo=albedo.float(),
                                                       normal=normal.float())
    ref = box_oracle(box_oracle(x, 3), 3) * 0.5
    assert float((out.double() - ref).abs().max()) < 1e-6


def test_bands_on_two_threads_give_the_one_thread_result(render, monkeypatch):
    _compiled(torch.device("cpu"))
    from torchgi.backends import c_kernels

    d = Denoiser("guided", subsample=2)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = d(render)
        monkeypatch.setattr(c_kernels.runtime, "_MIN_BAND_PIXELS", 16)
        torch.set_num_threads(2)
        two = d(render)
    finally:
        torch.set_num_threads(threads)
    assert float(((one - two).abs() / (one.abs() + 1e-3)).max()) < 1e-5


@pytest.mark.parametrize("name", ["color", "emission", "albedo", "normal", "depth", "direct"])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_input_is_named_by_every_back_end(render, name, value):
    inputs = {k: getattr(render, k).clone() for k in ("color", "albedo", "normal", "depth", "emission")}
    if name == "direct":  # the papers' split: direct light kept as sampled, read by the pipeline
        inputs |= {"direct": render.direct.clone(), "indirect": render.indirect}
    inputs[name][0, 0, 10, 20] = value
    d = Denoiser("guided", filter_direct=name != "direct")
    for backend in ("c", "torch"):
        with backends.use(backend), pytest.raises(NonFiniteError, match=name):
            d(**inputs)


def test_guide_statistics_and_edge_share_match_the_torch_code(render):
    _compiled(torch.device("cpu"))
    n, d = render.normal, render.depth
    for hit in (render.hit, None):
        with backends.use("c"):
            st = backends.run(backends.GuideStatsOp(n, d, hit))
        with backends.use("torch"):
            ref = backends.run(backends.GuideStatsOp(n, d, hit))
        assert torch.equal(st[:, :11], ref[:, :11])  # extremes and counts exactly
        assert torch.allclose(st[:, 11:], ref[:, 11:], rtol=1e-5, atol=1e-3)  # sums (float lanes, then double)
    spec = backends.GuideSpec(n, d, (0, 1, 2, 3), (0.5, 0.5, 0.5, 1 / float(d.max())), (0.5, 0.5, 0.5, 0.0))
    with backends.use("c"):
        share = backends.run(backends.EdgeShareOp(spec, 0.1))
    with backends.use("torch"):
        ref = backends.run(backends.EdgeShareOp(spec, 0.1))
    assert abs(share - ref) < 1e-3 and 0 < ref < 1


@pytest.mark.parametrize(("subsample", "crop", "spp"), [(1, 0, 1), (2, 0, 1), (2, 3, 1), (2, 3, 4)])
def test_tiles_give_the_untiled_result(render, subsample, crop, spp):
    """max_memory_mb: tiles with the footprint as overlap; the light and guide are centred by the
    image's constants, so each tile computes the untiled sums (measured 2e-7 at 4K: README). At
    4 spp the back-off toward the input (its window in the overlap) runs in each tile too."""
    gb = torchgi.render(torchgi.scenes.cornell(150).with_resolution(150 - crop, 131), spp=spp, bounces=1, seed=4)
    names = ("color", "albedo", "normal", "depth", "emission") + (("variance", "spp") if spp > 1 else ())
    inputs = {k: getattr(gb, k) for k in names}
    whole = Denoiser("guided", subsample=subsample)(**inputs)
    mb = 1.2 if spp == 1 else 2.0  # (the back-off's planes too: 3x4 tiles)
    tiled = Denoiser("guided", subsample=subsample, max_memory_mb=mb)(**inputs)  # 5x5 tiles (7x6 at half resolution)
    assert float(((tiled - whole).abs() / (whole.abs() + 1e-3)).max()) < 1e-5
    with backends.use("torch"):  # the torch code, float64: its own means, the same tiles
        f64 = {k: v.double() if v.is_floating_point() else v for k, v in inputs.items()}
        whole = Denoiser("guided", subsample=subsample)(**f64)
        tiled = Denoiser("guided", subsample=subsample, max_memory_mb=2 * mb)(**f64)
    assert float(((tiled - whole).abs() / (whole.abs() + 1e-3)).max()) < 1e-9


@pytest.mark.parametrize("method", ["guided", "pyramid"])
def test_auto_memory_tiles_only_calls_estimated_above_the_threshold(render, monkeypatch, method):
    """max_memory_mb="auto" (the default): untiled while the estimate (a tile's bytes per pixel
    over the image, and the output) is at most settings.pipeline.auto_tiles_from_mb, above it in tiles of
    auto_budget (2) x the inputs' memory, at least auto_floor_mb; None never tiles. The estimate by hand: the
    guided pipeline 4 (19 + 22) B per pixel at B = 1 (tiles.guided_bytes), the pyramid 480; the
    five float32 inputs 13 x 4 B per pixel, the output 12."""
    inputs = {k: getattr(render, k) for k in ("color", "albedo", "normal", "depth", "emission")}
    px = render.color.shape[-2] * render.color.shape[-1]
    whole = ({"guided": 164, "pyramid": 480}[method] + 12) * px / 2**20

    def run(threshold: float, floor: float = 0.0, times: float = 2.0, **kw) -> tuple[torch.Tensor, list[float]]:
        budgets = tile_budgets(monkeypatch)
        settings = DEFAULTS.replace(pipeline={"auto_tiles_from_mb": threshold, "auto_floor_mb": floor,
                                              "auto_budget": times})
        return Denoiser(method, settings=settings, **kw)(**inputs), budgets

    untiled, budgets = run(whole * 1.001)
    assert budgets == []
    if method == "guided":  # a budget of 6x the inputs: 2x2 tiles (the pyramid's 208 px overlap needs 100 MB)
        tiled, budgets = run(whole * 0.999, times=6.0)
        assert budgets == [pytest.approx(6 * 13 * 4 * px / 2**20)]
        assert float(((tiled - untiled).abs() / (untiled.abs() + 1e-3)).max()) < 1e-5
    assert run(0.0, floor=300.0)[1] == [300.0]  # the floor: one tile
    assert run(0.0, max_memory_mb=None)[1] == []
    assert Denoiser(method).max_memory_mb == "auto" and "max_memory_mb" not in repr(Denoiser(method))


def test_memory_bounds_and_sanitize_are_checked(render):
    with pytest.raises(ValueError, match="at least"):
        Denoiser("guided", max_memory_mb=0.01)(render)
    with pytest.raises(ValueError, match="max_memory_mb"):
        Denoiser("atrous", max_memory_mb=100)
    for bad_mb in (-1, 0, float("inf"), float("nan"), True, "10", "none"):
        with pytest.raises(ValueError, match="max_memory_mb"):
            Denoiser("guided", max_memory_mb=bad_mb)
    bad = render.replace(color=render.color.clone())
    bad.color[0, 1, 5, 7] = float("nan")
    with pytest.warns(UserWarning, match="color: replaced 1 non-finite"):
        out = Denoiser("guided", sanitize=True)(bad)
    assert bool(torch.isfinite(out).all())


@pytest.mark.parametrize("subsample", [1, 2])
def test_the_compiled_pipeline_of_each_device(render, device, subsample):
    """C on the CPU, Triton on CUDA (``--device cuda``), against the float64 torch code."""
    name = _compiled(device)
    inputs = {k: getattr(render, k) for k in ("color", "albedo", "normal", "depth", "emission")}
    d = Denoiser("guided", subsample=subsample)
    with backends.use(name):
        out = d(**{k: v.to(device) for k, v in inputs.items()}).cpu()
    assert last_backend("restore") == name
    with backends.use("torch"):
        ref = d(**{k: v.double() for k, v in inputs.items()})
    assert float(((out.double() - ref).abs() / (ref.abs() + 1e-3)).max()) < (5e-4 if subsample == 1 else 5e-3)


@pytest.mark.parametrize("case", ["default", "odd", "batch", "no-emission", "split", "hit", "conductor"])
def test_light_steps_around_another_filter_match_the_float64_torch_code(render, case):
    """LightInOp / LightOutOp (the steps of light.restore before and after a filter run apart, the
    learned pyramid's): the C kernels against the torch code in float64, every branch of
    _variants (light sources from the emission or from the colour, kept light, hit, albedo above
    1), with a filter that undershoots 0 somewhere (the clamp at 0 before remodulation)."""
    _compiled(torch.device("cpu"))
    _, _, inputs = next(v for v in _variants(render) if v[0] == case)
    color = inputs.get("color", inputs.get("direct", 0) + inputs.get("indirect", 0)).clone()
    emission = None if inputs.get("emission") is None else inputs["emission"].clone()
    color[..., 10:15, 20:26] += 5.0  # a light source (the box's own is a strip too thin for the opening)
    if emission is not None:
        emission[..., 10:15, 20:26] += 5.0
    kept = inputs.get("direct") if case == "split" else None
    args = {"color": color, "emission": emission, "kept": kept, "albedo": inputs["albedo"], "hit": inputs.get("hit")}
    level = torch.full((color.shape[0], 1, 1, 1), 0.1)
    with backends.use("c"):
        clamped, x, lights = backends.run(backends.LightInOp(**args, level=level, firefly=4.0))
        filtered = clamped * 1.1 - 0.02 * clamped.mean()
        out = backends.run(backends.LightOutOp(filtered.clone(), **args, lights=lights, inplace=True))
    assert last_backend("light_in") == "c" and last_backend("light_out") == "c"
    rel = lambda a, b: float(((a.double() - b.double()).abs() / (b.double().abs() + 1e-3)).max())
    for dt, bound in ((torch.float32, 1e-5), (torch.float64, 5e-4)):  # the same arithmetic; the maths (as restore's)
        ref_args = {k: None if v is None else v.to(dt) if v.is_floating_point() else v for k, v in args.items()}
        with backends.use("torch"):
            ref_clamped, ref_x, ref_lights = backends.run(backends.LightInOp(**ref_args, level=level.to(dt), firefly=4.0))
            ref = backends.run(backends.LightOutOp(filtered.to(dt), **ref_args, lights=ref_lights))
        assert torch.equal(lights, ref_lights) and int(lights.sum()) >= 30 * color.shape[0]
        assert rel(x, ref_x) < bound and rel(clamped, ref_clamped) < bound and bool((clamped < x).any())
        assert rel(out, ref) < bound


def test_light_steps_name_a_non_finite_input(render):
    _compiled(torch.device("cpu"))
    color = render.color.clone()
    color[0, 1, 7, 9] = float("nan")
    with backends.use("c"), pytest.raises(NonFiniteError, match="color"):
        backends.run(backends.LightInOp(color, render.emission, None, render.albedo, None, torch.ones(1, 1, 1, 1), 4.0))
