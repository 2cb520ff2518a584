"""A learned guided pyramid: a small network at a quarter of the resolution chooses, per pixel,
how the guided filter's linear models from a pyramid of scales are mixed, and how much of what
they leave out is given back, band by band (issue 28).

Each *candidate* is the guided filter (normal + depth guide) fitted at one scale ``s`` of the
image pyramid (``s x s`` means of the light and the guide, He & Sun 2015) with one radius and
one ε: its coefficients ``(a, b)`` say how the light follows the guide around each pixel at that
scale. The optional *colour* candidates (none by default: docs/pyramid.md) are fitted the same way on another guide: the normal (the guide's
first three channels) and a colour channel ``λ · log(lum(y) / m + 0.01)``, ``y`` the first
candidate's output at full resolution, ``m`` the image's mean luminance, ``λ`` the colour scale
(0.1): they follow the shadow and shading edges, reflections and highlights that normal and depth
do not show (as the blend's colour-guided passes do). Every candidate is a linear model over the
same guide ``I`` (the guide and the colour channel, each centred by its image mean; a channel a
candidate does not use has coefficient 0). A U-Net at 1/4 resolution (three levels, a few tens
of thousands of weights) reads scale-free statistics of the light, its local noise, the guide,
the sample count and what each candidate makes of the light, and gives per-pixel logits. Their
softmax ``w_k`` mixes the candidates' *coefficients*: those of scale >= 4 at 1/4 resolution,
where the weights are, those of scale 2 at 1/2 with the weights upsampled; the mixed
coefficients are upsampled and applied to the full-resolution guide once; candidates of scale
1 (the guided filter at full resolution, outputs ``y_j``) are mixed as outputs, their weights
upsampled to full resolution. That gives the model ``M``; what the guide cannot explain (shadow
edges, reflections, glossy highlights) stays in the residual ``x - M``, and the remaining
outputs, through a sigmoid, are per-pixel gains ``g_1, g_2, g_4 ∈ [0, 1]`` of its Laplacian
bands and ``g_8`` of its low-pass at 1/8::

    M = μ + (Σ_k w_k a_k) · I + Σ_k w_k b_k + Σ_j w_j y_j
    P_8 = g_8 · R_8,   P_s = up(P_2s) + g_s · (R_s - up(R_2s))  for s = 4, 2, 1
    out = M + P_1

where ``μ`` is the light's image mean (the ``b`` and ``y_j`` are fitted to the light centred
the same way), ``R_s`` the ``s x s`` means of ``x - M`` and ``up``
the bilinear x2 (so gains of 1 everywhere give back ``x``, gains of 0 the model: a coarse gain
corrects the model's low-frequency bias, whose noise the means have removed). The gains are
evaluated at 1/4 resolution and resampled to their band (bilinear x2 steps up, 2 x 2 means down
to 1/8).

With ``direct`` (the shipped network) the filter also gets the light before the Denoiser's
firefly clamp, ``raw``, and the network five more outputs at 1/4: a correction ``δ`` (three
channels, in units of ``m``, the image's mean luminance) and the gains ``h_4, h_16 ∈ [0, 1]``
(sigmoids) of the clamped-away light ``r = raw - x`` at 1/4 and at 1/16::

    L = m · δ + h_4 · r_4 + up²(mean₄(h_4') · r_16),   out = M + P_1 + up²(L)

(``r_s`` the ``s x s`` means of ``r``, each 1/4 block's scaled down to at most the luminance of
the block's clamped light, ``mean₄(h_4')`` the 1/16 gain's 4 x 4 means, ``up²`` two bilinear x2
steps): the clamp keeps a firefly's spike out of the filter, and ``h`` puts its energy back
spread over 4 x 4 or 16 x 16 px blocks where the network judges it real, never more than
doubling a block (a small bright lamp seen in a glossy floor loses a fifth of the image's light
to the clamp at 1 spp; docs/pyramid.md). Two more features: ``log(1 + lum(r_4) / m)`` and the
same of ``r_16`` brought to 1/4.

The network's features at 1/4 resolution, with ``m`` each image's mean luminance
(channel mean) of ``x`` and ``·₄`` a 4 x 4 mean:

- ``log(1 + x₄ / m)`` per channel; ``log(var₄ / (lum₄² + 0.01 m²) + 1e-4)`` with ``var₄ =
  (lum²)₄ - lum₄²`` (the local noise and texture); the centred guide ``I₄``; ``log(e + 1e-4)``
  with ``e = (|I|²)₄ - |I₄|²`` (the guide's edges; the floor keeps float32's cancellation in
  ``e``, ~1e-7, from reaching the network); ``log2(spp)``;
- per candidate ``log(1 + lum(v) / m) - log(1 + lum₄ / m)``, ``v`` the candidate's output at
  1/4 resolution (coefficients upsampled to it, or for finer candidates applied at their scale
  and averaged down).

Each level of the pyramid is the 2 x 2 means of the one below; coefficients go up one level at
a time by bilinear x2 (pixel centres aligned). So the full-resolution work is a pyramid of
means, the scale-1 fits, one product of the upsampled coefficients with the guide whatever the
number of coarser candidates (a mix of linear models is a linear model) and the residual's
pyramid. Coarse scales
remove the low-frequency noise a 1-spp image keeps; the residual's bands keep what the guide
does not explain where the noise allows. Trained end to end by ``scripts/train_pyramid.py`` on
project-rendered scenes that are never benchmark scenes; the weights ship beside this module
(``pyramid_weights.json``) with their training config, commit and data hash.
:func:`pyramid_inputs` and :func:`pyramid_mix` are the two halves training uses.

Tensor code around the seam's ``GuidedOp``, ``UpsampleApplyOp``, ``ModelResidualOp``, ``FineBandOp``, ``BlockMeanOp``
(compiled back ends run them eagerly, the torch code under autograd, tracing and export):
differentiable in the light, the guide and the weights, float16 in and out (computed in float32).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from torchgi import backends
from torchgi.backends.torch_code.filter_guided import apply_coefficients
from torchgi.backends.torch_code.pyramid import up2
from torchgi.core.check import (
    check_finite,
    check_floating,
    check_same_device,
    check_same_floating,
    check_shape,
    is_recording,
)
from torchgi.core.dtypes import compute_dtype
from torchgi.core.errors import RangeError, ShapeError
from torchgi.core.workspace import kept_buffer, reusable
from torchgi.filters.pyramid_net import BANDS, WEIGHTS, PyramidNet, default_net

__all__ = ["Pyramid", "PyramidNet", "default_net", "pyramid", "pyramid_inputs", "pyramid_mix", "pyramid_stats"]

FEATURE_SCALE = 4  # the network's resolution: 1/4
MIX_SCALE = 2  # where the coefficients are mixed: 1/2
# How far (px) the shipped network's output reaches into its input, rounded up to the 16 x 16
# blocks of its coarsest level: features up to 1/8 (a scale-8 fit of radius 4 and its bilinear
# step, ~80 px), the U-Net's receptive field (~110 px) and the mix's bilinear steps (~20 px).
# Tiles with this much overlap compute the untiled output up to float rounding (docs/pyramid.md).
REACH = 192
ALIGN = 16  # tile origins on multiples of this: the blocks of every level are the untiled ones


def _blocks(t: torch.Tensor, s: int = 2) -> torch.Tensor:
    """``s x s`` block means (a last partial block averaged over what it has) through the seam."""
    return backends.run(backends.BlockMeanOp(t, s))


_up = up2  # bilinear x2 of (B, C, h, w) cropped to a size: the pyramid's next finer level


def _up5(c: torch.Tensor, size: Sequence[int]) -> torch.Tensor:
    """:func:`_up` of coefficients ``(B, n + 1, C, h, w)``."""
    return _up(c.flatten(1, 2), size).unflatten(1, c.shape[1:3])


def _finer(c: torch.Tensor, s: int, target: int, levels: dict[int, torch.Tensor]) -> torch.Tensor:
    """Coefficients ``c`` of pyramid scale ``s`` upsampled level by level to scale ``target``."""
    while s > target:
        s //= 2
        c = _up5(c, levels[s].shape[-2:])
    return c


def _add(fresh: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``fresh + t`` (``t`` broadcasting into ``fresh``), into ``fresh`` where it is
    :func:`~torchgi.core.workspace.reusable`."""
    return fresh.add_(t) if reusable(fresh, t) else fresh + t


