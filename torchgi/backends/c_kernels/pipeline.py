"""The C back end's Denoiser pipeline: the guide statistics, the edge share, the fused guided
pipeline (:class:`~torchgi.backends.base.RestoreOp`) and the back-off toward the input after it
(:class:`~torchgi.backends.base.BackOffOp`) and the choice among radii before it
(:class:`~torchgi.backends.base.ChooseOp`); the same light steps around another filter
(:class:`~torchgi.backends.base.LightInOp`, :class:`~torchgi.backends.base.LightOutOp`)."""

from __future__ import annotations

import math

import torch

from torchgi.backends.base import (
    BackOffOp,
    ChooseOp,
    EdgeShareOp,
    GuideStatsOp,
    LightInOp,
    LightOutOp,
    RestoreOp,
)
from torchgi.backends.c_kernels import build
from torchgi.backends.c_kernels.filters import _box
from torchgi.backends.c_kernels.runtime import (
    _box_scratch,
    _buffer,
    _parts,
    _ptr,
    _run,
    _threads,
)
from torchgi.core.dtypes import variance_rounding
from torchgi.settings import GUIDED, PIPELINE


def guide_stats(desc: GuideStatsOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.GuideStatsOp` in one walk per image.

    Example:
        >>> n = torch.zeros(1, 3, 2, 2); d = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])
        >>> build.library() is None or guide_stats(GuideStatsOp(n, d, d > 2.5))[0, [3, 8]].tolist() == [1.0, 4.0]
        True
    """
    lib = build.library()
    n = desc.normal.contiguous()
    d = None if desc.depth is None else desc.depth.contiguous()
    hit = None if desc.hit is None else desc.hit.contiguous()
    B, _, H, W = n.shape
    rows = []
    for b in range(B):
        threads = _threads(H, H * W)
        buf = torch.zeros(threads, 15, dtype=torch.float64)
        lib.torchgi_guide_stats(n[b].data_ptr(), _ptr(None if d is None else d[b]),
                                _ptr(None if hit is None else hit[b]), H, W, threads, buf.data_ptr(), 120)
        rows.append(torch.cat([buf[:, :4].amin(0), buf[:, 4:9].amax(0), buf[:, 9:].sum(0)]))
    return torch.stack(rows)


def _plane_ptrs(planes: list[torch.Tensor], b: int) -> list[int | None]:
    """Image ``b``'s pointer of each guide plane, None past the guide's channels (4 in all)."""
    return [p[b, 0].data_ptr() for p in planes] + [None] * (4 - len(planes))


def _spec_planes(spec) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
    """A :class:`~torchgi.backends.base.GuideSpec`'s ``(B,1,H,W)`` source planes (contiguous),
    scales and offsets (float32)."""
    normal = spec.normal.contiguous()
    depth = None if spec.depth is None else spec.depth.contiguous()
    planes = [normal[:, c : c + 1] if c < 3 else depth for c in spec.channels]
    return planes, torch.tensor(spec.scale, dtype=torch.float32), torch.tensor(spec.offset, dtype=torch.float32)


def edge_share(desc: EdgeShareOp) -> float:
    """:class:`~torchgi.backends.base.EdgeShareOp` on the guide's source planes (no guide built).

    Example:
        >>> from torchgi.backends.base import GuideSpec
        >>> n = torch.zeros(1, 3, 2, 3); n[..., 2] = 1.0
        >>> build.library() is None or edge_share(EdgeShareOp(GuideSpec(n, None, (0,), (0.5,), (0.5,)), 0.1)) == 0.5
        True
    """
    lib = build.library()
    planes, scale, _ = _spec_planes(desc.spec)
    B, _, H, W = planes[0].shape
    count = 0.0
    for b in range(B):
        count += float(_parts(lib.torchgi_guide_edges, H, H * W, len(planes), *_plane_ptrs(planes, b),
                              scale.data_ptr(), H, W, float(desc.edge), doubles=1, extra_bytes=4 * W)[0])
    total = B * ((H + 1) // 2) * max(W - 1, 0)
    return count / total if total else float("nan")


def restore(desc: RestoreOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.RestoreOp` fused: per image a walk for the light-source mask,
    one for the demodulated light and its capped peak, the firefly bound's box, one for the clamp
    (with the s x s means of light and guide at half resolution), the guided filter's coefficient
    pass, and its last pass with the remodulation (the coefficients upsampled first at half
    resolution). The guide is read from its normal and depth planes, never built. Raises
    :class:`~torchgi.core.errors.NonFiniteError` naming an input with NaN/Inf.

    Example:
        >>> from torchgi.backends.base import GuideSpec
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5)
        >>> spec = GuideSpec(torch.zeros_like(c), None, (0,), (0.5,), (0.5,))
        >>> build.library() is None or restore(RestoreOp(c, None, None, a, None, spec, torch.ones(1, 1, 1, 1), 1, 1e-4, 1,
        ...                                        4.0)).shape == (1, 3, 8, 8)
        True
    """
    lib = build.library()
    light = _light_tensors(desc)
    color = light[0]
    planes, scale, offset = _spec_planes(desc.spec)
    B, _, H, W = color.shape
    n, s = len(planes), desc.subsample
    h, w = -(-H // s), -(-W // s)
    r_low = desc.radius if s == 1 else round(desc.radius / s)
    K, Q = n + 3 + n * (n + 1) // 2 + 3 * n, (n + 1) * 3
    ws = desc.workspace
    x, peak = _buffer(ws, "x", (3, H, W)), _buffer(ws, "peak", (1, 1, H, W))
    mask = _buffer(ws, "mask", (H, W), torch.uint8)
    low_x = _buffer(ws, "low_x", (3, h, w)) if s > 1 else None
    low_g = _buffer(ws, "low_g", (n, h, w)) if s > 1 else None
    coef = _buffer(ws, "coef", (Q, h, w))
    coef_box = _buffer(ws, "coef_box", (Q, h, w)) if s > 1 else None
    out = torch.empty(B, 3, H, W, dtype=torch.float32)
    eps = torch.full((n,), max(float(desc.eps), torch.finfo(torch.float32).tiny), dtype=torch.float32)
    unit, k = variance_rounding(torch.float32), float(desc.firefly)
    ones, zeros = torch.ones(n, dtype=torch.float32), torch.zeros(n, dtype=torch.float32)
    for b in range(B):
        light_in = _light_args(light, b)
        lights = _demodulate(lib, desc, light_in, b, H, W, mask, x, peak)
        mean = _box(peak, PIPELINE.firefly_radius)
        mean_p = (_parts(lib.torchgi_clamp, h, H * W, x.data_ptr(), mean.data_ptr(), k, H, W, s, _ptr(low_x),
                         doubles=3, extra_bytes=8 * W) / (H * W)).float()
        g = _plane_ptrs(planes, b)
        mean_g = (_parts(lib.torchgi_guide_pool, h, H * W, n, *g, scale.data_ptr(), offset.data_ptr(), H, W, s,
                         _ptr(low_g), doubles=n) / (H * W)).float()
        if desc.centre_src is not None:  # given (tiles of one image share them), not this call's means
            mean_p = desc.centre_src[b].reshape(-1).to(torch.float32).expand(3).contiguous()
            mean_g = desc.centre_guide[b].to(torch.float32).contiguous()
        # the coefficients from the guide's planes, or at half resolution from its block means
        g_low, sc_low, of_low = (g, scale, offset) if s == 1 else \
            ([p.data_ptr() for p in low_g] + [None] * (4 - n), ones, zeros)
        _run(lib.torchgi_restore_coefficients, h, w, n, *g_low, sc_low.data_ptr(), of_low.data_ptr(), mean_g.data_ptr(),
             (x if s == 1 else low_x).data_ptr(), mean_p.data_ptr(), 3, h, w, r_low, eps.data_ptr(), unit,
             coef.data_ptr(), _box_scratch(K, w))
        if s > 1:  # the coefficients' box means at low resolution, upsampled in the last pass
            _run(lib.torchgi_guided_apply, h, w, coef.data_ptr(), n, 3, None, None, None, h, w, r_low,
                 coef_box.data_ptr(), _box_scratch(Q, w))
        _run(lib.torchgi_guided_finish, H, W, (coef if s == 1 else coef_box).data_ptr(), n, 3, *g, scale.data_ptr(),
             offset.data_ptr(), mean_g.data_ptr(), mean_p.data_ptr(), H, W, r_low, s, out[b].data_ptr(), *light_in,
             lights, _box_scratch(Q, W) + 3 * W if s == 1 else 7 * W + w)
    return out


def _light_tensors(desc: RestoreOp | LightInOp | LightOutOp) -> tuple[torch.Tensor | None, ...]:
    """The light inputs ``(color, emission, kept, albedo, hit)`` of ``desc``, contiguous."""
    return tuple(None if t is None else t.contiguous() for t in (desc.color, desc.emission, desc.kept, desc.albedo,
                                                                  desc.hit))


def _light_args(light: tuple[torch.Tensor | None, ...], b: int) -> list:
    """Image ``b``'s light inputs (:func:`_light_tensors`) as the C entry points take them."""
    return [None if t is None else t[b].data_ptr() for t in light] + [float(PIPELINE.albedo_floor),
                                                                        float(PIPELINE.albedo_ceiling)]


