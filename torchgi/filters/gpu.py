"""Triton kernel of one À-Trous level for CUDA tensors (float32, without autograd or tracing).

The torch code of a level launches about ten kernels per tap (250 per level); this kernel does
a level in one launch: each program filters a tile of pixels, walks the 25 taps with the
weighted sums in registers and writes the level's colour, variance and weight sum. Same maths
as ``atrous._iteration`` and the CPU kernel of :mod:`torchgi.filters.native`. Triton comes
with CUDA builds of torch; without it (or on the CPU) the filters run their torch code. With
``TRITON_INTERPRET=1`` set before torchgi is imported, the same kernel runs on CPU tensors
through Triton's interpreter (the tests check it there against the float64 oracle).
:func:`torchgi.filters.native.disabled` (or ``TORCHGI_NATIVE=0``) switches it off too.

Example:
    >>> from torchgi.filters import gpu
    >>> gpu.applies(torch.zeros(1))   # a CPU tensor, no interpreter: the torch code
    False
"""

from __future__ import annotations

import os

import torch

from torchgi.core.check import is_tracing
from torchgi.filters import native
from torchgi.filters.taps import kernel_5x5

try:  # shipped with CUDA builds of torch
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - CPU-only installs
    triton = None

__all__ = ["applies", "atrous_level", "empty_planes"]

_INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"
# pixels of a tile (rows x columns, coalesced along the row) and warps per program: on an H200 at
# 1080p, 5 levels (scripts/sweep_gpu_tiles.py): 4x64 / 4 warps 2.35 ms, 8x64 / 8 warps 2.33,
# 8x32 / 4 warps 2.62, 16x32 and 8x64 with 4 warps 14 (register spills)
_BH, _BW, _WARPS = 4, 64, 4
MAX_CHANNELS = 4  # colour channels the kernel takes
_taps: dict[torch.device, torch.Tensor] = {}


def applies(*tensors: torch.Tensor | None) -> bool:
    """The kernel takes eager float32 CUDA tensors without autograd (CPU ones under the
    interpreter)."""
    ts = [t for t in tensors if t is not None]
    if triton is None or not native.enabled() or is_tracing() or not ts:
        return False
    if any(t.dtype != torch.float32 or (t.device.type != "cuda" and not _INTERPRET) for t in ts):
        return False
    return not (torch.is_grad_enabled() and any(t.requires_grad for t in ts))


