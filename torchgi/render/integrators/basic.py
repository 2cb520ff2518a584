"""The readable path tracer: the specification the fast one (``path``) must match in expectation.

No compaction, no MIS, no Russian roulette: every path runs ``bounces + 1`` vertices with a
mask for the ones that ended. Light reaches the camera three ways: emitters and the sky seen
directly (camera rays only), and next-event estimation at every vertex (one point on the
emissive triangles, every point light, one sky direction). Rays that continue a path never
count the emission they find, so no light is counted twice.
"""

from __future__ import annotations

import torch

from torchgi.render.camera import camera_rays
from torchgi.render.integrators.common import (
    BSDF,
    CAMERA_DIMS,
    DIRECT,
    EMISSION,
    INDIRECT,
    LIGHT,
    SKY,
    Context,
    dims,
    emitted,
    surface,
)
from torchgi.render.lights import EMISSION as EMISSION_ROWS
from torchgi.render.lights import LIGHT_PDF, NORMAL, sample_area_light, sample_sky
from torchgi.render.materials import bsdf_eval, bsdf_sample, dot
from torchgi.render.sampler import sample_keys, uniform

__all__ = ["radiance"]


def radiance(
    ctx: Context, pixel: torch.Tensor, sample: torch.Tensor, *, stream: int = 0, record: str = "all",
    centre: bool = False,
) -> torch.Tensor:
    """Same contract as :func:`torchgi.render.integrators.path.radiance`."""
    tables = ctx.tables
    # ---- state, declared up front
    n = pixel.numel()
    out = torch.zeros(9, n)
    keys = sample_keys(ctx.seed, pixel, sample, stream)
    beta = torch.ones(3, n)  # path throughput
    bounces = 0 if record == "direct" else ctx.bounces

    # ---- camera ray
    jitter = None if centre else uniform(keys, CAMERA_DIMS)
    origin, direction = camera_rays(ctx.camera, pixel % ctx.pixels_per_image, jitter)
    origin = origin.expand(3, n)
    t, prim = ctx.accel.intersect(origin, direction)
    alive = prim >= 0
    if record != "indirect":
        out[EMISSION] += emitted(ctx, direction, prim)[0]
        if tables.sky is not None:
            out[EMISSION] += tables.sky * ~alive
    prim = prim.clamp(min=0)  # placeholder triangle for dead paths (their beta is 0)
    beta = beta * alive

    for depth in range(1, bounces + 2):
        s = surface(ctx, origin + direction * torch.where(alive, t, 0.0), direction, prim)
        u = uniform(keys, dims(depth))
        rows = DIRECT if depth == 1 else INDIRECT

        # ---- next-event estimation
        if not (depth == 1 and record == "indirect"):
            if tables.has_area:
                point, light = sample_area_light(tables, u[LIGHT])
                to_light = point - s.position
                dist2 = (to_light * to_light).sum(0)
                wl = to_light * torch.rsqrt(dist2)
                cos_l = -dot(light[NORMAL], wl)
                f_cos, _ = bsdf_eval(s.glossy, s.albedo, s.alpha, s.normal, s.wi, wl)
                visible = ~ctx.accel.occluded(s.origin, wl, torch.sqrt(dist2) * (1 - 1e-4))
                geometry = cos_l.clamp(min=0) / (dist2 * light[LIGHT_PDF])
                out[rows] += beta * f_cos * light[EMISSION_ROWS] * geometry * visible
            for p in range(tables.points.shape[0]):
                to_light = tables.points[p].reshape(3, 1) - s.position
                dist2 = (to_light * to_light).sum(0)
                wl = to_light * torch.rsqrt(dist2)
                f_cos, _ = bsdf_eval(s.glossy, s.albedo, s.alpha, s.normal, s.wi, wl)
                visible = ~ctx.accel.occluded(s.origin, wl, torch.sqrt(dist2) * (1 - 1e-4))
                out[rows] += beta * f_cos * tables.intensities[p].reshape(3, 1) / dist2 * visible
            if tables.sky is not None:
                wl, pdf_sky = sample_sky(s.normal, u[SKY])
                f_cos, _ = bsdf_eval(s.glossy, s.albedo, s.alpha, s.normal, s.wi, wl)
                visible = ~ctx.accel.occluded(s.origin, wl, None)
                out[rows] += beta * f_cos * tables.sky / pdf_sky.clamp(min=1e-20) * visible
        if depth == bounces + 1:
            break

        # ---- continue the path along a BSDF sample
        wo, weight, _ = bsdf_sample(s.glossy, s.albedo, s.alpha, s.normal, s.wi, u[BSDF])
        beta = beta * weight
        origin, direction = s.origin, wo
        t, prim = ctx.accel.intersect(origin, direction)
        alive = alive & (prim >= 0)
        prim = prim.clamp(min=0)
        beta = beta * alive
    return out
