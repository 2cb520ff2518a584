"""The Triton À-Trous level: each program filters a tile of pixels, walks the 25 taps with the
weighted sums in registers and writes the level's colour, variance and weight sum (one launch
per level). Tile sizes and warps from ``scripts/sweep_gpu_tiles.py`` (docs/calibration.md)."""

from __future__ import annotations

import torch

from torchgi.backends.base import ATrousLevelGradOp, ATrousLevelOp, ATrousOp
from torchgi.backends.levels import colour_scale, iterate_levels
from torchgi.backends.triton_kernels.common import _cdiv, _taps, tl, triton

# À-Trous tile (rows x columns, coalesced along the row), warps per program and taps per loop
# step (scripts/sweep_gpu_tiles.py on an H200; docs/calibration.md)
_BH, _BW, _WARPS, _UNROLL = 2, 128, 4, 2


def _unroll(C: int, variance: bool) -> int:
    """Taps per loop step of the À-Trous kernel for ``C`` colour channels: one with a variance
    to propagate or 4 channels, where two need over 128 registers (offline ptxas for sm_90;
    tests/backends/test_gpu.py checks the limit)."""
    return 1 if variance or C > 3 else _UNROLL


MAX_CHANNELS = 4  # colour channels the kernel takes


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




def atrous_level(desc: ATrousLevelOp) -> tuple[torch.Tensor, torch.Tensor]:
    """:class:`~torchgi.backends.base.ATrousLevelOp` by the level kernel: the guides' groups
    enter as its normal and position with their multipliers as inverse σ's (the normal's times
    ``step²``, which the kernel divides by), the colour scale as its σ (a value) or plane (a map).

    Example:
        >>> c = torch.full((1, 3, 8, 8), 0.5, device="cuda")                                        # doctest: +SKIP
        >>> torch.equal(atrous_level(ATrousLevelOp(c, (), None, torch.ones(1, 1, 1, 1, device="cuda"), 2))[0], c)  # doctest: +SKIP
        True
    """
    c, s, step = desc.color, desc.scale, desc.step
    B = c.shape[0]
    one = torch.ones(B, dtype=c.dtype, device=c.device)
    scalar = s is not None and s.shape[-2:] == (1, 1)
    fs = [one, one] if not desc.guides else [desc.feat_scale[:, 0], desc.feat_scale[:, -1]]
    inv = torch.stack([s.reshape(B) if scalar else one, fs[0] * step * step, fs[1]], 1)
    groups = [*desc.guides, None, None][:2]
    colour = None if s is None else 1.0 if scalar else s
    out, _, den = _atrous_level(c, groups[0], groups[1], inv, None, None, step, colour)
    return out, den


