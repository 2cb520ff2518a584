"""The C back end's temporal ops: the accumulation (:class:`~torchgi.backends.base.AccumulateOp`),
the change test after it (:class:`~torchgi.backends.base.ChangeOp`) and the output history
(:class:`~torchgi.backends.base.HistoryOp`), each in one walk per image."""

from __future__ import annotations

import torch

from torchgi.backends.base import (
    AccumulateOp,
    ChangeOp,
    HistoryOp,
)
from torchgi.backends.c_kernels import build
from torchgi.backends.c_kernels.runtime import (
    _buffer,
    _ptr,
    _run,
)
from torchgi.settings import PIPELINE


def accumulate(desc: AccumulateOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AccumulateOp` in one walk per image.

    Example:
        >>> z = lambda c: torch.zeros(1, c, 2, 2)
        >>> op = AccumulateOp(torch.ones(1, 3, 2, 2), z(1) + 9, z(2), z(3), z(1) + 1, z(1) > 0, z(3), z(3), z(2),
        ...                   z(1), z(3), z(1), z(1), 0.2, 32, 0.9, 0.05)
        >>> build.library() is None or accumulate(op)[0, :, 0, 0].tolist()[6:9] == [1.0, 1.0, 1.0]
        True
    """
    lib = build.library()
    d = desc
    ts = [t.contiguous() for t in (d.x, d.bound, d.motion, d.normal, d.depth, d.surface, d.light, d.output, d.moments,
                                   d.length, d.prev_normal, d.prev_depth, d.prev_surface)]
    B, _, H, W = d.x.shape
    out = _buffer(d.workspace, "accumulate", (B, 13, H, W))
    for b in range(B):
        _run(lib.torchgi_accumulate, H, W, *(t[b].data_ptr() for t in ts), H, W, d.alpha, float(d.max_history),
             d.normal_tolerance, d.depth_tolerance, out[b].data_ptr(), 0)
    return out


def change(desc: ChangeOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.ChangeOp` in one walk per image.

    Example:
        >>> z = lambda c: torch.zeros(1, c, 2, 2)
        >>> step = torch.cat([z(3) + 2, z(3), z(2), z(1) + 4, z(1) + 3, z(1), z(1) + 4, z(1)], 1)
        >>> op = ChangeOp(z(3), z(1), step, z(1), None, None, z(3) + 0.5, z(1) == 0, z(3), (4, 16), 3.0, 4)
        >>> build.library() is None or change(op)[0, :, 0, 0].tolist() == [2, 2, 2, 0, 0, 4, 4, 0, 1, 1, 1]
        True
    """
    lib = build.library()
    d = desc
    ts = [None if t is None else t.contiguous() for t in (d.x, d.bound, d.step, d.spatial_var, d.near, d.wide, d.albedo,
                                                           d.surface, d.emission)]
    B, _, H, W = d.x.shape
    out = _buffer(d.workspace, "change", (B, 11, H, W))
    for b in range(B):
        _run(lib.torchgi_change, H, W, *(_ptr(None if t is None else t[b]) for t in ts), H, W, d.radii[0], d.radii[1],
             d.threshold, d.follow, float(d.variance_history), PIPELINE.albedo_floor, PIPELINE.albedo_ceiling, out[b].data_ptr(), 0)
    return out


def history(desc: HistoryOp) -> tuple[torch.Tensor, torch.Tensor]:
    """:class:`~torchgi.backends.base.HistoryOp` in one walk per image.

    Example:
        >>> z = lambda c: torch.zeros(1, c, 1, 1)
        >>> op = HistoryOp(z(3) + 1, z(3), z(3) + 0.5, z(1) == 0, z(1) + 0.25, z(3) + 3, z(1) + 2, z(1) + 1, 4.0, 0.1)
        >>> build.library() is None or [v[0, :, 0, 0].tolist() for v in history(op)] == [[2.5] * 3, [1.25] * 3]
        True
    """
    lib = build.library()
    d = desc
    ts = [t.contiguous() for t in (d.out, d.emission, d.albedo, d.surface, d.spread, d.hist_out, d.kept, d.hist_length)]
    B, _, H, W = d.out.shape
    lit, image = _buffer(d.workspace, "history", (B, 3, H, W)), torch.empty(B, 3, H, W, dtype=torch.float32)
    for b in range(B):
        _run(lib.torchgi_history, H, W, *(t[b].data_ptr() for t in ts), H, W, d.clamp, d.output_alpha,
             PIPELINE.albedo_floor, PIPELINE.albedo_ceiling, lit[b].data_ptr(), image[b].data_ptr(), 0)
    return lit, image
