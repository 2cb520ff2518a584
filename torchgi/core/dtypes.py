"""Which dtype a filter computes in, and the rounding level its guided solve regularises to."""

from __future__ import annotations

import torch

__all__ = ["compute_dtype", "variance_rounding"]


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """float16/bfloat16 are accumulated in float32; float32/float64 as they are.

    Example:
        >>> compute_dtype(torch.float16), compute_dtype(torch.float64)
        (torch.float32, torch.float64)
    """
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


def variance_rounding(dtype: torch.dtype) -> float:
    """``16 · finfo(dtype).eps``: relative to ``E[I²]``, the rounding error a variance
    ``E[I²] - E[I]²`` computed in ``dtype`` may carry (a few eps; 16 leaves a margin). The guided
    filter raises ε to this level per pixel so flat guides and ``eps = 0`` stay exact.

    Example:
        >>> variance_rounding(torch.float32) == 16 * torch.finfo(torch.float32).eps
        True
    """
    return 16 * torch.finfo(dtype).eps
