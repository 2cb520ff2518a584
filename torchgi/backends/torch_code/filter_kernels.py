"""The torch code of per-pixel kernel application (:class:`~torchgi.backends.kernel_ops.ApplyKernelsOp`
and its gradients): the input zero-padded once by ``d (k // 2)`` (:class:`~torchgi.core.taps.Padded`),
each tap a shifted view of it (never a ``(B, k² C, H, W)`` unfold), the mask of taps inside the
image a shifted view of a padded plane of ones. Differentiable, traced and exported as pads,
slices and products."""

from __future__ import annotations

import torch

from torchgi.backends.kernel_ops import ApplyKernelsGradOp, ApplyKernelsOp
from torchgi.core.taps import Padded


def _taps(k: int, d: int) -> list[tuple[int, int]]:
    """The ``(dy, dx)`` offset of each tap ``t = i k + j``."""
    h = k // 2
    return [((i - h) * d, (j - h) * d) for i in range(k) for j in range(k)]


def kernel_apply(x: torch.Tensor, weights: torch.Tensor, dilation: int, normalize: bool
                 ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(out, den)`` of :class:`~torchgi.backends.kernel_ops.ApplyKernelsOp` (differentiable).

    Example:
        >>> x = torch.arange(3.0).view(1, 1, 1, 3)
        >>> w = torch.zeros(1, 9, 1, 3); w[:, 5] = 1.0   # the right neighbour (outside: left out)
        >>> kernel_apply(x, w, 1, False)[0].flatten().tolist()
        [1.0, 2.0, 0.0]
    """
    k = round(weights.shape[1] ** 0.5)
    R = dilation * (k // 2)
    xp = Padded(x, R)
    out = None
    for t, (dy, dx) in enumerate(_taps(k, dilation)):
        term = weights[:, t : t + 1] * xp.at(dy, dx)
        out = term if out is None else out + term
    if not normalize:
        return out, None
    inside = Padded(torch.ones_like(x[:1, :1]), R)
    den = None
    for t, (dy, dx) in enumerate(_taps(k, dilation)):
        term = weights[:, t : t + 1] * inside.at(dy, dx)
        den = term if den is None else den + term
    return out / den, den


def apply_kernels(desc: ApplyKernelsOp) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:class:`~torchgi.backends.kernel_ops.ApplyKernelsOp` in torch: :func:`kernel_apply`.

    Example:
        >>> x, w = torch.ones(1, 2, 4, 4), torch.ones(1, 9, 4, 4)
        >>> apply_kernels(ApplyKernelsOp(x, w, 2, True))[0].unique().tolist()
        [1.0]
    """
    return kernel_apply(desc.x, desc.weights, desc.dilation, desc.normalize)


def apply_kernels_grad(desc: ApplyKernelsGradOp) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """:class:`~torchgi.backends.kernel_ops.ApplyKernelsGradOp` in torch, written out (one shifted
    view per tap; no autograd).

    Example:
        >>> x, w = torch.ones(1, 1, 1, 3), torch.zeros(1, 9, 1, 3); w[:, 4] = 1.0   # the identity
        >>> out, g = x.clone(), torch.tensor([[[[1.0, 2.0, 3.0]]]])
        >>> apply_kernels_grad(ApplyKernelsGradOp(x, w, out, None, g, 1))[0].flatten().tolist()
        [1.0, 2.0, 3.0]
    """
    x, w, d = desc.x, desc.weights, desc.dilation
    k = round(w.shape[1] ** 0.5)
    R = d * (k // 2)
    gp = desc.scaled_grad()
    dx = dw = None
    if desc.need_weights:
        xp = Padded(x, R)
        inside = None if desc.den is None else Padded(torch.ones_like(x[:1, :1]), R)
        planes = []
        for dy, dx_ in _taps(k, d):
            if inside is None:
                planes.append((gp * xp.at(dy, dx_)).sum(1, keepdim=True))
            else:
                planes.append((gp * (xp.at(dy, dx_) - desc.out)).sum(1, keepdim=True) * inside.at(dy, dx_))
        dw = torch.cat(planes, 1)
    if desc.need_x:
        for t, (dy, dx_) in enumerate(_taps(k, d)):
            term = Padded(w[:, t : t + 1] * gp, R).at(-dy, -dx_)
            dx = term if dx is None else dx + term
    return dx, dw
