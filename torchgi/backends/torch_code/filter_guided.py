"""The torch code of the guided filter: products of the centred guide and source
box-filtered, the per-pixel ``C x C`` solve as a closed-form LDLᵀ in element-wise ops
(:func:`solve`: exportable, half-safe, no ``torch.linalg``), coefficients box-filtered and
applied; eagerly on the CPU the same through a :class:`~torchgi.backends.torch_code.filter_box.PlaneBoxer`
one image at a time with the solve in row strips. :func:`guided_filter` composes the filter at
1 / s resolution (He & Sun 2015) around the seam's :class:`~torchgi.backends.base.GuidedOp`."""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from torchgi.backends.autograd_ops import box_adjoint, box_mean
from torchgi.backends.base import (
    GuidedGradOp,
    GuidedOp,
    UpsampleApplyOp,
    run,
)
from torchgi.backends.torch_code.filter_box import PlaneBoxer, block_mean, in_place
from torchgi.core.check import is_tracing
from torchgi.core.dtypes import compute_dtype, variance_rounding


def _pairs(n: int) -> list[tuple[int, int]]:
    """Lower-triangle index pairs ``(i, j), j <= i`` of an ``n x n`` symmetric matrix."""
    return [(i, j) for i in range(n) for j in range(i + 1)]


def solve(
    mI: list[torch.Tensor], mp: torch.Tensor, mII: dict[tuple[int, int], torch.Tensor],
    mIp: list[torch.Tensor], eps: torch.Tensor, out: list[torch.Tensor] | None = None,
) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Per-pixel ``a = (Σ + diag(ε))^-1 cov`` and ``b = mean(p) - aᵀ mean(I)``.

    ``mI[i]`` is ``(B,1,H,W)``, ``mp`` ``(B,Cs,H,W)``, ``mII[(i,j)]`` ``(B,1,H,W)`` for j <= i,
    ``mIp[i]`` ``(B,Cs,H,W)``; ``eps`` is ``(B,n,1,1)`` or ``(B,n,H,W)``. Returns ``a`` as a list over guide
    channels of ``(B,Cs,H,W)`` and ``b (B,Cs,H,W)``, written into ``out`` (``n + 1`` tensors)
    when given. LDLᵀ (``E = L·D``), no square roots, no branches, elementwise ops only.

    ``Σ_ii = E[I_i²] - E[I_i]²`` carries a rounding error of a few ``finfo.eps · E[I_i²]``;
    each ε_i is raised to ``16 · finfo.eps · E[I_i²]`` per pixel (plus the smallest normal
    number) and pivots are clamped there, so flat guides and ``eps = 0`` give finite, exact
    box means instead of amplified rounding noise.

    Example:
        >>> one = torch.ones(1, 1, 1, 1)   # E[I] = 0, E[I²] = 1, E[p] = 0, E[Ip] = 0.5: a = 0.5 / (1 + ε)
        >>> a, b = solve([0 * one], 0 * one, {(0, 0): one}, [0.5 * one], torch.zeros(1, 1, 1, 1))
        >>> round(float(a[0]), 5), float(b)   # ε raised to the rounding level, 16 · eps(float32)
        (0.5, 0.0)
    """
    n = len(mI)
    outs: list[dict] = [{} if out is None else {"out": o} for o in (out or [None] * (n + 1))]
    L, D, _ = _factor(mI, mII, eps)
    cov = [torch.addcmul(mIp[i], mI[i], mp, value=-1) for i in range(n)]
    a = _substitute(L, D, cov, outs[:n])
    b = mp
    for i in range(n):
        b = torch.addcmul(b, a[i], mI[i], value=-1, **(outs[n] if i + 1 == n else {}))
    return a, b


def _factor(
    mI: list[torch.Tensor], mII: dict[tuple[int, int], torch.Tensor], eps: torch.Tensor
) -> tuple[dict[tuple[int, int], torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
    """LDLᵀ of ``Σ + diag(ε_eff)`` (see :func:`solve`): ``L[(i, j)]`` (i > j), the pivots ``D`` and
    the raised ``ε_eff`` per guide channel, all ``(B,1,H,W)``."""
    n = len(mI)
    unit = variance_rounding(mI[0].dtype)
    eps = eps.clamp_min(torch.finfo(mI[0].dtype).tiny)
    A: dict[tuple[int, int], torch.Tensor] = {}
    eps_eff: list[torch.Tensor] = []
    for i, j in _pairs(n):
        s = torch.addcmul(mII[(i, j)], mI[i], mI[j], value=-1)
        if i == j:
            eps_eff.append(torch.maximum(mII[(i, i)] * unit, eps[:, i : i + 1]))
            s = s.clamp_min(0) + eps_eff[i]
        A[(i, j)] = s
    L: dict[tuple[int, int], torch.Tensor] = {}
    E: dict[tuple[int, int], torch.Tensor] = {}
    D: list[torch.Tensor] = []
    for j in range(n):
        d = A[(j, j)]
        for k in range(j):
            d = torch.addcmul(d, L[(j, k)], E[(j, k)], value=-1)
        D.append(torch.maximum(d, eps_eff[j]))
        for i in range(j + 1, n):
            v = A[(i, j)]
            for k in range(j):
                v = torch.addcmul(v, L[(i, k)], E[(j, k)], value=-1)
            E[(i, j)] = v
            L[(i, j)] = v / D[j]
    return L, D, eps_eff


def _substitute(
    L: dict[tuple[int, int], torch.Tensor], D: list[torch.Tensor], rhs: list[torch.Tensor],
    outs: list[dict] | None = None,
) -> list[torch.Tensor]:
    """``x = (L D Lᵀ)^-1 rhs`` from :func:`_factor`'s ``L, D``; ``rhs`` a list over guide
    channels of ``(B,Cs,H,W)``; ``outs[i]`` the ``out=`` keyword of ``x[i]``'s last op, if any."""
    n = len(D)
    outs = outs or [{}] * n
    y: list[torch.Tensor] = []
    for i in range(n):
        v = rhs[i]
        for k in range(i):
            v = torch.addcmul(v, L[(i, k)], y[k], value=-1)
        y.append(v)
    x: list[torch.Tensor] = list(rhs)
    for i in reversed(range(n)):
        last = i + 1 == n
        v = torch.div(y[i], D[i], **(outs[i] if last else {}))
        for k in range(i + 1, n):
            v = torch.addcmul(v, L[(k, i)], x[k], value=-1, **(outs[i] if k + 1 == n else {}))
        x[i] = v
    return x


