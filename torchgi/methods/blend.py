"""Method "blend": a learned per-pixel blend of guided filters (:mod:`torchgi.filters.blend`)."""

from __future__ import annotations

from typing import Any

import torch

from torchgi.buffers import GBuffer
from torchgi.filters import guide_from
from torchgi.filters.blend import blend, default_net
from torchgi.methods.base import Method, noise_spp

__all__ = ["Blend"]


class Blend(Method):
    """``Denoiser("blend")``: no parameters; expects ``depth`` (the guide it was trained with);
    noisier renders than 1 spp are fed to it as 1 spp.

    Example:
        >>> from torchgi import Denoiser
        >>> from torchgi.render import render, scenes
        >>> Denoiser("blend").weights(render(scenes.cornell(16), spp=1)).shape
        torch.Size([1, 9, 16, 16])
    """

    name = "blend"
    needs = ("depth",)
    learned = temporal = exportable = True

    def filter(self, x: torch.Tensor, gb: GBuffer, surface: torch.Tensor, raw: torch.Tensor | None = None, *,
               workspace: dict | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        # depth over each image's largest, as in training and in the exported form
        # (its network knows 1 spp and more: noisier renders than 1 spp are fed to it as 1 spp)
        return blend(x, guide_from(gb.normal, gb.depth, depth_scale="image"),
                     spp=max(noise_spp(gb, surface, self.settings), 1.0), return_weights=True)

    def deploy(self, spp: float, samples: float | None, frame: GBuffer | None, variance: bool,
               sigma_position: float | None) -> tuple[dict[str, Any], torch.nn.Module]:
        return {"spp": max(spp, 1.0), **({"samples": float(samples)} if variance else {})}, default_net()

    @staticmethod
    def deployed_filter(params: dict[str, Any], net: torch.nn.Module | None, x: torch.Tensor, normal: torch.Tensor,
                        geometry: torch.Tensor, radius: int | None = None,
                        raw: torch.Tensor | None = None) -> torch.Tensor:
        return blend(x, guide_from(normal, geometry, depth_scale="image"), spp=params["spp"], net=net)
