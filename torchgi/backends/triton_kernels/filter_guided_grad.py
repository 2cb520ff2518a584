"""The Triton guided filter's gradients (:class:`~torchgi.backends.base.GuidedGradOp`): the
written-out backward of :func:`torchgi.backends.torch_code.filter_guided.guided_grad` with its
box means from the forward's two box kernels and its per-pixel steps in two launches: the
solve's adjoint (:func:`_adjoint`: the LDLᵀ of the forward, then for every source channel the
gradients of the box means) and the last step (:func:`_gradients`: dI, dp from the transposed
boxes)."""

from __future__ import annotations

import torch

from torchgi.backends.autograd_ops import window_counts
from torchgi.backends.base import GuidedGradOp
from torchgi.backends.triton_kernels.common import _cdiv, tl, triton
from torchgi.backends.triton_kernels.filter_guided import _PIX, _box_products, _factored, _plane, _solve, _split
from torchgi.core.dtypes import variance_rounding

if triton is not None:

    @triton.jit
    def _count(i, H, W, r):
        # pixels of the (2r+1)² window around flat pixel i, clipped to the image
        y = i // W
        x = i - y * W
        return ((tl.minimum(x + r, W - 1) - tl.maximum(x - r, 0) + 1) *
                (tl.minimum(y + r, H - 1) - tl.maximum(y - r, 0) + 1)).to(tl.float32)

    @triton.jit
    def _diagonal(dA, mi, q, eps_ptr, unit, tiny):
        # the diagonal of A = mII - mI mIᵀ + diag(ε_eff): the gradient of mII_ii (Σ clamped at 0
        # and ε raised to the rounding level pass none) and of ε_i; dmI_i's share is -2 mI_i dvar
        dvar = tl.where(q - mi * mi >= 0.0, dA, 0.0)
        from_eps = tl.maximum(tl.load(eps_ptr), tiny) >= q * unit
        return dvar, dvar + tl.where(from_eps, 0.0, dA * unit), tl.where(from_eps, dA, 0.0)

    @triton.jit
    def _adjoint(  # noqa: PLR0915 - the solve's adjoint for up to 4 guide channels unrolled in one launch
                 m_ptr, a_ptr, adj_ptr, eps_ptr, s_ptr, de_ptr, H, W, r, Cs, n_blk, sm_b, sa_b, sadj_b, ss_b, sde_b,
                 unit, tiny, N: tl.constexpr, BLOCK: tl.constexpr):
        # From the box means m (the forward's K planes), the coefficients a (not boxed) and adj (the
        # transposed boxes of g I and g: the gradients of a and b), the gradients of the K means
        # divided by the window's pixels (s, the order of m) and of ε per pixel (de).
        blk, b = _split(tl.program_id(0), n_blk)
        b = b.to(tl.int64)
        HW = H * W
        i = blk * BLOCK + tl.arange(0, BLOCK)
        m = i < HW
        inv = 1.0 / _count(i, H, W, r)
        base = m_ptr + b * sm_b + i
        P = N * (N + 1) // 2
        zero = tl.zeros([BLOCK], dtype=tl.float32)
        mi0, mi1, mi2, mi3, q00, q11, q22, q33, d0, d1, d2, d3, l10, l20, l30, l21, l31, l32 = _factored(
            base, eps_ptr + b * N, HW, Cs, m, unit, tiny, zero, N)  # the forward's LDLᵀ (_solve)
        dm0, dm1, dm2, dm3 = zero, zero, zero, zero  # dL/dmI
        t00, t10, t11, t20, t21, t22, t30, t31, t32, t33 = zero, zero, zero, zero, zero, zero, zero, zero, zero, zero
        pa = a_ptr + b * sa_b + i
        pj = adj_ptr + b * sadj_b + i
        ps = s_ptr + b * ss_b + i
        for c in range(Cs):
            mp = _plane(base, N + c, HW, m)
            db = _plane(pj, N * Cs + c, HW, m)  # b = mp - Σ_k a_k mI_k
            c0 = _plane(pj, c, HW, m) - db * mi0  # a = A^-1 cov: z = A^-1 (da - db mI)
            k0 = _plane(pa, c, HW, m)
            c1, c2, c3, k1, k2, k3 = zero, zero, zero, zero, zero, zero
            if N > 1:
                c1 = _plane(pj, Cs + c, HW, m) - db * mi1
                k1 = _plane(pa, Cs + c, HW, m)
            if N > 2:
                c2 = _plane(pj, 2 * Cs + c, HW, m) - db * mi2
                k2 = _plane(pa, 2 * Cs + c, HW, m)
            if N > 3:
                c3 = _plane(pj, 3 * Cs + c, HW, m) - db * mi3
                k3 = _plane(pa, 3 * Cs + c, HW, m)
            y1 = c1 - l10 * c0
            y2 = c2 - l20 * c0 - l21 * y1
            y3 = c3 - l30 * c0 - l31 * y1 - l32 * y2
            z3 = y3 / d3
            z2 = y2 / d2 - l32 * z3
            z1 = y1 / d1 - l21 * z2 - l31 * z3
            z0 = c0 / d0 - l10 * z1 - l20 * z2 - l30 * z3
            dm0 -= db * k0 + z0 * mp
            dm1 -= db * k1 + z1 * mp
            dm2 -= db * k2 + z2 * mp
            dm3 -= db * k3 + z3 * mp
            tl.store(ps + (N + c) * HW, (db - z0 * mi0 - z1 * mi1 - z2 * mi2 - z3 * mi3) * inv, mask=m)
            tl.store(ps + (N + Cs + P + c) * HW, z0 * inv, mask=m)
            if N > 1:
                tl.store(ps + (N + Cs + P + Cs + c) * HW, z1 * inv, mask=m)
            if N > 2:
                tl.store(ps + (N + Cs + P + 2 * Cs + c) * HW, z2 * inv, mask=m)
            if N > 3:
                tl.store(ps + (N + Cs + P + 3 * Cs + c) * HW, z3 * inv, mask=m)
            # dA = -z aᵀ, symmetrised below the diagonal
            t00 -= z0 * k0
            t10 -= z1 * k0 + z0 * k1
            t11 -= z1 * k1
            t20 -= z2 * k0 + z0 * k2
            t21 -= z2 * k1 + z1 * k2
            t22 -= z2 * k2
            t30 -= z3 * k0 + z0 * k3
            t31 -= z3 * k1 + z1 * k3
            t32 -= z3 * k2 + z2 * k3
            t33 -= z3 * k3
        pe = de_ptr + b * sde_b + i
        po = ps + (N + Cs) * HW  # the mII planes
        dv, g, d = _diagonal(t00, mi0, q00, eps_ptr + b * N, unit, tiny)
        dm0 -= 2.0 * mi0 * dv
        tl.store(po, g * inv, mask=m)
        tl.store(pe, d, mask=m)
        if N > 1:
            dv, g, d = _diagonal(t11, mi1, q11, eps_ptr + b * N + 1, unit, tiny)
            dm1 -= 2.0 * mi1 * dv + t10 * mi0
            dm0 -= t10 * mi1
            tl.store(po + HW, t10 * inv, mask=m)
            tl.store(po + 2 * HW, g * inv, mask=m)
            tl.store(pe + HW, d, mask=m)
        if N > 2:
            dv, g, d = _diagonal(t22, mi2, q22, eps_ptr + b * N + 2, unit, tiny)
            dm2 -= 2.0 * mi2 * dv + t20 * mi0 + t21 * mi1
            dm0 -= t20 * mi2
            dm1 -= t21 * mi2
            tl.store(po + 3 * HW, t20 * inv, mask=m)
            tl.store(po + 4 * HW, t21 * inv, mask=m)
            tl.store(po + 5 * HW, g * inv, mask=m)
            tl.store(pe + 2 * HW, d, mask=m)
        if N > 3:
            dv, g, d = _diagonal(t33, mi3, q33, eps_ptr + b * N + 3, unit, tiny)
            dm3 -= 2.0 * mi3 * dv + t30 * mi0 + t31 * mi1 + t32 * mi2
            dm0 -= t30 * mi3
            dm1 -= t31 * mi3
            dm2 -= t32 * mi3
            tl.store(po + 6 * HW, t30 * inv, mask=m)
            tl.store(po + 7 * HW, t31 * inv, mask=m)
            tl.store(po + 8 * HW, t32 * inv, mask=m)
            tl.store(po + 9 * HW, g * inv, mask=m)
            tl.store(pe + 3 * HW, d, mask=m)
        tl.store(ps, dm0 * inv, mask=m)
        if N > 1:
            tl.store(ps + HW, dm1 * inv, mask=m)
        if N > 2:
            tl.store(ps + 2 * HW, dm2 * inv, mask=m)
        if N > 3:
            tl.store(ps + 3 * HW, dm3 * inv, mask=m)

    @triton.jit
    def _gradients(  # noqa: PLR0915 - the last step for up to 4 guide channels unrolled in one launch
                   t_ptr, ab_ptr, g_ptr, I_ptr, p_ptr, dI_ptr, dp_ptr, H, W, r, Cs, n_blk, st_b, sab_b, sg_b, sI_b,
                   sp_b, N: tl.constexpr, DI: tl.constexpr, BLOCK: tl.constexpr):
        # dp_c = T_p + Σ_k T_Ip I_k; dI_k = Σ_c g_c ā_kc + T_I + Σ_c T_Ip p_c + Σ_j T_II (2 on the
        # diagonal) I_j, with T the transposed boxes (box means of the adjoint times the pixels)
        blk, b = _split(tl.program_id(0), n_blk)
        b = b.to(tl.int64)
        HW = H * W
        i = blk * BLOCK + tl.arange(0, BLOCK)
        m = i < HW
        cnt = _count(i, H, W, r)
        pt = t_ptr + b * st_b + i
        pI = I_ptr + b * sI_b + i
        P = N * (N + 1) // 2
        zero = tl.zeros([BLOCK], dtype=tl.float32)
        I0 = _plane(pI, 0, HW, m)
        I1, I2, I3, u0, u1, u2, u3 = zero, zero, zero, zero, zero, zero, zero
        if N > 1:
            I1 = _plane(pI, 1, HW, m)
        if N > 2:
            I2 = _plane(pI, 2, HW, m)
        if N > 3:
            I3 = _plane(pI, 3, HW, m)
        for c in range(Cs):
            gc = _plane(g_ptr + b * sg_b + i, c, HW, m)
            pc = _plane(p_ptr + b * sp_b + i, c, HW, m)
            w0 = _plane(pt, N + Cs + P + c, HW, m) * cnt
            dp = _plane(pt, N + c, HW, m) * cnt + w0 * I0
            u0 += w0 * pc + gc * _plane(ab_ptr + b * sab_b + i, c, HW, m)
            if N > 1:
                w1 = _plane(pt, N + Cs + P + Cs + c, HW, m) * cnt
                dp += w1 * I1
                u1 += w1 * pc + gc * _plane(ab_ptr + b * sab_b + i, Cs + c, HW, m)
            if N > 2:
                w2 = _plane(pt, N + Cs + P + 2 * Cs + c, HW, m) * cnt
                dp += w2 * I2
                u2 += w2 * pc + gc * _plane(ab_ptr + b * sab_b + i, 2 * Cs + c, HW, m)
            if N > 3:
                w3 = _plane(pt, N + Cs + P + 3 * Cs + c, HW, m) * cnt
                dp += w3 * I3
                u3 += w3 * pc + gc * _plane(ab_ptr + b * sab_b + i, 3 * Cs + c, HW, m)
            tl.store(dp_ptr + b * sp_b + c * HW + i, dp, mask=m)
        if DI:
            q = pt + (N + Cs) * HW  # T_II in the order (0,0), (1,0), (1,1), (2,0) ...
            u0 += (_plane(pt, 0, HW, m) + 2.0 * _plane(q, 0, HW, m) * I0) * cnt
            if N > 1:
                t10 = _plane(q, 1, HW, m) * cnt
                u0 += t10 * I1
                u1 += _plane(pt, 1, HW, m) * cnt + t10 * I0 + 2.0 * _plane(q, 2, HW, m) * cnt * I1
            if N > 2:
                t20 = _plane(q, 3, HW, m) * cnt
                t21 = _plane(q, 4, HW, m) * cnt
                u0 += t20 * I2
                u1 += t21 * I2
                u2 += _plane(pt, 2, HW, m) * cnt + t20 * I0 + t21 * I1 + 2.0 * _plane(q, 5, HW, m) * cnt * I2
            if N > 3:
                t30 = _plane(q, 6, HW, m) * cnt
                t31 = _plane(q, 7, HW, m) * cnt
                t32 = _plane(q, 8, HW, m) * cnt
                u0 += t30 * I3
                u1 += t31 * I3
                u2 += t32 * I3
                u3 += _plane(pt, 3, HW, m) * cnt + t30 * I0 + t31 * I1 + t32 * I2 + \
                    2.0 * _plane(q, 9, HW, m) * cnt * I3
            pd = dI_ptr + b * sI_b + i
            tl.store(pd, u0, mask=m)
            if N > 1:
                tl.store(pd + HW, u1, mask=m)
            if N > 2:
                tl.store(pd + 2 * HW, u2, mask=m)
            if N > 3:
                tl.store(pd + 3 * HW, u3, mask=m)