def _demodulate(lib, desc: RestoreOp | LightInOp, light_in: list, b: int, H: int, W: int, mask: torch.Tensor,
                x: torch.Tensor, peak: torch.Tensor) -> int | None:
    """The walks before the firefly clamp for image ``b``: the light-source ``mask (H, W)`` bytes,
    the demodulated light ``x (3, H, W)`` and its capped ``peak``. Returns the mask's pointer, or
    None where no light source was found; raises naming an input with NaN/Inf."""
    from torchgi.core.check import check_finite

    level, k, r = float(desc.level[b].reshape(())), float(desc.firefly), PIPELINE.light_square // 2
    rows = -(-H // _threads(H, H * W)) + 1  # the most rows of one band
    seen = _parts(lib.torchgi_lights, H, H * W, *light_in, H, W, PIPELINE.light * level, r, mask.data_ptr(), doubles=1,
                  extra_bytes=12 * W + 3 * (rows + 4 * r) * W + W)[0]
    lights = mask.data_ptr() if seen > 0 else None
    bad = _parts(lib.torchgi_prepare, H, H * W, *light_in, H, W, lights, level, k * level, x.data_ptr(),
                 peak.data_ptr(), doubles=4, extra_bytes=21 * W)
    if bool(bad.any()):  # counted in the walk: the named error (with its counts) from the torch check
        for name, t in desc.light_inputs():
            check_finite(t, name)
    return lights


def light_in(desc: LightInOp) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:class:`~torchgi.backends.base.LightInOp` in the walks of :func:`restore` before its filter:
    the light-source mask, the demodulated light with its capped peak, the firefly bound's box and
    the clamp (into a copy: the light before it is returned too). Raises
    :class:`~torchgi.core.errors.NonFiniteError` naming an input with NaN/Inf.

    Example:
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5)
        >>> build.library() is None or light_in(LightInOp(c, None, None, a, None, torch.ones(1, 1, 1, 1), 4.0))[2].dtype
        torch.bool
    """
    lib = build.library()
    light = _light_tensors(desc)
    B, _, H, W = light[0].shape
    ws = desc.workspace
    x, clamped = _buffer(ws, "light_in_x", (B, 3, H, W)), _buffer(ws, "light_in_clamped", (B, 3, H, W))
    mask = _buffer(ws, "light_in_mask", (B, 1, H, W), torch.uint8)
    peak = _buffer(ws, "light_in_peak", (1, 1, H, W))
    for b in range(B):
        _demodulate(lib, desc, _light_args(light, b), b, H, W, mask[b], x[b], peak)
        mean = _box(peak, PIPELINE.firefly_radius)
        clamped[b].copy_(x[b])
        _parts(lib.torchgi_clamp, H, H * W, clamped[b].data_ptr(), mean.data_ptr(), float(desc.firefly), H, W, 1, None,
               doubles=3, extra_bytes=8 * W)
    return clamped, x, mask.view(torch.bool)


def light_out(desc: LightOutOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.LightOutOp` in one walk per image (into ``filtered`` where
    ``inplace``).

    Example:
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5); none = torch.zeros(1, 1, 8, 8, dtype=torch.bool)
        >>> build.library() is None or torch.allclose(light_out(LightOutOp(c / 0.5, c, None, None, a, None, none)), c)
        True
    """
    lib = build.library()
    light = _light_tensors(desc)
    out = desc.filtered if desc.inplace and desc.filtered.is_contiguous() else desc.filtered.contiguous().clone()
    mask = desc.lights.contiguous().view(torch.uint8)
    B, _, H, W = out.shape
    for b in range(B):
        _run(lib.torchgi_finish, H, W, out[b].data_ptr(), *_light_args(light, b), H, W, mask[b].data_ptr(), 3 * W)
    return out


