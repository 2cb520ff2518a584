"""The torch back end: the torch code of every op - the reference (autograd, tracing, ONNX
export, float64, any device) and the CPU in-place paths used where no compiled kernel applies.

One file per op family: :mod:`.filter_box`, :mod:`.filter_guided`, :mod:`.filter_atrous`, :mod:`.filter_kernels` (the
filters), :mod:`.sampling` (importance, allocation), :mod:`.pipeline` (the Denoiser's guided
pipeline), :mod:`.pyramid` (the learned pyramid's full-resolution steps), :mod:`.accumulation` (the temporal ops), :mod:`.tracer` (the renderer's torch
wavefronts).
This module is the back end's registry: :func:`supports`, :func:`describe` and one function
per op name of :mod:`torchgi.backends.base`.
"""

from __future__ import annotations

from torchgi.backends.torch_code.accumulation import accumulate, change, history
from torchgi.backends.torch_code.filter_atrous import (
    atrous,
    atrous_level,
    atrous_level_grad,
    channel_planes,
    squared_distance,
)
from torchgi.backends.torch_code.filter_box import PlaneBoxer, block_mean, block_means, box, box_pool, in_place
from torchgi.backends.torch_code.filter_guided import (
    apply_coefficients,
    guided,
    guided_filter,
    guided_grad,
    solve,
    upsample_apply,
)
from torchgi.backends.torch_code.filter_kernels import apply_kernels, apply_kernels_grad
from torchgi.backends.torch_code.pipeline import back_off, choose, edge_share, guide_stats, light_in, light_out, restore
from torchgi.backends.torch_code.pyramid import applied_means, fine_band, mix_half, model_residual, up2
from torchgi.backends.torch_code.sampling import allocate, importance
from torchgi.backends.torch_code.tracer import guide_rays, path

__all__ = [
    "NAME", "PlaneBoxer", "accumulate", "allocate", "applied_means", "apply_coefficients", "apply_kernels", "apply_kernels_grad", "atrous", "atrous_level", "atrous_level_grad", "back_off", "block_mean", "block_means", "box", "box_pool",
    "change", "channel_planes", "choose", "describe", "edge_share", "fine_band", "guide_rays", "guide_stats", "guided", "guided_filter", "guided_grad",
    "history", "importance", "in_place", "light_in", "light_out", "mix_half", "model_residual", "path", "ready", "restore", "solve", "squared_distance",
    "supports", "up2", "upsample_apply",
]

NAME = "torch"


def supports(op: str, desc: object) -> str | None:
    """The torch code takes every call.

    Example:
        >>> supports("box", object()) is None
        True
    """
    return None


def ready(op: str, device: str) -> str | None:
    """None: the torch code takes every call of every op on every device (:func:`torchgi.backends.plan`).

    Example:
        >>> ready("box", "cuda") is None
        True
    """
    return None


def describe() -> str:
    """One line for :func:`torchgi.backends.status`.

    Example:
        >>> describe().startswith("always available")
        True
    """
    return "always available: the reference, autograd, tracing and export"
