"""The torch code of the learned pyramid's steps at full and half resolution (:class:`~torchgi.backends.base.MixHalfOp`,
:class:`~torchgi.backends.base.ModelResidualOp`, :class:`~torchgi.backends.base.FineBandOp`,
:class:`~torchgi.backends.base.AppliedMeansOp`): the reference (autograd, tracing, any dtype and
device), and what :func:`torchgi.filters.pyramid.pyramid_mix` computes while training."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from torchgi.backends.base import AppliedMeansOp, FineBandOp, MixHalfOp, ModelResidualOp
from torchgi.backends.torch_code.filter_box import block_mean
from torchgi.backends.torch_code.filter_guided import apply_coefficients


def up2(t: torch.Tensor, size: Sequence[int]) -> torch.Tensor:
    """Bilinear x2 of ``t (B, C, h, w)`` (torch's interpolate, align_corners=False) cropped to
    ``size``: a pyramid level brought to the next finer one.

    Example:
        >>> up2(torch.tensor([[[[0.0, 4.0]]]]), (2, 3))[0, 0, 0].tolist()
        [0.0, 1.0, 3.0]
    """
    return F.interpolate(t, scale_factor=2, mode="bilinear", align_corners=False)[..., : size[0], : size[1]]


def applied_means(desc: AppliedMeansOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AppliedMeansOp` in tensor ops.

    Example:
        >>> c = torch.tensor([2.0, 1.0]).view(1, 2, 1, 1, 1).expand(1, 2, 1, 2, 3)   # a = 2, b = 1
        >>> applied_means(AppliedMeansOp(c, torch.arange(6.0).view(1, 1, 2, 3), 2)).tolist()
        [[[[5.0, 8.0]]]]
    """
    return block_mean(apply_coefficients(desc.coeffs, desc.guide), desc.s)


def mix_half(desc: MixHalfOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.MixHalfOp` in tensor ops, term by term.

    Example:
        >>> c, w, f = torch.ones(1, 2, 1, 2, 2), torch.full((1, 1, 2, 2), 0.5), torch.full((1, 2, 1, 4, 3), 2.0)
        >>> mix_half(MixHalfOp(c, w, (f,))).unique().tolist()
        [2.0]
    """
    size = desc.fines[0].shape[-2:]
    w = up2(desc.weights, size)[:, :, None, None]
    fine = w[:, 0] * desc.fines[0]
    for k in range(1, len(desc.fines)):
        fine = fine + w[:, k] * desc.fines[k]
    return up2(desc.coarse.flatten(1, 2), size).unflatten(1, desc.coarse.shape[1:3]) + fine


def model_residual(desc: ModelResidualOp) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:class:`~torchgi.backends.base.ModelResidualOp` in tensor ops (``inplace`` is a permission
    the torch code does not use).

    Example:
        >>> m, y, x = torch.zeros(1, 3, 4, 4), torch.ones(1, 3, 4, 4), torch.full((1, 3, 4, 4), 3.0)
        >>> model, res, low = model_residual(ModelResidualOp(m, (y,), torch.full((1, 1, 2, 2), 2.0), x))
        >>> float(model.max()), float(res.min()), tuple(low.shape)
        (2.0, 1.0, (1, 3, 2, 2))
    """
    w = up2(desc.weights, desc.x.shape[-2:])
    mix = w[:, 0:1] * desc.ys[0]
    for k in range(1, len(desc.ys)):
        mix = mix + w[:, k : k + 1] * desc.ys[k]
    model = desc.model + mix
    res = desc.x - model
    return model, res, block_mean(res, 2)


def fine_band(desc: FineBandOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.FineBandOp` in tensor ops.

    Example:
        >>> z = torch.zeros(1, 1, 2, 2)
        >>> float(fine_band(FineBandOp(torch.ones(1, 1, 4, 4), torch.ones(1, 1, 4, 4), z, z, z + 0.5)).max())
        1.5
    """
    size = desc.residual.shape[-2:]
    detail = up2(desc.gain, size) * (desc.residual - up2(desc.means, size))
    return desc.model + (up2(desc.band, size) + detail)