def _unpack(planes: list[torch.Tensor], n: int, Cs: int):
    """Split box means of ``I_i``, ``p_c``, ``I_i I_j (j <= i)``, ``I_i p_c`` in that order (``(B,1,H,W)`` each) into the
    ``mI, mp, mII, mIp`` arguments of :func:`solve`."""
    pairs = _pairs(n)
    mI = planes[:n]
    mp = torch.cat(planes[n : n + Cs], 1)
    off = n + Cs
    mII = dict(zip(pairs, planes[off : off + len(pairs)]))
    off += len(pairs)
    mIp = [torch.cat(planes[off + i * Cs : off + (i + 1) * Cs], 1) for i in range(n)]
    return mI, mp, mII, mIp


def _guided_reference(
    I: torch.Tensor, p: torch.Tensor, r: int, eps: torch.Tensor, coefficients_only: bool = False
) -> torch.Tensor:
    """Differentiable, traceable path: box means of stacked planes (:func:`~torchgi.backends.autograd_ops.box_mean`:
    under autograd the compiled box forward and backward, traced :func:`box_pool`). Returns the output
    without ``mean(p)`` (centred inputs), or the box-filtered coefficients ``(B, n + 1, Cs, H, W)``
    (``a_0 .. a_{n-1}, b``)."""
    n, Cs = I.shape[1], p.shape[1]
    a, b = solve(*_box_means(I, p, r), eps)
    coeffs = box_mean(torch.cat(a + [b], 1), r)
    if coefficients_only:
        return coeffs.unflatten(1, (n + 1, Cs))
    return apply_coefficients(coeffs.unflatten(1, (n + 1, Cs)), I)


