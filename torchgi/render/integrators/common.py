"""What both integrators share: the render context, surface lookups, the guide pass, and the
layout of the radiance rows and random-number dimensions."""

from __future__ import annotations

import dataclasses

import torch

from torchgi.render.accel import Accel, offset
from torchgi.render.camera import camera_rays
from torchgi.render.lights import (
    ALBEDO,
    ALBEDO2,
    ALPHA,
    EMITTER_ROWS,
    GLOSSY_ROW,
    NORMAL,
    TEXTURE,
    TEXTURE_SCALE,
    Tables,
)
from torchgi.render.lights import EMISSION as EMISSION_ROWS
from torchgi.render.materials import dot
from torchgi.render.scene import Camera
from torchgi.render.textures import textured_albedo

__all__ = [
    "BSDF",
    "CAMERA_DIMS",
    "DIRECT",
    "EMISSION",
    "INDIRECT",
    "LIGHT",
    "ROULETTE",
    "RR_START",
    "SKIPS",
    "SKY",
    "Context",
    "Surface",
    "dims",
    "emitted",
    "guides",
    "surface",
]

# Rows of an integrator's (9, N) output.
EMISSION, DIRECT, INDIRECT = slice(0, 3), slice(3, 6), slice(6, 9)
CAMERA_DIMS = [0, 1]  # the pixel jitter
# A path vertex's random dimensions, as offsets into its block of _PER_VERTEX (pbrt's fixed
# Get1D/Get2D order: a sample's dimensions mean the same whatever else the path does)
LIGHT = slice(0, 3)  # light choice, then the point on it (2D)
SKY = slice(3, 5)  # sky direction
BSDF = slice(5, 7)  # BSDF direction
ROULETTE = 7  # Russian roulette
_PER_VERTEX = 8
RR_START = 3  # Russian roulette only past this many bounces (Context.roulette_from)

# Work the fast integrator leaves out when a scene does not need it (docs/design.md, Skips):
SKIPS = {
    "absent_lights": "no sampling of light types the scene lacks",
    "dead_paths": "no rays from paths that missed, died in Russian roulette or carry no throughput",
    "last_vertex_rays": "no BSDF ray from a diffuse last vertex (so none at all at bounces=0)",
}


def dims(depth: int) -> list[int]:
    """Random-number dimensions of path vertex ``depth`` (1 = first hit), indexed by
    :data:`LIGHT`, :data:`SKY`, :data:`BSDF`, :data:`ROULETTE`.

    Example:
        >>> dims(2)[BSDF], dims(2)[ROULETTE]
        ([15, 16], 17)
    """
    base = 2 + _PER_VERTEX * (depth - 1)
    return list(range(base, base + _PER_VERTEX))


@dataclasses.dataclass
class Context:
    """Everything an integrator reads: the scene tables, its BVH, the camera and settings."""

    tables: Tables
    accel: Accel
    camera: Camera
    bounces: int
    seed: int
    skip: frozenset[str] = frozenset()  # which of SKIPS are on (docs/design.md, Skips)
    roulette_from: int = RR_START  # bounces after which Russian roulette may end a path

    @property
    def pixels_per_image(self) -> int:
        width, height = self.camera.resolution
        return width * height


@dataclasses.dataclass
class Surface:
    """A path vertex: position, normal flipped towards ``wi``, material data."""

    position: torch.Tensor  # (3, N) on the surface
    origin: torch.Tensor  # (3, N) pushed off along the normal, for rays that leave it
    normal: torch.Tensor  # (3, N) facing wi
    wi: torch.Tensor  # (3, N) towards the previous vertex
    albedo: torch.Tensor  # (3, N)
    alpha: torch.Tensor  # (N,)
    glossy: torch.Tensor | None  # (N,) bool, None if the scene has no glossy material


