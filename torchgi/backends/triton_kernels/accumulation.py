"""The Triton temporal accumulation (:class:`~torchgi.backends.base.AccumulateOp`): one launch,
each program a block of pixels of one image; the same maths as the torch code
(``torch_code.accumulation``) and the C kernel (``c_kernels/accumulate.c``), tap by tap in the
same order: the history's four bilinear taps at pixel + motion, each counted where it is inside
the image, of the same kind (surface / background) and, on surfaces, within the normal and depth
tolerances; then the exponential averages of the light, scaled down to its bound where its
channel maximum exceeds it."""

from __future__ import annotations

import torch

from torchgi.backends.base import LUMA, AccumulateOp
from torchgi.backends.triton_kernels.common import _cdiv, _scaled_to, tl, triton
from torchgi.backends.triton_kernels.filter_guided import _split

_BLOCK = 256  # pixels per program

if triton is not None:

    @triton.jit
    def _tap(pn_ptr, pd_ptr, ps_ptr, tx, ty, w, H, W, HW, m, surf, n0, n1, n2, d, ntol, dtol):
        # one bilinear tap of the history at (tx, ty) with weight w: the weight kept where the tap
        # passes the tests, and its index in the image
        inside = (tx >= 0) & (tx <= W - 1) & (ty >= 0) & (ty <= H - 1) & m
        j = (tl.minimum(tl.maximum(ty, 0.0), H - 1.0).to(tl.int64) * W
             + tl.minimum(tl.maximum(tx, 0.0), W - 1.0).to(tl.int64))
        same = (tl.load(ps_ptr + j, mask=inside, other=0.0) > 0.5).to(tl.int32) == surf
        dot = (tl.load(pn_ptr + j, mask=inside, other=0.0) * n0 + tl.load(pn_ptr + HW + j, mask=inside, other=0.0) * n1
               + tl.load(pn_ptr + 2 * HW + j, mask=inside, other=0.0) * n2)
        close = (dot >= ntol) & (tl.abs(tl.load(pd_ptr + j, mask=inside, other=0.0) - d) <= dtol * tl.abs(d))
        keep = inside & same & (close | (surf == 0))
        return tl.where(keep, w, 0.0), j, keep

    @triton.jit
    def _round_half_even(v):
        # torch.round and C's rintf: halves to the even neighbour
        r = tl.floor(v + 0.5)
        odd = (r - 2.0 * tl.floor(r * 0.5)) != 0
        return tl.where(((r - v) == 0.5) & odd, r - 1.0, r)

    @triton.jit
    def _history(l3, h3, mm, ln, pn, pd, ps, px, py, H, W, HW, m, surf, n0, n1, n2, d, ntol, dtol, BLOCK: tl.constexpr):
        # the nine history planes' weighted sums over the four taps that pass, and the weights' sum
        x0f, y0f = tl.floor(px), tl.floor(py)
        fx, fy = px - x0f, py - y0f
        a0 = tl.zeros([BLOCK], dtype=tl.float32)
        a1, a2, a3, a4, a5, a6, a7, a8, total = a0, a0, a0, a0, a0, a0, a0, a0, a0
        for k in tl.static_range(4):
            dx, dy = k % 2, k // 2
            w0 = (fx * dx + (1 - fx) * (1 - dx)) * (fy * dy + (1 - fy) * (1 - dy))  # (exact: one term is 0)
            w, j, keep = _tap(pn, pd, ps, x0f + dx, y0f + dy, w0, H, W, HW, m, surf, n0, n1, n2, d, ntol, dtol)
            a0 += w * tl.load(l3 + j, mask=keep, other=0.0)
            a1 += w * tl.load(l3 + HW + j, mask=keep, other=0.0)
            a2 += w * tl.load(l3 + 2 * HW + j, mask=keep, other=0.0)
            a3 += w * tl.load(h3 + j, mask=keep, other=0.0)
            a4 += w * tl.load(h3 + HW + j, mask=keep, other=0.0)
            a5 += w * tl.load(h3 + 2 * HW + j, mask=keep, other=0.0)
            a6 += w * tl.load(mm + j, mask=keep, other=0.0)
            a7 += w * tl.load(mm + HW + j, mask=keep, other=0.0)
            a8 += w * tl.load(ln + j, mask=keep, other=0.0)
            total += w
        return a0, a1, a2, a3, a4, a5, a6, a7, a8, total

    @triton.jit
    def _accumulate(x_ptr, b_ptr, mo_ptr, n_ptr, d_ptr, surf_ptr, l_ptr, o_ptr, mm_ptr, len_ptr, pn_ptr, pd_ptr, ps_ptr,
                    out_ptr, H, W, n_blk, alpha, cap, ntol, dtol, lr, lg, lb, BLOCK: tl.constexpr):
        blk, b = _split(tl.program_id(0), n_blk)
        b = b.to(tl.int64)
        HW = H * W
        i = blk * BLOCK + tl.arange(0, BLOCK)
        m = i < HW
        o1, o2, o3 = b * HW + i, b * 2 * HW + i, b * 3 * HW + i
        px = (i % W).to(tl.float32) + tl.load(mo_ptr + o2, mask=m, other=0.0)
        py = (i // W).to(tl.float32) + tl.load(mo_ptr + o2 + HW, mask=m, other=0.0)
        a0, a1, a2, a3, a4, a5, a6, a7, a8, total = _history(
            l_ptr + b * 3 * HW, o_ptr + b * 3 * HW, mm_ptr + b * 2 * HW, len_ptr + b * HW, pn_ptr + b * 3 * HW,
            pd_ptr + b * HW, ps_ptr + b * HW, px, py, H, W, HW, m, (tl.load(surf_ptr + o1, mask=m, other=0) != 0).to(tl.int32),
            tl.load(n_ptr + o3, mask=m, other=0.0), tl.load(n_ptr + o3 + HW, mask=m, other=0.0),
            tl.load(n_ptr + o3 + 2 * HW, mask=m, other=0.0), tl.load(d_ptr + o1, mask=m, other=0.0), ntol, dtol, BLOCK)
        found = total > 1e-3
        t = tl.where(found, total, 1.0)
        h0, h1, h2 = tl.where(found, a0 / t, 0.0), tl.where(found, a1 / t, 0.0), tl.where(found, a2 / t, 0.0)
        hl = tl.where(found, _round_half_even(a8 / t), 0.0)
        length = tl.where(hl > 0, tl.minimum(hl + 1, cap), 1.0)
        a = tl.maximum(1.0 / length, alpha)
        x0 = tl.load(x_ptr + o3, mask=m, other=0.0)
        x1 = tl.load(x_ptr + o3 + HW, mask=m, other=0.0)
        x2 = tl.load(x_ptr + o3 + 2 * HW, mask=m, other=0.0)
        x0, x1, x2 = _scaled_to(x0, x1, x2, tl.load(b_ptr + o1, mask=m, other=0.0))
        lum = lr * x0 + lg * x1 + lb * x2
        m1, m2 = tl.where(found, a6 / t, 0.0), tl.where(found, a7 / t, 0.0)
        m1, m2 = m1 + a * (lum - m1), m2 + a * (lum * lum - m2)
        out = out_ptr + b * 13 * HW + i
        tl.store(out, h0 + a * (x0 - h0), mask=m)
        tl.store(out + HW, h1 + a * (x1 - h1), mask=m)
        tl.store(out + 2 * HW, h2 + a * (x2 - h2), mask=m)
        tl.store(out + 3 * HW, tl.where(found, a3 / t, 0.0), mask=m)
        tl.store(out + 4 * HW, tl.where(found, a4 / t, 0.0), mask=m)
        tl.store(out + 5 * HW, tl.where(found, a5 / t, 0.0), mask=m)
        tl.store(out + 6 * HW, m1, mask=m)
        tl.store(out + 7 * HW, m2, mask=m)
        tl.store(out + 8 * HW, length, mask=m)
        tl.store(out + 9 * HW, hl, mask=m)
        tl.store(out + 10 * HW, tl.maximum(m2 - m1 * m1, 0.0), mask=m)
        tl.store(out + 11 * HW, tl.minimum(length, (2 - a) / a), mask=m)
        tl.store(out + 12 * HW, lum, mask=m)

def accumulate(desc: AccumulateOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AccumulateOp` in one launch: ``(B, 13, H, W)`` float32
    (the planes the op describes), for CUDA tensors (CPU ones under ``TRITON_INTERPRET=1``).

    Example (CUDA; :class:`torchgi.TemporalDenoiser` calls it through the seam for such tensors):
        >>> z = lambda c: torch.zeros(1, c, 2, 2, device="cuda")                        # doctest: +SKIP
        >>> op = AccumulateOp(z(3) + 1, z(1) + 9, z(2), z(3), z(1) + 1, z(1) > 0, z(3), z(3), z(2), z(1), z(3),
        ...                   z(1), z(1), 0.2, 32, 0.9, 0.05)                               # doctest: +SKIP
        >>> accumulate(op)[0, :, 0, 0].tolist()[6:9]   # no history: moments of the frame, length 1  # doctest: +SKIP
        [1.0, 1.0, 1.0]
    """
    d = desc
    B, _, H, W = d.normal.shape
    out = torch.empty(B, 13, H, W, dtype=torch.float32, device=d.normal.device)
    if out.numel() == 0:
        return out
    n_blk = _cdiv(H * W, _BLOCK)
    c = lambda t: t.contiguous()
    _accumulate[(n_blk * B,)](
        c(d.x), c(d.bound), c(d.motion), c(d.normal), c(d.depth), c(d.surface.to(torch.uint8)), c(d.light),
        c(d.output), c(d.moments), c(d.length), c(d.prev_normal), c(d.prev_depth), c(d.prev_surface), out,
        H, W, n_blk, float(d.alpha), float(d.max_history), float(d.normal_tolerance), float(d.depth_tolerance),
        *LUMA, BLOCK=_BLOCK)
    return out