if triton is not None:

    @triton.jit
    def _pair(c_ptr, f_ptr, s_ptr, out_ptr, gp_ptr, p, q, ok, hw, h, sv, fs0, fs1, C: tl.constexpr,
              F: tl.constexpr, CS: tl.constexpr):
        # the pair (p centre, q neighbour) of one tap: w, E = -w Σ_k gp_pk (c_qk - out_pk), s_p and
        # the colour distance (the channel loop over at most 4 colour and 6 guide planes, each
        # guide group's squared distance times its multiplier fs0, fs1)
        dcol = tl.zeros_like(h)
        G = tl.zeros_like(h)
        for k in tl.static_range(C):
            u = tl.load(c_ptr + k * hw + p, mask=ok, other=0.0) - tl.load(c_ptr + k * hw + q, mask=ok, other=0.0)
            dcol += u * u
        dfe = tl.zeros_like(h)
        for k in tl.static_range(F):
            v = tl.load(f_ptr + k * hw + p, mask=ok, other=0.0) - tl.load(f_ptr + k * hw + q, mask=ok, other=0.0)
            if k < 3:
                dfe += fs0 * v * v
            else:
                dfe += fs1 * v * v
        sp = tl.zeros_like(h)
        if CS == 1:
            sp += sv
        if CS == 2:
            sp = tl.load(s_ptr + p, mask=ok, other=0.0)
        w = tl.where(ok, h * tl.exp(-(sp * dcol + dfe)), 0.0)
        for k in tl.static_range(C):
            G += tl.load(gp_ptr + k * hw + p, mask=ok, other=0.0) * (
                tl.load(c_ptr + k * hw + q, mask=ok, other=0.0) - tl.load(out_ptr + k * hw + p, mask=ok, other=0.0))
        return w, -w * G, sp, dcol

    @triton.jit
    def _level_grad(c_ptr, f_ptr, fs_ptr, s_ptr, out_ptr, gp_ptr, taps_ptr, dc_ptr, df_ptr, ds_ptr, H, W, step,
                    C: tl.constexpr, F: tl.constexpr, CS: tl.constexpr, DF: tl.constexpr, DS: tl.constexpr,
                    BLOCK: tl.constexpr):
        # kernels.c's atrous_grad_rows (the same sums): each pixel gathers its gradients as the
        # centre of its 25 pairs and as the neighbour of the 25 pixels whose taps read it
        b = tl.program_id(1).to(tl.int64)
        hw = H * W
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        live = i < hw
        y, x = i // W, i % W
        c_ptr += b * C * hw
        f_ptr += b * F * hw
        out_ptr += b * C * hw
        gp_ptr += b * C * hw
        sv = 0.0
        if CS == 1:
            sv = tl.load(s_ptr + b)
        if CS == 2:
            s_ptr += b * hw
        fs0 = 1.0
        fs1 = 1.0
        if F > 0:
            fs0 = tl.load(fs_ptr + b * (F // 3))
            fs1 = tl.load(fs_ptr + b * (F // 3) + F // 3 - 1)
        for k in tl.static_range(C):
            tl.store(dc_ptr + b * C * hw + k * hw + i, tl.zeros([BLOCK], dtype=tl.float32), mask=live)
        for t in range(25):
            oy = (t // 5 - 2) * step
            ox = (t % 5 - 2) * step
            h = tl.zeros([BLOCK], dtype=tl.float32) + tl.load(taps_ptr + t)
            # as the centre: q = i + o
            ok = live & (y + oy >= 0) & (y + oy < H) & (x + ox >= 0) & (x + ox < W)
            q = i + oy * W + ox
            w, E, sp, dcol = _pair(c_ptr, f_ptr, s_ptr, out_ptr, gp_ptr, i, q, ok, hw, h, sv, fs0, fs1, C, F, CS)
            for k in tl.static_range(C):
                u = tl.load(c_ptr + k * hw + i, mask=ok, other=0.0) - tl.load(c_ptr + k * hw + q, mask=ok, other=0.0)
                a = dc_ptr + b * C * hw + k * hw + i
                tl.store(a, tl.load(a, mask=live, other=0.0) + 2.0 * E * sp * u, mask=live)
            if DF:
                for k in tl.static_range(F):
                    v = tl.load(f_ptr + k * hw + i, mask=ok, other=0.0) - tl.load(f_ptr + k * hw + q, mask=ok, other=0.0)
                    a = df_ptr + b * F * hw + k * hw + i
                    prev = tl.where(t == 0, 0.0, tl.load(a, mask=live, other=0.0))
                    tl.store(a, prev + 2.0 * E * (fs0 if k < 3 else fs1) * v, mask=live)
            if DS:
                a = ds_ptr + b * hw + i
                prev = tl.where(t == 0, 0.0, tl.load(a, mask=live, other=0.0))
                tl.store(a, prev + E * dcol, mask=live)
            # as the neighbour: p = i - o
            ok = live & (y - oy >= 0) & (y - oy < H) & (x - ox >= 0) & (x - ox < W)
            p = i - oy * W - ox
            w, E, sp, dcol = _pair(c_ptr, f_ptr, s_ptr, out_ptr, gp_ptr, p, i, ok, hw, h, sv, fs0, fs1, C, F, CS)
            for k in tl.static_range(C):
                u = tl.load(c_ptr + k * hw + p, mask=ok, other=0.0) - tl.load(c_ptr + k * hw + i, mask=ok, other=0.0)
                a = dc_ptr + b * C * hw + k * hw + i
                g = tl.load(gp_ptr + k * hw + p, mask=ok, other=0.0)
                tl.store(a, tl.load(a, mask=live, other=0.0) + w * g - 2.0 * E * sp * u, mask=live)
            if DF:
                for k in tl.static_range(F):
                    v = tl.load(f_ptr + k * hw + p, mask=ok, other=0.0) - tl.load(f_ptr + k * hw + i, mask=ok, other=0.0)
                    a = df_ptr + b * F * hw + k * hw + i
                    tl.store(a, tl.load(a, mask=live, other=0.0) - 2.0 * E * (fs0 if k < 3 else fs1) * v, mask=live)


def atrous_level_grad(desc: ATrousLevelGradOp) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """:class:`~torchgi.backends.base.ATrousLevelGradOp` in one launch (the guides side by side in
    one buffer).

    Example:
        >>> c = torch.rand(1, 3, 6, 6, device="cuda"); s = torch.ones(1, 1, 1, 1, device="cuda")  # doctest: +SKIP
        >>> out, den = atrous_level(ATrousLevelOp(c, (), None, s, 1))                                  # doctest: +SKIP
        >>> dc, _, ds = atrous_level_grad(ATrousLevelGradOp(c, (), None, s, out, torch.ones_like(c) / den, 1))  # doctest: +SKIP
        >>> round(float(dc.sum()), 3)                                                             # doctest: +SKIP
        108.0
    """
    c, out, gp = desc.color.contiguous(), desc.out.contiguous(), desc.gp.contiguous()
    B, C, H, W = c.shape
    f = torch.cat(desc.guides, 1).contiguous() if desc.guides else None
    F = 0 if f is None else f.shape[1]
    fs = None if f is None else desc.feat_scale.to(torch.float32).contiguous()
    cs, s = desc.scale_operand()
    dc = torch.empty_like(c)
    need_f, need_s = f is not None and desc.need_feat, s is not None and desc.need_scale
    df = torch.empty_like(f) if need_f else dc
    ds = torch.empty(B, 1, H, W, dtype=c.dtype, device=c.device) if need_s else dc
    _level_grad[(_cdiv(H * W, _GRAD_BLOCK), B)](
        c, dc if f is None else f, dc if fs is None else fs, dc if s is None else s, out, gp, _taps(c.device), dc, df, ds, H, W, desc.step,
        C=C, F=F, CS=cs, DF=need_f, DS=need_s, BLOCK=_GRAD_BLOCK)
    return dc, df if need_f else None, ds if need_s else None


_GRAD_BLOCK = 128  # pixels per program of the level's gradients
