"""The C back end's sampling ops: the importance map and the sample allocation."""

from __future__ import annotations

import torch

from torchgi.backends.base import (
    AllocateOp,
    ImportanceOp,
)
from torchgi.backends.c_kernels import build
from torchgi.backends.c_kernels.runtime import (
    _ptr,
    _run,
    _threads,
)


def _importance(normal: torch.Tensor, position: torch.Tensor, sigma_normal: float, sigma_position: float,
               hit: torch.Tensor | None, window: int) -> torch.Tensor:
    """Sampling importance ``(B,1,H,W)`` (``torch_code.sampling._core``) from float32 ``normal``
    and ``position`` ``(B,3,H,W)`` with the weights ``exp(-|Δn|² / σ_n - |Δx|² / σ_x)``, the
    bool ``hit (B,1,H,W)`` or None, over a ``window x window`` neighbourhood (offsets
    ``-(w//2) .. (w-1)//2``). Reads the inputs as they are: nothing image-sized is allocated
    but the output."""
    lib = build.library()
    B, _, H, W = normal.shape
    normal, position = normal.contiguous(), position.contiguous()
    hit = None if hit is None else hit.to(torch.float32).contiguous()
    out = torch.empty(B, 1, H, W, dtype=torch.float32)
    for b in range(B):
        _run(lib.torchgi_importance, H, W, normal[b].data_ptr(), position[b].data_ptr(), 1.0 / sigma_normal,
             1.0 / sigma_position, _ptr(None if hit is None else hit[b]), H, W, -(window // 2), (window - 1) // 2,
             out[b].data_ptr(), 0)
    return out


def _allocate(q: torch.Tensor, eligible: torch.Tensor | None, n_eligible: list[int], spare: list[int],
             min_samples: int) -> torch.Tensor:
    """Integer samples per pixel ``(B, N)`` int64 (``torch_code.allocate``) from the importance
    ``q (B, N)`` (float32 or float64, >= 0), the bool ``eligible (B, N)`` or None, each image's
    number of eligible pixels and spare samples (budget minus the minimum), and ``min_samples``."""
    lib = build.library()
    B, N = q.shape
    if N >= 2**31 or q.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"q: expected float32/float64 with at most 2^31 - 1 pixels per image, got {q.dtype}, {N}")
    q = q.contiguous()
    eligible = None if eligible is None else eligible.to(torch.bool).contiguous()
    threads = _threads(N, N)
    counts = torch.empty(B, N, dtype=torch.int64)
    bucket, hist = torch.empty(N, dtype=torch.int16), torch.empty(threads * 65536, dtype=torch.int32)
    for b in range(B):
        if lib.torchgi_allocate(q[b].data_ptr(), int(q.dtype == torch.float64),
                                _ptr(None if eligible is None else eligible[b]), N, n_eligible[b], spare[b], min_samples,
                                counts[b].data_ptr(), bucket.data_ptr(), hist.data_ptr(), threads):
            raise MemoryError("the C allocation kernel: out of memory")
    return counts


def importance(desc: ImportanceOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.ImportanceOp` straight from the normal / position planes.

    Example:
        >>> n = torch.zeros(1, 3, 4, 4); n[:, 2] = 1   # flat: nothing to sample
        >>> build.library() is None or float(importance(ImportanceOp(n, torch.zeros(1, 3, 4, 4), 0.1, 0.1, None, 3)).max()) == 0
        True
    """
    return _importance(desc.normal, desc.position, desc.sigma_normal, desc.sigma_position, desc.hit, desc.window)


def allocate(desc: AllocateOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AllocateOp`: the same double arithmetic, the remainders
    ranked by 2^16 buckets, then a sort of the bucket holding the cut.

    Example:
        >>> q = torch.tensor([[0.0, 1.0, 3.0]])
        >>> build.library() is None or allocate(AllocateOp(q, None, torch.tensor([3]), 7, 1)).tolist() == [[1, 2, 4]]
        True
    """
    n = desc.n_eligible
    return _allocate(desc.q, desc.eligible, n.tolist(), (desc.budget - desc.min_samples * n).tolist(),
                     desc.min_samples)


