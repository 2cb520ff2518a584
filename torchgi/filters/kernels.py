"""Per-pixel kernels applied to an image: the building block of kernel-predicting denoisers
(Bako et al. 2017, Vogels et al. 2018), where a network predicts a ``k x k`` kernel for every
pixel and the image is filtered with it, often at several dilations in turn.

Tap ``t = i k + j`` (row-major) of pixel ``(y, x)`` reads ``x`` at ``(y + (i - k//2) d, x + (j -
k//2) d)``; taps outside the image are left out (zero padding, and with ``normalize`` their
weights leave the weight sum too, so a kernel stays normalised at the borders). Computed by
the back end :mod:`torchgi.backends` picks: the C kernels for float32 on the CPU (forward and,
under autograd, the backward: :class:`~torchgi.backends.KernelApply`), else the torch code
(shifted views of one padded input; traced and exported as pads, slices and products).
"""

from __future__ import annotations

import torch
from torch import nn

from torchgi import backends
from torchgi.backends.torch_code.filter_kernels import kernel_apply
from torchgi.core.check import (
    check_int,
    check_same_device,
    check_same_floating,
    check_shape,
    finite_or_sanitized_later,
    is_recording,
    is_tracing,
)
from torchgi.core.dtypes import compute_dtype
from torchgi.core.errors import RangeError, ShapeError

__all__ = ["ApplyKernels", "apply_kernels"]


def apply_kernels(
    x: torch.Tensor, weights: torch.Tensor, *, dilation: int = 1, normalize: bool = False
) -> torch.Tensor:
    """Filter ``x`` with a ``k x k`` kernel per pixel: ``out_p = Σ_t weights_{t,p} x_{p + d o_t}``.

    Args:
        x: ``(B, C, H, W)`` image, finite, any units.
        weights: ``(B, k², H, W)``, ``k`` odd (9, 25, 49 ... taps), same dtype and device as
            ``x``, finite; tap ``t = i k + j`` at offset ``((i - k//2) d, (j - k//2) d)`` pixels.
        dilation: ``d >= 1``, the spacing of the taps in pixels (À-Trous style scales: 1, 2, 4 ...).
        normalize: divide by the sum of the weights of the taps inside the image (a kernel
            needs not sum to 1; e.g. ``exp`` or ``softmax`` outputs). Every pixel's sum must be
            non-zero: a pixel whose sum is 0 raises :class:`~torchgi.core.RangeError`.

    Returns:
        ``(B, C, H, W)`` in the dtype of ``x`` (float16/bfloat16 computed in float32).
        Differentiable with respect to ``x`` and ``weights``.

    Example:
        >>> x = torch.arange(12.0).view(1, 1, 3, 4)
        >>> w = torch.zeros(1, 9, 3, 4); w[:, 4] = 1.0          # the centre tap: the identity
        >>> torch.equal(apply_kernels(x, w), x)
        True
        >>> box = torch.ones(1, 9, 3, 4)                         # a 3x3 mean, shrinking at borders
        >>> apply_kernels(x, box, normalize=True)[0, 0, 0, 0].item()   # (0 + 1 + 4 + 5) / 4
        2.5
    """
    sizes = check_shape(x, "B C H W", "x")
    check_shape(weights, "B K H W", "weights", {"B": sizes["B"], "H": sizes["H"], "W": sizes["W"]})
    check_same_device({"x": x, "weights": weights})
    check_same_floating({"x": x, "weights": weights})
    K = weights.shape[1]
    k = round(K**0.5)
    if k * k != K or k % 2 == 0:
        raise ShapeError(f"weights: expected k² channels for an odd k (9, 25, 49, ...), got {K} "
                         f"(shape {tuple(weights.shape)})")
    check_int(dilation, "dilation", 1)
    if not isinstance(normalize, bool):
        raise RangeError(f"normalize: expected a bool, got {normalize!r}")
    (x, weights), check_finite_inputs = finite_or_sanitized_later({"x": x, "weights": weights}, False)
    ct = compute_dtype(x.dtype)
    xc, wc = x.to(ct), weights.to(ct)
    if is_tracing():
        out = kernel_apply(xc, wc, dilation, normalize)[0]
    elif torch.is_grad_enabled() and (xc.requires_grad or wc.requires_grad):
        out = backends.KernelApply.apply(xc, wc, dilation, normalize)
    else:
        out = backends.run(backends.ApplyKernelsOp(xc, wc, dilation, normalize))[0]
    check_finite_inputs()
    if normalize and not is_recording() and out.numel() and not bool(torch.isfinite(out.detach()).all()):
        raise RangeError("weights: a pixel's weights over the taps inside the image sum to 0 "
                         "(normalize=True divides by that sum)")
    return out.to(x.dtype)


class ApplyKernels(nn.Module):
    """Module form of :func:`apply_kernels` (the weights are an input, e.g. a network's output).

    Args:
        dilation: the taps' spacing in pixels.
        normalize: divide by the weights' sum over the taps inside the image.

    Example:
        >>> f = ApplyKernels(dilation=2, normalize=True)
        >>> f(torch.rand(1, 3, 8, 8), torch.rand(1, 25, 8, 8)).shape
        torch.Size([1, 3, 8, 8])
    """

    def __init__(self, dilation: int = 1, normalize: bool = False) -> None:
        super().__init__()
        check_int(dilation, "dilation", 1)
        self.dilation, self.normalize = dilation, normalize

    def forward(self, x: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        return apply_kernels(x, weights, dilation=self.dilation, normalize=self.normalize)

    def extra_repr(self) -> str:
        return f"dilation={self.dilation}, normalize={self.normalize}"
