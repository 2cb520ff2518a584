"""The Triton per-pixel kernel application and its gradients
(:class:`~torchgi.backends.kernel_ops.ApplyKernelsOp`, :class:`~torchgi.backends.kernel_ops.ApplyKernelsGradOp`):
each program takes a block of pixels of one image and walks the ``k²`` taps (a loop, not
unrolled), one channel at a time; gathers only (no atomics): the gradient of ``x`` at a pixel
sums the taps of the pixels that read it."""

from __future__ import annotations

import torch

from torchgi.backends.kernel_ops import ApplyKernelsGradOp, ApplyKernelsOp
from torchgi.backends.triton_kernels.common import _cdiv, tl, triton

_BLOCK = 256  # pixels per program

if triton is not None:

    @triton.jit
    def _source(y, x, t, k, d, H, W, live):
        # the pixel tap t of (y, x) reads, (sy, sx), and whether it lies inside the image
        sy = y + (t // k - k // 2) * d
        sx = x + (t % k - k // 2) * d
        return sy, sx, live & (sy >= 0) & (sy < H) & (sx >= 0) & (sx < W)

    @triton.jit
    def _forward(x_ptr, w_ptr, out_ptr, den_ptr, C, H, W, k, d, NORMALIZE: tl.constexpr, BLOCK: tl.constexpr):
        # out = Σ_t w_t x(· + o_t) over the taps inside the image, divided by their weight sum
        b = tl.program_id(1)
        HW = H * W
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        live = i < HW
        y, x = i // W, i % W
        den = tl.zeros([BLOCK], dtype=tl.float32)
        if NORMALIZE:
            for t in range(k * k):
                sy, sx, inside = _source(y, x, t, k, d, H, W, live)
                den += tl.load(w_ptr + (b * k * k + t) * HW + i, mask=inside, other=0.0)
            tl.store(den_ptr + b * HW + i, den, mask=live)
        for c in range(C):
            acc = tl.zeros([BLOCK], dtype=tl.float32)
            for t in range(k * k):
                sy, sx, inside = _source(y, x, t, k, d, H, W, live)
                wt = tl.load(w_ptr + (b * k * k + t) * HW + i, mask=inside, other=0.0)
                acc += wt * tl.load(x_ptr + (b * C + c) * HW + sy * W + sx, mask=inside, other=0.0)
            if NORMALIZE:
                acc = acc / den
            tl.store(out_ptr + (b * C + c) * HW + i, acc, mask=live)

    @triton.jit
    def _gradients(x_ptr, w_ptr, out_ptr, gp_ptr, dx_ptr, dw_ptr, C, H, W, k, d, NORMALIZE: tl.constexpr,
                   DX: tl.constexpr, DW: tl.constexpr, BLOCK: tl.constexpr):
        # dw_t = Σ_c gp_c (x_c(· + o_t) - out_c) (out only when normalised), 0 outside;
        # dx_c = Σ_t (w_t gp_c)(· - o_t)
        b = tl.program_id(1)
        HW = H * W
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        live = i < HW
        y, x = i // W, i % W
        if DW:
            for t in range(k * k):
                sy, sx, inside = _source(y, x, t, k, d, H, W, live)
                acc = tl.zeros([BLOCK], dtype=tl.float32)
                for c in range(C):
                    g = tl.load(gp_ptr + (b * C + c) * HW + i, mask=live, other=0.0)
                    xq = tl.load(x_ptr + (b * C + c) * HW + sy * W + sx, mask=inside, other=0.0)
                    if NORMALIZE:
                        xq = xq - tl.load(out_ptr + (b * C + c) * HW + i, mask=live, other=0.0)
                    acc += g * xq
                tl.store(dw_ptr + (b * k * k + t) * HW + i, tl.where(inside, acc, 0.0), mask=live)
        if DX:
            for c in range(C):
                acc = tl.zeros([BLOCK], dtype=tl.float32)
                for t in range(k * k):
                    py, px, inside = _source(y, x, t, k, -d, H, W, live)  # the pixel whose tap t reads (y, x)
                    p = py * W + px
                    wt = tl.load(w_ptr + (b * k * k + t) * HW + p, mask=inside, other=0.0)
                    acc += wt * tl.load(gp_ptr + (b * C + c) * HW + p, mask=inside, other=0.0)
                tl.store(dx_ptr + (b * C + c) * HW + i, acc, mask=live)


def apply_kernels(desc: ApplyKernelsOp) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:class:`~torchgi.backends.kernel_ops.ApplyKernelsOp` in one launch.

    Example:
        >>> x, w = torch.ones(1, 2, 4, 4, device="cuda"), torch.ones(1, 9, 4, 4, device="cuda")  # doctest: +SKIP
        >>> apply_kernels(ApplyKernelsOp(x, w, 2, True))[0].unique().tolist()                     # doctest: +SKIP
        [1.0]
    """
    x, w = desc.x.contiguous(), desc.weights.contiguous()
    B, C, H, W = x.shape
    k = round(w.shape[1] ** 0.5)
    out = torch.empty_like(x)
    den = torch.empty(B, 1, H, W, dtype=x.dtype, device=x.device) if desc.normalize else out
    _forward[(_cdiv(H * W, _BLOCK), B)](x, w, out, den, C, H, W, k, desc.dilation, NORMALIZE=desc.normalize,
                                        BLOCK=_BLOCK)
    return out, den if desc.normalize else None


def apply_kernels_grad(desc: ApplyKernelsGradOp) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """:class:`~torchgi.backends.kernel_ops.ApplyKernelsGradOp` in one launch (``grad / den`` first).

    Example:
        >>> x = torch.ones(1, 1, 1, 3, device="cuda"); w = torch.zeros(1, 9, 1, 3, device="cuda")  # doctest: +SKIP
        >>> w[:, 4] = 1.0; g = torch.tensor([[[[1.0, 2.0, 3.0]]]], device="cuda")                     # doctest: +SKIP
        >>> apply_kernels_grad(ApplyKernelsGradOp(x, w, x, None, g, 1))[0].flatten().tolist()        # doctest: +SKIP
        [1.0, 2.0, 3.0]
    """
    x, w, out = desc.x.contiguous(), desc.weights.contiguous(), desc.out.contiguous()
    gp = desc.scaled_grad()
    B, C, H, W = x.shape
    k = round(w.shape[1] ** 0.5)
    dx = torch.empty_like(x) if desc.need_x else x
    dw = torch.empty_like(w) if desc.need_weights else w
    _gradients[(_cdiv(H * W, _BLOCK), B)](x, w, out, gp, dx, dw, C, H, W, k, desc.dilation,
                                          NORMALIZE=desc.den is not None, DX=desc.need_x, DW=desc.need_weights,
                                          BLOCK=_BLOCK)
    return dx if desc.need_x else None, dw if desc.need_weights else None
