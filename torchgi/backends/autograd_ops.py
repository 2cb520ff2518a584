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
    as the caller holds them, ``guide0``, ``guide1`` ``(B, 3, H, W)`` or None, shared by every
    level, with the level's multiplier of each present guide ``mult (B|1, G, 1, 1)`` (the
    kernels weigh guide ``g``'s squared distance by ``mult_g²``: no scaled copy of the guides is
    kept); ``last``: the last level, whose output comes contiguous (the others in the back end's
    own layout, which the next level reads as it is); saved: the inputs, the output and the
    weight sums.

    Example:
        >>> c = torch.rand(1, 3, 8, 8, requires_grad=True)
        >>> ATrousLevel.apply(c, None, None, None, torch.ones(1, 1, 1, 1), 1).sum().backward()
        >>> c.grad.shape
        torch.Size([1, 3, 8, 8])
    """

    @staticmethod
    def _feat_scale(color: torch.Tensor, mult: torch.Tensor | None) -> torch.Tensor | None:
        """``mult²`` as the ops' ``feat_scale (B, G)``."""
        return None if mult is None else mult.detach().square().flatten(1).expand(color.shape[0], -1).contiguous()

    @staticmethod
    def forward(ctx: Any, color: torch.Tensor, guide0: torch.Tensor | None, guide1: torch.Tensor | None,
                mult: torch.Tensor | None, scale: torch.Tensor | None, step: int, last: bool = False) -> torch.Tensor:
        guides = tuple(g for g in (guide0, guide1) if g is not None)
        out, den = run(ATrousLevelOp(color, guides, ATrousLevel._feat_scale(color, mult), scale, step, last))
        ctx.save_for_backward(color, guide0, guide1, mult, scale, out, den)
        ctx.step = step
        return out

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        color, guide0, guide1, mult, scale, out, den = ctx.saved_tensors
        present = [i for i, t in enumerate((guide0, guide1)) if t is not None]
        guides = tuple((guide0, guide1)[i] for i in present)
        need_feat = bool(guides) and any(ctx.needs_input_grad[1:4])
        need_scale = scale is not None and ctx.needs_input_grad[4]
        dc, df, ds = run(ATrousLevelGradOp(color, guides, ATrousLevel._feat_scale(color, mult), scale, out, g / den,
                                           ctx.step, need_feat, need_scale))
        if ds is not None and scale.shape[-2:] == (1, 1):
            ds = ds.sum((2, 3), keepdim=True)
        dguide, dmult = [None, None], None
        if df is not None:
            parts = df.split(3, dim=1)
            for k, i in enumerate(present):
                dguide[i] = parts[k] if ctx.needs_input_grad[1 + i] else None
            if ctx.needs_input_grad[3]:  # the distance is homogeneous of degree 2 in mult_g and in f_g (and
                # blind to its offset): mult_g ∂L/∂mult_g = Σ (f_g - mean f_g) ∂L/∂f_g
                dmult = torch.cat([(d * (f - f.mean((2, 3), keepdim=True))).sum((1, 2, 3), keepdim=True)
                                   for d, f in zip(parts, guides)], 1)
                dmult = dmult.sum(0, keepdim=True) if mult.shape[0] == 1 < dmult.shape[0] else dmult
                dmult = torch.where(mult > 0, dmult / torch.where(mult > 0, mult, 1.0), 0.0)
        return dc, dguide[0], dguide[1], dmult, ds, None, None
