"""The colour-weighted classical methods, "atrous" (Dammertz et al. 2010) and "bilateral"
(brute-force cross-bilateral on normal + depth), and "none" (the noisy image, assembled)."""

from __future__ import annotations

import math
from typing import Any

import torch

from torchgi.buffers import GBuffer
from torchgi.filters import atrous, cross_bilateral
from torchgi.geometry import sigma_position_rule
from torchgi.methods.base import Method, noise_spp

__all__ = ["ATrous", "Bilateral", "NoFilter"]


class ATrous(Method):
    """``Denoiser("atrous")``: parameters ``iterations``, ``sigma_normal``, ``sigma_position``
    (scene units squared), ``sigma_color``; needs ``position``; settings ``Settings.atrous``.

    Example:
        >>> from torchgi import Denoiser
        >>> from torchgi.render import render, scenes
        >>> Denoiser("atrous")(render(scenes.cornell(16), spp=1)).shape
        torch.Size([1, 3, 16, 16])
    """

    name = "atrous"
    group = "atrous"
    needs = ("position",)
    params = ("iterations", "sigma_normal", "sigma_position", "sigma_color")
    exportable = True
    geometry = "position"
    onnx_optimize = False  # its unrolled levels make the ONNX optimiser the slow part of an export

    def filter(self, x: torch.Tensor, gb: GBuffer, surface: torch.Tensor, raw: torch.Tensor | None = None, *,
               workspace: dict | None = None) -> tuple[torch.Tensor, None]:
        a, p = self.settings.atrous, self.params
        scale = self.scale(x, surface)
        iterations = self.iterations(noise_spp(gb, surface, self.settings))
        sigma_x = p.get("sigma_position")
        if sigma_x is None and gb.position is not None:
            sigma_x = sigma_position_rule(gb.position, surface, a.sigma_position_footprints)
        out = atrous(x * scale, gb.normal, gb.position, iterations=iterations,
                     sigma_normal=p.get("sigma_normal", a.sigma_normal), sigma_position=sigma_x,
                     sigma_color=p.get("sigma_color"))
        return out / scale, None

    def iterations(self, spp: float) -> int:
        """Given, or enough levels for a ``footprint · quality / sqrt(spp)`` px footprint, within
        ``[min_iterations, max_iterations]``."""
        a = self.settings.atrous
        q = self.settings.pipeline.quality_scale(self.quality)
        levels = round(math.log2(a.footprint * q / math.sqrt(spp)) + 2)
        return self.params.get("iterations", max(a.min_iterations, min(a.max_iterations, levels)))

    def deploy(self, spp: float, samples: float | None, frame: GBuffer | None, variance: bool,
               sigma_position: float | None) -> tuple[dict[str, Any], None]:
        a, p = self.settings.atrous, self.params
        sigma_x = p.get("sigma_position", sigma_position)
        if sigma_x is None:
            raise ValueError("sigma_position: an exported À-Trous needs a fixed σ_x (scene units squared)")
        return {
            "iterations": self.iterations(spp),
            "sigma_normal": p.get("sigma_normal", a.sigma_normal), "sigma_position": sigma_x,
            "sigma_color": p.get("sigma_color", a.deployed_sigma_color),
            **({"samples": float(samples)} if variance else {}),
        }, None

    @staticmethod
    def deployed_filter(params: dict[str, Any], net: torch.nn.Module | None, x: torch.Tensor, normal: torch.Tensor,
                        geometry: torch.Tensor, radius: int | None = None,
                        raw: torch.Tensor | None = None) -> torch.Tensor:
        return atrous(x, normal, geometry, iterations=params["iterations"], sigma_normal=params["sigma_normal"],
                      sigma_position=params["sigma_position"], sigma_color=params["sigma_color"])


class Bilateral(Method):
    """``Denoiser("bilateral")``: parameters ``radius``, ``sigma_space`` (px), ``sigma_color``;
    settings ``Settings.bilateral``.

    Example:
        >>> from torchgi import Denoiser
        >>> from torchgi.render import render, scenes
        >>> Denoiser("bilateral")(render(scenes.cornell(16), spp=1)).shape
        torch.Size([1, 3, 16, 16])
    """

    name = "bilateral"
    group = "bilateral"
    params = ("radius", "sigma_space", "sigma_color")

    def filter(self, x: torch.Tensor, gb: GBuffer, surface: torch.Tensor, raw: torch.Tensor | None = None, *,
               workspace: dict | None = None) -> tuple[torch.Tensor, None]:
        b, p = self.settings.bilateral, self.params
        scale = self.scale(x, surface)
        radius = self.radius(noise_spp(gb, surface, self.settings), b.radius)
        guides = [gb.normal] + ([gb.depth / gb.depth.amax().clamp_min(1e-12)] if gb.depth is not None else [])
        out = cross_bilateral(x * scale, guides, radius=radius, sigma_space=p.get("sigma_space", radius / 2),
                              sigma_color=p.get("sigma_color", b.sigma_color),
                              sigma_guides=[b.sigma_guide] * len(guides))
        return out / scale, None


class NoFilter(Method):
    """``Denoiser("none")``: the noisy image as it is (the input ``color``).

    Example:
        >>> import torch
        >>> from torchgi import Denoiser
        >>> c = torch.rand(1, 3, 4, 4)
        >>> Denoiser("none")(color=c, albedo=c, normal=c) is c
        True
    """

    name = "none"
    filters = False
