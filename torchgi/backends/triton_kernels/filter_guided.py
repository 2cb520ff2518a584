"""The Triton guided filter in six launches: products of the centred guide and source summed
down the columns (sliding windows, double accumulators), those sums summed along the rows (a
running difference and a prefix sum, double), the per-pixel LDLᵀ solve (written once for four
guide channels; absent channels enter as exact zeros), the two box passes again over the
coefficients, and the apply; the box filter from the same two passes."""

from __future__ import annotations

import torch

from torchgi.backends.base import BoxOp, GuidedOp
from torchgi.backends.triton_kernels.common import _cdiv, tl, triton
from torchgi.core.dtypes import variance_rounding

# guided filter: pixels per program of the column pass (columns) / row pass (rows x columns) /
# solve and apply; rows per program of the column pass (each starts with a full window), rows
# per loop step and warps. A column-pass program is a chain of row steps that waits on its
# loads: one warp with four rows in flight was the fastest (docs/calibration.md)
_COL_BW, _COL_ROWS, _COL_UNROLL, _COL_WARPS = 128, 128, 4, 1
_ROW_BH, _ROW_BW = 8, 128
_PIX = 256

if triton is not None:

    @triton.jit
    def _split(i, n):
        # a flat program index as (i mod n, i div n): grids are 1-D (no 65535 limit on y and z)
        return i % n, i // n

    @triton.jit
    def _source(g_ptr, p_ptr, mg_ptr, mp_ptr, b, i, NG, NP, sg_b, sp_b, HW, CENTRE: tl.constexpr):
        # plane i of the stack [g (NG planes), p (NP planes)] and the mean it is centred by
        in_g = i < NG
        j = tl.where(in_g, i, i - NG)
        base = tl.where(in_g, g_ptr + b * sg_b, p_ptr + b * sp_b) + j * HW
        mu = 0.0
        if CENTRE:
            mu = tl.load(tl.where(in_g, mg_ptr + b * NG, mp_ptr + b * NP) + j)
        return base, mu

    @triton.jit
    def _product(pa, pb, ma, mb, two, mask):
        # (a - ma)·(b - mb) (b - mb = 1 where there is no second factor), 0 where masked, in double
        u = tl.load(pa, mask=mask, other=0.0) - ma
        v = tl.load(pb, mask=mask & two, other=0.0) - mb
        return tl.where(mask, u * tl.where(two, v, 1.0), 0.0).to(tl.float64)

    @triton.jit
    def _column_sums(g_ptr, p_ptr, mg_ptr, mp_ptr, tab_ptr, s_ptr, K, H, W, r, n_x, n_y, NG, NP, sg_b, sp_b, ROWS,
                     CENTRE: tl.constexpr, BW: tl.constexpr, UNROLL: tl.constexpr):
        # s[b, k] = Σ over the rows y-r..y+r of x[tab[k, 0]] · x[tab[k, 1]] (1 for -1), x the
        # stack [g, p] of planes centred by their means (CENTRE): a window slid down ROWS rows
        # from a full sum at the chunk's first row, in double. Rows are loaded UNROLL at a time
        # (a program is a chain of row steps: its loads' latency is what it waits on).
        k, t = _split(tl.program_id(0), K)
        xb, t = _split(t, n_x)
        yb, b = _split(t, n_y)
        y0 = yb * ROWS
        b = b.to(tl.int64)
        HW = H * W
        ia = tl.load(tab_ptr + 2 * k)
        ib = tl.load(tab_ptr + 2 * k + 1)
        x = xb * BW + tl.arange(0, BW)
        m = x < W
        two = x * 0 + ib >= 0  # a second factor
        pa, ma = _source(g_ptr, p_ptr, mg_ptr, mp_ptr, b, ia, NG, NP, sg_b, sp_b, HW, CENTRE)
        pb, mb = _source(g_ptr, p_ptr, mg_ptr, mp_ptr, b, tl.maximum(ib, 0), NG, NP, sg_b, sp_b, HW, CENTRE)
        pa += x
        pb += x
        acc = tl.zeros([BW], dtype=tl.float64)
        for yy in tl.range(tl.maximum(y0 - r, 0), tl.minimum(y0 + r + 1, H), loop_unroll_factor=UNROLL):
            acc += _product(pa + yy * W, pb + yy * W, ma, mb, two, m)
        ps = s_ptr + (b * K + k) * HW + x
        tl.store(ps + y0 * W, acc.to(tl.float32), mask=m)
        for y in tl.range(y0 + 1, tl.minimum(y0 + ROWS, H), loop_unroll_factor=UNROLL):
            yi = y + r
            yo = y - r - 1
            mi = m & (x * 0 + yi < H)  # (masks built from tensors: the interpreter's loop counters are ints)
            mo = m & (x * 0 + yo >= 0)
            acc += _product(pa + yi * W, pb + yi * W, ma, mb, two, mi) - _product(pa + yo * W, pb + yo * W, ma, mb,
                                                                                  two, mo)
            tl.store(ps + y * W, acc.to(tl.float32), mask=m)

    @triton.jit
    def _row_means(s_ptr, m_ptr, K, H, W, r, n_x, n_y, ss_b, ss_k, BH: tl.constexpr, BW: tl.constexpr):
        # m = (Σ over the columns x-r..x+r of s) / window size: the window of the tile's left
        # neighbour column summed once, then a prefix sum of what enters minus what leaves
        k, t = _split(tl.program_id(0), K)
        xb, t = _split(t, n_x)
        yb, b = _split(t, n_y)
        b = b.to(tl.int64)
        x0 = xb * BW
        y = (yb * BH + tl.arange(0, BH))[:, None]
        x = (x0 + tl.arange(0, BW))[None, :]
        my = y < H
        base = s_ptr + b * ss_b + k * ss_k + y * W
        hi = tl.minimum(x0 + r, W)
        left = tl.zeros([BH], dtype=tl.float64)
        for j0 in range(tl.maximum(x0 - 1 - r, 0), hi, BW):
            j = j0 + tl.arange(0, BW)[None, :]
            left += tl.sum(tl.load(base + j, mask=my & (j < hi), other=0.0).to(tl.float64), axis=1)
        d = tl.load(base + x + r, mask=my & (x + r < W), other=0.0).to(tl.float64) \
            - tl.load(base + x - r - 1, mask=my & (x - r - 1 >= 0), other=0.0).to(tl.float64)
        win = left[:, None] + tl.cumsum(d, axis=1)
        count = (tl.minimum(x + r, W - 1) - tl.maximum(x - r, 0) + 1) * (tl.minimum(y + r, H - 1) - tl.maximum(y - r, 0) + 1)
        ok = my & (x < W)
        tl.store(m_ptr + b * ss_b + k * ss_k + y * W + x, (win / tl.where(ok, count, 1).to(tl.float64)).to(tl.float32),
                 mask=ok)

    @triton.jit
    def _plane(base, k, HW, m):
        return tl.load(base + k * HW, mask=m, other=0.0)

    @triton.jit
    def _pivot(mean_sq, mean, eps_ptr, unit, tiny):
        # ε raised to the rounding level of the variance, and the diagonal Σ_ii + ε (Σ_ii >= 0)
        e = tl.maximum(mean_sq * unit, tl.maximum(tl.load(eps_ptr), tiny))
        return e, tl.maximum(mean_sq - mean * mean, 0.0) + e

    @triton.jit
    def _factored(base, eps_ptr, HW, Cs, m, unit, tiny, zero, N: tl.constexpr):
        # The LDLᵀ of a pixel block's Σ + diag(ε) from the box means at base (torch_code.filter_guided
        # ._factor's order of operations): the guide means mI, the means of I_i² (q), the pivots d
        # and L below the diagonal, for four guide channels; channels past N are 0 with ε = 1.
        mi0 = _plane(base, 0, HW, m)
        q00 = _plane(base, N + Cs, HW, m)
        e0, a00 = _pivot(q00, mi0, eps_ptr, unit, tiny)
        mi1, mi2, mi3, q11, q22, q33 = zero, zero, zero, zero, zero, zero
        a10, a20, a21, a30, a31, a32 = zero, zero, zero, zero, zero, zero
        e1, e2, e3 = zero + 1.0, zero + 1.0, zero + 1.0
        a11, a22, a33 = e1, e2, e3
        if N > 1:
            mi1 = _plane(base, 1, HW, m)
            a10 = _plane(base, N + Cs + 1, HW, m) - mi1 * mi0
            q11 = _plane(base, N + Cs + 2, HW, m)
            e1, a11 = _pivot(q11, mi1, eps_ptr + 1, unit, tiny)
        if N > 2:
            mi2 = _plane(base, 2, HW, m)
            a20 = _plane(base, N + Cs + 3, HW, m) - mi2 * mi0
            a21 = _plane(base, N + Cs + 4, HW, m) - mi2 * mi1
            q22 = _plane(base, N + Cs + 5, HW, m)
            e2, a22 = _pivot(q22, mi2, eps_ptr + 2, unit, tiny)
        if N > 3:
            mi3 = _plane(base, 3, HW, m)
            a30 = _plane(base, N + Cs + 6, HW, m) - mi3 * mi0
            a31 = _plane(base, N + Cs + 7, HW, m) - mi3 * mi1
            a32 = _plane(base, N + Cs + 8, HW, m) - mi3 * mi2
            q33 = _plane(base, N + Cs + 9, HW, m)
            e3, a33 = _pivot(q33, mi3, eps_ptr + 3, unit, tiny)
        d0 = tl.maximum(a00, e0)
        l10 = a10 / d0
        l20 = a20 / d0
        l30 = a30 / d0
        d1 = tl.maximum(a11 - l10 * a10, e1)
        e21 = a21 - l20 * a10
        l21 = e21 / d1
        e31 = a31 - l30 * a10
        l31 = e31 / d1
        d2 = tl.maximum(a22 - l20 * a20 - l21 * e21, e2)
        e32 = a32 - l30 * a20 - l31 * e21
        l32 = e32 / d2
        d3 = tl.maximum(a33 - l30 * a30 - l31 * e31 - l32 * e32, e3)
        return mi0, mi1, mi2, mi3, q00, q11, q22, q33, d0, d1, d2, d3, l10, l20, l30, l21, l31, l32

    @triton.jit
    def _solve(
               m_ptr, eps_ptr, a_ptr, HW, Cs, n_blk, sm_b, sa_b, unit, tiny, N: tl.constexpr, BLOCK: tl.constexpr):
        # a = (Σ + diag(ε))^-1 cov, b = mean(p) - aᵀ mean(I) for every source channel: torch_code.filter_guided.solve
        # written out for four guide channels; channels past N are 0 with ε = 1, so they give a = 0.
        # Σ is loaded and factorised once per pixel, then each source channel is solved with it.
        blk, b = _split(tl.program_id(0), n_blk)
        b = b.to(tl.int64)
        i = blk * BLOCK + tl.arange(0, BLOCK)
        m = i < HW
        base = m_ptr + b * sm_b + i
        P = N * (N + 1) // 2
        zero = tl.zeros([BLOCK], dtype=tl.float32)
        mi0, mi1, mi2, mi3, _, _, _, _, d0, d1, d2, d3, l10, l20, l30, l21, l31, l32 = _factored(
            base, eps_ptr + b * N, HW, Cs, m, unit, tiny, zero, N)
        pa = a_ptr + b * sa_b + i
        for g in range(Cs):
            mp = _plane(base, N + g, HW, m)
            c0 = _plane(base, N + Cs + P + g, HW, m) - mi0 * mp
            c1, c2, c3 = zero, zero, zero
            if N > 1:
                c1 = _plane(base, N + Cs + P + Cs + g, HW, m) - mi1 * mp
            if N > 2:
                c2 = _plane(base, N + Cs + P + 2 * Cs + g, HW, m) - mi2 * mp
            if N > 3:
                c3 = _plane(base, N + Cs + P + 3 * Cs + g, HW, m) - mi3 * mp
            y1 = c1 - l10 * c0
            y2 = c2 - l20 * c0 - l21 * y1
            y3 = c3 - l30 * c0 - l31 * y1 - l32 * y2
            q3 = y3 / d3
            q2 = y2 / d2 - l32 * q3
            q1 = y1 / d1 - l21 * q2 - l31 * q3
            q0 = c0 / d0 - l10 * q1 - l20 * q2 - l30 * q3
            tl.store(pa + g * HW, q0, mask=m)
            if N > 1:
                tl.store(pa + (Cs + g) * HW, q1, mask=m)
            if N > 2:
                tl.store(pa + (2 * Cs + g) * HW, q2, mask=m)
            if N > 3:
                tl.store(pa + (3 * Cs + g) * HW, q3, mask=m)
            tl.store(pa + (N * Cs + g) * HW, mp - q0 * mi0 - q1 * mi1 - q2 * mi2 - q3 * mi3, mask=m)

    @triton.jit
    def _apply(ma_ptr, g_ptr, mg_ptr, off_ptr, out_ptr, HW, Cs, n_blk, sma_b, sg_b, so_b, N: tl.constexpr,
               BLOCK: tl.constexpr):
        # out = mean(b) + offset + Σ_i mean(a_i) (I_i - mean(I_i)) for every source channel (the
        # centred guide loaded once)
        blk, b = _split(tl.program_id(0), n_blk)
        b = b.to(tl.int64)
        i = blk * BLOCK + tl.arange(0, BLOCK)
        m = i < HW
        pa = ma_ptr + b * sma_b + i
        pg = g_ptr + b * sg_b + i
        g0 = _plane(pg, 0, HW, m) - tl.load(mg_ptr + b * N)
        if N > 1:
            g1 = _plane(pg, 1, HW, m) - tl.load(mg_ptr + b * N + 1)
        if N > 2:
            g2 = _plane(pg, 2, HW, m) - tl.load(mg_ptr + b * N + 2)
        if N > 3:
            g3 = _plane(pg, 3, HW, m) - tl.load(mg_ptr + b * N + 3)
        for c in range(Cs):
            acc = _plane(pa, N * Cs + c, HW, m) + tl.load(off_ptr + b * Cs + c) + _plane(pa, c, HW, m) * g0
            if N > 1:
                acc += _plane(pa, Cs + c, HW, m) * g1
            if N > 2:
                acc += _plane(pa, 2 * Cs + c, HW, m) * g2
            if N > 3:
                acc += _plane(pa, 3 * Cs + c, HW, m) * g3
            tl.store(out_ptr + b * so_b + c * HW + i, acc, mask=m)


