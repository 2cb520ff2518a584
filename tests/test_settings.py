"""The Denoiser's settings: each default inside its stated range, with a unit and a reason; the
Denoiser reads them (a hand-computed radius and level count)."""

import dataclasses
import math

import pytest

from torchgi import Denoiser
from torchgi.settings import ATROUS, BILATERAL, GUIDED, PIPELINE, describe


@pytest.mark.parametrize("settings", [PIPELINE, GUIDED, ATROUS, BILATERAL])
def test_every_default_lies_in_its_range(settings):
    rows = describe(settings)
    assert [r["name"] for r in rows] == [f.name for f in dataclasses.fields(settings)]
    for r in rows:
        low, high = r["range"]
        assert low <= r["value"] <= high, r
        assert r["unit"] and r["reason"], r


def test_settings_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        GUIDED.radius = 9


def test_the_denoiser_reads_them():
    """radius = max(2, round(scale · 4 / sqrt(spp))); levels = clamp(round(log2(16 · scale / sqrt(spp)) + 2), 2, 8)."""
    assert Denoiser("guided", "high").deploy(spp=1).params["radius"] == 6  # round(1.5 · 4)
    assert Denoiser("guided", "fast").deploy(spp=16).params["radius"] == 2  # round(0.5) -> the floor of 2
    assert Denoiser("atrous").deploy(spp=1, sigma_position=1.0).params["iterations"] == 6  # log2(16) + 2
    assert Denoiser("atrous", "fast").deploy(spp=64, sigma_position=1.0).params["iterations"] == 2  # log2(1) + 2
    assert math.isclose(Denoiser("atrous").deploy(spp=1, sigma_position=1.0).params["sigma_normal"], 0.1)
