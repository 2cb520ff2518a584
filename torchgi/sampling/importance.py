"""Sampling importance from the filter's own geometry weights (Bauszat et al. 2011; docs/design.md, Sampling)::

    W_p = Σ_{q ∈ window(p)} G_n(p,q) · G_x(p,q),   W̃_p = W_p / |window(p)|,   q_p = 1 - W̃_p

with ``G_n = exp(-|n_p - n_q|² / σ_n)`` and ``G_x = exp(-|x_p - x_q|² / σ_x)``, the À-Trous
geometry weights at step 1, read through the same shifted-view taps (:mod:`torchgi.core.taps`),
in the back end :mod:`torchgi.backends` picks (eager float32 CPU calls: the C kernel).
"""

from __future__ import annotations

import torch

from torchgi import backends
from torchgi.core.check import (
    check_finite,
    check_int,
    check_positive,
    check_same_device,
    check_same_floating,
    check_shape,
)
from torchgi.core.dtypes import compute_dtype
from torchgi.core.errors import DTypeError, RangeError

__all__ = ["importance_map"]


def importance_map(
    normal: torch.Tensor,
    position: torch.Tensor,
    *,
    window: int = 4,
    sigma_normal: float = 0.1,
    sigma_position: float = 0.1,
    hit: torch.Tensor | None = None,
    fused: bool = False,
) -> torch.Tensor:
    """Per-pixel sampling importance ``q_p in [0, 1]`` from normal and position discontinuities.

    Args:
        normal: ``(B, 3, H, W)`` world-space normals in [-1, 1].
        position: ``(B, 3, H, W)`` world-space positions, scene units (any offset).
        window: window size ``w`` in 2..10 (offsets ``-(w//2) .. (w-1)//2`` in x and y).
        sigma_normal, sigma_position: σ_n (normal distance squared), σ_x (scene units squared).
        hit: ``(B, 1, H, W)`` bool; background pixels get importance 0 and are no neighbours.
        fused: run the taps through ``torch.compile`` (one loop over pixels, several times
            faster than eager; the first call compiles, a few seconds).

    Returns:
        ``(B, 1, H, W)`` importance in [0, 1], dtype of the inputs (float16/bfloat16 computed in
        float32). ``|window(p)|`` counts the taps inside the image (and on geometry), so borders
        are not mistaken for edges.

    Example:
        >>> n = torch.zeros(1, 3, 6, 6); n[:, 2] = 1
        >>> float(importance_map(n, torch.zeros(1, 3, 6, 6)).max())   # flat: nothing to sample
        0.0
    """
    sizes = check_shape(normal, "B 3 H W", "normal")
    check_shape(position, "B 3 H W", "position", sizes)
    if hit is not None:
        check_shape(hit, "B 1 H W", "hit", sizes)
        if hit.dtype != torch.bool:
            raise DTypeError(f"hit: expected a bool tensor, got {hit.dtype}")
    check_same_device({"normal": normal, "position": position, "hit": hit})
    check_same_floating({"normal": normal, "position": position})
    check_int(window, "window", 2)
    if window > 10:
        raise RangeError(f"window: expected 2..10, got {window}")
    check_positive(sigma_normal, "sigma_normal")
    check_positive(sigma_position, "sigma_position")
    check_finite(normal, "normal")
    check_finite(position, "position")
    ct = compute_dtype(normal.dtype)
    op = backends.ImportanceOp(normal.to(ct), position.to(ct), sigma_normal, sigma_position, hit, window, fused)
    return backends.run(op).to(normal.dtype)
