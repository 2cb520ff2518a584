"""Solid albedo textures: :class:`Texture` (a material's ``texture``) and the maths both
tracers evaluate at a hit point (``tracer.c`` computes the same bit for bit: its
``lattice_hash`` and ``texture_weight``)."""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from torchgi.core.errors import ConfigError
from torchgi.render.values import _no_unknown_keys, _number, _vec3

__all__ = ["TEXTURES", "Texture", "lattice_hash", "texture_weight", "textured_albedo"]


TEXTURES = ("checker", "stripes", "noise")  # Texture.kind; their codes in SceneArrays.texture are 1, 2, 3


@dataclasses.dataclass(frozen=True)
class Texture:
    """A solid (3D, world-space) albedo texture: the albedo at a point ``p`` (scene units) is
    ``albedo + t (albedo2 - albedo)`` with ``t`` in [0, 1] from the pattern at ``scale * p``:

    * ``checker``: ``t = (floor(x) + floor(y) + floor(z)) mod 2`` (cells of side 1 / ``scale``);
    * ``stripes``: ``t = floor(x + z) mod 2`` (slabs across the x + z direction);
    * ``noise``: value noise, ``t`` interpolated (smoothstep, trilinear) between random values
      at the integer lattice (a 32-bit integer hash of the lattice point, the same in the torch
      and C tracers: :func:`texture_weight`).

    Solid textures need no UV coordinates, so any mesh takes one; they are fixed in the world
    (a moving mesh slides through its texture).

    Args:
        kind: one of :data:`TEXTURES`.
        albedo2: the second colour, each channel in [0, 1].
        scale: pattern frequency, cells per scene unit, > 0.

    Example:
        >>> Texture("checker", (0.1, 0.1, 0.1), 4.0).kind
        'checker'
    """

    kind: str
    albedo2: tuple[float, float, float] = (0.1, 0.1, 0.1)
    scale: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in TEXTURES:
            raise ConfigError(f"material.texture.type: expected one of {', '.join(TEXTURES)}, got {self.kind!r}")
        albedo2 = _vec3(self.albedo2, "material.texture.albedo2", low=0.0)
        if max(albedo2) > 1:
            raise ConfigError(f"material.texture.albedo2: expected values in [0, 1], got {self.albedo2!r}")
        object.__setattr__(self, "albedo2", albedo2)
        object.__setattr__(self, "scale", _number(self.scale, "material.texture.scale", 0.0, None))

    @property
    def code(self) -> int:
        """The kind's code in :attr:`SceneArrays.texture` (0 is "no texture")."""
        return TEXTURES.index(self.kind) + 1


def _texture(cfg: Any) -> Texture | None:
    """A material's ``texture`` key: None, a :class:`Texture`, or a mapping
    ``{type, albedo2, scale}`` (errors name the key)."""
    if cfg is None or isinstance(cfg, Texture):
        return cfg
    _no_unknown_keys(cfg, "material.texture", ("type", "albedo2", "scale"))
    if "type" not in cfg:
        raise ConfigError(f"material.texture.type: required, one of {', '.join(TEXTURES)}")
    return Texture(cfg["type"], cfg.get("albedo2", (0.1, 0.1, 0.1)), cfg.get("scale", 1.0))


_MASK32 = 0xFFFFFFFF


def _mix32(h: torch.Tensor) -> torch.Tensor:
    """The finaliser of :func:`lattice_hash` on int64 tensors holding 32-bit values."""
    h = h ^ (h >> 16)
    h = (h * 0x7FEB352D) & _MASK32
    h = h ^ (h >> 15)
    h = (h * 0x846CA68B) & _MASK32
    return h ^ (h >> 16)


def lattice_hash(i: torch.Tensor, j: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """A value in [0, 1) for each integer lattice point ``(i, j, k)`` (int64 tensors of one
    shape), from a 32-bit integer hash that ``tracer.c``'s ``lattice_hash`` computes bit for bit.

    Example:
        >>> z = torch.zeros(1, dtype=torch.int64)
        >>> float(lattice_hash(z, z, z)) == float(lattice_hash(z, z, z)) and 0 <= float(lattice_hash(z, z + 1, z)) < 1
        True
    """
    h = ((i * 0x8DA6B343) ^ (j * 0xD8163841) ^ (k * 0xCB1AB31F)) & _MASK32
    return (_mix32(h) >> 8).to(torch.float32) * (1.0 / 16777216.0)


def texture_weight(code: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """The weight ``t (N,)`` in [0, 1] of a :class:`~torchgi.render.scene.Texture`'s second
    colour at scaled points ``p (3, N)`` (the hit point times the texture's scale), for texture
    codes ``code (N,)`` (1 checker, 2 stripes, 3 value noise; 0: no texture, ``t = 0``).

    Example:
        >>> p = torch.tensor([[0.5, 1.5], [0.5, 0.5], [0.5, 0.5]])
        >>> texture_weight(torch.tensor([1, 1]), p).tolist()   # neighbouring checker cells
        [0.0, 1.0]
    """
    f = torch.floor(p)
    cell = f.to(torch.int64)
    checker = ((cell[0] + cell[1] + cell[2]) & 1).to(torch.float32)
    stripes = (torch.floor(p[0] + p[2]).to(torch.int64) & 1).to(torch.float32)
    x = p - f
    w = x * x * (3.0 - 2.0 * x)  # smoothstep
    noise = torch.zeros_like(p[0])
    for corner in range(8):
        d = [(corner >> axis) & 1 for axis in range(3)]
        weight = torch.ones_like(p[0])
        for axis in range(3):
            weight = weight * (w[axis] if d[axis] else 1.0 - w[axis])
        noise = noise + weight * lattice_hash(cell[0] + d[0], cell[1] + d[1], cell[2] + d[2])
    return torch.where(code == 1, checker, torch.where(code == 2, stripes, torch.where(code == 3, noise, 0.0)))


def textured_albedo(
    albedo: torch.Tensor, albedo2: torch.Tensor, code: torch.Tensor, scale: torch.Tensor, position: torch.Tensor
) -> torch.Tensor:
    """The albedo ``(3, N)`` at world ``position (3, N)``: ``albedo + t (albedo2 - albedo)`` with
    ``t = texture_weight(code, scale * position)`` (``albedo`` itself where ``code`` is 0).

    Example:
        >>> a, b = torch.full((3, 1), 0.8), torch.full((3, 1), 0.2)
        >>> textured_albedo(a, b, torch.tensor([1]), torch.tensor([2.0]), torch.full((3, 1), 0.75))[:, 0]
        tensor([0.2000, 0.2000, 0.2000])
    """
    t = texture_weight(code, position * scale)
    return albedo + t * (albedo2 - albedo)