def surface(ctx: Context, position: torch.Tensor, direction: torch.Tensor, prim: torch.Tensor) -> Surface:
    """Look up the vertex where rays along ``direction`` hit triangles ``prim`` (all hits)."""
    rows = ctx.tables.tri.index_select(1, prim)
    ng = rows[NORMAL]
    wi = -direction
    n = torch.where(dot(ng, wi) < 0, -ng, ng)
    return Surface(
        position=position,
        origin=offset(position, n, ctx.tables.scale),
        normal=n,
        wi=wi,
        albedo=rows[ALBEDO] if not ctx.tables.any_texture else textured_albedo(
            rows[ALBEDO], rows[ALBEDO2], rows[TEXTURE].to(torch.int64), rows[TEXTURE_SCALE], position),
        alpha=rows[ALPHA],
        glossy=rows[GLOSSY_ROW] > 0 if ctx.tables.any_glossy else None,
    )


def emitted(ctx: Context, direction: torch.Tensor, prim: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Radiance ``(3, N)`` met along ``direction`` at triangles ``prim`` (-1 = miss): the
    emission where the ray meets an emitter's front face, else 0; and the triangles'
    first ``EMITTER_ROWS`` rows of ``Tables.tri`` (triangle 0's on misses)."""
    hit = prim >= 0
    rows = ctx.tables.tri[:EMITTER_ROWS].index_select(1, torch.where(hit, prim, 0))
    front = (dot(rows[NORMAL], direction) < 0) & hit
    return rows[EMISSION_ROWS] * front, rows


def guides(ctx: Context, pixel: torch.Tensor, jitter: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """First-hit guides of camera rays through ``pixel (N,)`` (index within one image) at
    ``jitter (2, N)`` in the pixel (None: its centre).

    Returns ``albedo, normal, position (3, N)``, ``depth (1, N)`` (distance along the ray, 0 on
    a miss) and ``hit (1, N)``; the normal faces the camera, everything is 0 on a miss.
    """
    origin, direction = camera_rays(ctx.camera, pixel, jitter)
    t, prim = ctx.accel.intersect(origin, direction)
    hit = prim >= 0
    t = torch.where(hit, t, 0.0)
    s = surface(ctx, origin + direction * t, direction, prim.clamp(min=0))
    return {
        "albedo": s.albedo * hit,
        "normal": s.normal * hit,
        "position": s.position * hit,
        "depth": t[None],
        "hit": hit[None],
    }


def through_mirrors(ctx: Context, pixel: torch.Tensor, max_roughness: float,
                    bounces: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The albedo and normal ``(3, N)`` of the first non-specular hit of camera rays through
    ``pixel (N,)``'s centre: where a ray meets a glossy surface of roughness below
    ``max_roughness`` it follows the mirror reflection, up to ``bounces`` times, as Intel Open
    Image Denoise asks of its guides on mirrors. Also ``(N,)`` bool: where a reflection met a
    surface (elsewhere - no mirror, or a mirror that shows the background - the first hit's
    guides stand).
    """
    albedo, normal = torch.zeros(3, pixel.numel()), torch.zeros(3, pixel.numel())
    found = torch.zeros(pixel.numel(), dtype=torch.bool)  # rays that followed a mirror to a surface that is not one
    if not ctx.tables.any_glossy:  # no glossy material: no mirror, nothing to trace
        return albedo, normal, found
    origin, direction = camera_rays(ctx.camera, pixel, None)
    t, prim = ctx.accel.intersect(origin, direction)
    moved = torch.zeros_like(found)  # rays that followed a mirror
    live = prim >= 0
    for _ in range(bounces + 1):
        s = surface(ctx, origin + direction * torch.where(live, t, 0.0), direction, prim.clamp(min=0))
        mirror = live & s.glossy & (s.alpha < max_roughness)
        met = live & ~mirror & moved
        albedo = torch.where(met, s.albedo, albedo)
        normal = torch.where(met, s.normal, normal)
        found |= met
        if not bool(mirror.any()):
            break
        direction = torch.where(mirror, direction - 2 * dot(direction, s.normal) * s.normal, direction)
        origin = torch.where(mirror, s.origin, origin)
        t, prim = ctx.accel.intersect(origin, direction)
        moved |= mirror
        live = mirror & (prim >= 0)
    return albedo, normal, found
