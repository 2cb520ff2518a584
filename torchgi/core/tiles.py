"""Overlapping tiles under a memory budget: how the Denoiser runs large images in bounded memory
(``Denoiser(max_memory_mb=...)``, docs/pipeline.md): the side a budget allows
(:func:`tile_side`), the tiles with their cores (:func:`tiles`) and a pipeline run over them and
stitched (:func:`tiled`); the tile bytes of the guided pipeline (:func:`guided_bytes`) and the
default budget (:func:`auto_budget`) and the check of a given one (:func:`check_budget`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import torch

__all__ = ["auto_budget", "check_budget", "guided_bytes", "tile_side", "tiled", "tiles"]


def tile_side(color: torch.Tensor, max_memory_mb: float, per_pixel: float, halo: int, s: int) -> int:
    """The side (px, a multiple of ``s``) of square tiles with ``halo`` px of overlap whose planes
    (``per_pixel`` bytes per pixel of a tile) fit within ``max_memory_mb`` beyond the inputs
    beside the ``(B, 3, H, W)`` output of ``color``'s size; raises naming ``max_memory_mb`` when
    no tile of 16 px or more fits."""
    out_bytes = color.numel() * color.element_size()
    budget = 0.9 * max_memory_mb * 2**20 - out_bytes  # 10 % for what the estimate misses
    side = (math.isqrt(int(max(budget, 0) / per_pixel)) - 2 * halo) // s * s
    if side < max(s, 16):
        need = (out_bytes + per_pixel * (max(s, 16) + 2 * halo) ** 2) / 0.9 / 2**20
        raise ValueError(f"max_memory_mb: {max_memory_mb} MB cannot hold the output and a tile of this "
                         f"{color.shape[-2]}x{color.shape[-1]} image; at least {math.ceil(need)} MB")
    return side


def tiles(H: int, W: int, side: int, halo: int, s: int = 1) -> Iterator[tuple[slice, slice, slice, slice, slice, slice]]:
    """Tiles of at most ``side x side`` px over ``H x W``, as even as multiples of ``s`` allow, with
    ``halo`` px of the image around each: ``(rows, cols)`` of the tile with its halo,
    ``(core_rows, core_cols)`` of its core within that, ``(out_rows, out_cols)`` of the core in
    the image."""
    even = lambda n: -(-n // -(-n // side) // s) * s  # n px in the fewest tiles of <= side, evened out
    th, tw = even(H), even(W)
    for y0 in range(0, H, th):
        for x0 in range(0, W, tw):
            rows = slice(max(0, y0 - halo), min(H, y0 + th + halo))
            cols = slice(max(0, x0 - halo), min(W, x0 + tw + halo))
            h, w = min(th, H - y0), min(tw, W - x0)
            yield (rows, cols, slice(y0 - rows.start, y0 - rows.start + h), slice(x0 - cols.start, x0 - cols.start + w),
                   slice(y0, y0 + h), slice(x0, x0 + w))


def check_budget(max_memory_mb: Any, method: str, tiled: tuple[str, ...]) -> None:
    """Raise naming ``max_memory_mb`` unless it is a finite number of MB > 0 (for a ``method`` of
    ``tiled`` only), "auto" or None.

    Example:
        >>> check_budget(800, "pyramid", ("guided", "pyramid"))
    """
    if max_memory_mb is None or (isinstance(max_memory_mb, str) and max_memory_mb == "auto"):
        return
    if isinstance(max_memory_mb, bool) or not isinstance(max_memory_mb, (int, float)) or not 0 < max_memory_mb < math.inf:
        raise ValueError(f"max_memory_mb: expected a finite number of MB > 0, 'auto' or None for no limit; "
                         f"got {max_memory_mb!r}")
    if method not in tiled:
        raise ValueError(f"max_memory_mb: tiles are implemented for methods {', '.join(map(repr, tiled))} only, "
                         f"not {method!r}")


def auto_budget(color: torch.Tensor, inputs: int, per_pixel: float, from_mb: float, times: float,
                floor_mb: float) -> float | None:
    """``max_memory_mb="auto"``: None (untiled) where the whole image's estimate - ``per_pixel``
    bytes per pixel of a tile over it and the ``(B, 3, H, W)`` output of ``color``'s size - is at
    most ``from_mb``; above, the budget (MB) of its tiles: ``times`` x the ``inputs`` (bytes), at
    least ``floor_mb``.

    Example:
        >>> auto_budget(torch.zeros(1, 3, 2160, 3840), 411 * 2**20, 480, 2048, 2.0, 512)
        822.0
    """
    whole = (per_pixel * color.shape[-2] * color.shape[-1] + color.numel() * color.element_size()) / 2**20
    return None if whole <= from_mb else max(times * inputs / 2**20, floor_mb)


def guided_bytes(B: int, kept: bool, back_off: bool, candidates: int = 1) -> int:
    """Bytes per pixel that a tile of the guided pipeline holds (``B`` images): copies of its inputs
    and the pipeline's planes, about ``4 (B (19 + 3 kept) + 22)`` (the C back end's;
    docs/pipeline.md), with a variance (``back_off``) the back-off's residual, sums and weights:
    ``4 x 16 B`` more, and with ``candidates`` > 1 radii their outputs and
    :func:`torchgi.light.choose`'s planes: ``4 x (9 candidates + 5) B``.

    Example:
        >>> guided_bytes(1, False, False)
        164
    """
    return 4 * (B * (19 + 3 * kept + 16 * back_off + (9 * candidates + 5) * (candidates > 1)) + 22)


def tiled(op: Callable[..., torch.Tensor], color: torch.Tensor, max_memory_mb: float, halo: int, s: int,
          per_pixel: float) -> torch.Tensor:
    """``op(rows, cols)`` over square tiles (side a multiple of ``s``, so that the s x s blocks
    are the untiled ones) with ``halo`` px of overlap, a tile's ``per_pixel`` bytes per pixel
    (:func:`guided_bytes`) within ``max_memory_mb`` beyond the inputs with the ``(B, 3, H, W)``
    output; stitched."""
    H, W = color.shape[-2:]
    out = torch.empty_like(color)
    side = tile_side(color, max_memory_mb, per_pixel, halo, s)
    for rows, cols, core_rows, core_cols, out_rows, out_cols in tiles(H, W, side, halo, s):
        tile = op(rows, cols)
        out[..., out_rows, out_cols] = tile[..., core_rows, core_cols]
        del tile
    return out
