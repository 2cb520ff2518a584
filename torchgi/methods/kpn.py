"""Method "kpn": the multi-resolution kernel-predicting network (:mod:`torchgi.filters.kpn`) on
the render's own layers, as in its training: the noisy colour, its variance and sample count,
albedo, normal, depth and the light seen directly, which passes unfiltered. It runs a pipeline
of its own, eager and deployed: no firefly clamp and no back-off (it was trained without them)."""

from __future__ import annotations

from typing import Any

import torch

from torchgi.buffers import GBuffer, mean_spp
from torchgi.core.dtypes import compute_dtype
from torchgi.core.tiles import tiled
from torchgi.filters.kpn import ALIGN, REACH, default_net, kpn, log_depth_mean
from torchgi.methods.base import Method, budget

# bytes per pixel and image that a call holds at its peak beyond its inputs (float32, measured: docs/kpn.md)
_KPN_BYTES = 330

__all__ = ["KPNMethod"]


class KPNMethod(Method):
    """``Denoiser("kpn")``: no parameters; expects ``depth``; told the mean sample count on
    surfaces (1 without ``spp``) and given the ``variance`` where the render has one; with
    ``filter_direct=False`` and a direct/indirect split, direct light passes as sampled, as the
    emission does. Under ``max_memory_mb`` it runs in tiles overlapping by
    :data:`~torchgi.filters.kpn.REACH` px (the depth centred by the whole image's mean): the
    untiled output to rounding. ``Denoiser.weights(gb)`` is its compositor weights ``(B, 3, H, W)``
    (untiled).

    Example:
        >>> from torchgi import Denoiser
        >>> from torchgi.render import render, scenes
        >>> Denoiser("kpn")(render(scenes.cornell(16), spp=2)).shape
        torch.Size([1, 3, 16, 16])
    """

    name = "kpn"
    needs = ("depth",)
    learned = tiles = exportable = own_pipeline = True
    onnx_optimize = False  # the optimiser is the slow part of its export; onnxruntime runs the graph as exported

    def run(self, gb: GBuffer, kept: torch.Tensor | None, surface: torch.Tensor, workspace: dict,
            weights: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        own = gb.emission if gb.emission is not None else torch.zeros_like(gb.color)
        if kept is not None:
            own = own + kept
        spp = 1.0 if gb.spp is None else max(mean_spp(gb.spp, surface), 1.0)
        layers = (gb.color, gb.albedo, gb.normal, gb.depth, own, gb.variance)
        per_pixel = _KPN_BYTES * gb.color.shape[0] * torch.finfo(compute_dtype(gb.color.dtype)).bits / 32
        mb = None if weights else budget(gb, per_pixel, self.max_memory_mb, self.settings)
        if mb is None:
            out, chosen = kpn(*layers[:4], emission=own, variance=gb.variance, spp=spp, return_weights=True)
            return out, chosen if weights else None
        mean = log_depth_mean(gb.depth.to(compute_dtype(gb.depth.dtype)))  # the whole image's, in every tile

        def op(rows: slice, cols: slice) -> torch.Tensor:
            c, a, n, d, e, v = (None if t is None else t[..., rows, cols] for t in layers)
            return kpn(c, a, n, d, emission=e, variance=v, spp=spp, depth_mean=mean)

        return tiled(op, gb.color, mb, REACH, ALIGN, per_pixel), None

    def deploy(self, spp: float, samples: float | None, frame: GBuffer | None, variance: bool,
               sigma_position: float | None) -> tuple[dict[str, Any], torch.nn.Module]:
        # told the render's sample count, as in training (not the count its noise corresponds to)
        return {"spp": max(float(samples if samples is not None else spp), 1.0),
                **({"samples": float(samples)} if variance else {})}, default_net()

    @staticmethod
    def deployed_run(params: dict[str, Any], net: torch.nn.Module | None, color: torch.Tensor,
                     emission: torch.Tensor | None, albedo: torch.Tensor, normal: torch.Tensor, geometry: torch.Tensor,
                     variance: torch.Tensor | None) -> torch.Tensor:
        return kpn(color, albedo, normal, geometry, emission=emission, variance=variance, spp=params["spp"], net=net)
