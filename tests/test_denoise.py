"""torchgi.Denoiser: every method lowers the error of a 1 spp render; inputs, presets, bad input."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

pytest.importorskip("embreex", reason="the render extra is not installed")

import torchgi  # noqa: E402
from torchgi import metrics  # noqa: E402
from torchgi.denoise import Denoiser  # noqa: E402

PRESETS = Path(__file__).resolve().parents[1] / "configs" / "denoise"


@pytest.fixture(scope="module")
def cornell():
    scene = torchgi.scenes.cornell(48)
    return torchgi.render(scene, spp=1, bounces=1, seed=1), torchgi.render(scene, spp=256, bounces=1, seed=2)


@pytest.mark.parametrize("method", ["guided", "atrous", "bilateral"])
def test_every_method_lowers_the_error(cornell, method):
    noisy, ref = cornell
    out = Denoiser(method)(noisy)
    assert out.shape == noisy.color.shape and out.dtype == noisy.color.dtype
    assert float(metrics.relmse(out, ref.color)) < 0.8 * float(metrics.relmse(noisy.color, ref.color))


def test_none_returns_the_noisy_colour_and_emission_passes_untouched(cornell):
    noisy, _ = cornell
    assert torch.equal(Denoiser("none")(noisy), noisy.color)
    # emission is added back, never filtered: the output moves by exactly the emission
    dark = torchgi.GBuffer(**{k: getattr(noisy, k) for k in ("direct", "indirect", "albedo", "normal", "position",
                                                             "depth", "spp", "hit")},
                           emission=torch.zeros_like(noisy.emission))
    for method in ("guided", "atrous"):
        diff = Denoiser(method)(noisy) - Denoiser(method)(dark)
        torch.testing.assert_close(diff, noisy.emission, rtol=1e-5, atol=1e-5)


def test_named_tensors_equal_the_gbuffer_call(cornell):
    noisy, _ = cornell
    named = {k: getattr(noisy, k) for k in ("color", "albedo", "normal", "position", "depth", "emission",
                                            "direct", "indirect", "spp", "hit")}
    assert torch.equal(Denoiser("guided")(**named), Denoiser("guided")(noisy))
    # colour-only input (a Mitsuba / Blender render): works and still helps
    only = Denoiser("guided")(color=noisy.color, emission=noisy.emission, albedo=noisy.albedo, normal=noisy.normal,
                              depth=noisy.depth)
    assert float(metrics.relmse(only, cornell[1].color)) < float(metrics.relmse(noisy.color, cornell[1].color))


def test_presets_load_through_the_registry():
    for preset in sorted(PRESETS.glob("*.yaml")):
        d = Denoiser.from_config(str(preset))
        assert d.method == preset.stem and preset.stem in repr(d)


def test_bad_input(cornell):
    noisy, _ = cornell
    with pytest.raises(ValueError, match="method"):
        Denoiser("oidn")
    with pytest.raises(ValueError, match="radius"):
        Denoiser("atrous", radius=3)
    with pytest.raises(ValueError, match="color"):
        Denoiser("guided")(albedo=noisy.albedo, normal=noisy.normal)
    with pytest.raises(ValueError, match="albedo and normal"):
        Denoiser("guided")(color=noisy.color)
    with pytest.raises(ValueError, match="colour"):
        Denoiser("guided")(colour=noisy.color)
    with pytest.raises(ValueError):
        Denoiser("guided")(color=noisy.color, albedo=noisy.albedo[..., :10], normal=noisy.normal)
