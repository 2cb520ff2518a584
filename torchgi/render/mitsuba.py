"""Mitsuba 3 as a reference renderer (the ``ref`` extra, variant ``scalar_rgb``).

``render_gbuffer`` renders a Mitsuba scene dict with an AOV integrator and returns a
:class:`~torchgi.GBuffer` with torchgi's conventions: colour, albedo, world-space shading
normal, position and distance-along-ray depth from the first hit, and the hit mask.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from torchgi.buffers import GBuffer
from torchgi.core.check import require

__all__ = ["load_mitsuba", "cornell_box", "render_gbuffer"]

_AOVS = "albedo:albedo,nn:sh_normal,pp:position,dd:depth"


def load_mitsuba(variant: str = "scalar_rgb") -> Any:
    """Import Mitsuba 3 and select ``variant``; error naming the ``ref`` extra if absent."""
    mi = require("mitsuba", "ref")
    mi.set_variant(variant)
    return mi


def cornell_box(resolution: int = 128) -> dict:
    """Mitsuba's built-in Cornell box scene dict at ``resolution``² pixels.

    Example:
        >>> cornell_box(32)["sensor"]["film"]["width"]
        32
    """
    mi = load_mitsuba()
    scene = mi.cornell_box()
    scene["sensor"]["film"]["width"] = resolution
    scene["sensor"]["film"]["height"] = resolution
    return scene


def render_gbuffer(scene: dict, *, spp: int, bounces: int = 1, seed: int = 0) -> GBuffer:
    """Render a Mitsuba scene dict to a GBuffer (B = 1, float32, CPU).

    Args:
        scene: a Mitsuba 3 scene dict with one sensor (its integrator is replaced).
        spp: samples per pixel, > 0.
        bounces: indirect bounces (``max_depth = bounces + 2``); 0 is direct light only.
        seed: Mitsuba's sampler seed.

    Returns:
        GBuffer with ``color (1,3,H,W)``, ``emission`` (light seen directly, from a second
        render with ``max_depth = 1``), ``albedo``, ``normal``, ``position``, ``depth
        (1,1,H,W)``, ``hit (1,1,H,W)`` and ``spp``. Guides are Mitsuba's AOVs, which average
        over the pixel's samples (not a single centre ray).

    Example:
        >>> render_gbuffer(cornell_box(16), spp=4).hit.all().item()
        True
    """
    if spp <= 0:
        raise ValueError(f"spp: expected > 0, got {spp}")
    if bounces < 0:
        raise ValueError(f"bounces: expected >= 0, got {bounces}")
    mi = load_mitsuba()
    scene = dict(scene)
    scene["integrator"] = {
        "type": "aov",
        "aovs": _AOVS,
        "color": {"type": "path", "max_depth": bounces + 2},
    }
    loaded = mi.load_dict(scene)
    mi.render(loaded, spp=spp, seed=seed)
    parts = {
        name: torch.from_numpy(np.array(bmp, dtype=np.float32).reshape(bmp.height(), bmp.width(), -1))
        .permute(2, 0, 1)[None]
        .contiguous()
        for name, bmp in loaded.sensors()[0].film().bitmap(raw=False).split()
    }
    color, albedo, normal = parts["<root>"], parts["albedo"], parts["nn"]
    position, depth = parts["pp"], parts["dd"]
    # Emission seen directly by the camera: Mitsuba's path tracer with max_depth = 1.
    scene["integrator"] = {"type": "path", "max_depth": 1}
    img = mi.render(mi.load_dict(scene), spp=spp, seed=seed)
    emission = torch.from_numpy(np.array(img, dtype=np.float32)[..., :3].copy()).permute(2, 0, 1)[None].contiguous()
    hit = depth > 0
    return GBuffer(
        color=color,
        emission=emission,
        albedo=albedo,
        normal=normal,
        position=position,
        depth=depth,
        hit=hit,
        spp=torch.full_like(depth, spp, dtype=torch.int64),
    )
