"""The Denoiser's light maths (docs/design.md, Denoiser pipeline): which pixels are surfaces, what
light is divided by, which pixels are light sources, the firefly bound, the scene's light level and the whole
demodulate / filter / remodulate step around a filter, and the step after it that backs off toward
the input where the filter's residual exceeds the noise (:func:`back_off`), and the per-pixel
choice among filters of several radii by their estimated error (:func:`choose`).

It sits below the back ends: :mod:`torchgi.denoise`, :mod:`torchgi.temporal` and the torch
back end's reference pipeline (``backends.torch_code``) all take it from here, and it imports
nothing of torchgi but :mod:`torchgi.core` and :mod:`torchgi.settings`. The two steps that
need a box mean (the light-source opening, the firefly bound) take it as an argument
``box(x, r)`` (``(B, C, H, W)`` mean over ``(2r+1)²``, count-normalised at borders): the
Denoiser hands in :func:`torchgi.filters.box`, a back end its own seam call, so that each
caller keeps its choice of kernel.

All tensors are ``(B, C, H, W)``; light is linear radiance (the renderer's units).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from torchgi.core import exported
from torchgi.core.check import is_recording
from torchgi.settings import GUIDED, PIPELINE

__all__ = [
    "BoxFn", "back_off", "centre", "choose", "clamp_fireflies", "demodulator", "emitting", "every4", "filter_light",
    "finish", "firefly_bound", "level", "light_sources", "median_level", "prepare", "restore", "samples", "scaled_to",
    "surface_mask",
]

BoxFn = Callable[[torch.Tensor, int], torch.Tensor]  # box(x (B,C,H,W), r) -> the (2r+1)² mean, same shape


def surface_mask(hit: torch.Tensor | None, albedo: torch.Tensor) -> torch.Tensor:
    """``(B,1,H,W)`` bool: pixels on geometry - ``hit`` when given, else non-zero albedo.

    Example:
        >>> surface_mask(None, torch.tensor([[[[0.0, 0.5]]]])).tolist()
        [[[[False, True]]]]
    """
    return hit if hit is not None else exported.channel_max(albedo) > 0


def demodulator(albedo: torch.Tensor, surface: torch.Tensor) -> torch.Tensor:
    """What light is divided by: the albedo (at least ``PIPELINE.albedo_floor``, at most
    ``PIPELINE.albedo_ceiling``: another renderer's "albedo" above 1 is not a reflectance) on
    surfaces, 1 on the background, which is filtered as it is.

    Example:
        >>> a = torch.tensor([[[[0.0, 0.5]]]])
        >>> demodulator(a, surface_mask(None, a)).tolist()
        [[[[1.0, 0.5]]]]
    """
    return exported.where(surface, albedo.clamp(PIPELINE.albedo_floor, PIPELINE.albedo_ceiling), 1.0)


def every4(t: torch.Tensor | None) -> torch.Tensor | None:
    """Every 4th row and column of ``t (B,C,H,W)`` (a view), None for None.

    Example:
        >>> every4(torch.zeros(1, 1, 8, 9)).shape
        torch.Size([1, 1, 2, 3])
    """
    return None if t is None else t[:, :, ::4, ::4]


def median_level(x: torch.Tensor, surface: torch.Tensor) -> torch.Tensor:
    """``(B,1,1,1)``: per image, the (lower) median over surface pixels of the channel maximum of
    ``x (B,C,H,W)`` (a scale for thresholds; pass :func:`every4` views, so that 1/16 of the pixels
    is read); 1 where there is none or it is not > 0. Plain tensor ops (exportable).

    Example:
        >>> x = torch.tensor([[[[1.0, 2.0, 9.0]]]])
        >>> median_level(x, torch.ones(1, 1, 1, 3, dtype=torch.bool)).flatten().tolist()
        [2.0]
    """
    peak = x.amax(1).flatten(1)
    on = surface[:, 0].flatten(1)
    ranked = torch.where(on, peak, torch.full((), float("inf"), dtype=x.dtype, device=x.device))
    count = on.sum(1, keepdim=True)
    if is_recording():  # the lower half sorted exports (a TopK); eager calls select in linear time
        m = ranked.topk(ranked.shape[1] // 2 + 1, 1, largest=False).values.gather(1, ((count - 1).clamp_min(0) // 2))
    else:
        m = torch.stack([ranked[b].kthvalue(max(int(count[b]) - 1, 0) // 2 + 1).values for b in range(len(ranked))]
                        ).view(-1, 1) if ranked.shape[1] else ranked.new_ones(len(ranked), 1)
    return torch.where((count > 0) & (m > 0), m, torch.ones_like(m)).reshape(-1, 1, 1, 1)


def light_sources(emission: torch.Tensor, threshold: torch.Tensor, box: BoxFn) -> torch.Tensor:
    """``(B,1,H,W)`` bool: pixels whose emission exceeds ``threshold (B,1,1,1)`` and that lie in a
    square of ``PIPELINE.light_square`` (3x3) such pixels (a morphological opening by two ``box``
    passes: whole lights, corners included, stay; single pixels and one-pixel fringes that a few
    samples hit along a light's silhouette do not).

    Example:
        >>> from torchgi.filters import box
        >>> e = torch.zeros(1, 3, 6, 6); e[..., 1:4, 1:4] = 10.0; e[..., 5, 5] = 10.0
        >>> int(light_sources(e, torch.ones(1, 1, 1, 1), box).sum())   # the 3x3 light, not the lone pixel
        9
    """
    bright = exported.channel_max(emission) > threshold
    if not is_recording() and not bool(bright.any()):
        return bright  # no light source in view: nothing to open
    r = PIPELINE.light_square // 2
    core = box(bright.to(emission.dtype), r) > 1 - 1e-3  # erosion: the whole window is bright
    return bright & (box(core.to(emission.dtype), r) > 0)  # dilation back


def firefly_bound(peak: torch.Tensor, scene_level: torch.Tensor, k: float, box: BoxFn) -> torch.Tensor:
    """``(B,1,H,W)``: ``k`` x the local level of the channel maximum ``peak (B,1,H,W)``: the box
    mean (``PIPELINE.firefly_radius``) of ``peak`` capped at ``k`` x ``scene_level``
    (:func:`median_level`).

    Example:
        >>> from torchgi.filters import box
        >>> firefly_bound(torch.ones(1, 1, 4, 4), torch.ones(1, 1, 1, 1), 4.0, box).flatten().tolist()[:2]
        [4.0, 4.0]
    """
    # (box sums round: a mean of zeros can come out as -1e-9, so the bound is clamped at 0)
    return k * box(torch.minimum(peak, k * scene_level), PIPELINE.firefly_radius).clamp_min(0)


def clamp_fireflies(x: torch.Tensor, scene_level: torch.Tensor, k: float, box: BoxFn) -> torch.Tensor:
    """Scale pixels of ``x (B,C,H,W)`` (>= 0) whose maximum exceeds ``k`` x their local level down
    to that bound (:func:`firefly_bound`), hue kept.

    Example:
        >>> from torchgi.filters import box
        >>> x = torch.ones(1, 3, 9, 9); x[..., 4, 4] = 1000.0
        >>> float(clamp_fireflies(x, torch.ones(1, 1, 1, 1), 4.0, box)[0, 0, 4, 4]) < 5
        True
    """
    peak = exported.channel_max(x)
    return scaled_to(x, peak, firefly_bound(peak, scene_level, k, box))


def scaled_to(x: torch.Tensor, peak: torch.Tensor, bound: torch.Tensor) -> torch.Tensor:
    """``x (B,C,H,W)`` scaled down, hue kept, where its channel maximum ``peak (B,1,H,W)`` exceeds
    ``bound (B,1,H,W)``; unchanged elsewhere.

    Example:
        >>> scaled_to(torch.tensor([[[[4.0]], [[2.0]]]]), torch.tensor([[[[4.0]]]]), torch.tensor([[[[1.0]]]])).flatten()
        tensor([1.0000, 0.5000])
    """
    over = peak > bound  # so peak > 0 wherever it divides
    return x * exported.where(over, bound / exported.where(over, peak, 1.0), 1.0)


def filter_light(x: torch.Tensor, scene_level: torch.Tensor, filter_fn: Callable[..., torch.Tensor],
                 firefly: float, box: BoxFn, unclamped: bool = False) -> torch.Tensor:
    """``filter_fn`` of demodulated light ``x (B,C,H,W)`` with its fireflies clamped at ``firefly``
    x their local level (``scene_level`` from :func:`median_level`), clamped at 0: light is >= 0
    and linear models can undershoot. With ``unclamped``, ``filter_fn(clamped, x)`` (a filter
    that gives back some of the light the clamp took).

    Example:
        >>> from torchgi.filters import box
        >>> filter_light(-torch.ones(1, 3, 4, 4), torch.ones(1, 1, 1, 1), lambda v: v, 4.0, box).max().item()
        0.0
    """
    clamped = clamp_fireflies(x, scene_level, firefly, box)
    return (filter_fn(clamped, x) if unclamped else filter_fn(clamped)).clamp_min(0)


def _without(color: torch.Tensor, emission: torch.Tensor | None, kept: torch.Tensor | None, albedo: torch.Tensor,
             surface: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """On every 4th row and column: the demodulated light without emission and kept light, and the surface."""
    c, e, k, a, on = (every4(t) for t in (color, emission, kept, albedo, surface))
    base = c - k if k is not None else c
    return (base - e if e is not None else base) / demodulator(a, on), on


def level(color: torch.Tensor, emission: torch.Tensor | None, kept: torch.Tensor | None, albedo: torch.Tensor,
          surface: torch.Tensor) -> torch.Tensor:
    """``(B,1,1,1)``: :func:`median_level` of the demodulated light without emission and kept
    light (each ``(B,3,H,W)`` or None), computed on every 4th row and column only.

    Example:
        >>> c = torch.full((1, 3, 8, 8), 0.5); a = torch.full_like(c, 0.5)
        >>> level(c, None, None, a, surface_mask(None, a)).flatten().tolist()
        [1.0]
    """
    return median_level(*_without(color, emission, kept, albedo, surface))


def centre(color: torch.Tensor, emission: torch.Tensor | None, kept: torch.Tensor | None, albedo: torch.Tensor,
           surface: torch.Tensor, cap: torch.Tensor) -> torch.Tensor:
    """``(B, 3)`` float64 on the CPU: per image and channel the mean of the demodulated light
    (without emission and kept light, at most ``cap (B,1,1,1)``) on every 4th row and column:
    a constant near the clamped light's mean, to centre it by before the filter's sums.

    Example:
        >>> c = torch.full((1, 3, 8, 8), 0.5); a = torch.full_like(c, 0.5)
        >>> centre(c, None, None, a, surface_mask(None, a), torch.full((1, 1, 1, 1), 4.0)).tolist()
        [[1.0, 1.0, 1.0]]
    """
    x, _ = _without(color, emission, kept, albedo, surface)
    return torch.minimum(x, cap).double().mean(dim=(2, 3)).cpu()


def restore(
    color: torch.Tensor, emission: torch.Tensor | None, kept: torch.Tensor | None, albedo: torch.Tensor,
    surface: torch.Tensor, filter_fn: Callable[..., torch.Tensor], firefly: float, box: BoxFn,
    scene_level: torch.Tensor | None = None, unclamped: bool = False,
) -> torch.Tensor:
    """The Denoiser's pipeline around ``filter_fn`` (demodulated light in, filtered out): light
    sources found (from ``emission``, else from the bright coherent regions of ``color``) and kept
    whole, the rest demodulated by :func:`demodulator`, its fireflies clamped, filtered, clamped at
    0 and remodulated. All ``(B, C, H, W)``; ``kept`` is light added back unfiltered (direct light
    in the papers' split) or None; ``firefly`` the method's clamp factor; ``scene_level``
    :func:`level` (None: computed here); ``unclamped``: ``filter_fn`` also gets the light before
    the firefly clamp (:func:`filter_light`). Returns the ``(B, 3, H, W)`` radiance.

    Example:
        >>> from torchgi.filters import box
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5)
        >>> out = restore(c, None, None, a, surface_mask(None, a), lambda x: x.mean((2, 3), keepdim=True).expand_as(x),
        ...               4.0, box)
        >>> out.shape, bool((out >= 0).all())
        (torch.Size([1, 3, 8, 8]), True)
    """
    if scene_level is None:
        scene_level = level(color, emission, kept, albedo, surface)
    demod = demodulator(albedo, surface)
    x, lights = _demodulated(color, emission, kept, demod, box, scene_level)
    clamped = clamp_fireflies(x, scene_level, firefly, box)
    out = filter_fn(clamped, x) if unclamped else filter_fn(clamped)
    return _remodulated(out, color, emission, kept, demod, lights)


def prepare(
    color: torch.Tensor, emission: torch.Tensor | None, kept: torch.Tensor | None, albedo: torch.Tensor,
    surface: torch.Tensor, firefly: float, box: BoxFn, scene_level: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`restore`'s steps before its filter, for a filter run apart (the Denoiser's learned
    pyramid, through :class:`~torchgi.backends.LightInOp`): the filter's input (the demodulated
    light, its fireflies clamped), the light before the clamp, both ``(B,3,H,W)``, and the
    light-source mask ``(B,1,H,W)`` bool that :func:`finish` takes. Arguments as :func:`restore`'s
    (``scene_level`` required).

    Example:
        >>> from torchgi.filters import box
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5)
        >>> clamped, x, lights = prepare(c, None, None, a, surface_mask(None, a), 4.0, box, torch.ones(1, 1, 1, 1))
        >>> torch.allclose(x, c / 0.5), bool((clamped <= x).all()), bool(lights.any())
        (True, True, False)
    """
    x, lights = _demodulated(color, emission, kept, demodulator(albedo, surface), box, scene_level)
    return clamp_fireflies(x, scene_level, firefly, box), x, lights


def finish(
    filtered: torch.Tensor, color: torch.Tensor, emission: torch.Tensor | None, kept: torch.Tensor | None,
    albedo: torch.Tensor, surface: torch.Tensor, lights: torch.Tensor,
) -> torch.Tensor:
    """:func:`restore`'s steps after its filter: ``filtered (B,3,H,W)`` clamped at 0 and
    remodulated, the light sources (``lights`` from :func:`prepare`) and ``kept`` light added
    back; without an emission input a light source's pixels are its colour.

    Example:
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5); none = torch.zeros(1, 1, 8, 8, dtype=torch.bool)
        >>> torch.equal(finish(c / 0.5, c, None, None, a, surface_mask(None, a), none), c)
        True
    """
    return _remodulated(filtered, color, emission, kept, demodulator(albedo, surface), lights)


def _demodulated(color: torch.Tensor, emission: torch.Tensor | None, kept: torch.Tensor | None, demod: torch.Tensor,
                 box: BoxFn, scene_level: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The demodulated light without light sources and kept light, and the light-source mask."""
    base = color - kept if kept is not None else color
    lights = light_sources(emission if emission is not None else base / demod, PIPELINE.light * scene_level, box)
    if emission is not None:
        return (base - exported.where(lights, emission, 0.0)) / demod, lights
    # no emission input: a light source's pixels pass whole and enter the filter at the median level
    return exported.where(lights, scene_level.expand_as(color), base / demod), lights


def _remodulated(out: torch.Tensor, color: torch.Tensor, emission: torch.Tensor | None, kept: torch.Tensor | None,
                 demod: torch.Tensor, lights: torch.Tensor) -> torch.Tensor:
    """A filter's output clamped at 0 (light is >= 0; linear models can undershoot), remodulated,
    with light sources and kept light added back."""
    out = out.clamp_min(0) * demod
    if emission is not None:
        light = exported.where(lights, emission, 0.0)
        kept = light if kept is None else kept + light
    out = out + kept if kept is not None else out
    return out if emission is not None else exported.where(lights, color, out)


def emitting(color: torch.Tensor, emission: torch.Tensor | None, albedo: torch.Tensor, surface: torch.Tensor,
             scene_level: torch.Tensor) -> torch.Tensor:
    """``(B,1,H,W)`` bool: pixels that emit - any ``emission`` (the sky and missed rays included)
    where it is given, else pixels whose demodulated ``color`` exceeds ``PIPELINE.light`` x
    ``scene_level`` (:func:`level`), the test :func:`restore` opens into light sources.

    Example:
        >>> c = torch.ones(1, 3, 1, 2); c[..., 1] = 100.0
        >>> emitting(c, None, torch.ones_like(c), torch.ones(1, 1, 1, 2, dtype=torch.bool), torch.ones(1, 1, 1, 1)).tolist()
        [[[[False, True]]]]
    """
    if emission is not None:
        return exported.channel_max(emission) > 0
    return exported.channel_max(color / demodulator(albedo, surface)) > PIPELINE.light * scene_level


def back_off(out: torch.Tensor, color: torch.Tensor, variance: torch.Tensor | None,
             spp: float | torch.Tensor | None, emitting: torch.Tensor, box: BoxFn) -> torch.Tensor:
    """``out`` moved toward ``color`` where the filter's residual is larger than the noise it
    removed (James-Stein shrinkage): ``out + w (color - out)``, all ``(B, 3, H, W)``.

    With ``e`` the mean of ``|color - out|²`` and ``v`` that of the noise variance over
    ``PIPELINE.backoff_radius`` (channels summed), ``w = clamp(1 - k v / e, 0, 1)``: for a filter
    of error ``b²`` (its bias and its own variance) on an input of noise ``σ²``, ``e ≈ b² + σ²``
    and ``1 - σ² / e`` is the blend that minimises the local error, so the filter is kept where
    noise dominates and backs off where its bias does: the error falls with the sample count
    instead of stopping at the filter's bias. The window pools only pixels that do not emit
    (``emitting (B,1,H,W)`` bool: a light's residual, many times the scene's, would make its
    neighbours back off); an emitting pixel decides alone, ``w = clamp(1 - k (σ² / |res|² +
    1 / n), 0, 1)`` (``n`` samples that agree do not prove a pixel noise-free: a horizon pixel
    whose 2 samples both hit the sky).

    The noise: ``variance`` (of the mean, ``(B,1|3,H,W)``) with ``k = 1 + PIPELINE.backoff_margin /
    sqrt(spp - 1)`` (a variance from few samples is itself noisy; a pixel of fewer than 2 samples
    keeps ``out``; ``spp`` a float, a ``(B,1,H,W)`` plane or None: taken as 2). Without a ``variance`` nothing is done: a noise
    estimate from the image alone cannot tell fine detail from noise, nor noise that a renderer's
    pixel filter made smooth from signal.

    Example:
        >>> from torchgi.filters import box
        >>> truth = torch.linspace(0, 4, 16).view(1, 1, 1, 16).expand(1, 3, 16, 16)
        >>> color = truth + 0.01 * torch.randn(1, 3, 16, 16)   # nearly noise-free input
        >>> blurred = truth.mean().expand_as(truth)             # a filter far off the signal
        >>> none = torch.zeros(1, 1, 16, 16, dtype=torch.bool)
        >>> fixed = back_off(blurred, color, torch.full((1, 1, 16, 16), 1e-4), torch.full((1, 1, 16, 16), 64), none, box)
        >>> bool((fixed - truth).abs().mean() < 0.1 * (blurred - truth).abs().mean())
        True
    """
    n = samples(spp) if torch.is_tensor(spp) else spp
    if variance is None or n is not None and (n < 2 if isinstance(n, float)
                                              else not is_recording() and float(n.max()) < 2):
        return out  # no variance measured (or no pixel of 2 samples): nothing to compare with
    if out.dtype in (torch.float16, torch.bfloat16):  # squares of radiance overflow float16: work in float32
        return back_off(out.float(), color.float(), variance.float(), spp, emitting, box).to(out.dtype)
    B, C, H, W = out.shape
    res = color - out
    channels = range(C)  # (channel by channel: broadcasts over channels run slowly)
    r2 = sum(res[:, c : c + 1].square() for c in channels)
    noise = sum(variance[:, c : c + 1] for c in channels) if variance.shape[1] > 1 else variance * C
    n = 2.0 if n is None else n
    # every division guarded by a where whose other branch stays finite, so gradients do too
    measured = n >= 2 if torch.is_tensor(n) else None  # (fewer than 2 samples: no variance, the filter kept)
    n = exported.where(measured, n, 2.0) if measured is not None else n
    k = 1 + PIPELINE.backoff_margin / ((n - 1).sqrt() if torch.is_tensor(n) else math.sqrt(n - 1))
    any_lit = is_recording() or bool(emitting.any())
    planes = torch.cat([r2, noise], 1)
    sums = box(exported.where(emitting, 0.0, planes) if any_lit else planes, PIPELINE.backoff_radius)
    floor = torch.finfo(out.dtype).eps ** 2  # (its square is still a normal number)
    e, v = sums[:, :1], sums[:, 1:]
    w = exported.where(e > floor, 1 - k * v / exported.where(e > floor, e, 1.0), 0.0)
    if any_lit:
        own = 1 - k * (noise / exported.where(r2 > floor, r2, 1.0) + 1 / n)
        w = exported.where(emitting, exported.where(r2 > floor, own, 0.0), w)
    if measured is not None:
        w = exported.where(measured, w, 0.0)
    w = w.clamp(0, 1)
    return torch.addcmul(out.reshape(B, C, -1), w.reshape(B, 1, -1), res.view(B, C, -1)).view(B, C, H, W)


def choose(outs: list[torch.Tensor], radii: list[int], variance: torch.Tensor, emitting: torch.Tensor,
           box: BoxFn) -> torch.Tensor:
    """A per-pixel blend of ``outs`` (each ``(B, 3, H, W)``: one linear filter of the same input at
    each of ``radii``, sharpest first) weighted by each one's estimated local error.

    A filter of radius ``r`` leaves ``v_r σ² = c σ² / (2r+1)²`` of the input's noise variance ``σ²``
    (``c = GUIDED.choose_noise``; 0.44 for a box mean applied twice on a flat guide, more at
    edges) and a bias ``b_r``. Against the
    sharpest output, ``|out_r - out_1|²`` pooled over ``PIPELINE.backoff_radius`` estimates
    ``b_r² + (v_1 - v_r) σ²`` (the sharpest's own bias taken as 0), so each output's error is
    estimated as ``max(that - (v_1 - v_r) σ², 0) + v_r σ²`` and the outputs are weighted by
    ``softmax(-error / (GUIDED.choose_temperature v_1 σ²))``: the wide filter where the light is
    smooth, the narrow one where the wide one's bias shows above the noise. Squares are weighted
    as relMSE weights them (``1 / (out² + 0.01)`` of ``outs[len(outs) // 2]``) and pooled over pixels
    that do not emit (``emitting (B,1,H,W)`` bool: a light's variance would make its neighbours
    blur). ``variance``: of the colour's mean, ``(B, 1|3, H, W)``; every pixel needs one (2 samples
    or more). Differentiable; float16 and bfloat16 are worked in float32.

    Example:
        >>> from torchgi.filters import box
        >>> edge = (torch.arange(16.0) >= 8).float().view(1, 1, 1, 16).expand(1, 3, 16, 16)
        >>> sharp, wide = edge + 0.02, box(edge, 4)        # the wide one blurs the edge
        >>> none = torch.zeros(1, 1, 16, 16, dtype=torch.bool)
        >>> out = choose([sharp, wide], [1, 4], torch.full((1, 1, 16, 16), 1e-4), none, box)
        >>> bool((out - edge).abs().amax() < 0.05)
        True
    """
    if outs[0].dtype in (torch.float16, torch.bfloat16):  # squares of radiance overflow float16
        return choose([o.float() for o in outs], radii, variance.float(), emitting, box).to(outs[0].dtype)
    if len(outs) != len(radii) or len(outs) < 2:
        raise ValueError(f"outs, radii: expected one output per radius, at least 2; got {len(outs)} and {len(radii)}")
    C = outs[0].shape[1]
    channels = range(C)  # (channel by channel: broadcasts over channels run slowly)
    mid = outs[len(outs) // 2]
    weight = 1 / (sum(mid[:, c : c + 1].square() for c in channels) / C + 0.01)
    noise = sum(variance[:, c : c + 1] for c in channels) if variance.shape[1] > 1 else variance * C
    planes = [noise * weight] + [sum((o[:, c : c + 1] - outs[0][:, c : c + 1]).square() for c in channels) * weight
                                 for o in outs[1:]]
    stacked = torch.cat(planes, 1)
    any_lit = is_recording() or bool(emitting.any())
    sums = box(exported.where(emitting, 0.0, stacked) if any_lit else stacked, PIPELINE.backoff_radius)
    sigma = sums[:, :1]
    share = [GUIDED.choose_noise / (2 * r + 1) ** 2 for r in radii]
    errors = [sigma * share[0]] + [(sums[:, k : k + 1] - sigma * (share[0] - share[k])).clamp_min(0) + sigma * share[k]
                                   for k in range(1, len(outs))]
    # no noise measured (a noise-free window): the sharpest; every division guarded by a where
    # whose other branch stays finite (gradients and onnxruntime, which flushes tiny numbers, too)
    floor = torch.finfo(sigma.dtype).eps ** 2  # (its square is still a normal number)
    noisy = sigma > floor
    scale = exported.where(noisy, GUIDED.choose_temperature * share[0] * sigma, 1.0).clamp_min(floor)
    if len(outs) == 2:  # the softmax of two as sigmoids (onnxruntime's Softmax over channels transposes: slow)
        d = (errors[1] - errors[0]) / scale
        w = torch.cat([torch.sigmoid(d), torch.sigmoid(-d)], 1)
    else:
        w = torch.softmax(-torch.cat(errors, 1) / scale, 1)
    sharpest = torch.zeros_like(w[:, :1])
    w = exported.where(noisy, w, torch.cat([sharpest + 1] + [sharpest] * (len(outs) - 1), 1))
    return sum(w[:, k : k + 1] * o for k, o in enumerate(outs))


def samples(spp: torch.Tensor | None) -> float | torch.Tensor | None:
    """The sample count of ``spp (B,1,H,W)`` as a float when every pixel has the same (the usual
    render), else the plane as float32; None for None.

    Example:
        >>> samples(torch.full((1, 1, 2, 2), 4)), samples(None)
        (4.0, None)
    """
    if spp is None:
        return None
    if not is_recording() and spp.numel() and bool((spp == spp.reshape(-1)[0]).all()):
        return float(spp.reshape(-1)[0])
    return spp.to(torch.float32)
