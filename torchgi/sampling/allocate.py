"""A fixed sample budget apportioned by importance (docs/design.md, Sampling), and its exclusive scan::

    n_p = minSamples + floor(q_p / Q · s),   s = S - minSamples · numPixels,   Q = Σ q_p

then the remainders go to the largest fractional parts (Hamilton's method), so the total is
exactly ``S`` — the paper drops them. Ties are broken by pixel index, so the result is
deterministic. Computed in the back end :mod:`torchgi.backends` picks (on the CPU the C kernel:
the same arithmetic, the remainders ranked by buckets instead of ``kthvalue``).
"""

from __future__ import annotations

import torch

from torchgi import backends
from torchgi.core.check import check_finite, check_floating, check_int, check_range, check_shape
from torchgi.core.errors import DTypeError, RangeError

__all__ = ["allocate", "exclusive_scan"]

# the largest budget per image whose float64 shares stay exact integers (2^52)
MAX_BUDGET = 2**52


def allocate(
    importance: torch.Tensor, budget: int, *, min_samples: int = 1, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Integer samples per pixel that sum to ``budget`` in every image, in proportion to importance.

    Args:
        importance: ``(B, 1, H, W)`` finite values >= 0 (e.g. :func:`importance_map`).
        budget: samples per image ``S``; at least ``min_samples ·`` (eligible pixels), at most 2^52.
        min_samples: samples every eligible pixel gets first.
        mask: ``(B, 1, H, W)`` bool, pixels that may be sampled (e.g. ``gb.hit``); the others
            get 0. Default: every pixel.

    Returns:
        ``(B, 1, H, W)`` int64 counts; ``|n_p - (min + q_p / Q · s)| < 1`` for every pixel. With
        ``Q = 0`` the spare samples are spread evenly.

    Example:
        >>> q = torch.tensor([[[[0.0, 1.0, 3.0]]]])
        >>> allocate(q, 7, min_samples=1)[0, 0, 0].tolist()
        [1, 2, 4]
    """
    check_shape(importance, "B 1 H W", "importance")
    check_floating(importance, "importance")
    check_finite(importance, "importance")
    check_range(importance, "importance", 0.0)
    check_int(budget, "budget")
    if budget > MAX_BUDGET:
        raise RangeError(f"budget: expected at most 2**52 samples per image, got {budget}")
    check_int(min_samples, "min_samples")
    B = importance.shape[0]
    q = importance.flatten(1)
    eligible = None
    if mask is not None:
        check_shape(mask, "B 1 H W", "mask", {"B": B, "H": importance.shape[2], "W": importance.shape[3]})
        if mask.dtype != torch.bool:
            raise DTypeError(f"mask: expected a bool tensor, got {mask.dtype}")
        eligible = mask.flatten(1)
    n_eligible = eligible.sum(1) if eligible is not None else torch.full((B,), q.shape[1], dtype=torch.int64, device=q.device)
    need = int(n_eligible.max()) * min_samples
    if budget < need:
        raise RangeError(
            f"budget: {budget} samples cannot give min_samples={min_samples} to {int(n_eligible.max())} pixels "
            f"(needs at least {need})"
        )
    return backends.run(backends.AllocateOp(q, eligible, n_eligible, budget, min_samples)).view_as(importance)


def exclusive_scan(counts: torch.Tensor) -> torch.Tensor:
    """Offsets of each pixel's first sample within its image: ``cumsum - counts``.

    Args:
        counts: ``(B, 1, H, W)`` integer samples per pixel.

    Returns:
        ``(B, 1, H, W)`` int64 offsets in row-major pixel order.

    Example:
        >>> exclusive_scan(torch.tensor([[[[2, 0, 3]]]]))[0, 0, 0].tolist()
        [0, 2, 2]
    """
    check_shape(counts, "B 1 H W", "counts")
    if counts.is_floating_point() or counts.dtype == torch.bool:
        raise DTypeError(f"counts: expected an integer tensor, got {counts.dtype}")
    flat = counts.flatten(1).to(torch.int64)
    return (flat.cumsum(1) - flat).view_as(counts)
