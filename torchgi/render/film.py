"""The film: per-pixel running mean of the radiance rows and the variance of the colour.

Samples reach the film in blocks: each pixel's samples, in sample order, cut into blocks of at
most :data:`BLOCK` samples. A block's sum is a sequential segment reduction and its colour
``M2`` a second pass about the block mean; blocks then merge into the pixel's running
``(n, mean, M2)`` in block order with Chan et al.'s update (Welford's, one block at a time).
Because block boundaries depend only on the sample index, neither the chunk size nor the
worker count changes a bit of the result.
"""

from __future__ import annotations

import torch

__all__ = ["BLOCK", "Film"]

BLOCK = 1024


class Film:
    """Accumulator for ``num_pixels`` pixels and ``rows`` radiance rows (float64).

    Example:
        >>> film = Film(2, rows=3)
        >>> x = torch.tensor([[1.0, 3.0, 5.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
        >>> film.add_blocks(x, pixel=torch.tensor([0, 1]), counts=torch.tensor([2, 1]), color_rows=slice(0, 3))
        >>> film.mean[0].tolist(), film.m2[0].tolist()
        ([2.0, 5.0], [2.0, 0.0])
    """

    def __init__(self, num_pixels: int, rows: int = 9) -> None:
        self.n = torch.zeros(num_pixels, dtype=torch.float64)
        self.mean = torch.zeros(rows, num_pixels, dtype=torch.float64)
        self.m2 = torch.zeros(3, num_pixels, dtype=torch.float64)

    def add_blocks(
        self, values: torch.Tensor, pixel: torch.Tensor, counts: torch.Tensor, color_rows: slice | None
    ) -> None:
        """Merge consecutive blocks of samples.

        Args:
            values: ``(rows, S)`` samples, block after block, each block's in sample order.
            pixel: ``(K,)`` the pixel (index into this film) of each block; a pixel's blocks
                appear in sample order.
            counts: ``(K,)`` samples per block (> 0), summing to ``S``.
            color_rows: the rows whose sum is the colour (its variance is tracked), or None.
        """
        nb = counts.to(torch.float64)
        size = int(counts[0]) if counts.numel() else 0
        if counts.numel() and bool((counts == size).all()):
            # Equal blocks (a uniform spp): a reshape, no segment bookkeeping.
            rows = values.view(values.shape[0], -1, size)
            block_mean = rows.sum(2, dtype=torch.float64) / nb
            if color_rows is not None:
                dev = rows[color_rows] - block_mean[color_rows].unsqueeze(2)
                block_m2 = (dev * dev).sum(2)
        else:
            x = values.to(torch.float64)
            block_mean = torch.segment_reduce(x.T, "sum", lengths=counts, axis=0).T / nb  # (rows, K)
            if color_rows is not None:
                dev = x[color_rows] - block_mean[color_rows].repeat_interleave(counts, dim=1)
                block_m2 = torch.segment_reduce((dev * dev).T, "sum", lengths=counts, axis=0).T
        if color_rows is None:
            block_m2 = torch.zeros(3, counts.numel(), dtype=torch.float64)
        # Blocks of one pixel merge one after another: round r takes each pixel's r-th block.
        first = torch.ones_like(pixel, dtype=torch.bool)
        first[1:] = pixel[1:] != pixel[:-1]
        start = torch.cummax(torch.where(first, torch.arange(pixel.numel()), 0), 0).values
        rank = torch.arange(pixel.numel()) - start
        for r in range(int(rank.max()) + 1 if rank.numel() else 0):
            sel = (rank == r).nonzero().squeeze(1)
            p = pixel.index_select(0, sel)
            na, nb_r = self.n.index_select(0, p), nb.index_select(0, sel)
            n = na + nb_r
            mean = self.mean.index_select(1, p)
            delta = block_mean.index_select(1, sel) - mean
            self.mean.index_copy_(1, p, mean + delta * (nb_r / n))
            if color_rows is not None:
                dc = delta[color_rows]
                m2 = self.m2.index_select(1, p) + block_m2.index_select(1, sel) + dc * dc * (na * nb_r / n)
                self.m2.index_copy_(1, p, m2)
            self.n.index_copy_(0, p, n)

    def variance_of_mean(self) -> torch.Tensor:
        """``(3, P)`` sample variance of the colour divided by n (0 where n < 2)."""
        n = self.n
        return torch.where(n > 1, self.m2 / (n * (n - 1)).clamp(min=1), 0.0)
