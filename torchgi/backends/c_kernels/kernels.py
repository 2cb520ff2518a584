"""The C back end's per-pixel kernel application and its gradients (``kernels.c``):
:class:`~torchgi.backends.kernel_ops.ApplyKernelsOp` and :class:`~torchgi.backends.kernel_ops.ApplyKernelsGradOp`,
one walk over the rows of each image."""

from __future__ import annotations

import torch

from torchgi.backends.c_kernels import build
from torchgi.backends.c_kernels.runtime import _ptr, _run
from torchgi.backends.kernel_ops import ApplyKernelsGradOp, ApplyKernelsOp


def apply_kernels(desc: ApplyKernelsOp) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:class:`~torchgi.backends.kernel_ops.ApplyKernelsOp` in C.

    Example:
        >>> x, w = torch.ones(1, 2, 4, 4), torch.ones(1, 9, 4, 4)
        >>> build.library() is None or apply_kernels(ApplyKernelsOp(x, w, 2, True))[0].unique().tolist()
        [1.0]
    """
    lib = build.library()
    x, w = desc.x.contiguous(), desc.weights.contiguous()
    B, C, H, W = x.shape
    k = round(w.shape[1] ** 0.5)
    out = torch.empty_like(x)
    den = torch.empty(B, 1, H, W, dtype=x.dtype) if desc.normalize else None
    for b in range(B):
        _run(lib.torchgi_apply_kernels, H, W, x[b].data_ptr(), w[b].data_ptr(), C, H, W, k, desc.dilation,
             out[b].data_ptr(), _ptr(None if den is None else den[b]), 0)
    return out, den


def apply_kernels_grad(desc: ApplyKernelsGradOp) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """:class:`~torchgi.backends.kernel_ops.ApplyKernelsGradOp` in C (``grad / den`` in torch first).

    Example:
        >>> x, w = torch.ones(1, 1, 1, 3), torch.zeros(1, 9, 1, 3); w[:, 4] = 1.0   # the identity
        >>> g = torch.tensor([[[[1.0, 2.0, 3.0]]]])
        >>> build.library() is None or apply_kernels_grad(ApplyKernelsGradOp(x, w, x, None, g, 1))[0].flatten().tolist()
        [1.0, 2.0, 3.0]
    """
    lib = build.library()
    x, w, out = desc.x.contiguous(), desc.weights.contiguous(), desc.out.contiguous()
    gp = desc.scaled_grad()
    B, C, H, W = x.shape
    k = round(w.shape[1] ** 0.5)
    dx = torch.empty_like(x) if desc.need_x else None
    dw = torch.empty_like(w) if desc.need_weights else None
    for b in range(B):
        _run(lib.torchgi_apply_kernels_grad, H, W, x[b].data_ptr(), w[b].data_ptr(), out[b].data_ptr(),
             gp[b].data_ptr(), C, H, W, k, desc.dilation, int(desc.den is not None),
             _ptr(None if dx is None else dx[b]), _ptr(None if dw is None else dw[b]), 0)
    return dx, dw
