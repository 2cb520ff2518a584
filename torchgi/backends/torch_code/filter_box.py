"""The torch code of the box filter: two separable ``avg_pool2d`` passes without padding in the
counts (:func:`box_pool`: each window summed directly, so no long float32 prefix sums; under
autograd and tracing, exported to ONNX as ``AveragePool``); eagerly on the CPU,
:class:`PlaneBoxer` (blocked prefix sums - a 16x16 triangular matmul per block plus a carry -
into reused buffers, a cache-sized stack of planes at a time)."""

from __future__ import annotations

import itertools

import torch
import torch.nn.functional as F

from torchgi.backends.base import (
    BlockMeanOp,
    BoxOp,
    GuidedOp,
    eager,
)

# exported, a box up to this wide is one square AveragePool, not two separable ones (faster in
# onnxruntime at every width measured up to this one: docs/benchmarks/onnx.md)
_SQUARE_EXPORTED = 17
# block widths of PlaneBoxer's blocked prefix sums (docs/calibration.md)
_BLOCK_W, _BLOCK_H = 16, 16


def in_place(desc: BoxOp | GuidedOp) -> bool:
    """The in-place CPU paths (:class:`PlaneBoxer`, the guided workspace) take eager CPU calls
    (no autograd, no tracing: :func:`~torchgi.backends.base.eager`).

    Example:
        >>> in_place(BoxOp(torch.ones(1, 1, 2, 2), 1)), in_place(BoxOp(torch.ones(1, 1, 2, 2, requires_grad=True), 1))
        (True, False)
    """
    return all(t.device.type == "cpu" for t in desc.tensors() if t is not None) and eager(desc) is None


def _counts(n: int | torch.Tensor, r: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    j = torch.arange(n, device=device)
    hi = torch.clamp(j + (r + 1), max=n)
    lo = torch.clamp(j - r, min=0)
    return hi, lo


def box_pool(x: torch.Tensor, r: int) -> torch.Tensor:
    """Separable count-normalised box mean of ``(..., H, W)`` (exported, up to 17 wide, one square
    pool: the same means).

    Example:
        >>> box_pool(torch.arange(3.0).view(1, 1, 1, 3), 1)
        tensor([[[[0.5000, 1.0000, 1.5000]]]])
    """
    shape = x.shape
    y = x.reshape(-1, 1, shape[-2], shape[-1])
    k = 2 * r + 1
    if k <= _SQUARE_EXPORTED and torch.compiler.is_exporting():  # one square pool: faster in onnxruntime
        return F.avg_pool2d(y, k, stride=1, padding=r, count_include_pad=False).reshape(shape)
    y = F.avg_pool2d(y, (1, k), stride=1, padding=(0, r), count_include_pad=False)
    y = F.avg_pool2d(y, (k, 1), stride=1, padding=(r, 0), count_include_pad=False)
    return y.reshape(shape)


def block_mean(x: torch.Tensor, s: int) -> torch.Tensor:
    """Means of the ``s x s`` blocks of ``x (B, C, H, W)``: ``(B, C, ⌈H/s⌉, ⌈W/s⌉)``, a last
    partial block averaged over the pixels it has. (``count_include_pad=False`` changes nothing
    here - there is no padding - but exported, onnxruntime runs that form several times faster:
    docs/benchmarks/onnx.md.)

    Example:
        >>> block_mean(torch.arange(3.0).view(1, 1, 1, 3), 2)
        tensor([[[[0.5000, 2.0000]]]])
    """
    return F.avg_pool2d(x, s, ceil_mode=True, count_include_pad=False)


def block_means(desc: BlockMeanOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.BlockMeanOp` in torch: :func:`block_mean`.

    Example:
        >>> block_means(BlockMeanOp(torch.arange(3.0).view(1, 1, 1, 3), 2))
        tensor([[[[0.5000, 2.0000]]]])
    """
    return block_mean(desc.x, desc.s)


def _segments(n: int, r: int) -> list[tuple[int, int]]:
    """Split ``[0, n)`` where ``min(j+r, n-1)`` or ``j-r-1 >= 0`` change form."""
    cuts = sorted({0, n, min(max(n - r, 0), n), min(r + 1, n)})
    return [(a, b) for a, b in itertools.pairwise(cuts) if b > a]


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
        >>> torch.allclose(boxer(x, torch.empty_like(x)), box_pool(x[None, None], 1)[0, 0])
        True
    """

    def __init__(self, H: int, W: int, radius: int, dtype: torch.dtype = torch.float32) -> None:
        self.H, self.W, self.r = H, W, radius
        self.stack = max(1, _STACK_ELEMENTS // max(H * W, 1))  # planes boxed together
        self._prefix_buf = torch.empty(self.stack, H, W, dtype=dtype)  # prefix sums along W, then H
        self._rows_buf = torch.empty(self.stack, H, W, dtype=dtype)  # box sums along W
        self._upper = torch.triu(torch.ones(_BLOCK_W, _BLOCK_W, dtype=dtype))
        self._lower = torch.tril(torch.ones(_BLOCK_H, _BLOCK_H, dtype=dtype))
        # running totals of the block sums: along H a triangular matmul, along W a cumsum of the
        # strided totals (whichever was faster, docs/calibration.md)
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



def box(desc: BoxOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.BoxOp` in torch: :class:`PlaneBoxer` eagerly on the CPU,
    else :func:`box_pool`.

    Example:
        >>> box(BoxOp(torch.arange(3.0).view(1, 1, 1, 3), 1))
        tensor([[[[0.5000, 1.0000, 1.5000]]]])
    """
    x = desc.x
    if not in_place(desc) or x.numel() == 0:
        return box_pool(x, desc.radius)
    B, C, H, W = x.shape
    out = torch.empty(B, C, H, W, dtype=x.dtype)
    PlaneBoxer(H, W, desc.radius, x.dtype)(x.reshape(B * C, H, W), out.view(B * C, H, W))
    return out


