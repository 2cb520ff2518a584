"""The C back end's filters: the box filter, the guided filter (its coefficient and apply
passes, and its gradients) and one À-Trous level per call."""

from __future__ import annotations

import torch

from torchgi.backends.base import (
    ATrousLevelGradOp,
    ATrousLevelOp,
    ATrousOp,
    BoxOp,
    GuidedGradOp,
    GuidedOp,
    UpsampleApplyOp,
)
from torchgi.backends.c_kernels import build
from torchgi.backends.c_kernels.runtime import (
    _PAD,
    _as_padded,
    _box_scratch,
    _layout,
    _parts,
    _ptr,
    _run,
    _taps,
    empty_planes,
    padded,
    result,
)
from torchgi.backends.levels import colour_scale, iterate_levels, scaled_guides
from torchgi.core.dtypes import variance_rounding


def _atrous_level(
    c: torch.Tensor, feat: torch.Tensor | None, feat_scale: list[float] | torch.Tensor, var: torch.Tensor | None,
    valid: torch.Tensor | None, step: int, colour_scale: torch.Tensor | None, plain_out: bool = False,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """One À-Trous level with the arguments of ``torch_code.filter_atrous._iteration``, except that ``feat`` holds
    groups of 3 planes whose squared distances are multiplied by ``feat_scale`` (one per group,
    a list for every image or a ``(B, G)`` tensor; the level's ``1 / step²`` for normals).
    Returns the filtered colour ``(B,C,H,W)`` and the propagated variance, both in :func:`padded`
    layout (pass them on as they are; the colour contiguous with ``plain_out``), and the weight
    sum ``(B,1,H,W)``."""
    taps = _taps()
    lib = build.library()
    B, C, H, W = c.shape
    F = 0 if feat is None else feat.shape[1]
    fs = torch.as_tensor(feat_scale, dtype=torch.float32)
    if F % 3 or fs.numel() not in (F // 3, B * F // 3):
        raise ValueError(f"feat: expected groups of 3 planes with one scale each, got {F} planes, {feat_scale}")
    fs = fs.reshape(-1, F // 3).expand(B, -1).contiguous() if F else torch.ones(B, 1)
    rs, ps = _layout(H, W)
    c = _as_padded(c)
    feat = None if feat is None else _as_padded(feat)
    var = None if var is None else _as_padded(var)
    valid = None if valid is None else _as_padded(valid.to(torch.float32).expand(B, 1, H, W))
    plane = colour_scale is not None and colour_scale.shape[-2:] == (H, W)
    cs = None if colour_scale is None else _as_padded(colour_scale.expand(B, 1, H, W)) if plane else \
        colour_scale.reshape(B).contiguous()
    out = torch.empty(B, C, H, W, dtype=torch.float32) if plain_out else padded(B, C, H, W)
    var_out = None if var is None else padded(B, C, H, W)
    den = torch.empty(B, 1, H, W, dtype=torch.float32)
    for b in range(B):
        cs_b = None if cs is None else (cs[b] if plane else cs[b : b + 1])
        _run(lib.torchgi_atrous_level, H, W, c[b].data_ptr(), C, _ptr(None if feat is None else feat[b]), F,
             fs[b].data_ptr(), _ptr(None if var is None else var[b]), _ptr(None if valid is None else valid[b]), _ptr(cs_b),
             int(plane), H, W, rs, ps, step, taps.data_ptr(), out[b].data_ptr(), out.stride(2), out.stride(1),
             _ptr(None if var_out is None else var_out[b]), den[b].data_ptr(),
             (2 * C + 1) * (W + _PAD))
    return out, var_out, den


def _box(x: torch.Tensor, r: int) -> torch.Tensor:
    """Count-normalised box means over ``(2r+1)²`` windows of float32 ``x (B,C,H,W)`` (the
    coefficient pass of the guided filter without the apply)."""
    lib = build.library()
    B, C, H, W = x.shape
    x = x.contiguous()
    out = torch.empty_like(x)
    for b in range(B):
        _run(lib.torchgi_guided_apply, H, W, x[b].data_ptr(), 0, C, None, None, None, H, W, r, out[b].data_ptr(),
             _box_scratch(C, W))
    return out


def _guided(
    I: torch.Tensor, p: torch.Tensor, mean_I: torch.Tensor, mean_p: torch.Tensor, offset: torch.Tensor, r: int,
    eps: torch.Tensor, coefficients_only: bool = False, holder: dict | None = None, into: torch.Tensor | None = None,
) -> torch.Tensor:
    """Guided filter of ``p (B,Cs,H,W)`` by ``I (B,n,H,W)`` (n <= 4), both centred inside by
    ``mean_p``, ``mean_I`` (``(B,C,1,1)``), ``eps (B,n,1,1)`` (>= 0), radius ``r``;
    ``offset (B,Cs,1,1)`` is added to the output. Returns ``(B,Cs,H,W)``, or the box-filtered
    coefficients ``(B,n+1,Cs,H,W)`` (``a_0..a_{n-1}, b``). ``holder`` keeps the coefficient
    planes between calls of one size (no page faults); the result goes into ``into`` where it fits
    (:func:`result`)."""
    lib = build.library()
    B, n, H, W = I.shape
    Cs = p.shape[1]
    I, p = I.contiguous(), p.contiguous()
    K = n + Cs + n * (n + 1) // 2 + n * Cs
    Q = (n + 1) * Cs
    key = (n, Cs, H, W)
    if holder is not None and holder.get("native_key") == key:
        coef = holder["native_coef"]
    else:
        coef = torch.empty(Q, H, W, dtype=torch.float32)
        if holder is not None:
            holder["native_key"], holder["native_coef"] = key, coef
    out = result(into, (B, n + 1, Cs, H, W) if coefficients_only else (B, Cs, H, W))
    eps = eps.reshape(B, n).to(torch.float32).clamp_min(torch.finfo(torch.float32).tiny).contiguous()
    offset = offset.reshape(B, Cs).to(torch.float32).contiguous()
    mean_I = mean_I.reshape(B, n).to(torch.float32).contiguous()
    mean_p = mean_p.reshape(B, Cs).to(torch.float32).contiguous()
    unit = variance_rounding(torch.float32)
    for b in range(B):
        _run(lib.torchgi_guided_coefficients, H, W, I[b].data_ptr(), mean_I[b].data_ptr(), n, p[b].data_ptr(),
             mean_p[b].data_ptr(), Cs, H, W, r,
             eps[b].data_ptr(), unit, coef.data_ptr(),
             _box_scratch(K, W))
        _run(lib.torchgi_guided_apply, H, W, coef.data_ptr(), n, Cs, None if coefficients_only else I[b].data_ptr(),
             mean_I[b].data_ptr(), offset[b].data_ptr(), H, W, r, out[b].data_ptr(),
             _box_scratch(Q, W))
    return out


# ---------------------------------------------------------------------------------------- ops
def upsample_apply(desc: UpsampleApplyOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.UpsampleApplyOp` in one walk per image (the fast guided
    filter's last pass of the Denoiser's pipeline, without its remodulation).

    Example:
        >>> c = torch.zeros(1, 2, 1, 2, 2); c[:, 1] = 3.0   # a = 0, b = 3
        >>> out = build.library() is None or upsample_apply(UpsampleApplyOp(c, torch.rand(1, 1, 4, 3)))
        >>> out is True or bool((out == 3).all())
        True
    """
    lib = build.library()
    coeffs, guide = desc.coeffs.contiguous(), desc.guide.contiguous()
    B, n, H, W = guide.shape
    Cs, w = coeffs.shape[2], coeffs.shape[-1]
    out = result(desc.out, (B, Cs, H, W))
    for b in range(B):
        planes = [guide[b, i].data_ptr() for i in range(n)] + [None] * (4 - n)
        _run(lib.torchgi_upsample_apply, H, W, coeffs[b].data_ptr(), n, Cs, *planes, H, W, out[b].data_ptr(),
             7 * W + w)
    return out



def box(desc: BoxOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.BoxOp` by the guided kernel's box passes.

    Example:
        >>> build.library() is None or box(BoxOp(torch.arange(3.0).view(1, 1, 1, 3), 1)).tolist() == [[[[0.5, 1.0, 1.5]]]]
        True
    """
    return _box(desc.x, desc.radius)


def guided(desc: GuidedOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.GuidedOp` in two kernels (coefficients, apply).

    Example:
        >>> p = torch.rand(1, 1, 6, 6); m = p.mean((2, 3), keepdim=True)
        >>> out = build.library() is None or guided(GuidedOp(torch.ones(1, 1, 6, 6), p, torch.ones(1, 1, 1, 1), m, 0,
        ...                                           torch.zeros(1, 1, 1, 1)))
        >>> out is True or torch.allclose(out, p, atol=1e-6)   # r = 0 and a constant guide: the source
        True
    """
    return _guided(desc.guide, desc.src, desc.mean_guide, desc.mean_src, desc.mean_src, desc.radius, desc.eps,
                   coefficients_only=desc.coefficients_only, holder=desc.workspace, into=desc.out)


def guided_grad(desc: GuidedGradOp) -> tuple[torch.Tensor | None, ...]:
    """:class:`~torchgi.backends.base.GuidedGradOp` in one kernel call per image
    (``torchgi_guided_grad``, ``guided_grad.c``: the forward's coefficients recomputed and the
    adjoint streamed in one walk per band of rows); ε's gradient summed in double per band.

    Example:
        >>> I, p = torch.zeros(1, 1, 4, 4), torch.rand(1, 1, 4, 4)   # a flat guide, r = 0: q = p
        >>> g = build.library() and guided_grad(GuidedGradOp(I, p, torch.ones(1, 1, 1, 1), 0, torch.ones(1, 1, 4, 4)))
        >>> g is None or torch.allclose(g[1], torch.ones(1, 1, 4, 4))
        True
    """
    lib = build.library()
    I, p, g, r = desc.guide.contiguous(), desc.src.contiguous(), desc.grad.contiguous(), desc.radius
    B, n, H, W = I.shape
    Cs = p.shape[1]
    K, Q = n + Cs + n * (n + 1) // 2 + n * Cs, (n + 1) * Cs
    eps = desc.eps.expand(B, n, 1, 1).reshape(B, n).clamp_min(torch.finfo(torch.float32).tiny).contiguous()
    dI = torch.empty_like(I) if desc.need_guide else None
    dp = torch.empty_like(p) if desc.need_src else None
    deps = torch.empty(B, n, dtype=torch.float64)
    rows = 2 * K + Q + n * Cs  # the column sums' and the means' rows
    scratch = 8 * (rows * (W + 8) + 2 * W + 8) + 4 * (rows * (W + 16) + (2 + n) * W + (2 * r + 2) * (K + Q) * W)
    for b in range(B):
        deps[b] = _parts(lib.torchgi_guided_grad, H, H * W, I[b].data_ptr(), p[b].data_ptr(), g[b].data_ptr(), n, Cs,
                         H, W, r, eps[b].data_ptr(), variance_rounding(torch.float32),
                         _ptr(None if dI is None else dI[b]), _ptr(None if dp is None else dp[b]), doubles=n,
                         extra_bytes=scratch)
    d_eps = None
    if desc.need_eps:
        d_eps = deps.to(torch.float32).view(B, n, 1, 1)
        d_eps = d_eps.sum(0, keepdim=True) if desc.eps.shape[0] == 1 < B else d_eps
    return dI, dp, d_eps


def atrous(desc: ATrousOp) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """:class:`~torchgi.backends.base.ATrousOp`, a level per kernel call: the guides divided by
    the square roots of their σ's once, into :func:`padded` planes; the kernel scales the normals'
    distances by ``1 / step²``.

    Example:
        >>> c = torch.full((1, 3, 8, 8), 0.5)
        >>> desc = ATrousOp(c, None, None, None, None, torch.ones(1, 1, 1, 1), None, None, iterations=2)
        >>> build.library() is None or torch.allclose(atrous(desc)[0], c)   # a constant image stays constant
        True
    """
    guides = scaled_guides(desc)
    feat = None
    if guides:
        feat = empty_planes(desc.color, 3 * len(guides))
        for k, (g, s, _) in enumerate(guides):
            torch.mul(g, s, out=feat[:, 3 * k : 3 * k + 3])

    def level(c, var, valid, i):
        step = 2**i
        scale = colour_scale(desc, i, var)
        return _atrous_level(c, feat, [1.0 / step**2 if per_step else 1.0 for _, _, per_step in guides], var, valid,
                             step, scale)

    return iterate_levels(desc, level)




def atrous_level(desc: ATrousLevelOp) -> tuple[torch.Tensor, torch.Tensor]:
    """:class:`~torchgi.backends.base.ATrousLevelOp` in one kernel call per image (the groups'
    multipliers applied by the kernel); the output in :func:`padded` layout, as the next level
    and the gradients' kernel read it (contiguous with ``plain_out``).

    Example:
        >>> c = torch.full((1, 3, 8, 8), 0.5)
        >>> build.library() is None or torch.equal(atrous_level(ATrousLevelOp(c, (), None, torch.ones(1, 1, 1, 1), 2))[0], c)
        True
    """
    feat = None
    if desc.guides:  # one padded copy of the guides for the level (the kernel reads one buffer)
        feat = empty_planes(desc.color, 3 * len(desc.guides))
        for k, g in enumerate(desc.guides):
            feat[:, 3 * k : 3 * k + 3].copy_(g)
    fs = [] if feat is None else desc.feat_scale
    out, _, den = _atrous_level(desc.color, feat, fs, None, None, desc.step, desc.scale, desc.plain_out)
    return out, den


def _rows(t: torch.Tensor) -> torch.Tensor:
    """``t (B, C, H, W)`` as the gradients' kernel reads it: unit column stride (padded rows kept
    as they are), else a contiguous copy."""
    return t if t.stride(3) == 1 else t.contiguous()


def atrous_level_grad(desc: ATrousLevelGradOp) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """:class:`~torchgi.backends.base.ATrousLevelGradOp` in one kernel call per image: colour,
    guides and output read in their own row and plane strides (the forward's padded rows).

    Example:
        >>> c = torch.rand(1, 3, 6, 6); s = torch.ones(1, 1, 1, 1)
        >>> out, den = atrous_level(ATrousLevelOp(c, (), None, s, 1)) if build.library() else (c, None)
        >>> g = build.library() and atrous_level_grad(ATrousLevelGradOp(c, (), None, s, out, torch.ones_like(c) / den, 1))
        >>> g is None or round(float(g[0].sum()), 3) == 108.0   # a constant shift of c moves every output
        True
    """
    lib = build.library()
    c, out = _rows(desc.color), _rows(desc.out)
    f = [_rows(g) for g in desc.guides]
    gp = desc.gp.contiguous()
    B, C, H, W = c.shape
    F = 3 * len(f)
    fs = desc.feat_scale.to(torch.float32).reshape(B, len(f)).contiguous() if f else None
    csm, s = desc.scale_operand()
    dc = torch.empty(B, C, H, W, dtype=torch.float32)
    df = torch.empty(B, F, H, W, dtype=torch.float32) if f and desc.need_feat else None
    ds = None if s is None or not desc.need_scale else torch.empty(B, 1, H, W, dtype=torch.float32)
    guide = [(g, g.stride(2), g.stride(1)) for g in f] + [(None, 0, 0)] * (2 - len(f))
    for b in range(B):
        _run(lib.torchgi_atrous_level_grad, H, W, c[b].data_ptr(), c.stride(2), c.stride(1), C,
             *(x for g, rs, ps in guide for x in (_ptr(None if g is None else g[b]), rs, ps)), F,
             _ptr(None if fs is None else fs[b]), _ptr(None if s is None else s[b]), csm, out[b].data_ptr(),
             out.stride(2), out.stride(1), gp[b].data_ptr(), H, W, desc.step, _taps().data_ptr(), dc[b].data_ptr(),
             _ptr(None if df is None else df[b]), _ptr(None if ds is None else ds[b]), 0)
    return dc, df, ds
