"""Batched sample processing (docs/design.md, Sampling): fixed-size batches of samples mapped to their
pixels through the exclusive scan of the per-pixel counts, and a race-free accumulation.

Memory is bounded by the batch size: the sample → pixel map of a batch is found by binary
search in the inclusive scan, never by materialising all samples.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import torch

from torchgi.core.check import check_int, check_shape
from torchgi.core.errors import DTypeError, ShapeError
from torchgi.sampling.allocate import exclusive_scan

__all__ = ["SampleBatch", "accumulate", "sample_batches"]


class SampleBatch(NamedTuple):
    """One batch of samples of image ``image``: flat pixel index and the sample's index within
    its pixel (``0 .. n_p - 1``), both ``(N,)`` int64, pixels in ascending order."""

    image: int
    pixel: torch.Tensor
    sample: torch.Tensor


def sample_batches(counts: torch.Tensor, batch_size: int) -> Iterator[SampleBatch]:
    """Walk all samples of ``counts`` in batches of at most ``batch_size``.

    Args:
        counts: ``(B, 1, H, W)`` integer samples per pixel (e.g. :func:`allocate`).
        batch_size: samples per batch, >= 1.

    Yields:
        :class:`SampleBatch` per batch, image by image; each (pixel, sample) pair appears once.

    Example:
        >>> counts = torch.tensor([[[[2, 0, 1]]]])
        >>> [(b.pixel.tolist(), b.sample.tolist()) for b in sample_batches(counts, 2)]
        [([0, 0], [0, 1]), ([2], [0])]
    """
    check_shape(counts, "B 1 H W", "counts")
    if counts.is_floating_point() or counts.dtype == torch.bool:
        raise DTypeError(f"counts: expected an integer tensor, got {counts.dtype}")
    check_int(batch_size, "batch_size", 1)
    offsets = exclusive_scan(counts).flatten(1)
    ends = offsets + counts.flatten(1).to(torch.int64)  # inclusive scan
    for b in range(counts.shape[0]):
        total = int(ends[b, -1])
        for start in range(0, total, batch_size):
            s = torch.arange(start, min(start + batch_size, total), device=counts.device)
            pixel = torch.searchsorted(ends[b], s, right=True)
            yield SampleBatch(b, pixel, s - offsets[b, pixel])


def accumulate(values: torch.Tensor, pixel: torch.Tensor, num_pixels: int) -> torch.Tensor:
    """Sum per pixel of ``values (N, C)`` whose pixels ``(N,)`` are in ascending order.

    A segmented reduction (``torch.segment_reduce``), not atomics: the same inputs give the
    same bits on every device and run. Differentiable in ``values``.

    Example:
        >>> accumulate(torch.ones(3, 1), torch.tensor([0, 0, 2]), 4).flatten().tolist()
        [2.0, 0.0, 1.0, 0.0]
    """
    check_int(num_pixels, "num_pixels")
    if values.dim() != 2 or pixel.dim() != 1 or values.shape[0] != pixel.shape[0]:
        raise ShapeError(f"values (N, C) and pixel (N,) must match, got {tuple(values.shape)}, {tuple(pixel.shape)}")
    if pixel.numel() and bool((pixel[1:] < pixel[:-1]).any()):
        raise ValueError("pixel: expected ascending pixel indices (as sample_batches yields them)")
    lengths = torch.bincount(pixel, minlength=num_pixels)
    if lengths.numel() > num_pixels:
        raise ValueError(f"pixel: index {int(pixel.max())} is outside num_pixels={num_pixels}")
    return torch.segment_reduce(values, "sum", lengths=lengths, axis=0)
