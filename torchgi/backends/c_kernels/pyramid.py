"""The C back end's walks of the learned pyramid at full resolution (``pyramid.c``):
:class:`~torchgi.backends.base.MixHalfOp`, :class:`~torchgi.backends.base.ModelResidualOp`,
:class:`~torchgi.backends.base.FineBandOp`, :class:`~torchgi.backends.base.BlockMeanOp` and
:class:`~torchgi.backends.base.AppliedMeansOp`."""

from __future__ import annotations

import torch

from torchgi.backends.base import AppliedMeansOp, BlockMeanOp, FineBandOp, MixHalfOp, ModelResidualOp
from torchgi.backends.c_kernels import build
from torchgi.backends.c_kernels.runtime import _run, result


def mix_half(desc: MixHalfOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.MixHalfOp` in one walk per image.

    Example:
        >>> c, w, f = torch.ones(1, 2, 1, 2, 2), torch.full((1, 1, 2, 2), 0.5), torch.full((1, 2, 1, 4, 3), 2.0)
        >>> build.library() is None or mix_half(MixHalfOp(c, w, (f,))).unique().tolist()
        [2.0]
    """
    lib = build.library()
    coarse, wgt = desc.coarse.contiguous(), desc.weights.contiguous()
    fs = [f.contiguous() for f in desc.fines]
    B, Q, (h, w), (h4, w4), n = fs[0].shape[0], fs[0].shape[1] * fs[0].shape[2], fs[0].shape[-2:], wgt.shape[-2:], len(fs)
    out = result(desc.out, tuple(fs[0].shape))
    for b in range(B):
        ptrs = [f[b].data_ptr() for f in fs] + [None] * (4 - n)
        _run(lib.torchgi_mix_half, h, w * Q, coarse[b].data_ptr(), wgt[b].data_ptr(), *ptrs, n, Q, h, w, h4, w4,
             out[b].data_ptr(), 2 * w + w + w4 + (n + 1) * w)
    return out


def model_residual(desc: ModelResidualOp) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:class:`~torchgi.backends.base.ModelResidualOp` in one walk per image (the model into
    ``desc.model`` where ``inplace``).

    Example:
        >>> m, y, x = torch.zeros(1, 3, 4, 4), torch.ones(1, 3, 4, 4), torch.full((1, 3, 4, 4), 3.0)
        >>> build.library() is None or model_residual(ModelResidualOp(m, (y,), torch.full((1, 1, 2, 2), 2.0), x))[1].min().item()
        1.0
    """
    lib = build.library()
    model = desc.model if desc.inplace and desc.model.is_contiguous() else desc.model.contiguous().clone()
    ys = [y.contiguous() for y in desc.ys]
    wgt, x = desc.weights.contiguous(), desc.x.contiguous()
    B, C, H, W = x.shape
    h, w, n = (H + 1) // 2, (W + 1) // 2, len(ys)
    res = result(desc.out, tuple(x.shape))
    low = torch.empty(B, C, h, w, dtype=x.dtype)
    for b in range(B):
        ptrs = [y[b].data_ptr() for y in ys] + [None] * (4 - n)
        _run(lib.torchgi_model_residual, h, W, model[b].data_ptr(), *ptrs, n, wgt[b].data_ptr(), x[b].data_ptr(), C,
             H, W, res[b].data_ptr(), low[b].data_ptr(), 3 * W + n * w)
    return model, res, low


def fine_band(desc: FineBandOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.FineBandOp` in one walk per image.

    Example:
        >>> z = torch.zeros(1, 1, 2, 2)
        >>> build.library() is None or fine_band(FineBandOp(torch.ones(1, 1, 4, 4), torch.ones(1, 1, 4, 4), z, z, z + 0.5)).max().item()
        1.5
    """
    lib = build.library()
    model, res, low, band, gain = (t.contiguous() for t in (desc.model, desc.residual, desc.means, desc.band, desc.gain))
    B, C, H, W = model.shape
    out = torch.empty_like(model)
    for b in range(B):
        _run(lib.torchgi_fine_band, H, W, model[b].data_ptr(), res[b].data_ptr(), low[b].data_ptr(), band[b].data_ptr(),
             gain[b].data_ptr(), C, H, W, out[b].data_ptr(), 3 * W + 3 * ((W + 1) // 2))
    return out


def block_means(desc: BlockMeanOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.BlockMeanOp` in one walk over the block rows of every plane.

    Example:
        >>> build.library() is None or block_means(BlockMeanOp(torch.arange(3.0).view(1, 1, 1, 3), 2)).tolist()
        [[[[0.5, 2.0]]]]
    """
    lib = build.library()
    x, s = desc.x.contiguous(), desc.s
    B, C, H, W = x.shape
    h, w = -(-H // s), -(-W // s)
    out = torch.empty(B, C, h, w, dtype=x.dtype)
    _run(lib.torchgi_block_mean, h, B * C * W * s, x.data_ptr(), B * C, H, W, s, out.data_ptr(), W)
    return out


def applied_means(desc: AppliedMeansOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AppliedMeansOp` in one walk per image.

    Example:
        >>> c = torch.tensor([2.0, 1.0]).view(1, 2, 1, 1, 1).expand(1, 2, 1, 2, 3)   # a = 2, b = 1
        >>> build.library() is None or applied_means(AppliedMeansOp(c, torch.arange(6.0).view(1, 1, 2, 3), 2)).tolist()
        [[[[5.0, 8.0]]]]
    """
    lib = build.library()
    coeffs, guide, s = desc.coeffs.contiguous(), desc.guide.contiguous(), desc.s
    B, n, H, W = guide.shape
    C = coeffs.shape[2]
    out = torch.empty(B, C, -(-H // s), -(-W // s), dtype=torch.float32)
    for b in range(B):
        _run(lib.torchgi_applied_means, -(-H // s), C * W * s * (n + 1), coeffs[b].data_ptr(), guide[b].data_ptr(), n,
             C, H, W, s, out[b].data_ptr(), 2 * W)
    return out
