"""The compiled kernels under autograd: ``torch.autograd.Function``s whose forward and backward
each run through the seam (:func:`~torchgi.backends.base.run`), so a training step runs at the
kernels' pace; traced and exported calls keep the torch code. The guided filter's is
:class:`~torchgi.backends.torch_code.filter_guided.GuidedFunction` (beside the solve it reuses)."""

from __future__ import annotations

from typing import Any

import torch

from torchgi.backends.base import ApplyKernelsGradOp, ApplyKernelsOp, ATrousLevelGradOp, ATrousLevelOp, BoxOp, run
from torchgi.core.check import is_tracing
from torchgi.core.dtypes import compute_dtype

__all__ = ["ATrousLevel", "BoxMean", "KernelApply", "box_adjoint", "box_mean", "window_counts"]


def box_mean(x: torch.Tensor, radius: int) -> torch.Tensor:
    """The ``(2r+1)²`` box mean of ``x (B,C,H,W)`` through the seam (:class:`BoxOp`), summed in the
    compute dtype and cast back, without :func:`torchgi.filters.box`'s argument checks: what the
    back ends hand :mod:`torchgi.light` as its box. Under autograd (not traced) it is
    :class:`BoxMean`: forward and backward each one box through the seam, so the compiled kernels
    run both.

    Example:
        >>> box_mean(torch.arange(3.0).view(1, 1, 1, 3), 1)
        tensor([[[[0.5000, 1.0000, 1.5000]]]])
    """
    y = x.to(compute_dtype(x.dtype))
    if torch.is_grad_enabled() and y.requires_grad and not is_tracing():
        return BoxMean.apply(y, radius).to(x.dtype)
    return run(BoxOp(y, radius)).to(x.dtype)


def window_counts(H: int, W: int, radius: int, like: torch.Tensor) -> torch.Tensor:
    """How many pixels the ``(2r+1)²`` window around each pixel of an ``H x W`` image holds
    (it shrinks at the borders): ``(H, W)``, dtype and device of ``like``.

    Example:
        >>> window_counts(1, 3, 1, torch.ones(1)).tolist()
        [[2.0, 3.0, 2.0]]
    """
    def axis(n: int) -> torch.Tensor:
        j = torch.arange(n, device=like.device)
        return ((j + radius).clamp(max=n - 1) - (j - radius).clamp(min=0) + 1).to(like.dtype)

    return axis(H)[:, None] * axis(W)[None, :]


class BoxMean(torch.autograd.Function):
    """The count-normalised box mean as an autograd function whose backward is a box too:
    ``y_i = (1 / N_i) Σ_{j ∈ w_i} x_j`` gives ``∂L/∂x_j = N_j · mean_{i ∈ w_j}(g_i / N_i)``
    (windows are symmetric), ``N`` the :func:`window_counts`. Both passes go through
    :func:`run` (the compiled kernels for float32), nothing is saved but the radius; the
    backward is itself differentiable (it calls :func:`box_mean`).

    Example:
        >>> x = torch.arange(3.0).view(1, 1, 1, 3).requires_grad_()
        >>> BoxMean.apply(x, 1).sum().backward()
        >>> x.grad   # 1/2 + 1/3, 1/2 + 1/3 + 1/2, 1/3 + 1/2
        tensor([[[[0.8333, 1.3333, 0.8333]]]])
    """

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, radius: int) -> torch.Tensor:
        ctx.radius = radius
        return run(BoxOp(x, radius))

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[torch.Tensor, None]:
        return box_adjoint(g, ctx.radius), None


def box_adjoint(x: torch.Tensor, radius: int, overwrite: bool = False) -> torch.Tensor:
    """The transpose of the count-normalised box mean applied to ``x (B,C,H,W)``: ``N · box(x / N)``
    (:class:`BoxMean`'s backward); ``overwrite``: ``x`` is a stack the caller no longer needs, divided
    in place.

    Example:
        >>> box_adjoint(torch.ones(1, 1, 1, 3), 1).tolist()   # 1/2 + 1/3, 1/2 + 1/3 + 1/2, 1/3 + 1/2
        [[[[0.8333333730697632, 1.3333333730697632, 0.8333333730697632]]]]
    """
    n = window_counts(x.shape[-2], x.shape[-1], radius, x)
    if overwrite:
        return box_mean(x.div_(n), radius).mul_(n)
    return box_mean(x / n, radius) * n