if triton is not None:

    @triton.jit
    def _sq(a, b):
        u = a - b
        return u * u

    @triton.jit
    def _level(c_ptr, f_ptr, var_ptr, valid_ptr, cs_ptr, taps_ptr, out_ptr, vout_ptr, den_ptr,
               H, W, step, fs0, fs1, s_b, s_c, s_h, f_b, f_c, f_h, v_b, v_c, v_h, a_b, a_h, k_b, k_h,
               o_b, o_c, o_h, d_b, d_h,
               C: tl.constexpr, F: tl.constexpr, CS: tl.constexpr, V: tl.constexpr, VALID: tl.constexpr,
               BH: tl.constexpr, BW: tl.constexpr):
        # Channels are separate 2-D tiles (c0..c3, f0..f5) under compile-time guards: a channel
        # axis in one 3-D tile is spread over threads and every tap's sum over it goes through
        # shared memory (measured: 9.4 ms for 5 levels at 1080p on an H200).
        b = tl.program_id(2)
        y = (tl.program_id(1) * BH + tl.arange(0, BH))[:, None]
        x = (tl.program_id(0) * BW + tl.arange(0, BW))[None, :]
        inside = (y < H) & (x < W)
        pc = c_ptr + b * s_b + y * s_h + x
        c0 = tl.load(pc, mask=inside, other=0.0)
        if C > 1:
            c1 = tl.load(pc + s_c, mask=inside, other=0.0)
        if C > 2:
            c2 = tl.load(pc + 2 * s_c, mask=inside, other=0.0)
        if C > 3:
            c3 = tl.load(pc + 3 * s_c, mask=inside, other=0.0)
        if F > 0:
            pf = f_ptr + b * f_b + y * f_h + x
            f0 = tl.load(pf, mask=inside, other=0.0)
            f1 = tl.load(pf + f_c, mask=inside, other=0.0)
            f2 = tl.load(pf + 2 * f_c, mask=inside, other=0.0)
        if F > 3:
            f3 = tl.load(pf + 3 * f_c, mask=inside, other=0.0)
            f4 = tl.load(pf + 4 * f_c, mask=inside, other=0.0)
            f5 = tl.load(pf + 5 * f_c, mask=inside, other=0.0)
        if CS == 1:
            cs = tl.load(cs_ptr + b)
        if CS == 2:
            cs = tl.load(cs_ptr + b * k_b + y * k_h + x, mask=inside, other=0.0)
        zero = tl.zeros([BH, BW], dtype=tl.float32)
        n0 = zero
        n1 = zero
        n2 = zero
        n3 = zero
        v0 = zero
        v1 = zero
        v2 = zero
        v3 = zero
        den = zero
        for t in tl.static_range(25):
            oy = (t // 5 - 2) * step
            ox = (t % 5 - 2) * step
            ok = inside & (y + oy >= 0) & (y + oy < H) & (x + ox >= 0) & (x + ox < W)
            qc = pc + oy * s_h + ox
            q0 = tl.load(qc, mask=ok, other=0.0)
            if C > 1:
                q1 = tl.load(qc + s_c, mask=ok, other=0.0)
            if C > 2:
                q2 = tl.load(qc + 2 * s_c, mask=ok, other=0.0)
            if C > 3:
                q3 = tl.load(qc + 3 * s_c, mask=ok, other=0.0)
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
            if F > 0:
                qf = pf + oy * f_h + ox
                dn = _sq(f0, tl.load(qf, mask=ok, other=0.0)) + _sq(f1, tl.load(qf + f_c, mask=ok, other=0.0)) \
                    + _sq(f2, tl.load(qf + 2 * f_c, mask=ok, other=0.0))
                d += dn * fs0
            if F > 3:
                dx = _sq(f3, tl.load(qf + 3 * f_c, mask=ok, other=0.0)) \
                    + _sq(f4, tl.load(qf + 4 * f_c, mask=ok, other=0.0)) \
                    + _sq(f5, tl.load(qf + 5 * f_c, mask=ok, other=0.0))
                d += dx * fs1
            w = tl.load(taps_ptr + t) * tl.exp(-d)
            if VALID:
                w *= tl.load(valid_ptr + b * a_b + (y + oy) * a_h + x + ox, mask=ok, other=0.0)
            w = tl.where(ok, w, 0.0)
            den += w
            n0 += w * q0
            if C > 1:
                n1 += w * q1
            if C > 2:
                n2 += w * q2
            if C > 3:
                n3 += w * q3
            if V:
                qv = var_ptr + b * v_b + (y + oy) * v_h + x + ox
                w2 = w * w
                v0 += w2 * tl.load(qv, mask=ok, other=0.0)
                if C > 1:
                    v1 += w2 * tl.load(qv + v_c, mask=ok, other=0.0)
                if C > 2:
                    v2 += w2 * tl.load(qv + 2 * v_c, mask=ok, other=0.0)
                if C > 3:
                    v3 += w2 * tl.load(qv + 3 * v_c, mask=ok, other=0.0)
        has = den > 0
        safe = tl.where(has, den, 1.0)
        po = out_ptr + b * o_b + y * o_h + x
        tl.store(po, tl.where(has, n0 / safe, c0), mask=inside)
        if C > 1:
            tl.store(po + o_c, tl.where(has, n1 / safe, c1), mask=inside)
        if C > 2:
            tl.store(po + 2 * o_c, tl.where(has, n2 / safe, c2), mask=inside)
        if C > 3:
            tl.store(po + 3 * o_c, tl.where(has, n3 / safe, c3), mask=inside)
        if V:
            pv = var_ptr + b * v_b + y * v_h + x
            pvo = vout_ptr + b * o_b + y * o_h + x
            s2 = safe * safe
            tl.store(pvo, tl.where(has, v0 / s2, tl.load(pv, mask=inside, other=0.0)), mask=inside)
            if C > 1:
                tl.store(pvo + o_c, tl.where(has, v1 / s2, tl.load(pv + v_c, mask=inside, other=0.0)), mask=inside)
            if C > 2:
                tl.store(pvo + 2 * o_c, tl.where(has, v2 / s2, tl.load(pv + 2 * v_c, mask=inside, other=0.0)),
                         mask=inside)
            if C > 3:
                tl.store(pvo + 3 * o_c, tl.where(has, v3 / s2, tl.load(pv + 3 * v_c, mask=inside, other=0.0)),
                         mask=inside)
        tl.store(den_ptr + b * d_b + y * d_h + x, den, mask=inside)


def empty_planes(like: torch.Tensor, C: int) -> torch.Tensor:
    """A ``(B, C, H, W)`` float32 buffer on ``like``'s device (the feature planes
    :func:`atrous_level` reads)."""
    B, _, H, W = like.shape
    return torch.empty(B, C, H, W, dtype=torch.float32, device=like.device)


def _rows(t: torch.Tensor) -> torch.Tensor:
    """``t`` with unit stride along x (a copy otherwise)."""
    return t if t.stride(-1) == 1 else t.contiguous()


def atrous_level(
    c: torch.Tensor, feat: torch.Tensor | None, feat_scale: list[float], var: torch.Tensor | None,
    valid: torch.Tensor | None, step: int, colour_scale: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """One À-Trous level with the arguments of :func:`torchgi.filters.native.atrous_level`
    (``feat``: groups of 3 planes, at most 2, whose squared distances are multiplied by
    ``feat_scale``; ``c`` up to 4 channels). Returns the colour ``(B,C,H,W)``, the propagated
    variance and the weight sum ``(B,1,H,W)``."""
    B, C, H, W = c.shape
    F = 0 if feat is None else feat.shape[1]
    if C > MAX_CHANNELS or F not in (0, 3, 6) or len(feat_scale) != F // 3:
        raise ValueError(f"atrous_level: expected <= 4 colour channels and 0, 3 or 6 feature planes with a scale "
                         f"per 3; got C={C}, F={F}, {feat_scale}")
    if c.device not in _taps:
        _taps[c.device] = torch.tensor([h for _, _, h in kernel_5x5()], dtype=torch.float32, device=c.device)
    c = _rows(c)
    feat = None if feat is None else _rows(feat)
    var = None if var is None else _rows(var.expand(B, C, H, W))
    valid = None if valid is None else _rows(valid.to(torch.float32).expand(B, 1, H, W))
    plane = colour_scale is not None and colour_scale.shape[-2:] == (H, W)
    cs = None if colour_scale is None else _rows(colour_scale.expand(B, 1, H, W)) if plane else \
        colour_scale.reshape(B).contiguous()
    out = torch.empty(B, C, H, W, dtype=torch.float32, device=c.device)
    vout = None if var is None else torch.empty_like(out)
    den = torch.empty(B, 1, H, W, dtype=torch.float32, device=c.device)
    dummy = out  # pointer for absent inputs (never read: their flags are off)
    fs = list(feat_scale) + [1.0] * (2 - len(feat_scale))
    f_s = feat.stride() if feat is not None else (0, 0, 0, 1)
    v_s = var.stride() if var is not None else (0, 0, 0, 1)
    a_s = valid.stride() if valid is not None else (0, 0, 0, 1)
    k_s = cs.stride() if plane else (0, 0, 0, 1)
    grid = (triton.cdiv(W, _BW), triton.cdiv(H, _BH), B)
    _level[grid](
        c, dummy if feat is None else feat, dummy if var is None else var, dummy if valid is None else valid,
        dummy if cs is None else cs, _taps[c.device], out, dummy if vout is None else vout, den,
        H, W, step, fs[0], fs[1], *c.stride()[:3], *f_s[:3], *v_s[:3], a_s[0], a_s[2], k_s[0], k_s[2],
        *out.stride()[:3], den.stride(0), den.stride(2),
        C=C, F=F, CS=0 if cs is None else 2 if plane else 1, V=var is not None, VALID=valid is not None, BH=_BH, BW=_BW,
        num_warps=_WARPS,
    )
    return out, vout, den
