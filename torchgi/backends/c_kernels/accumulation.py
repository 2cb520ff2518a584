"""The C back end's temporal accumulation (:class:`~torchgi.backends.base.AccumulateOp`)."""

from __future__ import annotations

import torch

from torchgi.backends.base import (
    AccumulateOp,
)
from torchgi.backends.c_kernels import build
from torchgi.backends.c_kernels.runtime import (
    _run,
)


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
    out = torch.empty(B, 13, H, W, dtype=torch.float32)
    for b in range(B):
        _run(lib.torchgi_accumulate, H, W, *(t[b].data_ptr() for t in ts), H, W, d.alpha, float(d.max_history),
             d.normal_tolerance, d.depth_tolerance, out[b].data_ptr(), 0)
    return out


