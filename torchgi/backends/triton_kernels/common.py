"""What the Triton kernels share: Triton itself (None without it), whether its interpreter runs
them on CPU tensors, grid sizes, the tap weights and the firefly scaling."""

from __future__ import annotations

import functools
import os

import torch

from torchgi.core.taps import kernel_5x5

try:  # shipped with CUDA builds of torch
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - CPU-only installs
    triton = tl = None

_INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"


@functools.cache
def _taps(device: torch.device) -> torch.Tensor:
    """The 25 tap weights, float32, on ``device``."""
    return torch.tensor([h for _, _, h in kernel_5x5()], dtype=torch.float32, device=device)


def _cdiv(a: int, b: int) -> int:
    """``ceil(a / b)`` for grid sizes (``triton.cdiv`` goes through Triton's slower JIT wrapper)."""
    return -(-a // b)


if triton is not None:

    @triton.jit
    def _scaled_to(x0, x1, x2, bound):
        # light.scaled_to for three channel blocks: scaled down, hue kept, where their maximum
        # exceeds bound
        peak = tl.maximum(tl.maximum(x0, x1), x2)
        over = peak > bound
        f = bound / tl.where(over, peak, 1.0)
        return tl.where(over, x0 * f, x0), tl.where(over, x1 * f, x1), tl.where(over, x2 * f, x2)
