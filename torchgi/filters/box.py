"""Box filter (mean over a ``(2r+1)²`` window).

Borders are count-normalised: the window shrinks at the image edge, so the output is the
mean of the pixels that exist. Any ``r >= 0`` works, including ``r`` larger than the image.
Computed by the back end :mod:`torchgi.backends` picks: the C or Triton kernels (sums in
double) for eager float32 calls and the torch code's blocked prefix sums for other eager CPU
calls (cost independent of ``r``), else the torch code's two separable average pools
(differentiable, exported to ONNX as ``AveragePool``: each window summed directly, cost
growing with ``r``).

Precision: sums run along one axis at a time over mean-free data where the caller
centres it (the guided filter does), so float32 keeps ~1e-6 relative accuracy at 4K.
"""

from __future__ import annotations

import torch
from torch import nn

from torchgi import backends
from torchgi.backends.torch_code import PlaneBoxer
from torchgi.core.check import check_finite, check_floating, check_int, check_shape

__all__ = ["Box", "PlaneBoxer", "box"]


def box(x: torch.Tensor, radius: int) -> torch.Tensor:
    """Mean over the ``(2r+1) x (2r+1)`` window around each pixel, count-normalised at borders.

    Args:
        x: ``(B, C, H, W)`` floating tensor, finite.
        radius: window radius ``r >= 0`` in pixels; any size (``r >= H`` averages whole columns).

    Returns:
        ``(B, C, H, W)``, same dtype and device as ``x`` (float16/bfloat16 are summed in float32).
        Cost does not depend on ``radius``.

    Example:
        >>> box(torch.arange(3.0).view(1, 1, 1, 3), 1)
        tensor([[[[0.5000, 1.0000, 1.5000]]]])
    """
    check_shape(x, "B C H W", "x")
    check_floating(x, "x")
    check_finite(x, "x")
    check_int(radius, "radius")
    return backends.box_mean(x, radius)


class Box(nn.Module):
    """Module form of :func:`box`.

    Example:
        >>> Box(2)(torch.ones(1, 1, 4, 4)).sum().item()
        16.0
    """

    def __init__(self, radius: int) -> None:
        super().__init__()
        check_int(radius, "radius")
        self.radius = radius

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return box(x, self.radius)

    def extra_repr(self) -> str:
        return f"radius={self.radius}"
