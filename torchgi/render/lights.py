"""The scene as torch tables, and light sampling: emissive triangles, point lights, the sky.

Emissive triangles are one-sided (they emit towards their face normal) and are chosen with
probability proportional to area x emitted luminance, then sampled uniformly by area.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from torchgi.render.materials import cosine_hemisphere, to_world
from torchgi.render.scene import GLOSSY, SceneArrays

__all__ = [
    "ALBEDO",
    "ALBEDO2",
    "ALPHA",
    "EMISSION",
    "EMITTER_ROWS",
    "GLOSSY_ROW",
    "LIGHT_PDF",
    "NORMAL",
    "TEXTURE",
    "TEXTURE_SCALE",
    "TRI_ROWS",
    "Tables",
    "sample_area_light",
    "sample_sky",
]


# Rows of Tables.tri (per triangle) and Tables.light (per emissive triangle).
# The rows an emitter lookup needs come first, so it can gather ``tri[:EMITTER_ROWS]`` only.
NORMAL, EMISSION, LIGHT_PDF = slice(0, 3), slice(3, 6), 6
EMITTER_ROWS = 7
ALBEDO, ALPHA, GLOSSY_ROW = slice(7, 10), 10, 11
TEXTURE, TEXTURE_SCALE, ALBEDO2 = 12, 13, slice(14, 17)
TRI_ROWS = 17
V0, E1, E2 = slice(17, 20), slice(20, 23), slice(23, 26)


@dataclasses.dataclass(frozen=True)
class Tables:
    """The scene as torch tables laid out for one gather per lookup.

    ``tri (17, T)`` packs, per triangle, the unit face normal (rows 0-2), emission (3-5), the
    area density of light sampling (6, 0 off lights), albedo (7-9), GGX alpha (10), 1.0 if
    glossy (11), the texture's code (12, 0 for none), its scale (13) and second colour (14-16);
    ``light (26, L)`` holds those rows for the emissive triangles plus their first vertex and
    edges (17-25). ``table.index_select(1, idx)`` gives ``(rows, N)``.
    """

    tri: torch.Tensor
    any_glossy: bool
    any_texture: bool
    light: torch.Tensor
    light_cdf: torch.Tensor  # (L,) float32, last = 1 (u < 1 - 2^-25 never passes it)
    light_tris: torch.Tensor  # (L,) triangle index of each light
    points: torch.Tensor  # (P, 3)
    intensities: torch.Tensor  # (P, 3)
    sky: torch.Tensor | None  # (3, 1)
    scale: float

    @property
    def has_area(self) -> bool:
        return self.light_tris.numel() > 0

    @staticmethod
    def from_arrays(a: SceneArrays) -> Tables:
        """Build the tables (CPU, float32) from a scene's flattened arrays."""
        t = torch.from_numpy
        mat = t(a.material)
        glossy = (t(a.kind) == GLOSSY).to(torch.float32)
        tri = torch.cat(
            [
                t(a.normals).T,
                t(a.emission).T[:, mat],
                t(a.light_pdf)[None],
                t(a.albedo).T[:, mat],
                t(a.roughness)[mat][None],
                glossy[mat][None],
                t(a.texture).to(torch.float32)[mat][None],
                t(a.texture_scale)[mat][None],
                t(a.albedo2).T[:, mat],
            ]
        ).contiguous()
        light_tris = t(a.light_tris)
        corners = t(a.triangles)[light_tris]  # (L, 3, 3)
        light = torch.cat(
            [tri[:, light_tris], corners[:, 0].T, (corners[:, 1] - corners[:, 0]).T, (corners[:, 2] - corners[:, 0]).T]
        ).contiguous()
        cdf = torch.cumsum(t(a.light_prob), 0).to(torch.float32)
        if cdf.numel():
            cdf[-1] = 1.0
        return Tables(
            tri=tri,
            any_glossy=bool(glossy.any()),
            any_texture=bool((t(a.texture) > 0).any()),
            light=light,
            light_cdf=cdf,
            light_tris=light_tris,
            points=t(a.points),
            intensities=t(a.intensities),
            sky=None if a.sky is None else t(a.sky).reshape(3, 1),
            scale=a.scale,
        )


def sample_area_light(tables: Tables, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A point on an emissive triangle for each ``u (3, N)``.

    Returns the point ``(3, N)`` and the chosen triangle's ``Tables.light`` rows ``(21, N)``
    (its normal, emission and area density ``LIGHT_PDF`` = probability / area).
    """
    k = torch.searchsorted(tables.light_cdf, u[0], right=True).clamp_(max=tables.light_cdf.numel() - 1)
    rows = tables.light.index_select(1, k)
    su = torch.sqrt(u[1])
    b1 = su * (1.0 - u[2])
    b2 = su * u[2]
    return rows[V0] + rows[E1] * b1 + rows[E2] * b2, rows


def sample_sky(n: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A cosine-weighted direction about ``n (3, N)`` towards the sky and its pdf (solid angle)."""
    local = cosine_hemisphere(u)
    return to_world(local, n), local[2] * (1.0 / math.pi)