def _box_means(I: torch.Tensor, p: torch.Tensor, r: int):
    """The box means :func:`solve` takes (``mI, mp, mII, mIp``) of centred ``I (B,n,H,W)``,
    ``p (B,Cs,H,W)``, in one box call."""
    n, Cs = I.shape[1], p.shape[1]
    planes = [I, p] + [I[:, i : i + 1] * I[:, j : j + 1] for i, j in _pairs(n)] + [I[:, i : i + 1] * p for i in range(n)]
    return _unpack(list(box_mean(torch.cat(planes, 1), r).split(1, 1)), n, Cs)


class GuidedFunction(torch.autograd.Function):
    """The guided filter of centred ``I (B,n,H,W)``, ``p (B,Cs,H,W)`` with ``eps`` ``(B|1,n,1,1)``
    or ``(B|1,n,H,W)`` (the output without ``mean(p)``), whose backward is written out: the forward
    is one :class:`~torchgi.backends.base.GuidedOp` through the seam (the compiled kernels for
    float32) and saves only its inputs; the backward is one
    :class:`~torchgi.backends.base.GuidedGradOp` through the seam (:func:`guided_grad` in torch, a
    C kernel on the CPU, Triton on CUDA), which recomputes what it needs.

    Example:
        >>> I = torch.rand(1, 2, 8, 8, dtype=torch.float64, requires_grad=True)
        >>> p = torch.rand(1, 1, 8, 8, dtype=torch.float64, requires_grad=True)
        >>> eps = torch.full((1, 2, 1, 1), 0.01, dtype=torch.float64)
        >>> torch.autograd.gradcheck(lambda i, q: GuidedFunction.apply(i, q, eps, 1), (I, p))
        True
    """

    @staticmethod
    def forward(ctx: Any, I: torch.Tensor, p: torch.Tensor, eps: torch.Tensor, r: int) -> torch.Tensor:
        ctx.save_for_backward(I, p, eps)
        ctx.r = r
        zero_I = torch.zeros(I.shape[0], I.shape[1], 1, 1, dtype=I.dtype, device=I.device)
        zero_p = torch.zeros(p.shape[0], p.shape[1], 1, 1, dtype=p.dtype, device=p.device)
        return run(GuidedOp(I, p, zero_I, zero_p, r, eps.expand(I.shape[0], -1, -1, -1)))

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        I, p, eps = ctx.saved_tensors
        dI, dp, d_eps = run(GuidedGradOp(I, p, eps, ctx.r, g.contiguous(), *ctx.needs_input_grad[:3]))
        return dI, dp, d_eps, None


