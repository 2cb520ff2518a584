"""The dilated 5x5 neighbourhood ("dilated unfold") shared by À-Trous, the bilateral filter
and the adaptive-sampling importance map.

The 25 neighbours are never materialised as a ``(B, 25·C, H, W)`` tensor: callers pad their
buffers once per dilation and walk the taps as shifted *views* of the padded tensor
(``F.unfold`` at 1024x768 needs 2.3 GB and has no ONNX export). Taps that fall outside the
image read the zero padding and are masked by a padded validity plane.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["B3_SPLINE", "Padded", "kernel_5x5"]

# B3-spline generating kernel of the À-Trous transform (Dammertz et al. 2010, eq. 3).
B3_SPLINE = (1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16)


def kernel_5x5() -> list[tuple[int, int, float]]:
    """The 25 taps ``(dy, dx, h)`` of ``h = b ⊗ b``, ``dy, dx in -2..2``; ``h`` sums to 1.

    Example:
        >>> round(sum(h for _, _, h in kernel_5x5()), 12)
        1.0
    """
    return [(dy - 2, dx - 2, B3_SPLINE[dy] * B3_SPLINE[dx]) for dy in range(5) for dx in range(5)]


class Padded:
    """A ``(B, C, H, W)`` tensor padded by ``pad`` zeros on each side, read as shifted views.

    Example:
        >>> x = torch.arange(9.0).view(1, 1, 3, 3)
        >>> Padded(x, 2).at(0, 1)[0, 0, 0].tolist()   # right neighbours of the top row
        [1.0, 2.0, 0.0]
    """

    def __init__(self, x: torch.Tensor, pad: int) -> None:
        self.pad = pad
        self.H, self.W = x.shape[-2], x.shape[-1]
        self.padded = F.pad(x, (pad, pad, pad, pad))

    def at(self, oy: int, ox: int) -> torch.Tensor:
        """The view of the neighbour ``(oy, ox)`` pixels away (``|oy|, |ox| <= pad``), ``(B, C, H, W)``."""
        y0, x0 = self.pad + oy, self.pad + ox
        return self.padded[..., y0 : y0 + self.H, x0 : x0 + self.W]
