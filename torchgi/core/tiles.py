"""Overlapping tiles under a memory budget: how the Denoiser runs large images in bounded memory
(``Denoiser(max_memory_mb=...)``, docs/pipeline.md): the side a budget allows
(:func:`tile_side`), the tiles with their cores (:func:`tiles`) and a pipeline run over them and
stitched (:func:`tiled`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import torch

__all__ = ["tile_side", "tiled", "tiles"]


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


def tiled(op: Callable[..., torch.Tensor], color: torch.Tensor, max_memory_mb: float, halo: int, s: int,
           kept: bool, back_off: bool, candidates: int = 1) -> torch.Tensor:
    """``op(rows, cols)`` over square tiles (side a multiple of ``s``, so that the s x s blocks
    are the untiled ones) with ``halo`` px of overlap, the memory a tile needs within
    ``max_memory_mb`` beyond the inputs with the ``(B, 3, H, W)`` output; stitched. A tile
    holds copies of its inputs and the pipeline's planes: about ``4 (B (19 + 3 kept) + 22)``
    bytes per pixel (the C back end's; docs/pipeline.md), with a variance (``back_off``) the
    back-off's residual, sums and weights: ``4 x 16 B`` more, and with ``candidates`` > 1 radii
    their outputs and :func:`torchgi.light.choose`'s planes: ``4 x (9 candidates + 5) B``."""
    B, _, H, W = color.shape
    out = torch.empty_like(color)
    per_pixel = 4 * (B * (19 + 3 * kept + 16 * back_off + (9 * candidates + 5) * (candidates > 1)) + 22)
    side = tile_side(color, max_memory_mb, per_pixel, halo, s)
    for rows, cols, core_rows, core_cols, out_rows, out_cols in tiles(H, W, side, halo, s):
        tile = op(rows, cols)
        out[..., out_rows, out_cols] = tile[..., core_rows, core_cols]
        del tile
    return out