def _weighted(w: torch.Tensor, ts: Sequence[torch.Tensor]) -> torch.Tensor:
    """``Σ_k w[:, k] ts[k]`` for ``w (B, k, ...)`` broadcasting against each ``ts[k] (B, ...)``,
    term by term (neither the terms stacked nor their products: at 1920x1080 50-90 MB each)."""
    out = w[:, 0] * ts[0]
    inplace = reusable(out, *ts)
    for k in range(1, len(ts)):
        out = out.addcmul_(w[:, k], ts[k]) if inplace else out + w[:, k] * ts[k]
    return out


def _levels(t: torch.Tensor, top: int) -> dict[int, torch.Tensor]:
    """``{1: t, 2: means 2x2, 4: ..., top: ...}``, each level from the one below."""
    out = {1: t}
    s = 1
    while s < top:
        out[2 * s] = _blocks(out[s])
        s *= 2
    return out


def _luminance(x: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    return torch.mean(x, 1, keepdim=True, out=out)


def _groups(net: PyramidNet) -> dict[str, list[int]]:
    """The candidates' indices (into ``net.candidates``) by group and mixing scale: "geometric@1",
    "geometric@2", "geometric@4", "colour@1", ... (scale 1 is mixed as outputs at full
    resolution, scale 2 as coefficients at 1/2, coarser ones at 1/4)."""
    out: dict[str, list[int]] = {f"{g}@{m}": [] for g in ("geometric", "colour") for m in (1, MIX_SCALE, FEATURE_SCALE)}
    for k, (s, _, _) in enumerate(net.candidates):
        out[f"{'geometric' if k < len(net.geometric) else 'colour'}@{min(s, FEATURE_SCALE)}"].append(k)
    return out


def _features(x: torch.Tensor, xs: dict[int, torch.Tensor], gs: dict[int, torch.Tensor], mean_p: torch.Tensor,
              m: torch.Tensor, spp: float | torch.Tensor, views: list[torch.Tensor],
              workspace: dict | None = None) -> torch.Tensor:
    """The network's features at 1/4 resolution (module docstring) from the light ``x``, the
    pyramids of the centred light and guide, the light's mean ``mean_p`` and mean luminance
    ``m`` and the candidates' ``views`` (full-resolution temporaries kept in ``workspace``)."""
    B = x.shape[0]
    light4 = xs[FEATURE_SCALE] + mean_p
    kept = kept_buffer(workspace, "luminance", (B, 1, *x.shape[-2:]), x)
    lum = torch.div(_luminance(x, kept), m, out=kept)  # relative to the mean before squaring: no overflow at 1e20
    lum4 = _luminance(light4) / m
    var = (_blocks(lum.square(), FEATURE_SCALE) - lum4.square()).clamp_min(0)
    g4 = gs[FEATURE_SCALE]
    edge = (_blocks(torch.square(gs[1], out=kept_buffer(workspace, "square", gs[1].shape, gs[1])).sum(1, keepdim=True),
                    FEATURE_SCALE)
            - g4.square().sum(1, keepdim=True)).clamp_min(0)
    if isinstance(spp, torch.Tensor):
        level = torch.log2(spp.to(x.dtype).reshape(-1, 1, 1, 1).expand(B, 1, 1, 1))
    else:
        level = torch.full((B, 1, 1, 1), math.log2(spp), dtype=x.dtype, device=x.device)
    base = torch.log1p(lum4.clamp_min(-0.5))  # (below -0.5 only where the light is below 0)
    feats = [torch.log1p(light4.clamp_min(0) / m), torch.log(var / (lum4.square() + 0.01) + 1e-4),
             g4, torch.log(edge + 1e-4), level.expand_as(lum4)]
    feats += [torch.log1p(_luminance(v + mean_p).clamp_min(0) / m) - base for v in views]
    return torch.cat(feats, 1)


def _colour_channel(net: PyramidNet, coeffs: dict[str, list[torch.Tensor]], xs: dict[int, torch.Tensor],
                    gs: dict[int, torch.Tensor], mean_p: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """The colour candidates' guide channel ``(B, 1, H, W)``, centred: the scaled log-luminance of
    the first candidate's full-resolution output (its luminance is the model of the channel-mean
    coefficients)."""
    s0 = min(net.candidates[0][0], FEATURE_SCALE)
    if s0 == 1:
        first = _luminance(coeffs["geometric@1"][0])
    else:
        c0 = _finer(coeffs[f"geometric@{s0}"][0].mean(2, keepdim=True), s0, MIX_SCALE, xs)
        first = backends.run(backends.UpsampleApplyOp(c0, gs[1]))
    lum_guide = net.colour_scale * torch.log((first + _luminance(mean_p)).clamp_min(0) / m + 0.01)
    return lum_guide - lum_guide.mean((2, 3), keepdim=True)


def pyramid_stats(x: torch.Tensor, guide: torch.Tensor) -> dict[str, torch.Tensor]:
    """The image statistics :func:`pyramid` centres and scales by: ``"mean"`` the light's mean
    ``(B, C, 1, 1)``, ``"guide_mean"`` the guide's ``(B, G, 1, 1)`` and ``"level"`` the mean
    luminance of ``|x|`` ``(B, 1, 1, 1)`` (at least float's smallest normal; light below 0 must
    not make it 0 or negative), of ``x (B, C, H, W)`` and ``guide (B, G, H, W)``. Each is a mean
    over the pixels, so the statistics of a whole image are the pixel-weighted means of its
    tiles' (how tiles get the untiled output: ``pyramid(..., stats=)``).

    Example:
        >>> st = pyramid_stats(torch.ones(2, 3, 4, 4), torch.zeros(2, 4, 4, 4))
        >>> st["mean"].shape, st["guide_mean"].shape, float(st["level"][0])
        (torch.Size([2, 3, 1, 1]), torch.Size([2, 4, 1, 1]), 1.0)
    """
    level = _luminance(x.abs().mean((2, 3), keepdim=True))
    return {"mean": x.mean((2, 3), keepdim=True), "guide_mean": guide.mean((2, 3), keepdim=True), "level": level}


def pyramid_inputs(
    x: torch.Tensor, guide: torch.Tensor, spp: float | torch.Tensor, net: PyramidNet, raw: torch.Tensor | None = None,
    workspace: dict | None = None, stats: dict[str, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, dict[str, list[torch.Tensor]], dict[str, torch.Tensor]]:
    """The first half of :func:`pyramid`: the network's features ``(B, F, ⌈H/4⌉, ⌈W/4⌉)``, the
    candidates' coefficients by group and mixing scale (keys of :func:`_groups`; a list of ``(B,
    n + 1, C, h, w)``, one per candidate, ``h, w`` the 1/2 or 1/4 resolution, over the guide's
    ``G`` channels for the geometric ones, the first ``min(G, 3)`` and the colour channel for the
    colour ones; at scale 1 the candidates' centred outputs ``(B, C, H, W)``) and what
    :func:`pyramid_mix` needs besides (the centred guide, its colour channel, the light's mean),
    all in the compute dtype. ``x (B, C, H, W) >= 0``, ``guide (B, G, H, W)``, ``spp`` a float
    or ``(B,)`` tensor; ``workspace`` and ``stats`` as :func:`pyramid`'s.

    Example:
        >>> net = PyramidNet()
        >>> f, c, rest = pyramid_inputs(torch.rand(1, 3, 16, 16), torch.rand(1, 4, 16, 16), 1.0, net)
        >>> f.shape, len(c["geometric@4"]), c["geometric@4"][0].shape
        (torch.Size([1, 19, 4, 4]), 4, torch.Size([1, 5, 3, 4, 4]))
    """
    B = x.shape[0]
    stats = pyramid_stats(x, guide) if stats is None else stats
    mean_p, mean_g = stats["mean"], stats["guide_mean"]
    top = max(net.top, FEATURE_SCALE)
    xs = _levels(torch.sub(x, mean_p, out=kept_buffer(workspace, "x", x.shape, x)), top)  # (out=None: a new tensor)
    gs = _levels(torch.sub(guide, mean_g, out=kept_buffer(workspace, "guide", guide.shape, guide)), top)
    m = stats["level"].clamp_min(torch.finfo(x.dtype).tiny)  # each image's mean light level
    coeffs, views = {}, []
    workspaces = {} if workspace is None else workspace  # one per scale: the fits of one size share scratch planes

    def fit(levels: dict[int, torch.Tensor], s: int, r: int, e: float) -> torch.Tensor:
        """One candidate's coefficients at its mixing scale (at scale 1 its centred output); its
        view at 1/4 appended to ``views``."""
        (n, h, w), C = levels[s].shape[1:], x.shape[1]
        eps = torch.full((B, n, 1, 1), e, dtype=x.dtype, device=x.device)
        zero = torch.zeros((B, n, 1, 1), dtype=x.dtype, device=x.device)
        into = kept_buffer(workspace, f"fit{len(views)}", (B, n + 1, C, h, w) if s > 1 else (B, C, h, w), x)
        c = backends.run(backends.GuidedOp(levels[s], xs[s], zero, torch.zeros_like(mean_p), r, eps,
                                           coefficients_only=s > 1, workspace=workspaces.setdefault(s, {}), out=into))
        if s == 1:
            views.append(_blocks(c, FEATURE_SCALE))
            return c
        # what the candidate makes of the light at 1/4 resolution (a feature)
        if s < FEATURE_SCALE:  # finer: applied at its scale, then averaged down
            views.append(backends.run(backends.AppliedMeansOp(c, levels[s], FEATURE_SCALE // s)))
            return c
        c = _finer(c, s, FEATURE_SCALE, xs)
        views.append(apply_coefficients(c, levels[FEATURE_SCALE]))
        return c

    groups = _groups(net)
    for key in ("geometric@1", "geometric@2", "geometric@4"):
        coeffs[key] = [fit(gs, *net.candidates[k]) for k in groups[key]]
    rest = {"guide": gs[1], "mean": mean_p}
    if net.colour:
        rest["colour"] = _colour_channel(net, coeffs, xs, gs, mean_p, m)
        keep = min(guide.shape[1], 3)
        lum_levels = _levels(rest["colour"], top)
        cs = {s: torch.cat([gs[s][:, :keep], lum_levels[s]], 1) for s in lum_levels
              if s > 1 or groups["colour@1"]}
        for key in ("colour@1", "colour@2", "colour@4"):
            coeffs[key] = [fit(cs, *net.candidates[k]) for k in groups[key]]
    coeffs = {k: v for k, v in coeffs.items() if v}
    order = [k for key in groups.values() for k in key]  # the views were made in group order
    views = [views[order.index(k)] for k in range(len(net.candidates))]
    feats = _features(x, xs, gs, mean_p, m, spp, views, workspace)
    if net.direct:  # the light the firefly clamp took away, at 1/4 and 1/16
        r4 = (torch.zeros_like(xs[FEATURE_SCALE]) if raw is None
              else _blocks(torch.sub(raw, x, out=kept_buffer(workspace, "removed", x.shape, x)).clamp_min_(0), FEATURE_SCALE))
        # at most the block's own (clamped) light: a rare huge sample adds at most that, spread
        lr, lx = _luminance(r4), _luminance((xs[FEATURE_SCALE] + mean_p).clamp_min(0))
        r4 = r4 * (lx / lr.clamp_min(torch.finfo(x.dtype).tiny)).clamp(max=1)
        r16 = _blocks(r4, 4)
        rest["removed4"] = r4
        r16up = _up(_up(r16, _blocks(r4).shape[-2:]), r4.shape[-2:])
        feats = torch.cat([feats, torch.log1p(_luminance(r4) / m), torch.log1p(_luminance(r16up) / m)], 1)
    return feats, coeffs, rest


def pyramid_mix(
    net: PyramidNet, head: torch.Tensor, coeffs: dict[str, list[torch.Tensor]], x: torch.Tensor,
    rest: dict[str, torch.Tensor], return_weights: bool = False, workspace: dict | None = None,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """The second half of :func:`pyramid`: ``head = net(features)`` at 1/4 resolution; the
    softmax of its candidate logits mixes the candidates' ``coeffs`` (:func:`pyramid_inputs`),
    those of scale >= 4 at 1/4, those of scale 2 at 1/2 with the weights upsampled; the mix is
    upsampled to full resolution and applied to the guide and its colour channel, and the
    residual of the light ``x (B, C, H, W)`` is given back band by band with the sigmoid of the
    gain logits (module docstring); ``workspace`` as :func:`pyramid`'s. Returns ``(B, C, H, W)`` and, with ``return_weights``, the
    weights ``(B, K + 4, ⌈H/4⌉, ⌈W/4⌉)`` at 1/4 resolution: the candidates', then the four gains.

    Example:
        >>> net = PyramidNet()
        >>> x, g = torch.rand(1, 3, 16, 16), torch.rand(1, 4, 16, 16)
        >>> f, c, rest = pyramid_inputs(x, g, 1.0, net)
        >>> pyramid_mix(net, net(f), c, x, rest).shape
        torch.Size([1, 3, 16, 16])
    """
    K = len(net.candidates)
    full = x.shape[-2:]
    half = ((full[0] + 1) // 2, (full[1] + 1) // 2)
    w = torch.softmax(head[:, :K], 1)
    groups = _groups(net)
    mixed = {}
    for group in ("geometric", "colour"):
        coarse, fine = f"{group}@{FEATURE_SCALE}", f"{group}@{MIX_SCALE}"
        out = _weighted(w[:, groups[coarse], None, None], coeffs[coarse]) if coarse in coeffs else 0
        if fine in coeffs:  # up(out) + Σ up(w_k) fine_k in one walk (out 0: no coarser candidate)
            out = torch.zeros_like(coeffs[fine][0][..., : w.shape[-2], : w.shape[-1]]) if isinstance(out, int) else out
            into = kept_buffer(workspace, f"mix_{group}", coeffs[fine][0].shape, x)
            out = backends.run(backends.MixHalfOp(out, w[:, groups[fine]], tuple(coeffs[fine]), into))
        elif coarse in coeffs:
            out = _up5(out, half)
        mixed[group] = out
    G, keep = rest["guide"].shape[1], min(rest["guide"].shape[1], 3)
    geo, col = mixed["geometric"], mixed["colour"]
    if isinstance(col, torch.Tensor):  # the colour model's normal slopes and offset join the geometric ones
        geo = torch.cat([geo[:, :keep] + col[:, :keep], geo[:, keep:G], geo[:, G:] + col[:, -1:]], 1)
        slope = torch.cat([col[:, keep : keep + 1], torch.zeros_like(col[:, -1:])], 1)
        model = backends.run(backends.UpsampleApplyOp(slope, rest["colour"]))
    else:
        model = 0
    applied = backends.run(backends.UpsampleApplyOp(geo, rest["guide"], kept_buffer(workspace, "applied", x.shape, x)))
    model = _add(applied if isinstance(model, int) else _add(applied, model), rest["mean"])
    outputs = [k for k in ("geometric@1", "colour@1") if k in coeffs]  # scale 1: outputs, mixed at full resolution
    ys = tuple(y for k in outputs for y in coeffs[k])
    if ys:  # mixed into the model with their weights brought to full resolution, the residual and its 2 x 2 means
        w_half = _up(w[:, [k for key in outputs for k in groups[key]]], half)
        into = kept_buffer(workspace, "residual", x.shape, x)
        model, res1, res2 = backends.run(backends.ModelResidualOp(model, ys, w_half, x, inplace=True, out=into))
    else:
        res1 = x - model
        res2 = _blocks(res1)
    gain = torch.sigmoid(head[:, K : K + len(BANDS)])  # at 1/4
    gains = {2: _up(gain[:, 1:2], half), 4: gain[:, 2:3], 8: _blocks(gain[:, 3:])}
    res = {1: res1} | {2 * s: lv for s, lv in _levels(res2, BANDS[-1] // 2).items()}  # res2's levels at their scales
    lift = None
    if net.direct:  # the correction at 1/4, in units of the image's mean luminance (module docstring)
        j = K + len(BANDS)
        lift = _luminance(rest["mean"]) * head[:, j : j + 3] + torch.sigmoid(head[:, j + 3 : j + 4]) * rest["removed4"]
        r16 = _blocks(rest["removed4"], 4)
        g16 = _blocks(torch.sigmoid(head[:, j + 4 : j + 5]), 4)
        lift = lift + _up(_up(g16 * r16, _blocks(lift).shape[-2:]), lift.shape[-2:])
    band = gains[8] * res[8]
    for s in BANDS[-2:0:-1]:
        size = res[s].shape[-2:]
        detail = res[s] - _up(res[2 * s], size)
        detail = detail.mul_(gains[s]) if reusable(detail, gains[s]) else gains[s] * detail
        band = _add(_up(band, size), detail)
        if s == FEATURE_SCALE and lift is not None:  # upsampled with the bands (the same bilinear steps)
            band = _add(band, lift)
    # the finest band: model + (up(band) + up(gain) (res1 - up(res2))) in one walk
    out = backends.run(backends.FineBandOp(model, res1, res2, band, _up(gain[:, :1], half)))
    return (out, torch.cat([w, gain], 1)) if return_weights else out


def pyramid(
    x: torch.Tensor, guide: torch.Tensor, *, spp: float | torch.Tensor = 1.0, net: PyramidNet | None = None,
    raw: torch.Tensor | None = None, return_weights: bool = False, workspace: dict | None = None,
    stats: dict[str, torch.Tensor] | None = None,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Filter ``x`` with the learned guided pyramid (module docstring).

    Args:
        x: ``(B, C, H, W)`` source, >= 0 (the Denoiser's demodulated, firefly-clamped light), any
            scale (the network's inputs are relative to each image's mean); values below 0 (an
            emission pass from other samples than the colour's can leave some) stay finite.
        guide: ``(B, G, H, W)``, ``1 <= G <= 4``, same dtype and device (e.g.
            :func:`~torchgi.filters.guide_from` with ``depth_scale="image"``).
        spp: samples per pixel the noise corresponds to, a float or ``(B,)`` tensor (>= 1).
        net: the network, on ``x``'s device; None = the shipped one there (:func:`default_net`).
        raw: ``(B, C, H, W)`` the light before its firefly clamp (``>= x`` where the clamp scaled
            ``x`` down), same dtype and device; a ``net`` with ``direct`` gives some of ``raw - x``
            back at 1/4 and 1/16 resolution. None: nothing was clamped.
        return_weights: also return the ``(B, K + 4, ⌈H/4⌉, ⌈W/4⌉)`` weights (the per-pixel
            choice: the candidates' in ``net.candidates`` order, then the gains of the
            residual's bands at scales 1, 2, 4 and its low-pass at 8, all at 1/4 resolution).
        workspace: None, or a dict in which the CPU path keeps the guided fits' scratch planes
            and the results of its steps at full and half resolution between calls (overwritten
            by the next call; the Denoiser's holds 597 MiB after a 1920x1080 call, which a new call
            would otherwise fault in page by page).
        stats: None (computed from ``x`` and ``guide``), or :func:`pyramid_stats` of the whole
            image this ``x`` is a tile of (float32, or float64 for float64 input): a tile whose
            origin is on multiples of :data:`ALIGN` px with :data:`REACH` px of the image around
            it is filtered as in the whole image up to float rounding (the Denoiser's
            ``max_memory_mb``). Not with a ``net`` that has colour candidates.

    Returns:
        ``(B, C, H, W)`` in the dtype and on the device of ``x`` (float16 is computed in float32),
        and the weights when asked.

    Example:
        >>> x, g = torch.rand(1, 3, 16, 16), torch.rand(1, 4, 16, 16)
        >>> out, w = pyramid(x, g, spp=1.0, net=PyramidNet(), return_weights=True)
        >>> out.shape, w.shape
        (torch.Size([1, 3, 16, 16]), torch.Size([1, 13, 4, 4]))
    """
    check_shape(x, "B C H W", "x")
    check_floating(x, "x")
    check_shape(guide, "B G H W", "guide", {"B": x.shape[0], "H": x.shape[2], "W": x.shape[3]})
    tensors = {"x": x, "guide": guide} if raw is None else {"x": x, "guide": guide, "raw": raw}
    if raw is not None:
        check_shape(raw, "B C H W", "raw", dict(zip("BCHW", x.shape, strict=True)))
    check_same_device(tensors)
    check_same_floating(tensors)
    if not 1 <= guide.shape[1] <= 4:
        raise ShapeError(f"guide: expected 1 to 4 channels, got {guide.shape[1]} (shape {tuple(guide.shape)})")
    if isinstance(spp, bool) or isinstance(spp, (int, float)) and not (math.isfinite(spp) and spp >= 1):
        raise RangeError(f"spp: expected a finite number >= 1, got {spp!r}")
    net = default_net(x.device) if net is None else net
    if next(net.parameters()).device != x.device:
        raise ValueError(f"net: on {next(net.parameters()).device}, x on {x.device} (move one of them)")
    if not is_recording():
        for name, t in tensors.items():
            check_finite(t, name)
    ct = compute_dtype(x.dtype)
    if stats is not None:
        _check_stats(stats, x, guide, ct, net)
    xs, gs = x.to(ct), guide.to(ct)
    feats, coeffs, rest = pyramid_inputs(xs, gs, spp, net, None if raw is None else raw.to(ct), workspace, stats)
    p = next(net.parameters())
    feats = feats.to(p.dtype)
    if not is_recording():  # oneDNN's convolutions run faster channels-last; the mix reads channels
        head = net(feats.contiguous(memory_format=torch.channels_last)).contiguous()
    else:
        head = net(feats)
    out, w = pyramid_mix(net, head.to(ct), coeffs, xs, rest, return_weights=True, workspace=workspace)
    out = out.to(x.dtype)
    return (out, w.to(x.dtype)) if return_weights else out


def _check_stats(stats: dict[str, torch.Tensor], x: torch.Tensor, guide: torch.Tensor, ct: torch.dtype,
                 net: PyramidNet) -> None:
    """``pyramid``'s ``stats``: :func:`pyramid_stats`'s keys, shapes and the compute dtype."""
    if net.colour:
        raise ValueError("stats: a net with colour candidates centres their channel by its own image mean; "
                         "it cannot take a whole image's statistics")
    B, C, G = x.shape[0], x.shape[1], guide.shape[1]
    if not isinstance(stats, dict) or set(stats) != {"mean", "guide_mean", "level"}:
        raise ValueError(f"stats: expected pyramid_stats()'s dict (mean, guide_mean, level), got {stats!r:.80}")
    for key, spec in (("mean", f"{B} {C} 1 1"), ("guide_mean", f"{B} {G} 1 1"), ("level", f"{B} 1 1 1")):
        check_shape(stats[key], spec, f"stats[{key!r}]")
        if stats[key].dtype != ct or stats[key].device != x.device:
            raise ValueError(f"stats[{key!r}]: expected {ct} on {x.device} (the compute dtype of x), "
                             f"got {stats[key].dtype} on {stats[key].device}")
        check_finite(stats[key], f"stats[{key!r}]")


class Pyramid(nn.Module):
    """Module form of :func:`pyramid`; the network is a submodule (moves with ``.to()``).

    Example:
        >>> Pyramid(PyramidNet())(torch.rand(1, 3, 8, 8), torch.rand(1, 4, 8, 8), spp=2.0).shape
        torch.Size([1, 3, 8, 8])
    """

    def __init__(self, net: PyramidNet | None = None) -> None:
        super().__init__()
        self.net = net if net is not None else PyramidNet.load(WEIGHTS)
        self._workspace: dict = {}

    def forward(self, x: torch.Tensor, guide: torch.Tensor, spp: float | torch.Tensor = 1.0,
                raw: torch.Tensor | None = None) -> torch.Tensor:
        return pyramid(x, guide, spp=spp, net=self.net, raw=raw, workspace=self._workspace)

    def release(self) -> None:
        """Free the CPU scratch buffers kept between calls."""
        self._workspace.clear()