def back_off(desc: BackOffOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.BackOffOp` for one sample count (``desc.spp`` a float or
    None) in two walks per image around the box pass.

    Example:
        >>> c = torch.ones(1, 3, 4, 4); lit = torch.zeros(1, 1, 4, 4, dtype=torch.bool)
        >>> build.library() is None or round(back_off(BackOffOp(c + 1, c, torch.full_like(c, 1e-6), 64.0, lit)).mean().item(), 4)
        1.0
    """
    lib = build.library()
    n = 2.0 if desc.spp is None else float(desc.spp)
    if n < 2:
        return desc.out
    out, color, var = (t.contiguous() for t in (desc.out, desc.color, desc.variance))
    emit = desc.emitting.contiguous()
    B, _, H, W = out.shape
    k = 1 + PIPELINE.backoff_margin / math.sqrt(n - 1)
    floor = torch.finfo(torch.float32).eps ** 2
    planes = torch.empty(B, 2, H, W, dtype=torch.float32)
    for b in range(B):
        _run(lib.torchgi_backoff_planes, H, W, color[b].data_ptr(), out[b].data_ptr(), var[b].data_ptr(),
             var.shape[1], emit[b].data_ptr(), H, W, planes[b].data_ptr(), 0)
    sums = _box(planes, PIPELINE.backoff_radius)
    dst = torch.empty_like(out)
    for b in range(B):
        _run(lib.torchgi_backoff_apply, H, W, color[b].data_ptr(), out[b].data_ptr(), var[b].data_ptr(),
             var.shape[1], emit[b].data_ptr(), sums[b].data_ptr(), H, W, k, 1 / n, floor, dst[b].data_ptr(), 0)
    return dst


def choose(desc: ChooseOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.ChooseOp` in two walks per image around the box pass.

    Example:
        >>> c = torch.ones(1, 3, 4, 4); lit = torch.zeros(1, 1, 4, 4, dtype=torch.bool)
        >>> build.library() is None or round(choose(ChooseOp((c, c + 1), (1, 4), torch.zeros_like(c), lit)).mean().item(), 4)
        1.0
    """
    lib = build.library()
    outs = [o.contiguous() for o in desc.outs]
    var, emit = desc.variance.contiguous(), desc.emitting.contiguous()
    n = len(outs)
    B, _, H, W = outs[0].shape
    share = torch.tensor([GUIDED.choose_noise / (2 * r + 1) ** 2 for r in desc.radii] + [0.0] * (4 - n),
                         dtype=torch.float32)
    floor = torch.finfo(torch.float32).eps ** 2
    planes = torch.empty(B, n, H, W, dtype=torch.float32)
    for b in range(B):
        ptrs = [o[b].data_ptr() for o in outs] + [None] * (4 - n)
        _run(lib.torchgi_choose_planes, H, W, *ptrs, n, var[b].data_ptr(), var.shape[1], emit[b].data_ptr(), H, W,
             planes[b].data_ptr(), 0)
    sums = _box(planes, PIPELINE.backoff_radius)
    dst = torch.empty_like(outs[0])
    for b in range(B):
        ptrs = [o[b].data_ptr() for o in outs] + [None] * (4 - n)
        _run(lib.torchgi_choose_apply, H, W, *ptrs, n, sums[b].data_ptr(), share.data_ptr(),
             float(GUIDED.choose_temperature), floor, H, W, dst[b].data_ptr(), 0)
    return dst
