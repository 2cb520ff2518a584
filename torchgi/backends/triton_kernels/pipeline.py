"""The Triton Denoiser pipeline (:class:`~torchgi.backends.base.RestoreOp`): four launches of its
own around the guided filter's kernels."""

from __future__ import annotations

import torch

from torchgi.backends.autograd_ops import box_mean
from torchgi.backends.base import RestoreOp
from torchgi.backends.triton_kernels import filter_guided
from torchgi.backends.triton_kernels.common import _cdiv, _scaled_to, tl, triton
from torchgi.backends.triton_kernels.filter_guided import _box, _guided, _split
from torchgi.core.check import check_finite
from torchgi.light import demodulator, light_sources, surface_mask
from torchgi.settings import PIPELINE

if triton is not None:

    @triton.jit
    def _demodulator(a_ptr, h_ptr, i, HW, m, floor, ceil, HAS_HIT: tl.constexpr):
        # what light is divided by per channel: the albedo (in [floor, ceil]) on surfaces, else 1
        a0 = tl.load(a_ptr + i, mask=m, other=0.0)
        a1 = tl.load(a_ptr + HW + i, mask=m, other=0.0)
        a2 = tl.load(a_ptr + 2 * HW + i, mask=m, other=0.0)
        if HAS_HIT:
            on = tl.load(h_ptr + i, mask=m, other=0) != 0
        else:
            on = (a0 > 0) | (a1 > 0) | (a2 > 0)
        return (tl.where(on, tl.minimum(tl.maximum(a0, floor), ceil), 1.0),
                tl.where(on, tl.minimum(tl.maximum(a1, floor), ceil), 1.0),
                tl.where(on, tl.minimum(tl.maximum(a2, floor), ceil), 1.0))

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
    def _pixels(a_ptr, h_ptr, l_ptr, HW, n_blk, floor, ceil, HAS_HIT: tl.constexpr, HAS_L: tl.constexpr,
                BLOCK: tl.constexpr):
        # this program's image b, pixels i (mask m, offsets in 3- and 1-plane images), demodulator
        # and light-source mask
        blk, b = _split(tl.program_id(0), n_blk)
        b = b.to(tl.int64)
        i = blk * BLOCK + tl.arange(0, BLOCK)
        m = i < HW
        o3, o1 = b * 3 * HW + i, b * HW + i
        d0, d1, d2 = _demodulator(a_ptr + b * 3 * HW, h_ptr + b * HW, i, HW, m, floor, ceil, HAS_HIT)
        light = i < 0
        if HAS_L:
            light = tl.load(l_ptr + o1, mask=m, other=0) != 0
        return b, i, m, o3, o1, d0, d1, d2, light

    @triton.jit
    def _prepare(c_ptr, e_ptr, k_ptr, a_ptr, h_ptr, l_ptr, lvl_ptr, x_ptr, pk_ptr, k_fire, floor, ceil, HW, n_blk,
                 HAS_E: tl.constexpr, HAS_K: tl.constexpr, HAS_HIT: tl.constexpr, HAS_L: tl.constexpr,
                 BLOCK: tl.constexpr):
        # the demodulated light x (3 planes) and its channel maximum capped at k level
        b, _i, m, o3, o1, d0, d1, d2, light = _pixels(a_ptr, h_ptr, l_ptr, HW, n_blk, floor, ceil, HAS_HIT, HAS_L,
                                                      BLOCK)
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
        x0, x1, x2 = _scaled_to(x0, x1, x2, k_fire * tl.maximum(tl.load(mean_ptr + b * HW + i, mask=m, other=0.0), 0.0))
        tl.store(p, x0, mask=m)
        tl.store(p + HW, x1, mask=m)
        tl.store(p + 2 * HW, x2, mask=m)

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
    def _finish(q_ptr, coef_ptr, g_ptr, mg_ptr, off_ptr, c_ptr, e_ptr, k_ptr, a_ptr, h_ptr, l_ptr, out_ptr, floor, ceil,
                H, W, h, w, inv_s, n_blk, N: tl.constexpr, UPSAMPLE: tl.constexpr, HAS_E: tl.constexpr,
                HAS_K: tl.constexpr, HAS_HIT: tl.constexpr, HAS_L: tl.constexpr, BLOCK: tl.constexpr):
        # the filtered light q (3 planes) or, with UPSAMPLE, the guided filter applied from the
        # box-filtered coefficients at 1 / s resolution upsampled bilinearly by s (torch's
        # interpolate(scale_factor=s)); then remodulated
        HW = H * W
        b, i, m, o3, _o1, d0, d1, d2, light = _pixels(a_ptr, h_ptr, l_ptr, HW, n_blk, floor, ceil, HAS_HIT, HAS_L,
                                                      BLOCK)
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
        lights = light_sources(emission, PIPELINE.light * desc.level, box_mean)
    else:
        base = color - kept if kept is not None else color
        lights = light_sources(base / demodulator(albedo, surface_mask(hit, albedo)),
                                     PIPELINE.light * desc.level, box_mean)
    has_l = bool(lights.any())
    x, peak = torch.empty_like(color), torch.empty(B, 1, H, W, dtype=torch.float32, device=dev)
    n_blk = _cdiv(HW, filter_guided._PIX)
    flags = {"HAS_E": emission is not None, "HAS_K": kept is not None, "HAS_HIT": hit is not None, "HAS_L": has_l}
    lights = lights.contiguous().view(torch.uint8)  # bool planes as bytes
    ptrs = [color, emission if emission is not None else color, kept if kept is not None else color, albedo,
            hit.view(torch.uint8) if hit is not None else lights, lights]
    k = float(desc.firefly)
    _prepare[(n_blk * B,)](*ptrs, level, x, peak, k, float(PIPELINE.albedo_floor),
                           float(PIPELINE.albedo_ceiling), HW, n_blk, **flags, BLOCK=filter_guided._PIX)
    _clamp[(n_blk * B,)](x, _box(peak, PIPELINE.firefly_radius), k, HW, n_blk, BLOCK=filter_guided._PIX)
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
    _finish[(n_blk * B,)](q, coef, guide, mean_g, mean_p, *ptrs[:5], lights, out, float(PIPELINE.albedo_floor),
                          float(PIPELINE.albedo_ceiling), H, W,
                          h, w, 1.0 / s, n_blk, N=n, UPSAMPLE=s > 1, **flags, BLOCK=filter_guided._PIX)
    return out


# ---------------------------------------------------------------------------------------- ops
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
