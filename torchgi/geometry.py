"""Screen-space geometry of a frame's guides that both the Denoiser and adaptive sampling read:
the world-space footprint of a pixel and the one default rule for the À-Trous / importance
position σ_x when the scene's units are unknown. Imports nothing of torchgi above
:mod:`torchgi.core`.
"""

from __future__ import annotations

import torch

from torchgi.core.check import check_positive

__all__ = ["pixel_footprint", "sigma_position_rule"]


def pixel_footprint(position: torch.Tensor, hit: torch.Tensor) -> float:
    """Median world-space distance between horizontally adjacent pixels on geometry (scene
    units; 1.0 when it is 0): the scale for ``sigma_position`` when the scene's units are unknown.

    Example:
        >>> x = torch.arange(8.0).expand(1, 1, 4, 8) * 0.5
        >>> pixel_footprint(torch.cat([x, 0 * x, 0 * x], 1), torch.ones(1, 1, 4, 8, dtype=torch.bool))
        0.5
    """
    d = torch.linalg.vector_norm(position[..., 1:] - position[..., :-1], dim=1)
    both = (hit[..., 1:] & hit[..., :-1])[:, 0]
    median = float(d[both].median()) if bool(both.any()) else 0.0
    return median if median > 0 else 1.0  # no geometry or no spread: any scale will do


def sigma_position_rule(position: torch.Tensor, hit: torch.Tensor, footprints: float) -> float:
    """The one default rule for σ_x when the scene's units are unknown: ``(footprints x
    pixel_footprint)²``, in scene units squared (a position difference of ``footprints`` pixels
    weighs ``exp(-1)``). The Denoiser's À-Trous uses 4 footprints, the importance map 2.

    Example:
        >>> x = torch.arange(8.0).expand(1, 1, 4, 8) * 0.5
        >>> sigma_position_rule(torch.cat([x, 0 * x, 0 * x], 1), torch.ones(1, 1, 4, 8, dtype=torch.bool), 4)
        4.0
    """
    check_positive(footprints, "footprints")
    return (footprints * pixel_footprint(position, hit)) ** 2
