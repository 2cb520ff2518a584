"""The torch code of the Denoiser's guided pipeline: its guide statistics, the edge share
that decides half resolution, and the whole pipeline (:func:`torchgi.light.restore` around
:func:`~torchgi.backends.torch_code.filter_guided.guided_filter`); the steps before and after
another filter (:func:`torchgi.light.prepare`, :func:`torchgi.light.finish`)."""

from __future__ import annotations

import math

import torch

from torchgi import light
from torchgi.backends.autograd_ops import box_mean
from torchgi.backends.base import (
    BackOffOp,
    ChooseOp,
    EdgeShareOp,
    GuideStatsOp,
    LightInOp,
    LightOutOp,
    RestoreOp,
)
from torchgi.backends.torch_code.filter_guided import guided_filter
from torchgi.core.check import check_finite
from torchgi.core.dtypes import compute_dtype


def guide_stats(desc: GuideStatsOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.GuideStatsOp` by reductions.

    Example:
        >>> n = torch.zeros(1, 3, 2, 2); d = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])
        >>> guide_stats(GuideStatsOp(n, d, d > 2.5))[0, [3, 8]].tolist()   # depth min, depth max on hit
        [1.0, 4.0]
    """
    n, d = desc.normal, desc.depth
    B = n.shape[0]
    planes = n if d is None else torch.cat([n, d], 1)
    lo, hi = planes.amin(dim=(2, 3)).double(), planes.amax(dim=(2, 3)).double()
    if d is None:
        lo, hi = torch.cat([lo, lo.new_full((B, 1), math.inf)], 1), torch.cat([hi, hi.new_full((B, 1), -math.inf)], 1)
        dmax = lo.new_full((B, 1), -math.inf)
    else:
        valid = d if desc.hit is None else torch.where(desc.hit, d, -torch.inf)
        dmax = valid.amax(dim=(1, 2, 3)).double().view(B, 1)
    bad_n = (~torch.isfinite(n)).flatten(1).sum(1, keepdim=True).double()
    bad_d = torch.zeros_like(bad_n) if d is None else (~torch.isfinite(d)).flatten(1).sum(1, keepdim=True).double()
    sums = planes.double().sum(dim=(2, 3))
    sums = sums if d is not None else torch.cat([sums, sums.new_zeros(B, 1)], 1)
    return torch.cat([lo, hi, dmax, bad_n, bad_d, sums], 1).cpu()


def edge_share(desc: EdgeShareOp) -> float:
    """:class:`~torchgi.backends.base.EdgeShareOp` on the guide built by torch ops.

    Example:
        >>> from torchgi.backends.base import GuideSpec
        >>> n = torch.zeros(1, 3, 2, 3); n[..., 2] = 1.0
        >>> edge_share(EdgeShareOp(GuideSpec(n, None, (0,), (0.5,), (0.5,)), 0.1))   # 1 of 2 neighbours
        0.5
    """
    guide = desc.spec.build()
    edges = (guide[:, :, ::2, 1:] - guide[:, :, ::2, :-1]).square().sum(1) > desc.edge**2
    return float(edges.float().mean())


def restore(desc: RestoreOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.RestoreOp` as the Denoiser's torch code: the steps of
    :func:`torchgi.light.restore` in eager ops around the guided filter (whose own back end is
    chosen through the seam, as for :func:`torchgi.filters.guided`).

    Example:
        >>> from torchgi.backends.base import GuideSpec
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5)
        >>> spec = GuideSpec(torch.zeros_like(c), None, (0,), (0.5,), (0.5,))
        >>> restore(RestoreOp(c, None, None, a, None, spec, torch.ones(1, 1, 1, 1), 1, 1e-4, 1, 4.0)).shape
        torch.Size([1, 3, 8, 8])
    """
    for name, t in desc.light_inputs():
        check_finite(t, name)
    guide = desc.spec.build()
    B, n = guide.shape[:2]
    eps = torch.full((B, n, 1, 1), float(desc.eps), dtype=compute_dtype(guide.dtype), device=guide.device)
    return light.restore(desc.color, desc.emission, desc.kept, desc.albedo, light.surface_mask(desc.hit, desc.albedo),
                         lambda x: guided_filter(x, guide, desc.radius, eps, desc.workspace, desc.subsample),
                         desc.firefly, box_mean, desc.level)


def light_in(desc: LightInOp) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:class:`~torchgi.backends.base.LightInOp` by :func:`torchgi.light.prepare` in tensor ops
    (its box through the seam).

    Example:
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5)
        >>> clamped, x, lights = light_in(LightInOp(c, None, None, a, None, torch.ones(1, 1, 1, 1), 4.0))
        >>> clamped.shape, lights.dtype
        (torch.Size([1, 3, 8, 8]), torch.bool)
    """
    for name, t in desc.light_inputs():
        check_finite(t, name)
    d = desc
    return light.prepare(d.color, d.emission, d.kept, d.albedo, light.surface_mask(d.hit, d.albedo), d.firefly,
                         box_mean, d.level)


def light_out(desc: LightOutOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.LightOutOp` by :func:`torchgi.light.finish` in tensor ops
    (``inplace`` is a permission the torch code does not use).

    Example:
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5); none = torch.zeros(1, 1, 8, 8, dtype=torch.bool)
        >>> torch.equal(light_out(LightOutOp(c / 0.5, c, None, None, a, None, none)), c)
        True
    """
    d = desc
    return light.finish(d.filtered, d.color, d.emission, d.kept, d.albedo, light.surface_mask(d.hit, d.albedo),
                        d.lights)


def back_off(desc: BackOffOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.BackOffOp` by :func:`torchgi.light.back_off` in tensor ops
    (the reference: autograd, tracing, any dtype and device; its box through the seam, as the
    pipeline's).

    Example:
        >>> c = torch.ones(1, 3, 4, 4); lit = torch.zeros(1, 1, 4, 4, dtype=torch.bool)
        >>> round(back_off(BackOffOp(c + 1, c, torch.full_like(c, 1e-6), 64.0, lit)).mean().item(), 4)   # noise-free: the input
        1.0
    """
    d = desc
    return light.back_off(d.out, d.color, d.variance, d.spp, d.emitting, box_mean)


def choose(desc: ChooseOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.ChooseOp` by :func:`torchgi.light.choose` in tensor ops (the
    reference: autograd, tracing, any dtype and device; its box through the seam).

    Example:
        >>> c = torch.ones(1, 3, 4, 4); lit = torch.zeros(1, 1, 4, 4, dtype=torch.bool)
        >>> round(choose(ChooseOp((c, c + 1), (1, 4), torch.zeros_like(c), lit)).mean().item(), 4)   # noise-free: the sharpest
        1.0
    """
    d = desc
    return light.choose(list(d.outs), list(d.radii), d.variance, d.emitting, box_mean)