def guided_grad(desc: GuidedGradOp) -> tuple[torch.Tensor | None, ...]:
    """:class:`~torchgi.backends.base.GuidedGradOp` in seven launches: the box means of the
    products (two), the forward's solve, the box means of ``a`` (two, for ``dI``) and of ``g I / N,
    g / N`` (two), the solve's adjoint, the box of its planes (two), the last step; ε's gradient
    summed over its per-pixel planes in torch.

    Example:
        >>> I, p = torch.zeros(1, 1, 4, 4, device="cuda"), torch.rand(1, 1, 4, 4, device="cuda")  # doctest: +SKIP
        >>> ones, eps = torch.ones_like(p), torch.ones(1, 1, 1, 1, device="cuda")                # doctest: +SKIP
        >>> torch.allclose(guided_grad(GuidedGradOp(I, p, eps, 0, ones))[1], ones)                # doctest: +SKIP
        True
    """
    I, p, g, r = desc.guide.contiguous(), desc.src.contiguous(), desc.grad.contiguous(), desc.radius
    B, n, H, W = I.shape
    Cs, HW = p.shape[1], H * W
    K = n + Cs + n * (n + 1) // 2 + n * Cs
    pairs = [(i, -1) for i in range(n + Cs)] + [(i, j) for i in range(n) for j in range(i + 1)] + \
        [(i, n + c) for i in range(n) for c in range(Cs)]  # the order of torch_code.filter_guided._box_means
    means = _box_products(I, p, None, None, pairs, r)
    coef = torch.empty(B, (n + 1) * Cs, H, W, dtype=torch.float32, device=I.device)
    eps = desc.eps.expand(B, n, 1, 1).reshape(B, n).contiguous()
    unit, tiny, n_blk = variance_rounding(torch.float32), torch.finfo(torch.float32).tiny, _cdiv(HW, _PIX)
    _solve[(n_blk * B,)](means, eps, coef, HW, Cs, n_blk, means.stride(0), coef.stride(0), unit, tiny, N=n, BLOCK=_PIX)
    counts = window_counts(H, W, r, g)
    adj = _box_products(I, g / counts, None, None, [(i, n + c) for i in range(n) for c in range(Cs)] +
                        [(n + c, -1) for c in range(Cs)], r).mul_(counts)  # box^T(v) = N box(v / N)
    stack = torch.empty(B, K, H, W, dtype=torch.float32, device=I.device)
    de = torch.empty(B, n, H, W, dtype=torch.float32, device=I.device)
    _adjoint[(n_blk * B,)](means, coef, adj, eps, stack, de, H, W, r, Cs, n_blk, means.stride(0), coef.stride(0),
                           adj.stride(0), stack.stride(0), de.stride(0), unit, tiny, N=n, BLOCK=_PIX)
    del means, adj
    abar = _box_products(coef, None, None, None, [(q, -1) for q in range(n * Cs)], r) if desc.need_guide else coef
    T = _box_products(stack, None, None, None, [(k, -1) for k in range(K)], r)
    dI, dp = torch.empty_like(I), torch.empty_like(p)
    _gradients[(n_blk * B,)](T, abar, g, I, p, dI, dp, H, W, r, Cs, n_blk, T.stride(0), abar.stride(0), g.stride(0),
                             I.stride(0), p.stride(0), N=n, DI=desc.need_guide, BLOCK=_PIX)
    d_eps = None
    if desc.need_eps:
        d_eps = de.sum((2, 3), keepdim=True)
        d_eps = d_eps.sum(0, keepdim=True) if desc.eps.shape[0] == 1 < B else d_eps
    return dI if desc.need_guide else None, dp if desc.need_src else None, d_eps
