"""The torch code of an À-Trous level: the 25 taps as shifted views of padded tensors (never a
``(B, 25·C, H, W)`` unfold), optionally through ``torch.compile`` (``fused``)."""

from __future__ import annotations

import functools

import torch

from torchgi.backends.autograd_ops import ATrousLevel
from torchgi.backends.base import ATrousLevelGradOp, ATrousLevelOp, ATrousOp
from torchgi.backends.levels import colour_scale, iterate_levels, scaled_guides
from torchgi.core.check import is_tracing
from torchgi.core.taps import Padded, kernel_5x5

_TAPS = kernel_5x5()


def squared_distance(a: list[torch.Tensor], b: list[torch.Tensor]) -> torch.Tensor:
    """Σ (a - b)² over channels ``(B,1,H,W)``: either one ``(B,C,H,W)`` tensor each (a channel
    reduction: few ops, compact ONNX graphs) or lists of ``(B,1,H,W)`` planes (pointwise only:
    what ``torch.compile`` fuses into one loop).

    Example:
        >>> squared_distance([torch.ones(1, 2, 1, 1)], [torch.zeros(1, 2, 1, 1)]).item()
        2.0
    """
    out = (a[0] - b[0]).square().sum(1, keepdim=True)
    for u, v in zip(a[1:], b[1:]):
        out = out + (u - v).square()
    return out


def channel_planes(t: torch.Tensor, split: bool) -> list[torch.Tensor]:
    """``t (B,C,H,W)`` as a list of channel planes (``split``) or as ``[t]``.

    Example:
        >>> [p.shape[1] for p in channel_planes(torch.ones(1, 3, 2, 2), True)]
        [1, 1, 1]
    """
    return [t[:, k : k + 1] for k in range(t.shape[1])] if split else [t]


