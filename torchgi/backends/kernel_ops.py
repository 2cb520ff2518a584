"""Per-pixel kernels at the back-end seam: kernels given (:func:`torchgi.filters.apply_kernels`:
the forward :class:`ApplyKernelsOp` and its gradients :class:`ApplyKernelsGradOp`, the building
block of kernel-predicting denoisers) and the edge-avoiding kernel of one À-Trous level
(:class:`ATrousLevelOp`, :class:`ATrousLevelGradOp`: what :func:`torchgi.filters.atrous` runs per
level under autograd), and the guided filter's gradients (:class:`GuidedGradOp`: what
:class:`~torchgi.backends.torch_code.filter_guided.GuidedFunction` runs backward). Re-exported by :mod:`torchgi.backends.base`.

Tap ``t = i k + j`` of a ``k x k`` kernel at dilation ``d`` reads the pixel ``(y + (i - k//2) d,
x + (j - k//2) d)``; taps outside the image are left out of the sum (and, normalised, of the
weight sum)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["ATrousLevelGradOp", "ATrousLevelOp", "ApplyKernelsGradOp", "ApplyKernelsOp", "GuidedGradOp"]


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

    def scaled_grad(self) -> torch.Tensor:
        """``gp``: ``grad / den``, or ``grad`` without ``normalize``; contiguous."""
        return (self.grad if self.den is None else self.grad / self.den).contiguous()


@dataclass(eq=False, slots=True)
class ATrousLevelOp:
    """One À-Trous level without variance or holes: ``out_p = Σ_q w_pq c_q / den_p`` over the 25
    taps at ``step`` inside the image, ``w_pq = h_t exp(-(s_p |c_p - c_q|² + Σ_g m_g |f_gp - f_gq|²))``,
    for ``color (B,C,H,W)``, the guides ``guides`` (0 to 2 tensors ``f_g (B,3,H,W)``, as the
    caller holds them: the same serve every level) with ``feat_scale (B,G)``, the multiplier
    ``m_g`` of each guide's squared distance (each level brings its own), and the colour scale
    ``scale`` ``(B,1,1,1)`` or a ``(B,1,H,W)`` map (None: no colour weight). Returns ``(out,
    den)``, ``den (B,1,H,W)``; ``out`` may come in a back end's own strided layout (the C kernels'
    padded rows), which the next level reads without a copy, or contiguous with ``plain_out``
    (the last level: the caller's result)."""

    color: torch.Tensor
    guides: tuple[torch.Tensor, ...]
    feat_scale: torch.Tensor | None
    scale: torch.Tensor | None
    step: int
    plain_out: bool = False

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.color, *self.guides, self.feat_scale, self.scale)


@dataclass(eq=False, slots=True)
class ATrousLevelGradOp:
    """The gradients of :class:`ATrousLevelOp` given its inputs, its ``out`` and ``gp = grad / den``
    ``(B,C,H,W)``: with ``E_pq = -w_pq Σ_k gp_pk (c_qk - out_pk)``, ``dcolor`` (the value path
    ``Σ_p w_pq gp_p`` and the colour distance's), ``dguides`` (a ``(B,3G,H,W)`` tensor, the
    gradient of each guide itself, through its multiplier ``m_g``; None without guides or with
    ``need_feat`` False) and ``dscale (B,1,H,W)`` per pixel (None without a colour weight or
    ``need_scale``). Inputs may come in any layout with unit column stride. Returns ``(dcolor,
    dguides, dscale)``."""

    color: torch.Tensor
    guides: tuple[torch.Tensor, ...]
    feat_scale: torch.Tensor | None
    scale: torch.Tensor | None
    out: torch.Tensor
    gp: torch.Tensor
    step: int
    need_feat: bool = True
    need_scale: bool = True

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.color, *self.guides, self.feat_scale, self.scale, self.out, self.gp)

    def scale_operand(self) -> tuple[int, torch.Tensor | None]:
        """How a kernel reads ``scale``: 0 and None (no colour weight), 1 and its ``(B,)`` values,
        or 2 and a contiguous ``(B, 1, H, W)`` plane (a map)."""
        s = self.scale
        if s is None:
            return 0, None
        B, _, H, W = self.color.shape
        if s.shape[-2:] == (1, 1):
            return 1, s.reshape(B).contiguous()
        return 2, s.expand(B, 1, H, W).contiguous()


@dataclass(eq=False, slots=True)
class GuidedGradOp:
    """The gradients of the guided filter of the centred ``guide (B,n,H,W)`` (n <= 4) and ``src
    (B,Cs,H,W)`` (zero means: the output is ``q`` without ``mean(src)``) with ``eps`` ``(B|1,n,1,1)``
    or a per-pixel ``(B|1,n,H,W)`` map and ``radius``, given ``grad (B,Cs,H,W)`` of the output.
    Returns ``(dguide, dsrc, deps)`` (``deps`` in the shape of ``eps``), each None where
    ``need_guide`` / ``need_src`` / ``need_eps`` is False. Where a pivot or ``Σ_ii`` is clamped
    (rounding level, flat guides) the gradient is that of the unclamped formula, and ``ε`` below
    the rounding level gets none (it is not used)."""

    guide: torch.Tensor
    src: torch.Tensor
    eps: torch.Tensor
    radius: int
    grad: torch.Tensor
    need_guide: bool = True
    need_src: bool = True
    need_eps: bool = True

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.guide, self.src, self.eps, self.grad)
