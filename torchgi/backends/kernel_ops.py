"""Per-pixel kernels applied to an image at the back-end seam (:func:`torchgi.filters.apply_kernels`):
the forward (:class:`ApplyKernelsOp`) and its gradients (:class:`ApplyKernelsGradOp`), the
building block of kernel-predicting denoisers. Re-exported by :mod:`torchgi.backends.base`.

Tap ``t = i k + j`` of a ``k x k`` kernel at dilation ``d`` reads the pixel ``(y + (i - k//2) d,
x + (j - k//2) d)``; taps outside the image are left out of the sum (and, normalised, of the
weight sum)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["ApplyKernelsGradOp", "ApplyKernelsOp"]


@dataclass(eq=False, slots=True)
class ApplyKernelsOp:
    """``out = Σ_t weights_t · x(· + o_t)`` for ``x (B,C,H,W)`` and ``weights (B,k²,H,W)`` (one
    float dtype and device), divided by ``den = Σ_t weights_t`` over the taps inside the image when
    ``normalize``. Returns ``(out, den)``: ``den (B,1,H,W)``, or None without ``normalize``."""

    x: torch.Tensor
    weights: torch.Tensor
    dilation: int
    normalize: bool

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.x, self.weights)


@dataclass(eq=False, slots=True)
class ApplyKernelsGradOp:
    """The gradients of :class:`ApplyKernelsOp` for ``grad (B,C,H,W)`` of its output, given its
    inputs, its ``out`` and ``den`` (None without ``normalize``): with ``gp = grad / den`` (or
    ``grad``), ``dweights_t = Σ_c gp_c (x_c(· + o_t) - out_c)`` over the taps inside (``out`` not
    subtracted without ``normalize``; 0 outside) and ``dx_c = Σ_t (weights_t gp_c)(· - o_t)``.
    Returns ``(dx, dweights)``, each None where ``need_x`` / ``need_weights`` is False."""

    x: torch.Tensor
    weights: torch.Tensor
    out: torch.Tensor
    den: torch.Tensor | None
    grad: torch.Tensor
    dilation: int
    need_x: bool = True
    need_weights: bool = True

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.x, self.weights, self.out, self.den, self.grad)
