"""The torch code of the temporal accumulation (:class:`~torchgi.backends.base.AccumulateOp`)."""

from __future__ import annotations

import torch

from torchgi.backends.base import (
    LUMA,
    AccumulateOp,
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