def guided_grad(desc: GuidedGradOp) -> tuple[torch.Tensor | None, ...]:
    """:class:`~torchgi.backends.base.GuidedGradOp` in torch (the reference of the compiled
    kernels): the box means and the solve recomputed, then the adjoint of each step: the box's
    transpose through the seam, the solve's through the same LDLᵀ (``∂L/∂cov = A^-1 ∂L/∂a``,
    ``∂L/∂A = -(A^-1 ∂L/∂a) aᵀ``; ``A`` is symmetric); each intermediate dropped once used.

    Example:
        >>> I, p = torch.zeros(1, 1, 4, 4), torch.rand(1, 1, 4, 4)   # a flat guide: q = box(box(p))
        >>> dI, dp, _ = guided_grad(GuidedGradOp(I, p, torch.ones(1, 1, 1, 1), 0, torch.ones(1, 1, 4, 4)))
        >>> torch.allclose(dp, torch.ones(1, 1, 4, 4))   # r = 0: q = p
        True
    """
    I, p, eps, r, g = desc.guide, desc.src, desc.eps, desc.radius, desc.grad
    n, Cs = I.shape[1], p.shape[1]
    Ii = I.split(1, 1)
    mI, mp, mII, mIp = _box_means(I, p, r)
    L, D, _ = _factor(mI, mII, eps)
    a = _substitute(L, D, [torch.addcmul(mIp[i], mI[i], mp, value=-1) for i in range(n)])
    b = mp
    for i in range(n):
        b = torch.addcmul(b, a[i], mI[i], value=-1)
    coeffs = box_mean(torch.cat(a + [b], 1), r).split(Cs, 1)  # ā_0 .. ā_{n-1}, b̄
    del b  # (each intermediate is dropped once used: the backward's peak memory)
    # q = Σ_i ā_i I_i + b̄
    dI = [(g * coeffs[i]).sum(1, keepdim=True) for i in range(n)]
    del coeffs
    adj = box_adjoint(torch.cat([g * Ii[i] for i in range(n)] + [g], 1), r, overwrite=True).split(Cs, 1)
    stack, deps = _solve_adjoint(adj, a, L, D, mI, mp, mII, eps)
    del adj, a, L, D, mI, mp, mII, mIp
    T = box_adjoint(stack, r, overwrite=True)
    del stack
    pairs = _pairs(n)
    TI, Tp = T[:, :n].split(1, 1), T[:, n : n + Cs]
    TII = dict(zip(pairs, T[:, n + Cs : n + Cs + len(pairs)].split(1, 1)))
    TIp = T[:, n + Cs + len(pairs) :].split(Cs, 1)
    dp = Tp
    for i in range(n):
        dI[i] = dI[i] + TI[i] + (TIp[i] * p).sum(1, keepdim=True)
        dp = torch.addcmul(dp, TIp[i], Ii[i])
    for (i, j), t in TII.items():
        if i == j:
            dI[i] = dI[i] + 2 * t * Ii[i]
        else:
            dI[i] = torch.addcmul(dI[i], t, Ii[j])
            dI[j] = torch.addcmul(dI[j], t, Ii[i])
    d_eps = None
    if desc.need_eps:
        d_eps = torch.cat(deps, 1)
        d_eps = d_eps if eps.shape[-2:] == d_eps.shape[-2:] else d_eps.sum((2, 3), keepdim=True)
        d_eps = d_eps.sum(0, keepdim=True) if eps.shape[0] == 1 < d_eps.shape[0] else d_eps
    return torch.cat(dI, 1) if desc.need_guide else None, dp if desc.need_src else None, d_eps


