"""The torch code of the temporal ops: the accumulation (:class:`~torchgi.backends.base.AccumulateOp`),
the change test after it (:class:`~torchgi.backends.base.ChangeOp`) and the output history
(:class:`~torchgi.backends.base.HistoryOp`)."""

from __future__ import annotations

import torch

from torchgi import light
from torchgi.backends.base import (
    LUMA,
    AccumulateOp,
    ChangeOp,
    HistoryOp,
)


def accumulate(desc: AccumulateOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AccumulateOp` by tensor ops: four bilinear taps of the
    history gathered at ``pixel + motion``, each kept where it passes the consistency tests.

    Example:
        >>> z = lambda c: torch.zeros(1, c, 2, 2)
        >>> out = accumulate(AccumulateOp(torch.ones(1, 3, 2, 2), z(1) + 9, z(2), z(3), z(1) + 1, z(1) > 0, z(3),
        ...                               z(3), z(2), z(1), z(3), z(1), z(1), 0.2, 32, 0.9, 0.05))
        >>> [round(v, 4) for v in out[0, :, 0, 0].tolist()]   # no history: the frame itself, length 1
        [1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0]
    """
    d = desc
    normal, depth, surface = d.normal, d.depth, d.surface
    B, _, H, W = normal.shape
    dt, dev = normal.dtype, normal.device
    ys = torch.arange(H, dtype=dt, device=dev).view(1, H, 1)
    xs = torch.arange(W, dtype=dt, device=dev).view(1, 1, W)
    px, py = xs + d.motion[:, 0], ys + d.motion[:, 1]  # (B, H, W): pixel-centre coordinates in the previous frame
    x0, y0 = torch.floor(px), torch.floor(py)
    fx, fy = px - x0, py - y0
    values = torch.cat([d.light, d.output, d.moments, d.length], 1).flatten(2)  # (B, 9, HW)
    tests = torch.cat([d.prev_normal, d.prev_depth, d.prev_surface], 1).flatten(2)  # (B, 5, HW)
    acc = torch.zeros(B, 9, H, W, dtype=dt, device=dev)
    total = torch.zeros(B, 1, H, W, dtype=dt, device=dev)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        tx, ty = x0 + dx, y0 + dy
        w = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
        inside = (tx >= 0) & (tx <= W - 1) & (ty >= 0) & (ty <= H - 1)
        index = (ty.clamp(0, H - 1) * W + tx.clamp(0, W - 1)).to(torch.int64).flatten(1)  # (B, HW)
        t = tests.gather(2, index[:, None].expand(-1, 5, -1)).view(B, 5, H, W)
        same_kind = (t[:, 4:5] > 0.5) == surface
        close = ((t[:, :3] * normal).sum(1, keepdim=True) >= d.normal_tolerance) & (
            (t[:, 3:4] - depth).abs() <= d.depth_tolerance * depth.abs())
        w = torch.where(inside[:, None] & same_kind & (close | ~surface), w[:, None], 0.0)
        acc = acc + w * values.gather(2, index[:, None].expand(-1, 9, -1)).view(B, 9, H, W)
        total = total + w
    found = total > 1e-3
    hist = torch.where(found, acc / torch.where(found, total, 1.0), 0.0)
    hist_length = torch.where(found, torch.round(hist[:, 8:9]), 0.0)
    length = torch.where(hist_length > 0, (hist_length + 1).clamp_max(d.max_history), 1.0)
    a = torch.maximum(1.0 / length, torch.full((), d.alpha, dtype=dt, device=dev))
    peak = d.x.amax(1, keepdim=True)
    over = peak > d.bound
    x = torch.where(over, d.x * (d.bound / torch.where(over, peak, 1.0)), d.x)
    light = hist[:, :3] + a * (x - hist[:, :3])
    lum = (x * torch.tensor(LUMA, dtype=dt, device=dev).view(1, 3, 1, 1)).sum(1, keepdim=True)
    moments = hist[:, 6:8] + a * (torch.cat([lum, lum * lum], 1) - hist[:, 6:8])
    var = (moments[:, 1:2] - moments[:, :1].square()).clamp_min(0)
    # frames averaged: 1/length while the weights are equal, (2 - α)/α once the average is exponential
    frames = torch.minimum(length, (2 - a) / a)
    return torch.cat([light, hist[:, 3:6], moments, length, hist_length, var, frames, lum], 1)




def _extent(n: int, r: int, like: torch.Tensor) -> torch.Tensor:
    """``(n,)`` the number of pixels a window of radius ``r`` covers along an axis of ``n`` (clipped at the edges)."""
    i = torch.arange(n, device=like.device)
    return ((i + r).clamp(max=n - 1) - (i - r).clamp(min=0) + 1).to(like.dtype)


def change(desc: ChangeOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.ChangeOp` by tensor ops: per window radius, the change ``d`` of
    the mean luminance (this frame's against the accumulated light's) beyond ``threshold`` sigmas
    of the window mean's noise (``sqrt(box(spatial_var) / pixels in the window)``) drops the
    history, fully one sigma further, linearly between; the larger drop of the two radii counts.
    Before the drop, the history's light and moments are scaled by ``1 + g d / before`` per radius
    (``g = d² / (d² + (follow sigma)²)``, ``before`` the accumulated light's window mean; at most
    4x, 1 where ``before`` is 0): its window means follow a change too small to drop it.

    Example:
        >>> z = lambda c: torch.zeros(1, c, 2, 2)
        >>> step = torch.cat([z(3) + 2, z(3), z(2), z(1) + 4, z(1) + 3, z(1), z(1) + 4, z(1)], 1)
        >>> out = change(ChangeOp(z(3), z(1), step, z(1), None, None, z(3) + 0.5, z(1) == 0, z(3), (4, 16), 3.0, 4))
        >>> out[0, :, 0, 0].tolist()   # no change test: the step's light, remodulated by 0.5
        [2.0, 2.0, 2.0, 0.0, 0.0, 4.0, 4.0, 0.0, 1.0, 1.0, 1.0]
    """
    d = desc
    acc, _, moments, length, hist_length, temporal_var, frames, lum = d.step.split([3, 3, 2, 1, 1, 1, 1, 1], 1)
    if d.near is not None:
        H, W = d.x.shape[-2:]
        drop, scale = torch.zeros_like(lum), torch.ones_like(lum)
        for boxed, r in ((d.near, d.radii[0]), (d.wide, d.radii[1])):
            now, before, var = boxed.split(1, 1)
            # over the window's pixels; the box's sums can cancel below 0
            sigma2 = var.clamp_min(0) / (_extent(H, r, d.x)[:, None] * _extent(W, r, d.x))
            sigma, change = torch.sqrt(sigma2), now - before
            beyond = (change.abs() - d.threshold * sigma) / sigma.clamp_min(torch.finfo(d.x.dtype).tiny)
            drop = torch.maximum(drop, beyond.clamp(0, 1))  # without noise (sigma 0) any change drops
            if d.follow > 0:
                gain = change.square() / (change.square() + d.follow ** 2 * sigma2).clamp_min(torch.finfo(d.x.dtype).tiny)
                scale = scale * torch.where(before > 0, 1 + gain * change / torch.where(before > 0, before, 1.0),
                                            1.0).clamp(0, 4)
        old = hist_length > 0
        drop, scale = drop * old, torch.where(old, scale, 1.0)
        acc, moments = acc * scale, moments * torch.cat([scale, scale * scale], 1)
        # (1 - drop) h + drop x: this frame's values exactly at a full drop (h + drop (x - h) cancels)
        keep = 1 - drop
        acc = keep * acc + drop * light.scaled_to(d.x, d.x.amax(1, keepdim=True), d.bound)
        moments = keep * moments + drop * torch.cat([lum, lum * lum], 1)
        length, frames = keep * length + drop, keep * frames + drop
        temporal_var = (moments[:, 1:2] - moments[:, :1].square()).clamp_min(0)
    var = torch.where(length >= d.variance_history, temporal_var, d.spatial_var)
    color = acc * light.demodulator(d.albedo, d.surface) + d.emission
    return torch.cat([acc, moments, length, frames, var / frames, color], 1)


def history(desc: HistoryOp) -> tuple[torch.Tensor, torch.Tensor]:
    """:class:`~torchgi.backends.base.HistoryOp` by tensor ops.

    Example:
        >>> z = lambda c: torch.zeros(1, c, 1, 1)
        >>> out = history(HistoryOp(z(3) + 1, z(3), z(3) + 0.5, z(1) == 0, z(1) + 0.25, z(3) + 3, z(1) + 2, z(1) + 1,
        ...                         4.0, 0.1))
        >>> [v[0, :, 0, 0].tolist() for v in out]   # lit 2, history 3 clamped to 2 + sqrt(4 x 0.25) = 3, averaged
        [[2.5, 2.5, 2.5], [1.25, 1.25, 1.25]]
    """
    d = desc
    demod = light.demodulator(d.albedo, d.surface)
    lit = (d.out - d.emission) / demod
    sigma = torch.sqrt(d.clamp * d.spread.clamp_min(0))  # the box's sums can cancel below 0
    h = torch.maximum(torch.minimum(d.hist_out, lit + sigma), lit - sigma)
    beta = torch.maximum(1.0 / d.kept, torch.full((), d.output_alpha, dtype=lit.dtype, device=lit.device))
    lit = torch.where(d.hist_length > 0, h + beta * (lit - h), lit)
    return lit, lit * demod + d.emission
