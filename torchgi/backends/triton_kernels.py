"""The Triton back end, for CUDA tensors (float32, without autograd or tracing): an À-Trous level
and the guided filter (with the box filter it is built from).

The torch code of an À-Trous level launches about ten kernels per tap; the level kernel does a
level in one launch: each program filters a tile of pixels, walks the 25 taps with the weighted
sums in registers and writes the level's colour, variance and weight sum. Same maths as the
torch code and the C back end.

The guided filter is six launches: products of the centred guide and source summed down the
columns (sliding windows, double accumulators), those sums summed along the rows (a running
difference and a prefix sum, double), the per-pixel LDLᵀ solve (written once for four guide
channels; absent channels enter as exact zeros), the two box passes again over the
coefficients, and the apply. Cost does not depend on the radius beyond one window per tile.

Triton comes with CUDA builds of torch; without it (or on the CPU) the torch code runs. With
``TRITON_INTERPRET=1`` set before torchgi is imported, the same kernels run on CPU tensors
through Triton's interpreter (the tests check them there against float64 oracles). Tile sizes
and warps come from ``scripts/sweep_gpu_tiles.py`` (docs/calibration.md).

Example:
    >>> from torchgi.backends import BoxOp, triton_kernels
    >>> triton_kernels.supports("box", BoxOp(torch.zeros(1, 1, 2, 2), 1)) is not None   # a CPU tensor
    True
"""

from __future__ import annotations

import functools
import os

import torch

from torchgi.backends.base import ATrousOp, BoxOp, GuidedOp, RestoreOp, colour_scale, float32_eager, iterate_levels
from torchgi.core.dtypes import variance_rounding
from torchgi.core.taps import kernel_5x5

try:  # shipped with CUDA builds of torch
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - CPU-only installs
    triton = None

__all__ = ["MAX_CHANNELS", "NAME", "describe", "supports"]

NAME = "triton"

_INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"
# À-Trous tile (rows x columns, coalesced along the row), warps per program and taps per loop
# step (scripts/sweep_gpu_tiles.py on an H200; docs/calibration.md)
_BH, _BW, _WARPS, _UNROLL = 2, 128, 4, 2


def _unroll(C: int, variance: bool) -> int:
    """Taps per loop step of the À-Trous kernel for ``C`` colour channels: one with a variance
    to propagate or 4 channels, where two need over 128 registers (offline ptxas for sm_90;
    tests/test_gpu.py checks the limit)."""
    return 1 if variance or C > 3 else _UNROLL


MAX_CHANNELS = 4  # colour channels the kernel takes


@functools.cache
def _taps(device: torch.device) -> torch.Tensor:
    """The 25 tap weights, float32, on ``device``."""
    return torch.tensor([h for _, _, h in kernel_5x5()], dtype=torch.float32, device=device)


