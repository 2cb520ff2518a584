"""The torch code of the sampling ops: the importance map over the window's taps at step 1,
the allocation by float64 shares, floors and the largest remainders (Hamilton's method) by
``kthvalue``."""

from __future__ import annotations

import functools

import torch

from torchgi.backends.base import (
    AllocateOp,
    ImportanceOp,
)
from torchgi.core.taps import Padded


def _core(f: torch.Tensor, valid: torch.Tensor, window: int) -> torch.Tensor:
    """``1 - mean over the window of exp(-|f_p - f_q|²)`` over valid taps, 0 off ``valid``."""
    lo, hi = -(window // 2), (window - 1) // 2
    pad = max(-lo, hi)
    pf, pv = Padded(f, pad), Padded(valid, pad)
    total = torch.zeros_like(valid)
    count = torch.zeros_like(valid)
    for oy in range(lo, hi + 1):
        for ox in range(lo, hi + 1):
            v = pv.at(oy, ox)
            total = total + v * torch.exp(-(f - pf.at(oy, ox)).square().sum(1, keepdim=True))
            count = count + v
    return (1 - total / count.clamp_min(1)).clamp(0, 1) * valid


@functools.cache
def _compiled_core():
    """``torch.compile(_core, dynamic=False)`` built on first use: one specialised loop over pixels per
    (size, window); static shapes ran faster than ``dynamic=True`` (docs/calibration.md)."""
    return torch.compile(_core, dynamic=False)



def importance(desc: ImportanceOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.ImportanceOp` in torch: one feature vector per pixel,
    ``G_n · G_x = exp(-|f_p - f_q|²)``.

    Example:
        >>> n = torch.zeros(1, 3, 4, 4); n[:, 2] = 1   # flat: nothing to sample
        >>> float(importance(ImportanceOp(n, torch.zeros(1, 3, 4, 4), 0.1, 0.1, None, 3)).max())
        0.0
    """
    n, x = desc.normal, desc.position
    x = x - x.mean(dim=(2, 3), keepdim=True)
    f = torch.cat([n / desc.sigma_normal**0.5, x / desc.sigma_position**0.5], 1)
    valid = torch.ones_like(n[:, :1]) if desc.hit is None else desc.hit.to(n.dtype)
    core = _compiled_core() if desc.fused else _core
    return core(f, valid, desc.window)


def allocate(desc: AllocateOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AllocateOp` in torch (float64 shares, ``kthvalue``).

    Example:
        >>> q = torch.tensor([[0.0, 1.0, 3.0]])
        >>> allocate(AllocateOp(q, None, torch.tensor([3]), 7, 1)).tolist()
        [[1, 2, 4]]
    """
    q, eligible, n_eligible, min_samples = desc.q, desc.eligible, desc.n_eligible, desc.min_samples
    if eligible is None:
        eligible = torch.ones_like(q, dtype=torch.bool)
    q = q.to(torch.float64)
    q = torch.where(eligible, q, torch.zeros_like(q))
    spare = (desc.budget - min_samples * n_eligible).to(torch.float64)  # (B,)
    Q = q.sum(1)
    uniform = eligible.to(torch.float64) / n_eligible.clamp_min(1)[:, None]
    share = torch.where((Q > 0)[:, None], q / torch.where(Q > 0, Q, 1.0)[:, None], uniform)
    exact = share * spare[:, None]
    counts = exact.floor()
    left = (spare - counts.sum(1)).round().to(torch.int64)  # < number of eligible pixels
    frac = torch.where(eligible, exact - counts, torch.full_like(exact, -1.0))
    counts = counts.to(torch.int64)
    for b in range(q.shape[0]):  # the `left` largest remainders, ties to the lowest pixel index
        k = int(left[b])
        if k <= 0:
            continue
        threshold = -torch.kthvalue(-frac[b], k).values  # k-th largest remainder (O(N) selection)
        above = frac[b] > threshold
        tied = frac[b] == threshold
        take = above | (tied & (tied.cumsum(0) <= k - int(above.sum())))
        counts[b] += take.to(torch.int64)
    return torch.where(eligible, counts + min_samples, torch.zeros_like(counts))