def _iteration(
    c: torch.Tensor, feat: torch.Tensor | None, var: torch.Tensor | None, valid: torch.Tensor | None,
    step: int, colour_scale: torch.Tensor | None, split: bool = False,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """One À-Trous level.

    ``feat`` ``(B,F,H,W)`` holds the geometry guides already divided by the square roots of
    their σ's (normal also by the step), so ``w_n · w_x = exp(-|f(p) - f(q)|²``); None: no
    geometry weight. ``colour_scale`` is ``1/σ_rt,i`` ``(B,1,1,1)`` or, variance-guided,
    ``1/(σ² · blur(Var))`` ``(B,1,H,W)``; None: no colour weight. ``valid`` ``(B,1,H,W)``
    marks pixels that may act as sources (None: all). Returns the filtered colour, the
    propagated variance and the weight sum.

    With ``split`` every channel is its own plane and the level is pure pointwise arithmetic
    over shifted views, which ``torch.compile`` fuses into one loop (the ``fused=True`` path);
    without it channels are reduced with ``sum`` (fewer ops for eager code and ONNX).
    """
    pad = 2 * step
    pc = Padded(c, pad)
    pf = Padded(feat, pad) if feat is not None else None
    pv = Padded(torch.ones_like(c[:, :1]) if valid is None else valid.to(c.dtype), pad)  # 0 outside / on holes
    pvar = Padded(var, pad) if var is not None else None
    cc = channel_planes(c, split)
    ff = channel_planes(feat, split) if feat is not None else []
    num: list[torch.Tensor] = []
    var_num: list[torch.Tensor] = []
    den = torch.zeros_like(c[:, :1])
    for dy, dx, h in _TAPS:
        oy, ox = dy * step, dx * step
        cq = channel_planes(pc.at(oy, ox), split)
        d = None
        if colour_scale is not None:
            d = squared_distance(cc, cq) * colour_scale
        if pf is not None:
            dg = squared_distance(ff, channel_planes(pf.at(oy, ox), split))
            d = dg if d is None else d + dg
        w = pv.at(oy, ox) * h
        if d is not None:
            w = w * torch.exp(-d)
        num = [w * q for q in cq] if not num else [a + w * q for a, q in zip(num, cq)]
        den = den + w
        if pvar is not None:
            w2 = w.square()
            vq = channel_planes(pvar.at(oy, ox), split)
            var_num = [w2 * q for q in vq] if not var_num else [a + w2 * q for a, q in zip(var_num, vq)]
    ok = den > 0
    safe = torch.where(ok, den, torch.ones_like(den))
    out = torch.where(ok, torch.cat(num, 1) / safe, c)  # no weight at all: keep the centre pixel
    var_out = torch.where(ok, torch.cat(var_num, 1) / safe.square(), var) if var is not None else None
    return out, var_out, den


@functools.cache
def _compiled_iteration():
    """``torch.compile(_iteration, dynamic=True)``, built on first use (one compile serves
    every size and step)."""
    return torch.compile(_iteration, dynamic=True)



def atrous(desc: ATrousOp) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """:class:`~torchgi.backends.base.ATrousOp` in torch: per level, the guides divided by the
    square roots of their σ's (normals also by the step) so ``w_n · w_x = exp(-|f(p) - f(q)|²)``.

    Example:
        >>> c = torch.full((1, 3, 8, 8), 0.5)   # a constant image stays constant
        >>> out, _ = atrous(ATrousOp(c, None, None, None, None, torch.ones(1, 1, 1, 1), None, None, iterations=2))
        >>> torch.equal(out, c)
        True
    """
    guides = scaled_guides(desc)
    level_fn = _compiled_iteration() if desc.fused else _iteration
    by_level = level_backward(desc)
    raw, roots = [None, None], []
    if by_level:  # the guides as the caller holds them (no centred or scaled copy kept for the backward)
        present = [t for t, inv in ((desc.normal, desc.inv_normal), (desc.position, desc.inv_position)) if inv is not None]
        raw, roots, guides = present + raw[len(present):], [(s, per_step) for _, s, per_step in guides], []

    def level(c, var, valid, i):
        step = 2**i
        scale = colour_scale(desc, i, var)
        if by_level:
            mult = torch.cat([s / step if per_step else s for s, per_step in roots], 1) if roots else None
            return ATrousLevel.apply(c, *raw, mult, scale, step, i == desc.iterations - 1), None, None
        feat = torch.cat([g * (s / step if per_step else s) for g, s, per_step in guides], 1) if guides else None
        return level_fn(c, feat, var, valid, step, scale, desc.fused)

    return iterate_levels(desc, level)


def level_backward(desc: ATrousOp) -> bool:
    """Whether ``desc`` runs its levels as :class:`~torchgi.backends.autograd_ops.ATrousLevel`
    (forward and written-out gradients each through the seam): under autograd, not traced, without
    a variance or sub-sampling holes, not ``fused``.

    Example:
        >>> c = torch.ones(1, 3, 4, 4, requires_grad=True)
        >>> level_backward(ATrousOp(c, None, None, None, None, torch.ones(1, 1, 1, 1), None, None, iterations=1))
        True
    """
    return (torch.is_grad_enabled() and not is_tracing() and desc.variance is None and desc.valid is None
            and not desc.fused and any(t is not None and t.requires_grad for t in desc.tensors()))


def atrous_level(desc: ATrousLevelOp) -> tuple[torch.Tensor, torch.Tensor]:
    """:class:`~torchgi.backends.base.ATrousLevelOp` in torch: :func:`_iteration`.

    Example:
        >>> c = torch.full((1, 3, 8, 8), 0.5)
        >>> out, den = atrous_level(ATrousLevelOp(c, (), None, torch.ones(1, 1, 1, 1), 2))
        >>> torch.equal(out, c)
        True
    """
    out, _, den = _iteration(desc.color, scaled_feat(desc.guides, desc.feat_scale), None, None, desc.step, desc.scale)
    return out, den


def scaled_feat(guides: tuple[torch.Tensor, ...], feat_scale: torch.Tensor | None) -> torch.Tensor | None:
    """The guides ``f_g (B,3,H,W)`` times the square roots of their multipliers ``feat_scale
    (B,G)``, as one ``(B,3G,H,W)`` tensor (so plain squared distances carry the multipliers);
    None without guides.

    Example:
        >>> scaled_feat((torch.ones(1, 3, 1, 1), torch.ones(1, 3, 1, 1)), torch.tensor([[4.0, 9.0]])).flatten().tolist()
        [2.0, 2.0, 2.0, 3.0, 3.0, 3.0]
    """
    if not guides:
        return None
    return torch.cat([g * feat_scale[:, k, None, None, None].sqrt() for k, g in enumerate(guides)], 1)


def atrous_level_grad(desc: ATrousLevelGradOp) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """:class:`~torchgi.backends.base.ATrousLevelGradOp` written out in torch (no autograd): per
    tap, each pixel as the centre of a pair and as the neighbour of the pixel ``o_t`` before it.

    Example:
        >>> c = torch.rand(1, 3, 6, 6); s = torch.ones(1, 1, 1, 1)
        >>> out, den = atrous_level(ATrousLevelOp(c, (), None, s, 1))
        >>> dc, _, ds = atrous_level_grad(ATrousLevelGradOp(c, (), None, s, out, torch.ones_like(c) / den, 1))
        >>> round(float(dc.sum()), 4) == 6 * 6 * 3   # the sum of the outputs moves with a constant shift of c
        True
    """
    c, s, out, gp, step = desc.color, desc.scale, desc.out, desc.gp, desc.step
    f = scaled_feat(desc.guides, desc.feat_scale)  # the gradient of f, times the same roots, is the guides'
    pad = 2 * step
    pc, pgp, pout = Padded(c, pad), Padded(gp, pad), Padded(out, pad)
    pf = Padded(f, pad) if f is not None else None
    inside = Padded(torch.ones_like(c[:, :1]), pad)
    ps = Padded(s, pad) if s is not None and s.shape[-2:] != (1, 1) else None
    dc = torch.zeros_like(c)
    df = torch.zeros_like(f) if f is not None and desc.need_feat else None
    ds = torch.zeros_like(c[:, :1]) if s is not None and desc.need_scale else None
    for dy, dx, h in _TAPS:
        oy, ox = dy * step, dx * step
        for centre in (True, False):
            sy, sx = (oy, ox) if centre else (-oy, -ox)  # the other pixel of the pair
            cp, cq = (c, pc.at(sy, sx)) if centre else (pc.at(sy, sx), c)
            u = cp - cq
            dcol = u.square().sum(1, keepdim=True)
            sp = None if s is None else (s if centre or ps is None else ps.at(sy, sx))
            d = torch.zeros_like(dcol) if s is None else sp * dcol
            v = None
            if f is not None:
                v = f - pf.at(sy, sx) if centre else pf.at(sy, sx) - f
                d = d + v.square().sum(1, keepdim=True)
            w = h * torch.exp(-d) * inside.at(sy, sx)
            gpp, outp = (gp, out) if centre else (pgp.at(sy, sx), pout.at(sy, sx))
            E = -w * (gpp * (cq - outp)).sum(1, keepdim=True)
            E2s = 0 if s is None else 2 * E * sp
            if centre:
                dc = dc + E2s * u
                if df is not None:
                    df = df + 2 * E * v
                if ds is not None:
                    ds = ds + E * dcol
            else:
                dc = dc + w * gpp - E2s * u
                if df is not None:
                    df = df - 2 * E * v
    if df is not None:
        df = df * desc.feat_scale.sqrt().repeat_interleave(3, dim=1)[:, :, None, None]
    return dc, df, ds