def _solve_adjoint(
    adj: tuple[torch.Tensor, ...], a: list[torch.Tensor], L: dict, D: list[torch.Tensor], mI: list[torch.Tensor],
    mp: torch.Tensor, mII: dict[tuple[int, int], torch.Tensor], eps: torch.Tensor,
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The solve's adjoint in :func:`guided_grad`: from ``adj`` (the gradients of ``a_0..a_{n-1},
    b``), the gradients of the box means stacked in :func:`_box_means`' order and of each ``ε_i``
    per pixel."""
    n = len(a)
    db = adj[n]
    # b = mp - Σ_i a_i mI_i ;  a = A^-1 cov
    dmp = db
    dmI = [-(db * a[i]).sum(1, keepdim=True) for i in range(n)]
    z = _substitute(L, D, [torch.addcmul(adj[i], db, mI[i], value=-1) for i in range(n)])
    dmIp = z
    for i in range(n):
        dmI[i] = dmI[i] - (z[i] * mp).sum(1, keepdim=True)
        dmp = torch.addcmul(dmp, z[i], mI[i], value=-1)
    dmII: dict[tuple[int, int], torch.Tensor] = {}
    deps = []
    unit = variance_rounding(a[0].dtype)
    for i, j in _pairs(n):
        if i != j:
            d = -(z[i] * a[j] + z[j] * a[i]).sum(1, keepdim=True)
            dmII[(i, j)] = d
            dmI[i] = torch.addcmul(dmI[i], d, mI[j], value=-1)
            dmI[j] = torch.addcmul(dmI[j], d, mI[i], value=-1)
            continue
        dA = -(z[i] * a[i]).sum(1, keepdim=True)
        raw = (mII[(i, i)] - mI[i] * mI[i]) >= 0
        from_eps = eps[:, i : i + 1] >= mII[(i, i)] * unit
        dvar = torch.where(raw, dA, 0)
        dmII[(i, i)] = dvar + torch.where(from_eps, 0, dA * unit)
        dmI[i] = dmI[i] - 2 * mI[i] * dvar
        deps.append(torch.where(from_eps, dA, 0))
    return torch.cat(dmI + [dmp] + [dmII[k] for k in _pairs(n)] + dmIp, 1), deps


def upsample_apply(desc: UpsampleApplyOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.UpsampleApplyOp`: ``F.interpolate`` x2, then
    :func:`apply_coefficients` on the guide padded to that size, and the output cropped: the crop
    moves ``Cs`` planes, not the ``(n + 1) Cs`` of the coefficients (in onnxruntime a crop of the
    coefficients cost more than their upsampling: docs/benchmarks/onnx.md).

    Example:
        >>> c = torch.zeros(1, 2, 1, 2, 2); c[:, 1] = 3.0   # a = 0, b = 3
        >>> upsample_apply(UpsampleApplyOp(c, torch.rand(1, 1, 4, 3))).unique().tolist()
        [3.0]
    """
    return upsampled_apply(desc.coeffs, desc.guide, 2)


def upsampled_apply(coeffs: torch.Tensor, guide: torch.Tensor, s: int) -> torch.Tensor:
    """Coefficients ``(B, n + 1, Cs, h, w)`` on the ``s x s`` blocks of ``guide (B, n, H, W)``
    (``h, w = ⌈H/s⌉, ⌈W/s⌉``) upsampled bilinearly by ``s`` and applied to it: ``(B, Cs, H, W)``.
    The guide is padded to ``s h x s w`` and the output cropped (not the coefficients).

    Example:
        >>> c = torch.zeros(1, 2, 1, 2, 2); c[:, 0] = 1.0   # a = 1, b = 0: the guide itself
        >>> g = torch.rand(1, 1, 3, 4)
        >>> torch.equal(upsampled_apply(c, g, 2), g)
        True
    """
    H, W = guide.shape[-2:]
    h, w = coeffs.shape[-2:]
    up = F.interpolate(coeffs.flatten(1, 2), scale_factor=s, mode="bilinear", align_corners=False)
    padded = F.pad(guide, (0, s * w - W, 0, s * h - H), mode="replicate")  # (its pad is cropped away)
    return apply_coefficients(up.unflatten(1, coeffs.shape[1:3]), padded)[..., :H, :W]


def apply_coefficients(coeffs: torch.Tensor, I: torch.Tensor) -> torch.Tensor:
    """``b + Σ_i a_i I_i`` for coefficients ``(B, n + 1, Cs, H, W)`` and a centred guide ``(B, n, H, W)``.

    Example:
        >>> coeffs = torch.tensor([2.0, 1.0]).view(1, 2, 1, 1, 1)   # a = 2, b = 1
        >>> apply_coefficients(coeffs, torch.full((1, 1, 1, 1), 3.0)).item()
        7.0
    """
    n = I.shape[1]
    out = coeffs[:, n]
    for i in range(n):
        out = out + coeffs[:, i] * I[:, i : i + 1]
    return out


_STRIP_ELEMENTS = 1 << 16  # pixels per strip of the per-pixel solve: temporaries stay in L2