def _cdiv(a: int, b: int) -> int:
    """``ceil(a / b)`` for grid sizes (``triton.cdiv`` goes through Triton's slower JIT wrapper)."""
    return -(-a // b)


def describe() -> str:
    """One line for :func:`torchgi.backends.status`.

    Example:
        >>> isinstance(describe(), str)
        True
    """
    if triton is None:
        return "Triton not installed (it ships with CUDA builds of torch)"
    where = "CPU tensors through Triton's interpreter" if _INTERPRET else "CUDA tensors"
    return f"Triton {triton.__version__} kernels for {where}"


def supports(op: str, desc: BoxOp | GuidedOp | ATrousOp | RestoreOp) -> str | None:
    """None when the kernels take ``desc``: an À-Trous level, the guided or box filter of eager
    float32 CUDA tensors (CPU ones under the interpreter), at most 4 À-Trous colour channels;
    else why not.

    Example:
        >>> supports("importance", None)   # no Triton kernel of the importance map
        'no Triton kernel for importance'
    """
    if op not in ("box", "guided", "atrous", "restore"):
        return f"no Triton kernel for {op}"
    if triton is None:
        return "Triton not installed"
    ts = [t for t in desc.tensors() if t is not None]
    if any(t.device.type != "cuda" and not _INTERPRET for t in ts):
        return "the Triton kernels take CUDA tensors"
    why = float32_eager(op, desc, "Triton")
    if why is not None:
        return why
    if op == "atrous" and desc.color.shape[1] > MAX_CHANNELS:
        return f"the À-Trous kernel takes at most {MAX_CHANNELS} colour channels"
    return None


if triton is not None:

    @triton.jit
    def _channels(p, stride, mask, C: tl.constexpr):
        # up to four channel planes `stride` apart as tiles; channels past C are zeros (unused)
        a = tl.load(p, mask=mask, other=0.0)
        b, c, d = tl.zeros_like(a), tl.zeros_like(a), tl.zeros_like(a)
        if C > 1:
            b = tl.load(p + stride, mask=mask, other=0.0)
        if C > 2:
            c = tl.load(p + 2 * stride, mask=mask, other=0.0)
        if C > 3:
            d = tl.load(p + 3 * stride, mask=mask, other=0.0)
        return a, b, c, d

    @triton.jit
    def _add_weighted(a, b, c, d, w, qa, qb, qc, qd, C: tl.constexpr):
        # the first C of four channel sums, each plus w times its value
        a += w * qa
        if C > 1:
            b += w * qb
        if C > 2:
            c += w * qc
        if C > 3:
            d += w * qd
        return a, b, c, d

    @triton.jit
    def _store_channels(p, stride, mask, use, a, b, c, d, ka, kb, kc, kd, C: tl.constexpr):
        # the first C of four channel planes `stride` apart: a..d where `use`, else ka..kd
        tl.store(p, tl.where(use, a, ka), mask=mask)
        if C > 1:
            tl.store(p + stride, tl.where(use, b, kb), mask=mask)
        if C > 2:
            tl.store(p + 2 * stride, tl.where(use, c, kc), mask=mask)
        if C > 3:
            tl.store(p + 3 * stride, tl.where(use, d, kd), mask=mask)

    @triton.jit
    def _sq(a, b):
        u = a - b
        return u * u

    @triton.jit
    def _level(  # noqa: PLR0915 - one launch: its statements are mostly compile-time channel guards
               c_ptr, n_ptr, x_ptr, var_ptr, valid_ptr, cs_ptr, inv_ptr, taps_ptr, out_ptr, vout_ptr, den_ptr,
               H, W, step, cmul, v_b, v_c, a_b,
               C: tl.constexpr, N: tl.constexpr, X: tl.constexpr, CS: tl.constexpr, V: tl.constexpr,
               VALID: tl.constexpr, BH: tl.constexpr, BW: tl.constexpr, UNROLL: tl.constexpr):
        # Channels are separate 2-D tiles (c0..c3, normal, position) under compile-time guards: a
        # channel axis in one 3-D tile is spread over threads and every tap's sum over it goes
        # through shared memory (much slower: docs/calibration.md). Planes are
        # contiguous (B, C, H, W) except the variance (channel stride v_c: 0 when expanded) and
        # the valid mask (batch stride a_b). The guides enter raw: differences of nearby float32
        # values are exact, then scaled by the image's inverse σ (normals also by 1 / step²).
        b = tl.program_id(2).to(tl.int64)
        hw = H * W
        y = (tl.program_id(1) * BH + tl.arange(0, BH))[:, None]
        x = (tl.program_id(0) * BW + tl.arange(0, BW))[None, :]
        inside = (y < H) & (x < W)
        pix = y * W + x
        pc = c_ptr + b * C * hw + pix
        c0, c1, c2, c3 = _channels(pc, hw, inside, C)
        if N:
            pn = n_ptr + b * 3 * hw + pix
            n0, n1, n2, _ = _channels(pn, hw, inside, 3)
            sn = tl.load(inv_ptr + 3 * b + 1) / (step * step)
        if X:
            px = x_ptr + b * 3 * hw + pix
            x0, x1, x2, _ = _channels(px, hw, inside, 3)
            sx = tl.load(inv_ptr + 3 * b + 2)
        if CS == 1:
            cs = tl.load(inv_ptr + 3 * b) * cmul
        if CS == 2:
            cs = tl.load(cs_ptr + b * hw + pix, mask=inside, other=0.0)
        zero = tl.zeros([BH, BW], dtype=tl.float32)
        n_0 = zero
        n_1 = zero
        n_2 = zero
        n_3 = zero
        v0 = zero
        v1 = zero
        v2 = zero
        v3 = zero
        den = zero
        for t in tl.range(0, 25, loop_unroll_factor=UNROLL):
            oy = (t // 5 - 2) * step
            ox = (t % 5 - 2) * step
            ok = inside & (y + oy >= 0) & (y + oy < H) & (x + ox >= 0) & (x + ox < W)
            off = oy * W + ox
            q0, q1, q2, q3 = _channels(pc + off, hw, ok, C)
            d = zero
            if CS > 0:
                dc = _sq(c0, q0)
                if C > 1:
                    dc += _sq(c1, q1)
                if C > 2:
                    dc += _sq(c2, q2)
                if C > 3:
                    dc += _sq(c3, q3)
                d = dc * cs
            if N:
                m0, m1, m2, _ = _channels(pn + off, hw, ok, 3)
                d += (_sq(n0, m0) + _sq(n1, m1) + _sq(n2, m2)) * sn
            if X:
                m0, m1, m2, _ = _channels(px + off, hw, ok, 3)
                d += (_sq(x0, m0) + _sq(x1, m1) + _sq(x2, m2)) * sx
            w = tl.load(taps_ptr + t) * tl.exp(-d)
            if VALID:
                w *= tl.load(valid_ptr + b * a_b + pix + off, mask=ok, other=0.0)
            w = tl.where(ok, w, 0.0)
            den += w
            n_0, n_1, n_2, n_3 = _add_weighted(n_0, n_1, n_2, n_3, w, q0, q1, q2, q3, C)
            if V:
                u0, u1, u2, u3 = _channels(var_ptr + b * v_b + pix + off, v_c, ok, C)
                v0, v1, v2, v3 = _add_weighted(v0, v1, v2, v3, w * w, u0, u1, u2, u3, C)
        has = den > 0
        safe = tl.where(has, den, 1.0)
        # a pixel without weight keeps its value (and variance)
        _store_channels(out_ptr + b * C * hw + pix, hw, inside, has, n_0 / safe, n_1 / safe, n_2 / safe, n_3 / safe,
                        c0, c1, c2, c3, C)
        if V:
            p0, p1, p2, p3 = _channels(var_ptr + b * v_b + pix, v_c, inside, C)
            s2 = safe * safe
            _store_channels(vout_ptr + b * C * hw + pix, hw, inside, has, v0 / s2, v1 / s2, v2 / s2, v3 / s2,
                            p0, p1, p2, p3, C)
        tl.store(den_ptr + b * hw + pix, den, mask=inside)


def _atrous_level(
    c: torch.Tensor, normal: torch.Tensor | None, position: torch.Tensor | None, inv: torch.Tensor,
    var: torch.Tensor | None, valid: torch.Tensor | None, step: int, colour: float | torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """One À-Trous level of :func:`torchgi.filters.atrous` on raw guides: ``c (B,C,H,W)``, up to
    4 channels; ``normal`` / ``position`` ``(B,3,H,W)`` or None (no such weight); ``inv (B,3)``
    the images' inverse σ's of colour, normal and position (normal distances are also divided
    by ``step²`` here); ``var`` ``(B,C or 1,H,W)`` or None; ``valid (B or 1,1,H,W)`` sources or
    None; ``colour`` the colour weight's scale: None (no colour weight), a float (times
    ``inv[:, 0]``) or a ``(B,1,H,W)`` plane (variance-guided). Returns the colour
    ``(B,C,H,W)``, the propagated variance and the weight sum ``(B,1,H,W)``.

    Example (CUDA; :func:`atrous` calls it once per level):
        >>> c = torch.rand(1, 3, 32, 32, device="cuda")                              # doctest: +SKIP
        >>> inv = torch.ones(1, 3, device="cuda")                                   # doctest: +SKIP
        >>> out, var, den = _atrous_level(c, None, None, inv, None, None, 1, 1.0)   # doctest: +SKIP
        >>> out.shape, var is None, den.shape                                       # doctest: +SKIP
        (torch.Size([1, 3, 32, 32]), True, torch.Size([1, 1, 32, 32]))
    """
    B, C, H, W = c.shape
    if C > MAX_CHANNELS or inv.shape != (B, 3):
        raise ValueError(f"atrous_level: expected <= {MAX_CHANNELS} colour channels and inv of shape ({B}, 3); "
                         f"got C={C}, inv {tuple(inv.shape)}")
    c = c.contiguous()
    normal = None if normal is None else normal.contiguous()
    position = None if position is None else position.contiguous()
    # a variance plane for every channel, or a mask for every image, expanded from one stays
    # one (the kernel reads it with channel / batch stride 0): not copied C or B times
    if var is not None:
        var = (var[:, :1] if var.stride(1) == 0 else var).contiguous()
    if valid is not None:
        valid = (valid[:1] if valid.stride(0) == 0 else valid).to(torch.float32).contiguous()
    plane = isinstance(colour, torch.Tensor)
    cs = colour.expand(B, 1, H, W).contiguous() if plane else None
    out = torch.empty(B, C, H, W, dtype=torch.float32, device=c.device)
    vout = None if var is None else torch.empty_like(out)
    den = torch.empty(B, 1, H, W, dtype=torch.float32, device=c.device)
    dummy = out  # pointer for absent inputs (never read: their flags are off)
    grid = (_cdiv(W, _BW), _cdiv(H, _BH), B)
    _level[grid](
        c, dummy if normal is None else normal, dummy if position is None else position, dummy if var is None else var,
        dummy if valid is None else valid, dummy if cs is None else cs, inv.contiguous(), _taps(c.device), out,
        dummy if vout is None else vout, den,
        H, W, step, colour if isinstance(colour, float) else 1.0,
        0 if var is None else var.stride(0), 0 if var is None or var.shape[1] == 1 else H * W,
        0 if valid is None or valid.shape[0] == 1 else H * W,
        C=C, N=normal is not None, X=position is not None, CS=0 if colour is None else 2 if plane else 1,
        V=var is not None, VALID=valid is not None, BH=_BH, BW=_BW, UNROLL=_unroll(C, var is not None), num_warps=_WARPS,
    )
    return out, vout, den


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
    def _solve(  # noqa: PLR0915 - the LDLᵀ of up to 4 guide channels unrolled in one launch
               m_ptr, eps_ptr, a_ptr, HW, Cs, n_blk, sm_b, sa_b, unit, tiny, N: tl.constexpr, BLOCK: tl.constexpr):
        # a = (Σ + diag(ε))^-1 cov, b = mean(p) - aᵀ mean(I) for every source channel: torch_code.solve
        # written out for four guide channels; channels past N are 0 with ε = 1, so they give a = 0.
        # Σ is loaded and factorised once per pixel, then each source channel is solved with it.
        blk, b = _split(tl.program_id(0), n_blk)
        b = b.to(tl.int64)
        i = blk * BLOCK + tl.arange(0, BLOCK)
        m = i < HW
        base = m_ptr + b * sm_b + i
        P = N * (N + 1) // 2
        zero = tl.zeros([BLOCK], dtype=tl.float32)
        mi0 = _plane(base, 0, HW, m)
        e0, a00 = _pivot(_plane(base, N + Cs, HW, m), mi0, eps_ptr + b * N, unit, tiny)
        mi1, mi2, mi3 = zero, zero, zero
        a10, a20, a21, a30, a31, a32 = zero, zero, zero, zero, zero, zero
        e1, e2, e3 = zero + 1.0, zero + 1.0, zero + 1.0
        a11, a22, a33 = e1, e2, e3
        if N > 1:
            mi1 = _plane(base, 1, HW, m)
            a10 = _plane(base, N + Cs + 1, HW, m) - mi1 * mi0
            e1, a11 = _pivot(_plane(base, N + Cs + 2, HW, m), mi1, eps_ptr + b * N + 1, unit, tiny)
        if N > 2:
            mi2 = _plane(base, 2, HW, m)
            a20 = _plane(base, N + Cs + 3, HW, m) - mi2 * mi0
            a21 = _plane(base, N + Cs + 4, HW, m) - mi2 * mi1
            e2, a22 = _pivot(_plane(base, N + Cs + 5, HW, m), mi2, eps_ptr + b * N + 2, unit, tiny)
        if N > 3:
            mi3 = _plane(base, 3, HW, m)
            a30 = _plane(base, N + Cs + 6, HW, m) - mi3 * mi0
            a31 = _plane(base, N + Cs + 7, HW, m) - mi3 * mi1
            a32 = _plane(base, N + Cs + 8, HW, m) - mi3 * mi2
            e3, a33 = _pivot(_plane(base, N + Cs + 9, HW, m), mi3, eps_ptr + b * N + 3, unit, tiny)
        # LDLᵀ with E = L·D (torch_code.solve's order of operations)
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
        [(i, n + c) for i in range(n) for c in range(Cs)]  # the order of torch_code._product_specs
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


if triton is not None:

    @triton.jit
    def _demodulator(a_ptr, h_ptr, i, HW, m, floor, HAS_HIT: tl.constexpr):
        # what light is divided by per channel: the albedo (at least floor) on surfaces, else 1
        a0 = tl.load(a_ptr + i, mask=m, other=0.0)
        a1 = tl.load(a_ptr + HW + i, mask=m, other=0.0)
        a2 = tl.load(a_ptr + 2 * HW + i, mask=m, other=0.0)
        if HAS_HIT:
            on = tl.load(h_ptr + i, mask=m, other=0) != 0
        else:
            on = (a0 > 0) | (a1 > 0) | (a2 > 0)
        return (tl.where(on, tl.maximum(a0, floor), 1.0), tl.where(on, tl.maximum(a1, floor), 1.0),
                tl.where(on, tl.maximum(a2, floor), 1.0))

    @triton.jit
    def _light_in(c_ptr, e_ptr, k_ptr, j, m, d, light, level, HAS_E: tl.constexpr, HAS_K: tl.constexpr):
        # channel j's demodulated light: without emission and kept light, or at `level` on a light
        # source without an emission input
        v = tl.load(c_ptr + j, mask=m, other=0.0)
        if HAS_K:
            v -= tl.load(k_ptr + j, mask=m, other=0.0)
        if HAS_E:
            v = (v - tl.where(light, tl.load(e_ptr + j, mask=m, other=0.0), 0.0)) / d
        else:
            v = tl.where(light, level, v / d)
        return v

    @triton.jit
    def _pixels(a_ptr, h_ptr, l_ptr, HW, n_blk, floor, HAS_HIT: tl.constexpr, HAS_L: tl.constexpr,
                BLOCK: tl.constexpr):
        # this program's image b, pixels i (mask m, offsets in 3- and 1-plane images), demodulator
        # and light-source mask
        blk, b = _split(tl.program_id(0), n_blk)
        b = b.to(tl.int64)
        i = blk * BLOCK + tl.arange(0, BLOCK)
        m = i < HW
        o3, o1 = b * 3 * HW + i, b * HW + i
        d0, d1, d2 = _demodulator(a_ptr + b * 3 * HW, h_ptr + b * HW, i, HW, m, floor, HAS_HIT)
        light = i < 0
        if HAS_L:
            light = tl.load(l_ptr + o1, mask=m, other=0) != 0
        return b, i, m, o3, o1, d0, d1, d2, light

    @triton.jit
    def _prepare(c_ptr, e_ptr, k_ptr, a_ptr, h_ptr, l_ptr, lvl_ptr, x_ptr, pk_ptr, k_fire, floor, HW, n_blk,
                 HAS_E: tl.constexpr, HAS_K: tl.constexpr, HAS_HIT: tl.constexpr, HAS_L: tl.constexpr,
                 BLOCK: tl.constexpr):
        # the demodulated light x (3 planes) and its channel maximum capped at k level
        b, _i, m, o3, o1, d0, d1, d2, light = _pixels(a_ptr, h_ptr, l_ptr, HW, n_blk, floor, HAS_HIT, HAS_L, BLOCK)
        level = tl.load(lvl_ptr + b)
        x0 = _light_in(c_ptr, e_ptr, k_ptr, o3, m, d0, light, level, HAS_E, HAS_K)
        x1 = _light_in(c_ptr, e_ptr, k_ptr, o3 + HW, m, d1, light, level, HAS_E, HAS_K)
        x2 = _light_in(c_ptr, e_ptr, k_ptr, o3 + 2 * HW, m, d2, light, level, HAS_E, HAS_K)
        tl.store(x_ptr + o3, x0, mask=m)
        tl.store(x_ptr + o3 + HW, x1, mask=m)
        tl.store(x_ptr + o3 + 2 * HW, x2, mask=m)
        tl.store(pk_ptr + o1, tl.minimum(tl.maximum(tl.maximum(x0, x1), x2), k_fire * level), mask=m)

    @triton.jit
    def _clamp(x_ptr, mean_ptr, k_fire, HW, n_blk, BLOCK: tl.constexpr):
        # x scaled down to k max(mean, 0) where its channel maximum exceeds that, in place
        blk, b = _split(tl.program_id(0), n_blk)
        b = b.to(tl.int64)
        i = blk * BLOCK + tl.arange(0, BLOCK)
        m = i < HW
        p = x_ptr + b * 3 * HW + i
        x0 = tl.load(p, mask=m, other=0.0)
        x1 = tl.load(p + HW, mask=m, other=0.0)
        x2 = tl.load(p + 2 * HW, mask=m, other=0.0)
        peak = tl.maximum(tl.maximum(x0, x1), x2)
        bound = k_fire * tl.maximum(tl.load(mean_ptr + b * HW + i, mask=m, other=0.0), 0.0)
        over = peak > bound
        f = bound / tl.where(over, peak, 1.0)
        tl.store(p, tl.where(over, x0 * f, x0), mask=m)
        tl.store(p + HW, tl.where(over, x1 * f, x1), mask=m)
        tl.store(p + 2 * HW, tl.where(over, x2 * f, x2), mask=m)

    @triton.jit
    def _remodulate(q, c_ptr, e_ptr, k_ptr, j, m, d, light, HAS_E: tl.constexpr, HAS_K: tl.constexpr):
        # max(q, 0) x the demodulator + light sources' emission + kept light (a light source's
        # colour without an emission input)
        v = tl.maximum(q, 0.0) * d
        if HAS_K:
            v += tl.load(k_ptr + j, mask=m, other=0.0)
        if HAS_E:
            v += tl.where(light, tl.load(e_ptr + j, mask=m, other=0.0), 0.0)
        else:
            v = tl.where(light, tl.load(c_ptr + j, mask=m, other=0.0), v)
        return v

    @triton.jit
    def _bilinear(p, y0, y1, x0, x1, ly, lx, w, m):
        t = (1.0 - lx) * tl.load(p + y0 * w + x0, mask=m, other=0.0) + lx * tl.load(p + y0 * w + x1, mask=m, other=0.0)
        u = (1.0 - lx) * tl.load(p + y1 * w + x0, mask=m, other=0.0) + lx * tl.load(p + y1 * w + x1, mask=m, other=0.0)
        return (1.0 - ly) * t + ly * u

    @triton.jit
    def _finish(q_ptr, coef_ptr, g_ptr, mg_ptr, off_ptr, c_ptr, e_ptr, k_ptr, a_ptr, h_ptr, l_ptr, out_ptr, floor,
                H, W, h, w, inv_s, n_blk, N: tl.constexpr, UPSAMPLE: tl.constexpr, HAS_E: tl.constexpr,
                HAS_K: tl.constexpr, HAS_HIT: tl.constexpr, HAS_L: tl.constexpr, BLOCK: tl.constexpr):
        # the filtered light q (3 planes) or, with UPSAMPLE, the guided filter applied from the
        # box-filtered coefficients at 1 / s resolution upsampled bilinearly by s (torch's
        # interpolate(scale_factor=s)); then remodulated
        HW = H * W
        b, i, m, o3, _o1, d0, d1, d2, light = _pixels(a_ptr, h_ptr, l_ptr, HW, n_blk, floor, HAS_HIT, HAS_L, BLOCK)
        if UPSAMPLE:
            y, x = i // W, i % W
            sy = tl.maximum((y.to(tl.float32) + 0.5) * inv_s - 0.5, 0.0)
            sx = tl.maximum((x.to(tl.float32) + 0.5) * inv_s - 0.5, 0.0)
            y0, x0 = sy.to(tl.int32), sx.to(tl.int32)
            ly, lx = sy - y0.to(tl.float32), sx - x0.to(tl.float32)
            y1, x1 = tl.minimum(y0 + 1, h - 1), tl.minimum(x0 + 1, w - 1)
            cb = coef_ptr + b * (N + 1) * 3 * h * w
            q0 = _bilinear(cb + (N * 3) * h * w, y0, y1, x0, x1, ly, lx, w, m) + tl.load(off_ptr + b * 3)
            q1 = _bilinear(cb + (N * 3 + 1) * h * w, y0, y1, x0, x1, ly, lx, w, m) + tl.load(off_ptr + b * 3 + 1)
            q2 = _bilinear(cb + (N * 3 + 2) * h * w, y0, y1, x0, x1, ly, lx, w, m) + tl.load(off_ptr + b * 3 + 2)
            for k in tl.static_range(N):
                g = tl.load(g_ptr + b * N * HW + k * HW + i, mask=m, other=0.0) - tl.load(mg_ptr + b * N + k)
                q0 += _bilinear(cb + (k * 3) * h * w, y0, y1, x0, x1, ly, lx, w, m) * g
                q1 += _bilinear(cb + (k * 3 + 1) * h * w, y0, y1, x0, x1, ly, lx, w, m) * g
                q2 += _bilinear(cb + (k * 3 + 2) * h * w, y0, y1, x0, x1, ly, lx, w, m) * g
        else:
            q0 = tl.load(q_ptr + o3, mask=m, other=0.0)
            q1 = tl.load(q_ptr + o3 + HW, mask=m, other=0.0)
            q2 = tl.load(q_ptr + o3 + 2 * HW, mask=m, other=0.0)
        tl.store(out_ptr + o3, _remodulate(q0, c_ptr, e_ptr, k_ptr, o3, m, d0, light, HAS_E, HAS_K), mask=m)
        tl.store(out_ptr + o3 + HW, _remodulate(q1, c_ptr, e_ptr, k_ptr, o3 + HW, m, d1, light, HAS_E, HAS_K), mask=m)
        tl.store(out_ptr + o3 + 2 * HW, _remodulate(q2, c_ptr, e_ptr, k_ptr, o3 + 2 * HW, m, d2, light, HAS_E, HAS_K),
                 mask=m)


def _restore(desc: RestoreOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.RestoreOp` on CUDA: the light-source mask by the torch code
    (its two box passes here), one kernel for the demodulated light and its capped peak, the
    firefly bound's box, one for the clamp, the guided filter's kernels (at 1 / s resolution on
    ``avg_pool2d`` means: its coefficients only), and one for the apply (upsampling the
    coefficients) with the remodulation."""
    import torch.nn.functional as F

    from torchgi.core.check import check_finite
    from torchgi.denoise import _demodulator, _light_sources, _surface
    from torchgi.settings import PIPELINE

    for name, t in desc.light_inputs():
        check_finite(t, name)
    color, albedo = desc.color.contiguous(), desc.albedo.contiguous()
    emission = None if desc.emission is None else desc.emission.contiguous()
    kept = None if desc.kept is None else desc.kept.contiguous()
    hit = None if desc.hit is None else desc.hit.contiguous()
    B, _, H, W = color.shape
    HW, s, dev = H * W, desc.subsample, color.device
    guide = desc.spec.build().contiguous()
    n = guide.shape[1]
    level = desc.level.reshape(B).to(torch.float32).contiguous()
    if emission is not None:
        lights = _light_sources(emission, PIPELINE.light * desc.level)
    else:
        base = color - kept if kept is not None else color
        lights = _light_sources(base / _demodulator(albedo, _surface(hit, albedo)), PIPELINE.light * desc.level)
    has_l = bool(lights.any())
    x, peak = torch.empty_like(color), torch.empty(B, 1, H, W, dtype=torch.float32, device=dev)
    n_blk = _cdiv(HW, _PIX)
    flags = {"HAS_E": emission is not None, "HAS_K": kept is not None, "HAS_HIT": hit is not None, "HAS_L": has_l}
    lights = lights.contiguous().view(torch.uint8)  # bool planes as bytes
    ptrs = [color, emission if emission is not None else color, kept if kept is not None else color, albedo,
            hit.view(torch.uint8) if hit is not None else lights, lights]
    k = float(desc.firefly)
    _prepare[(n_blk * B,)](*ptrs, level, x, peak, k, float(PIPELINE.albedo_floor), HW, n_blk, **flags, BLOCK=_PIX)
    _clamp[(n_blk * B,)](x, _box(peak, PIPELINE.firefly_radius), k, HW, n_blk, BLOCK=_PIX)
    mean_p = (x.mean((2, 3)) if desc.centre_src is None else desc.centre_src.to(dev, torch.float32)).expand(B, 3)
    mean_g = guide.mean((2, 3)) if desc.centre_guide is None else desc.centre_guide.to(dev, torch.float32)
    mean_p, mean_g = mean_p.contiguous(), mean_g.contiguous()
    eps = torch.full((B, n, 1, 1), max(float(desc.eps), torch.finfo(torch.float32).tiny), dtype=torch.float32,
                     device=dev)
    out = torch.empty_like(color)
    if s == 1:
        q, coef, h, w = _guided(guide, x, mean_g, mean_p, mean_p, desc.radius, eps), x, H, W
    else:
        low_g, low_x = F.avg_pool2d(guide, s, ceil_mode=True), F.avg_pool2d(x, s, ceil_mode=True)
        q, h, w = x, low_x.shape[-2], low_x.shape[-1]
        coef = _guided(low_g.contiguous(), low_x.contiguous(), mean_g, mean_p, mean_p, round(desc.radius / s), eps,
                       coefficients_only=True).contiguous()
    _finish[(n_blk * B,)](q, coef, guide, mean_g, mean_p, *ptrs[:5], lights, out, float(PIPELINE.albedo_floor), H, W,
                          h, w, 1.0 / s, n_blk, N=n, UPSAMPLE=s > 1, **flags, BLOCK=_PIX)
    return out


# ---------------------------------------------------------------------------------------- ops
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


def atrous(desc: ATrousOp) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """:class:`~torchgi.backends.base.ATrousOp`, a level per launch on the raw guides with the
    images' inverse σ's (the kernel scales the distances; normals also by ``1 / step²``).

    Example:
        >>> c = torch.full((1, 3, 8, 8), 0.5, device="cuda")                                         # doctest: +SKIP
        >>> one = torch.ones(1, 1, 1, 1, device="cuda")                                             # doctest: +SKIP
        >>> torch.allclose(atrous(ATrousOp(c, None, None, None, None, one, None, None, 2))[0], c)   # doctest: +SKIP
        True
    """
    B, ct, dev = desc.color.shape[0], desc.color.dtype, desc.color.device
    inv = torch.stack([torch.ones(B, dtype=ct, device=dev) if t is None else t.reshape(B)
                       for t in (desc.inv_color, desc.inv_normal, desc.inv_position)], 1)
    n = desc.normal if desc.inv_normal is not None else None
    x = desc.position if desc.inv_position is not None else None

    def level(c, var, valid, i):
        return _atrous_level(c, n, x, inv, var, valid, 2**i, colour_scale(desc, i, var, factor_only=True))

    return iterate_levels(desc, level)


def restore(desc: RestoreOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.RestoreOp`: the Denoiser's guided pipeline in a few launches
    (:func:`_restore`).

    Example:
        >>> from torchgi.backends.base import GuideSpec
        >>> c = torch.rand(1, 3, 8, 8, device="cuda"); a = torch.full_like(c, 0.5)    # doctest: +SKIP
        >>> spec = GuideSpec(torch.zeros_like(c), None, (0,), (0.5,), (0.5,))          # doctest: +SKIP
        >>> restore(RestoreOp(c, None, None, a, None, spec, torch.ones(1, 1, 1, 1, device="cuda"), 1, 1e-4, 1,
        ...                   4.0)).shape                                              # doctest: +SKIP
        torch.Size([1, 3, 8, 8])
    """
    return _restore(desc)
