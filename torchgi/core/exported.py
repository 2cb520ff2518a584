"""Two element-wise steps written, while a graph is exported (``torch.compiler.is_exporting()``), the
way onnxruntime's CPU kernels run them fast; plain torch everywhere else (eager calls, autograd,
``torch.compile``): a select as arithmetic on the mask instead of a ``Where``, a channel maximum
as a ``Max`` of the channel slices instead of a ``ReduceMax`` (measured in
docs/benchmarks/onnx.md).
"""

from __future__ import annotations

import torch

__all__ = ["channel_max", "where"]


def where(cond: torch.Tensor, a: torch.Tensor | float, b: torch.Tensor | float) -> torch.Tensor:
    """``torch.where(cond, a, b)``; exported, ``a m + b (1 - m)`` with ``m`` the mask as 0/1 of the
    result's dtype (no ``Where``): the selected value exactly, provided the other one is finite
    (``inf · 0`` is NaN), so only where both branches are finite.

    ``cond`` is bool and broadcasts with ``a`` and ``b`` (tensors or numbers; at least one a
    tensor).

    Example:
        >>> where(torch.tensor([True, False]), torch.tensor([1.0, 2.0]), 0.0)
        tensor([1., 0.])
    """
    if not torch.compiler.is_exporting():
        return torch.where(cond, a, b)
    like = a if torch.is_tensor(a) else b
    m = cond.to(like.dtype)
    picked_a = a * m if not (isinstance(a, float | int) and a == 0) else None
    if isinstance(b, float | int) and b == 0:
        return picked_a if picked_a is not None else torch.zeros_like(m)
    picked_b = b * (1 - m)
    return picked_b if picked_a is None else picked_a + picked_b


def channel_max(x: torch.Tensor) -> torch.Tensor:
    """``x.amax(1, keepdim=True)`` of ``x (B, C, H, W)``: ``(B, 1, H, W)``; exported, a
    ``Max`` of the ``C`` channel slices.

    Example:
        >>> channel_max(torch.tensor([1.0, 5.0, 2.0]).view(1, 3, 1, 1)).flatten().tolist()
        [5.0]
    """
    if not torch.compiler.is_exporting() or x.shape[1] == 1:
        return x.amax(1, keepdim=True)
    out = x[:, :1]
    for c in range(1, x.shape[1]):
        out = torch.maximum(out, x[:, c : c + 1])
    return out