_tables: dict[tuple, torch.Tensor] = {}


def _table(pairs: list[tuple[int, int]], device: torch.device) -> torch.Tensor:
    """The ``(K, 2)`` int32 factor table of :func:`_box_products` on ``device`` (cached)."""
    key = (tuple(pairs), device)
    if key not in _tables:
        _tables[key] = torch.tensor(pairs, dtype=torch.int32, device=device).reshape(-1, 2)
    return _tables[key]


def _box_products(g: torch.Tensor, p: torch.Tensor | None, mean_g: torch.Tensor | None, mean_p: torch.Tensor | None,
                  pairs: list[tuple[int, int]], r: int) -> torch.Tensor:
    """Box means ``(B, K, H, W)`` of the products ``x[:, i] · x[:, j]`` (``x[:, i]`` for
    ``j = -1``) of the stack ``x = [g, p]`` of contiguous float32 ``(B, ·, H, W)`` planes (``p``
    None: ``g`` alone), each centred by its mean ``(B, ·)`` (None: not centred); windows of
    radius ``r`` shrink at the borders (count-normalised). Sums in double."""
    B, NG, H, W = g.shape
    NP = 0 if p is None else p.shape[1]
    K = len(pairs)
    sums = torch.empty(B, K, H, W, dtype=torch.float32, device=g.device)
    means = torch.empty_like(sums)
    if sums.numel() == 0:
        return means
    centre = mean_g is not None
    p = g if p is None else p
    n_x, n_y = _cdiv(W, _COL_BW), _cdiv(H, _COL_ROWS)
    _column_sums[(K * n_x * n_y * B,)](g, p, mean_g if centre else g, mean_p if centre else g, _table(pairs, g.device),
                                       sums, K, H, W, r, n_x, n_y, NG, NP, g.stride(0), p.stride(0), _COL_ROWS,
                                       CENTRE=centre, BW=_COL_BW, UNROLL=_COL_UNROLL, num_warps=_COL_WARPS)
    n_x, n_y = _cdiv(W, _ROW_BW), _cdiv(H, _ROW_BH)
    _row_means[(K * n_x * n_y * B,)](sums, means, K, H, W, r, n_x, n_y, sums.stride(0), sums.stride(1),
                                     BH=_ROW_BH, BW=_ROW_BW)
    return means