class KernelApply(torch.autograd.Function):
    """Per-pixel kernels applied to ``x`` (:class:`~torchgi.backends.base.ApplyKernelsOp`) as an
    autograd function: the forward and the gradients
    (:class:`~torchgi.backends.base.ApplyKernelsGradOp`) each one op through the seam (the compiled
    kernels for float32 on the CPU); saved: the inputs, the output and the weight sums.

    Example:
        >>> x = torch.rand(1, 2, 5, 5, requires_grad=True)
        >>> w = torch.rand(1, 9, 5, 5, requires_grad=True)
        >>> KernelApply.apply(x, w, 1, True).sum().backward()
        >>> x.grad.shape, w.grad.shape
        (torch.Size([1, 2, 5, 5]), torch.Size([1, 9, 5, 5]))
    """

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, weights: torch.Tensor, dilation: int, normalize: bool) -> torch.Tensor:
        out, den = run(ApplyKernelsOp(x, weights, dilation, normalize))
        ctx.save_for_backward(x, weights, out, den)
        ctx.dilation = dilation
        return out

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        x, w, out, den = ctx.saved_tensors
        dx, dw = run(ApplyKernelsGradOp(x, w, out, den, g.contiguous(), ctx.dilation, ctx.needs_input_grad[0],
                                        ctx.needs_input_grad[1]))
        return dx, dw, None, None


class ATrousLevel(torch.autograd.Function):
    """One À-Trous level (:class:`~torchgi.backends.base.ATrousLevelOp`) as an autograd function:
    the forward and the written-out gradients (:class:`~torchgi.backends.base.ATrousLevelGradOp`)
    each one op through the seam (the compiled kernels for float32 on the CPU). The guides come
    unscaled, ``feat (B, 3G, H, W)`` shared by every level, with the level's multiplier of each
    group ``mult (B, G, 1, 1)`` (the level's ``feat * mult`` is a temporary of the forward and of
    the backward, not kept); saved: the inputs, the output and the weight sums.

    Example:
        >>> c = torch.rand(1, 3, 8, 8, requires_grad=True)
        >>> ATrousLevel.apply(c, None, None, torch.ones(1, 1, 1, 1), 1).sum().backward()
        >>> c.grad.shape
        torch.Size([1, 3, 8, 8])
    """

    @staticmethod
    def _scaled(feat: torch.Tensor | None, mult: torch.Tensor | None) -> torch.Tensor | None:
        return None if feat is None else feat * mult.repeat_interleave(3, dim=1)

    @staticmethod
    def forward(ctx: Any, color: torch.Tensor, feat: torch.Tensor | None, mult: torch.Tensor | None,
                scale: torch.Tensor | None, step: int) -> torch.Tensor:
        out, den = run(ATrousLevelOp(color, ATrousLevel._scaled(feat, mult), scale, step))
        ctx.save_for_backward(color, feat, mult, scale, out, den)
        ctx.step = step
        return out

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        color, feat, mult, scale, out, den = ctx.saved_tensors
        need_feat = feat is not None and (ctx.needs_input_grad[1] or ctx.needs_input_grad[2])
        need_scale = scale is not None and ctx.needs_input_grad[3]
        dc, df, ds = run(ATrousLevelGradOp(color, ATrousLevel._scaled(feat, mult), scale, out, g / den, ctx.step,
                                           need_feat, need_scale))
        if ds is not None and scale.shape[-2:] == (1, 1):
            ds = ds.sum((2, 3), keepdim=True)
        dfeat = dmult = None
        if df is not None:  # feat * mult: each factor's gradient from the other
            dfeat = df * mult.repeat_interleave(3, dim=1) if ctx.needs_input_grad[1] else None
            if ctx.needs_input_grad[2]:
                dmult = (df * feat).sum((2, 3), keepdim=True).unflatten(1, (-1, 3)).sum(2)
                dmult = dmult.sum(0, keepdim=True) if mult.shape[0] == 1 < dmult.shape[0] else dmult
        return dc, dfeat, dmult, ds, None
