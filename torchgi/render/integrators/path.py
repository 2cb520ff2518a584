"""The fast path tracer: wavefronts with compaction, next-event estimation and MIS.

Per vertex: one light sample on the emissive triangles and one towards the sky, combined with
BSDF sampling by the power heuristic; every point light is sampled (no random choice). At the
last vertex (``depth = bounces + 1``) a diffuse surface takes its light samples with weight 1
and traces no BSDF ray (nothing could use it); a glossy one keeps MIS. Russian roulette starts
after ``Context.roulette_from`` bounces (3). Paths that miss or carry zero throughput are dropped, and light types
the scene lacks are never sampled (docs/design.md, Skips); each skip named in ``common.SKIPS`` can be
turned off (``Context.skip``) to measure it. Matches ``basic`` in expectation.

The active set is compacted once per vertex with one index vector (``index_select`` /
``index_add_``: boolean-mask indexing and ``x[:, idx] += v`` are much slower in torch), and
shadow rays that cannot contribute are disabled (``tmax = 0``) rather than compacted away.
"""

from __future__ import annotations

import math

import torch

from torchgi.render.camera import camera_rays
from torchgi.render.integrators.common import (
    BSDF,
    CAMERA_DIMS,
    DIRECT,
    EMISSION,
    INDIRECT,
    LIGHT,
    ROULETTE,
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

_SHADOW_END = 1.0 - 1e-4  # shadow rays to a light point stop just short of it


def _power(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Power-heuristic weight of the strategy with pdf ``a`` against ``b``."""
    a2 = a * a
    return torch.where(a2 > 0, a2 / (a2 + b * b), 0.0)


def radiance(
    ctx: Context, pixel: torch.Tensor, sample: torch.Tensor, *, stream: int = 0, record: str = "all",
    centre: bool = False,
) -> torch.Tensor:
    """Radiance of one path per ``(pixel, sample)``.

    Args:
        ctx: scene, BVH, camera, ``bounces`` and ``seed``.
        pixel: ``(N,)`` int64 global pixel index ``b*H*W + y*W + x``.
        sample: ``(N,)`` int64 sample index within the pixel.
        stream: random stream (separate passes over the same samples use different ones).
        record: "all"; "direct" (emission and direct light only); "indirect" (only light
            after >= 2 surface interactions, skipping the first vertex's light sampling).
        centre: camera rays through pixel centres (guide rays) instead of jittered ones.

    Returns:
        ``(9, N)`` float32: emission, direct and indirect RGB rows.
    """
    tables = ctx.tables
    skip_dead = "dead_paths" in ctx.skip
    # Without the "absent_lights" skip, an absent sky is sampled anyway (at zero radiance).
    sky = tables.sky if tables.sky is not None or "absent_lights" in ctx.skip else torch.zeros(3, 1)
    out = torch.zeros(9, pixel.numel())
    keys = sample_keys(ctx.seed, pixel, sample, stream)
    idx, keys, prim, t, direction, beta, position = _camera_paths(ctx, out, pixel, keys, record, centre, sky)
    bounces = 0 if record == "direct" else ctx.bounces
    for depth in range(1, bounces + 2):
        if idx.numel() == 0:
            break
        last = depth == bounces + 1
        rows = DIRECT if depth == 1 else INDIRECT
        record_here = not (depth == 1 and record == "indirect")
        s = surface(ctx, position, direction, prim)
        # MIS with BSDF sampling everywhere but at a diffuse last vertex.
        mis = None if not last else s.glossy
        if last and "last_vertex_rays" not in ctx.skip:  # MIS and a BSDF ray at every last vertex, as Mitsuba
            mis = torch.ones(idx.numel(), dtype=torch.bool)
        trace_on = not last or (mis is not None and (tables.has_area or sky is not None))
        need = _needed_dims(ctx, depth, trace_on, record_here, sky is not None)
        vertex = dims(depth)
        u = dict(zip(need, uniform(keys, [vertex[k] for k in need]))) if need else {}
        acc = torch.zeros(3, idx.numel())
        if record_here:
            _next_event(ctx, acc, s, beta, u, mis, last, sky)
        if not trace_on:
            out[rows].index_add_(1, idx, acc)
            break
        # ---- continue along a BSDF sample
        wo, weight, pdf = bsdf_sample(s.glossy, s.albedo, s.alpha, s.normal, s.wi, _stack(u, BSDF))
        beta = beta * weight
        live = beta.amax(0) > 0
        if last:
            live &= mis
        if depth > ctx.roulette_from:
            q = beta.amax(0).clamp(max=0.95)
            live &= u[ROULETTE] < q
            beta = beta / torch.where(live, q, 1.0)
        t, prim = ctx.accel.intersect(s.origin, wo, torch.where(live, math.inf, 0.0) if skip_dead else None)
        hit = (prim >= 0) & live
        if record_here:
            _bsdf_light(ctx, acc, s, beta, wo, pdf, t, prim, live, hit, sky)
        out[rows].index_add_(1, idx, acc)
        if last:
            break
        if skip_dead:  # paths that missed, died or lost all throughput go no further
            keep = hit.nonzero().squeeze(1)
            idx, keys, prim, t = (x.index_select(0, keep) for x in (idx, keys, prim, t))
            beta, direction = beta.index_select(1, keep), wo.index_select(1, keep)
            position = s.origin.index_select(1, keep) + direction * t
        else:
            beta, prim, t, direction = beta * hit, torch.where(hit, prim, 0), torch.where(hit, t, 1.0), wo
            position = s.origin + direction * t
    return out


def _stack(u: dict[int, torch.Tensor], dims: slice) -> torch.Tensor:
    """The rows of ``u`` for the vertex dimensions ``dims`` (``common.LIGHT``, ``SKY``, ``BSDF``)."""
    return torch.stack([u[d] for d in range(dims.start, dims.stop)])


def _camera_paths(
    ctx: Context, out: torch.Tensor, pixel: torch.Tensor, keys: torch.Tensor, record: str, centre: bool,
    sky: torch.Tensor | None,
) -> tuple[torch.Tensor, ...]:
    """Trace the camera rays, add the light they see directly to ``out``, and return the paths
    that go on: ``idx`` (their columns of ``out``), keys, primitive, distance, direction,
    throughput ``beta (3, n)`` and first-hit position."""
    n_total = pixel.numel()
    jitter = None if centre else uniform(keys, CAMERA_DIMS)
    origin, direction = camera_rays(ctx.camera, pixel % ctx.pixels_per_image, jitter)
    t, prim = ctx.accel.intersect(origin, direction)
    hit = prim >= 0
    if record != "indirect":
        # ---- light seen directly: emitters' front faces and the sky
        if ctx.tables.has_area:
            out[EMISSION] += emitted(ctx, direction, prim)[0]
        if sky is not None:
            out[EMISSION] += sky * ~hit
    if "dead_paths" in ctx.skip:  # camera rays that missed go no further
        idx = hit.nonzero().squeeze(1)
        keys, prim, t = keys.index_select(0, idx), prim.index_select(0, idx), t.index_select(0, idx)
        direction = direction.index_select(1, idx)
        beta = torch.ones(3, idx.numel())
    else:  # ... unless asked: they continue from a placeholder with zero throughput
        idx, beta = torch.arange(n_total), torch.ones(3, n_total) * hit
        prim, t = torch.where(hit, prim, 0), torch.where(hit, t, 1.0)
    return idx, keys, prim, t, direction, beta, origin + direction * t


def _bsdf_light(
    ctx: Context, acc: torch.Tensor, s, beta: torch.Tensor, wo: torch.Tensor, pdf: torch.Tensor, t: torch.Tensor,
    prim: torch.Tensor, live: torch.Tensor, hit: torch.Tensor, sky: torch.Tensor | None,
) -> None:
    """Add to ``acc`` the light the BSDF rays ``wo`` (of pdf ``pdf``) found: emitters they hit and
    the sky they reached, MIS-weighted against light sampling."""
    if ctx.tables.has_area:
        e, rows_l = emitted(ctx, wo, torch.where(live, prim, -1))
        cos_l = (-dot(rows_l[NORMAL], wo)).clamp(min=1e-12)
        t_hit = torch.where(hit, t, 0.0)  # t is +inf on misses
        pdf_light = rows_l[LIGHT_PDF] * t_hit * t_hit / cos_l
        acc += beta * e * _power(pdf, pdf_light)
    if sky is not None:
        miss = live & (prim < 0)
        pdf_sky = dot(s.normal, wo).clamp(min=0.0) * (1.0 / math.pi)
        acc += beta * sky * (_power(pdf, pdf_sky) * miss)


def _needed_dims(ctx: Context, depth: int, trace_on: bool, record_here: bool, has_sky: bool) -> list[int]:
    """Which of a vertex's random dimensions (see ``common.dims``) this vertex uses."""
    need = []
    if record_here and ctx.tables.has_area:
        need += range(LIGHT.start, LIGHT.stop)
    if record_here and has_sky:
        need += range(SKY.start, SKY.stop)
    if trace_on:
        need += range(BSDF.start, BSDF.stop)
        if depth > ctx.roulette_from:
            need.append(ROULETTE)
    return need


def _next_event(
    ctx: Context,
    acc: torch.Tensor,
    s,
    beta: torch.Tensor,
    u: dict[int, torch.Tensor],
    mis: torch.Tensor | None,
    last: bool,
    sky: torch.Tensor | None,
) -> None:
    """Add light sampled at vertices ``s`` to ``acc (3, N)``: emissive triangles, every point
    light, the sky. Weights: MIS (power heuristic) unless ``last``, where ``mis`` (None or a
    bool tensor) says which vertices keep MIS and the rest take weight 1."""
    tables = ctx.tables

    def weight(pdf_light: torch.Tensor, pdf_bsdf: torch.Tensor) -> torch.Tensor:
        if not last:
            return _power(pdf_light, pdf_bsdf)
        if mis is None:
            return torch.ones_like(pdf_light)
        return torch.where(mis, _power(pdf_light, pdf_bsdf), 1.0)

    if tables.has_area:
        point, light = sample_area_light(tables, _stack(u, LIGHT))
        to_light = point - s.position
        dist2 = dot(to_light, to_light)
        inv_dist = torch.rsqrt(dist2)
        wl = to_light * inv_dist
        cos_l = -dot(light[NORMAL], wl)
        f_cos, pdf_bsdf = bsdf_eval(s.glossy, s.albedo, s.alpha, s.normal, s.wi, wl)
        ok = (cos_l > 0) & (f_cos.amax(0) > 0)
        pdf_light = light[LIGHT_PDF] * dist2 / cos_l.clamp(min=1e-12)
        value = beta * f_cos * light[EMISSION_ROWS] * (weight(pdf_light, pdf_bsdf) / pdf_light * ok)
        tmax = torch.where(ok, dist2 * inv_dist * _SHADOW_END, 0.0)
        acc += value * ~ctx.accel.occluded(s.origin, wl, tmax)
    for p in range(tables.points.shape[0]):
        to_light = tables.points[p].reshape(3, 1) - s.position
        dist2 = dot(to_light, to_light)
        inv_dist = torch.rsqrt(dist2)
        wl = to_light * inv_dist
        f_cos, _ = bsdf_eval(s.glossy, s.albedo, s.alpha, s.normal, s.wi, wl)
        ok = f_cos.amax(0) > 0
        value = beta * f_cos * tables.intensities[p].reshape(3, 1) / dist2
        tmax = torch.where(ok, dist2 * inv_dist * _SHADOW_END, 0.0)
        acc += value * ~ctx.accel.occluded(s.origin, wl, tmax)
    if sky is not None:
        wl, pdf_sky = sample_sky(s.normal, _stack(u, SKY))
        f_cos, pdf_bsdf = bsdf_eval(s.glossy, s.albedo, s.alpha, s.normal, s.wi, wl)
        ok = (pdf_sky > 0) & (f_cos.amax(0) > 0)
        value = beta * f_cos * sky * (weight(pdf_sky, pdf_bsdf) / pdf_sky.clamp(min=1e-20) * ok)
        acc += value * ~ctx.accel.occluded(s.origin, wl, torch.where(ok, math.inf, 0.0))