def _box(x: torch.Tensor, r: int) -> torch.Tensor:
    """Count-normalised box mean ``(B, C, H, W)`` of radius ``r`` over each plane of a float32
    ``x (B, C, H, W)`` (what :func:`torchgi.filters.box` computes), in two kernels (sums in
    double).

    Example (CUDA; :func:`torchgi.filters.box` calls it for such tensors):
        >>> from torchgi import filters
        >>> x = torch.rand(1, 3, 64, 64, device="cuda")             # doctest: +SKIP
        >>> torch.allclose(_box(x, 4).cpu(), filters.box(x.cpu(), 4), atol=1e-6)  # doctest: +SKIP
        True
    """
    x = x.contiguous()
    return _box_products(x, None, None, None, [(c, -1) for c in range(x.shape[1])], r)


def _guided(
    I: torch.Tensor, p: torch.Tensor, mean_I: torch.Tensor, mean_p: torch.Tensor, offset: torch.Tensor, r: int,
    eps: torch.Tensor, coefficients_only: bool = False,
) -> torch.Tensor:
    """Guided filter with the arguments of the C back end's: ``p
    (B,Cs,H,W)`` by ``I (B,n,H,W)`` (n <= 4), centred by ``mean_p``, ``mean_I`` (``(B,C,1,1)``),
    ``eps (B,n,1,1)``, radius ``r``, ``offset (B,Cs,1,1)`` added to the output. Returns
    ``(B,Cs,H,W)`` float32, or the box-filtered coefficients ``(B,n+1,Cs,H,W)``.

    Example (CUDA; :func:`torchgi.filters.guided` calls it for such tensors):
        >>> I, p = torch.rand(1, 4, 64, 64, device="cuda"), torch.rand(1, 3, 64, 64, device="cuda")  # doctest: +SKIP
        >>> mI, mp = I.mean((2, 3), keepdim=True), p.mean((2, 3), keepdim=True)  # doctest: +SKIP
        >>> _guided(I, p, mI, mp, mp, 8, torch.full((1, 4, 1, 1), 0.01, device="cuda")).shape  # doctest: +SKIP
        torch.Size([1, 3, 64, 64])
    """
    B, n, H, W = I.shape
    Cs = p.shape[1]
    if not 1 <= n <= 4:
        raise ValueError(f"guided: expected 1 to 4 guide channels, got {n}")
    I, p = I.contiguous(), p.contiguous()
    mean_I, mean_p = mean_I.reshape(B, n).to(torch.float32).contiguous(), mean_p.reshape(B, Cs).to(torch.float32).contiguous()
    pairs = [(i, -1) for i in range(n + Cs)] + [(i, j) for i in range(n) for j in range(i + 1)] + \
        [(i, n + c) for i in range(n) for c in range(Cs)]  # the order of torch_code.filter_guided._box_means
    means = _box_products(I, p, mean_I, mean_p, pairs, r)  # of the guide and source centred
    Q, HW = (n + 1) * Cs, H * W
    coef = torch.empty(B, Q, H, W, dtype=torch.float32, device=I.device)
    n_blk = _cdiv(HW, _PIX)
    if coef.numel():
        e = eps.reshape(B, n).to(torch.float32).contiguous()
        _solve[(n_blk * B,)](means, e, coef, HW, Cs, n_blk, means.stride(0), coef.stride(0),
                                  variance_rounding(torch.float32), torch.finfo(torch.float32).tiny, N=n,
                                  BLOCK=_PIX)
    coef = _box_products(coef, None, None, None, [(q, -1) for q in range(Q)], r)
    if coefficients_only:
        return coef.unflatten(1, (n + 1, Cs))
    out = torch.empty(B, Cs, H, W, dtype=torch.float32, device=I.device)
    if out.numel():
        off = offset.reshape(B, Cs).to(torch.float32).contiguous()
        _apply[(n_blk * B,)](coef, I, mean_I, off, out, HW, Cs, n_blk, coef.stride(0), I.stride(0), out.stride(0),
                                  N=n, BLOCK=_PIX)
    return out


def box(desc: BoxOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.BoxOp` in two kernels (sums in double).

    Example:
        >>> x = torch.arange(3.0, device="cuda").view(1, 1, 1, 3)   # doctest: +SKIP
        >>> box(BoxOp(x, 1)).tolist()                                 # doctest: +SKIP
        [[[[0.5, 1.0, 1.5]]]]
    """
    return _box(desc.x, desc.radius)


def guided(desc: GuidedOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.GuidedOp` in six kernels.

    Example:
        >>> p = torch.rand(1, 3, 16, 16, device="cuda"); g = torch.rand(1, 4, 16, 16, device="cuda")  # doctest: +SKIP
        >>> mp, mg = p.mean((2, 3), keepdim=True), g.mean((2, 3), keepdim=True)                        # doctest: +SKIP
        >>> guided(GuidedOp(g, p, mg, mp, 4, torch.full((1, 4, 1, 1), 0.01, device="cuda"))).shape   # doctest: +SKIP
        torch.Size([1, 3, 16, 16])
    """
    return _guided(desc.guide, desc.src, desc.mean_guide, desc.mean_src, desc.mean_src, desc.radius, desc.eps,
                   coefficients_only=desc.coefficients_only)


