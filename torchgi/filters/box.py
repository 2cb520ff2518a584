"""Box filter (mean over a ``(2r+1)²`` window) by prefix sums: cost independent of ``r``.

Borders are count-normalised: the window shrinks at the image edge, so the output is the
mean of the pixels that exist. Any ``r >= 0`` works, including ``r`` larger than the image.

Four interchangeable implementations compute the same thing:

* ``_box_cumsum`` — separable ``torch.cumsum`` + ``index_select``: differentiable, traceable,
  exported to ONNX (``CumSum``/``Gather``), used whenever autograd or tracing is involved,
  for float64 and where no kernel applies.
* the compiled CPU kernel of :mod:`torchgi.filters.native` (box sums sliding down the rows in
  double, prefix sums along them) for float32 CPU calls without autograd or tracing;
* the Triton kernels of :mod:`torchgi.filters.gpu` (the same sums in double) for such CUDA calls;
* :class:`PlaneBoxer` — the CPU fast path where that kernel is unavailable (no C compiler):
  blocked prefix sums (a 16x16 triangular matmul per block plus a carry), differences of
  shifted views, one image plane at a time so the intermediates stay in the last-level cache,
  all into reused buffers (no per-op allocation).

Precision: sums run along one axis at a time over mean-free data where the caller
centres it (the guided filter does), so float32 keeps ~1e-6 relative accuracy at 4K.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from torchgi.core.check import check_finite, check_floating, check_int, check_shape, is_tracing
from torchgi.filters import gpu, native

__all__ = ["Box", "PlaneBoxer", "box"]

# Block widths of the blocked prefix sums, prefix matmul + carry + carry add per 1024x768
# plane on 2 cores: along W 16 wide (8 wide: 0.83 ms for the matmul alone); along H 16 high
# 0.36 ms in all (8 high 0.47 ms: its 95x95 carry matmul costs more than the prefix saves).
_BLOCK_W, _BLOCK_H = 16, 16


def compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """float16/bfloat16 are accumulated in float32; float32/float64 as they are."""
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


def use_fast_path(*tensors: torch.Tensor) -> bool:
    """The in-place CPU path applies to eager CPU code without autograd or tracing."""
    if is_tracing():
        return False
    if any(t.device.type != "cpu" for t in tensors):
        return False
    return not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors))


def _counts(n: int | torch.Tensor, r: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    j = torch.arange(n, device=device)
    hi = torch.clamp(j + (r + 1), max=n)
    lo = torch.clamp(j - r, min=0)
    return hi, lo


def _box_cumsum(x: torch.Tensor, r: int) -> torch.Tensor:
    """Separable count-normalised box mean of ``(..., H, W)`` by cumsum and gathers."""
    H, W = x.shape[-2], x.shape[-1]
    s = F.pad(torch.cumsum(x, -1), (1, 0))
    hi, lo = _counts(W, r, x.device)
    x = (s.index_select(-1, hi) - s.index_select(-1, lo)) / (hi - lo).to(x.dtype)
    s = F.pad(torch.cumsum(x, -2), (0, 0, 1, 0))
    hi, lo = _counts(H, r, x.device)
    return (s.index_select(-2, hi) - s.index_select(-2, lo)) / (hi - lo).to(x.dtype)[:, None]


def _segments(n: int, r: int) -> list[tuple[int, int]]:
    """Split ``[0, n)`` where ``min(j+r, n-1)`` or ``j-r-1 >= 0`` change form."""
    cuts = sorted({0, n, min(max(n - r, 0), n), min(r + 1, n)})
    return [(a, b) for a, b in zip(cuts, cuts[1:]) if b > a]


# Planes box-filtered together (PlaneBoxer._stack): about 1 MB of float32 per
# operand, so small images pay the per-op overhead once per stack, not once per plane, and
# large ones still go one cache-resident plane at a time.
_STACK_ELEMENTS = 1 << 18


class PlaneBoxer:
    """Box-filters ``(H, W)`` planes (or ``(P, H, W)`` stacks of them) on the CPU into
    caller-given outputs, reusing buffers.

    Writes box *means* (count-normalised). Not differentiable; the planes being read and
    the output may be the same tensor.

    Example:
        >>> boxer = PlaneBoxer(4, 5, radius=1, dtype=torch.float64)
        >>> x = torch.rand(4, 5, dtype=torch.float64)
        >>> torch.allclose(boxer(x, torch.empty_like(x)), box(x[None, None], 1)[0, 0])
        True
    """

    def __init__(self, H: int, W: int, radius: int, dtype: torch.dtype = torch.float32) -> None:
        self.H, self.W, self.r = H, W, radius
        self.stack = max(1, _STACK_ELEMENTS // max(H * W, 1))  # planes boxed together
        self._prefix_buf = torch.empty(self.stack, H, W, dtype=dtype)  # prefix sums along W, then H
        self._rows_buf = torch.empty(self.stack, H, W, dtype=dtype)  # box sums along W
        self._upper = torch.triu(torch.ones(_BLOCK_W, _BLOCK_W, dtype=dtype))
        self._lower = torch.tril(torch.ones(_BLOCK_H, _BLOCK_H, dtype=dtype))
        # running totals of the block sums along H as a triangular matmul (a cumsum over rows
        # is slower there); along W a cumsum of the strided totals is faster (0.03 vs 0.09 ms)
        nh = max(H // _BLOCK_H - 1, 1)
        self._carry_h = torch.tril(torch.ones(nh, nh, dtype=dtype))
        hh, lh = _counts(H, radius, torch.device("cpu"))
        hw, lw = _counts(W, radius, torch.device("cpu"))
        inv_h = 1.0 / (hh - lh).to(torch.float64)
        inv_w = 1.0 / (hw - lw).to(torch.float64)
        self.inv_count = torch.outer(inv_h, inv_w).to(dtype)
        self._seg_w, self._seg_h = _segments(W, radius), _segments(H, radius)

    def _prefix(self, x: torch.Tensor, s: torch.Tensor, dim: int) -> None:
        """Inclusive prefix sums of ``x (P, H, W)`` along ``dim`` (-1: W, -2: H) into ``s``:
        blocks by one triangular matmul, then each block adds the running total of the blocks
        before it."""
        P, H, W = x.shape
        b = _BLOCK_W if dim == -1 else _BLOCK_H
        n = x.shape[dim]
        nb = n // b
        m = nb * b
        if nb:
            if dim == -1:
                blocks = x[..., :m].reshape(P, H, nb, b)
                if m == W:
                    torch.matmul(blocks, self._upper, out=s.view(P, H, nb, b))
                else:
                    s[..., :m].copy_(torch.matmul(blocks, self._upper).view(P, H, m))
                if nb > 1:
                    carry = s[..., b - 1 : m - b : b].cumsum(-1)
                    s[..., b:m].unflatten(-1, (nb - 1, b)).add_(carry[..., None])
            else:
                if m == H:
                    torch.matmul(self._lower, x.view(P, nb, b, W), out=s.view(P, nb, b, W))
                else:
                    s[:, :m].copy_(torch.matmul(self._lower, x[:, :m].unflatten(1, (nb, b))).view(P, m, W))
                if nb > 1:
                    carry = torch.matmul(self._carry_h, s[:, b - 1 : m - b : b])
                    s[:, b:m].unflatten(1, (nb - 1, b)).add_(carry[:, :, None, :])
        for j in range(m, n):  # fewer than b leftovers
            if j == 0:
                s.select(dim, 0).copy_(x.select(dim, 0))
            else:
                torch.add(s.select(dim, j - 1), x.select(dim, j), out=s.select(dim, j))

    def _difference(self, s: torch.Tensor, out: torch.Tensor, dim: int, segments: list[tuple[int, int]]) -> None:
        """``out[j] = s[min(j+r, n-1)] - (s[j-r-1] if j > r else 0)`` along ``dim``, by views."""
        n, r = out.shape[dim], self.r
        for a, e in segments:
            hi = s.narrow(dim, n - 1, 1) if a >= n - r else s.narrow(dim, a + r, e - a)
            dst = out.narrow(dim, a, e - a)
            if e <= r + 1:
                dst.copy_(hi.expand_as(dst))
            else:
                torch.sub(hi, s.narrow(dim, a - r - 1, e - a), out=dst)

    def _stack(self, x: torch.Tensor, out: torch.Tensor) -> None:
        """Box means of at most ``self.stack`` planes ``x (P, H, W)`` into ``out``."""
        P = x.shape[0]
        prefix, rows = self._prefix_buf[:P], self._rows_buf[:P]
        self._prefix(x, prefix, -1)
        self._difference(prefix, rows, -1, self._seg_w)
        self._prefix(rows, prefix, -2)
        self._difference(prefix, out, -2, self._seg_h)
        out.mul_(self.inv_count)

    def __call__(self, x: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """Box means of ``x`` - one plane ``(H, W)`` or planes ``(P, H, W)`` - into ``out`` of
        the same shape (may be ``x`` itself); stacks of ``self.stack`` planes at a time."""
        if x.dim() == 2:
            self._stack(x[None], out[None])
            return out
        for a in range(0, x.shape[0], self.stack):
            self._stack(x[a : a + self.stack], out[a : a + self.stack])
        return out


def box(x: torch.Tensor, radius: int) -> torch.Tensor:
    """Mean over the ``(2r+1) x (2r+1)`` window around each pixel, count-normalised at borders.

    Args:
        x: ``(B, C, H, W)`` floating tensor, finite.
        radius: window radius ``r >= 0`` in pixels; any size (``r >= H`` averages whole columns).

    Returns:
        ``(B, C, H, W)``, same dtype and device as ``x`` (float16/bfloat16 are summed in float32).
        Cost does not depend on ``radius``.

    Example:
        >>> box(torch.arange(3.0).view(1, 1, 1, 3), 1)
        tensor([[[[0.5000, 1.0000, 1.5000]]]])
    """
    check_shape(x, "B C H W", "x")
    check_floating(x, "x")
    check_finite(x, "x")
    check_int(radius, "radius")
    ct = compute_dtype(x.dtype)
    xc = x.to(ct)
    B, C, H, W = x.shape
    if x.numel() and native.applies(xc):
        return native.box(xc, radius).to(x.dtype)
    if x.numel() and gpu.applies(xc):
        return gpu.box(xc, radius).to(x.dtype)
    if not use_fast_path(x) or x.numel() == 0:
        return _box_cumsum(xc, radius).to(x.dtype)
    boxer = PlaneBoxer(H, W, radius, ct)
    out = torch.empty(B, C, H, W, dtype=ct)
    boxer(xc.reshape(B * C, H, W), out.view(B * C, H, W))
    return out.to(x.dtype)


class Box(nn.Module):
    """Module form of :func:`box`.

    Example:
        >>> Box(2)(torch.ones(1, 1, 4, 4)).sum().item()
        16.0
    """

    def __init__(self, radius: int) -> None:
        super().__init__()
        self.radius = radius

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return box(x, self.radius)

    def extra_repr(self) -> str:
        return f"radius={self.radius}"