class _Workspace:
    """Buffers of the CPU path for one (guide channels, source channels, H, W, r, dtype).

    glibc returns large freed blocks to the OS, so fresh buffers are page-faulted in on every
    call (a large share of the run time, docs/calibration.md). :class:`Guided` keeps one workspace
    between calls; the functional form builds a new one each time.
    """

    def __init__(self, n: int, Cs: int, H: int, W: int, r: int, dtype: torch.dtype) -> None:
        self.key = (n, Cs, H, W, r, dtype)
        self.boxer = PlaneBoxer(H, W, r, dtype)
        self.I = torch.empty(n, H, W, dtype=dtype)  # centred guide of one image
        self.p = torch.empty(Cs, H, W, dtype=dtype)  # centred source of one image
        self.mI = torch.empty(n, H, W, dtype=dtype)
        self.mp = torch.empty(Cs, H, W, dtype=dtype)
        self.mII = torch.empty(len(_pairs(n)), H, W, dtype=dtype)
        self.mIp = torch.empty(n, Cs, H, W, dtype=dtype)
        self.coeffs = torch.empty(n + 1, Cs, H, W, dtype=dtype)  # a_0 .. a_{n-1}, b

    @classmethod
    def get(cls, holder: dict | None, n: int, Cs: int, H: int, W: int, r: int, dtype: torch.dtype) -> _Workspace:
        key = (n, Cs, H, W, r, dtype)
        if holder is not None and holder.get("ws") is not None and holder["ws"].key == key:
            return holder["ws"]
        ws = cls(*key)
        if holder is not None:
            holder["ws"] = ws
        return ws


def _guided_fast(
    g: torch.Tensor, p: torch.Tensor, mean_g: torch.Tensor, mean_p: torch.Tensor, r: int,
    eps: torch.Tensor, holder: dict | None = None, coefficients_only: bool = False,
) -> torch.Tensor:
    """CPU eager path: box means one plane at a time (cache-resident, reused buffers), the
    solve in row strips so its temporaries stay small; strips of the grouped buffers are views.
    Centring (by ``mean_g``, ``mean_p``) happens here, into the workspace. Returns the output,
    or the box-filtered coefficients ``(B, n + 1, Cs, H, W)``."""
    B, n, H, W = g.shape
    Cs = p.shape[1]
    ws = _Workspace.get(holder, n, Cs, H, W, r, g.dtype)
    boxer, pairs = ws.boxer, _pairs(n)
    out = torch.empty((B, n + 1, Cs, H, W) if coefficients_only else (B, Cs, H, W), dtype=g.dtype)
    for bi in range(B):
        Ib = torch.sub(g[bi], mean_g[bi], out=ws.I)
        pb = torch.sub(p[bi], mean_p[bi], out=ws.p)
        boxer(Ib, ws.mI)
        boxer(pb, ws.mp)
        # products and their box means a stack at a time: while a stack is in cache
        for group, factors in (
            (ws.mII, [(Ib[i], Ib[j]) for i, j in pairs]),
            (ws.mIp.view(n * Cs, H, W), [(Ib[i], pb[c]) for i in range(n) for c in range(Cs)]),
        ):
            for a in range(0, len(factors), boxer.stack):
                stack = group[a : a + boxer.stack]
                for dst, (u, v) in zip(stack, factors[a : a + boxer.stack]):
                    torch.mul(u, v, out=dst)
                boxer(stack, stack)
        e = eps[bi : bi + 1]
        strip = max(1, _STRIP_ELEMENTS // W)
        for y in range(0, H, strip):
            rows = slice(y, y + strip)
            solve(
                [ws.mI[i : i + 1, rows][None] for i in range(n)], ws.mp[:, rows][None],
                {pr: ws.mII[k : k + 1, rows][None] for k, pr in enumerate(pairs)},
                [ws.mIp[i, :, rows][None] for i in range(n)], e,
                out=[ws.coeffs[k, :, rows][None] for k in range(n + 1)],
            )
        planes = ws.coeffs.view(-1, H, W)
        boxer(planes, planes)
        if coefficients_only:
            out[bi].copy_(ws.coeffs)
            continue
        acc = torch.add(ws.coeffs[n], mean_p[bi], out=out[bi])
        for i in range(n):
            acc.addcmul_(ws.coeffs[i], Ib[i : i + 1])
    return out



def guided(desc: GuidedOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.GuidedOp` in torch: under autograd (not traced)
    :class:`GuidedFunction` (the compiled forward, the backward written out), the in-place CPU
    path eagerly on the CPU, else the differentiable reference (traced and exported).

    Example:
        >>> from torchgi.backends.torch_code.filter_box import box_pool
        >>> p = torch.rand(1, 1, 6, 6); m = p.mean((2, 3), keepdim=True)
        >>> flat = torch.ones(1, 1, 6, 6)   # a constant guide: the box mean of the box mean
        >>> out = guided(GuidedOp(flat, p, torch.ones(1, 1, 1, 1), m, 1, torch.zeros(1, 1, 1, 1)))
        >>> torch.allclose(out, box_pool(box_pool(p, 1), 1), atol=1e-6)
        True
    """
    g, p, e = desc.guide, desc.src, desc.eps
    if not desc.coefficients_only and not is_tracing() and torch.is_grad_enabled() \
            and any(t.requires_grad for t in desc.tensors()):
        return GuidedFunction.apply(g - desc.mean_guide, p - desc.mean_src, e, desc.radius) + desc.mean_src
    if in_place(desc) and e.shape[-2:] == (1, 1):
        return _guided_fast(g, p, desc.mean_guide, desc.mean_src, desc.radius, e, desc.workspace,
                            desc.coefficients_only)
    out = _guided_reference(g - desc.mean_guide, p - desc.mean_src, desc.radius, e, desc.coefficients_only)
    return out if desc.coefficients_only else out + desc.mean_src




def guided_filter(
    src: torch.Tensor, guide: torch.Tensor, radius: int, eps: torch.Tensor, workspace: dict | None = None,
    subsample: int = 1,
) -> torch.Tensor:
    """The guided filter of ``src (B,C,H,W)`` on ``guide (B,G,H,W)`` after its argument checks, each
    :class:`~torchgi.backends.base.GuidedOp` through the seam (:func:`~torchgi.backends.base.run`):
    light and guide centred by their means, and at ``subsample`` s > 1 the fast guided filter (He &
    Sun 2015): coefficients from s x s means at radius ``round(radius / s)``, upsampled bilinearly
    by the factor s (the grid of pixel centres does not depend on the size: tiles agree) and
    applied to the full-resolution guide. ``eps``: ``(B, G, 1, 1)`` or a ``(B, G, H, W)`` map
    (averaged over the s x s blocks) in the compute dtype;
    ``workspace``: a dict the CPU path keeps its buffers in between calls, or None. Returns
    ``(B, C, H, W)`` in the dtype of ``src``.

    Example:
        >>> src, guide = torch.rand(1, 3, 16, 16), torch.rand(1, 2, 16, 16)
        >>> eps = torch.full((1, 2, 1, 1), 0.01)
        >>> (guided_filter(src, guide, 2, eps, None, 2) - src).abs().mean() < 0.5
        tensor(True)
    """
    ct = compute_dtype(src.dtype)
    if src.numel() == 0:
        return src.clone()
    g, p = guide.to(ct), src.to(ct)
    mean_g, mean_p = g.mean(dim=(2, 3), keepdim=True), p.mean(dim=(2, 3), keepdim=True)
    if subsample == 1:
        return run(GuidedOp(g, p, mean_g, mean_p, radius, eps, workspace=workspace)).to(src.dtype)
    gc = g - mean_g
    low_g, low_p = block_mean(gc, subsample), block_mean(p - mean_p, subsample)
    zero_g, zero_p = torch.zeros_like(mean_g), torch.zeros_like(mean_p)  # low_g, low_p are centred
    eps = eps if eps.shape[-2:] == (1, 1) else block_mean(eps, subsample)
    coeffs = run(GuidedOp(low_g, low_p, zero_g, zero_p, round(radius / subsample), eps, coefficients_only=True,
                          workspace=workspace))
    return (upsampled_apply(coeffs, gc, subsample) + mean_p).to(src.dtype)
