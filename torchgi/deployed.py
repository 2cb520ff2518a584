"""The exportable form of the Denoiser (:meth:`torchgi.Denoiser.deploy`): its pipeline with every
choice fixed, as plain tensor code for ONNX export - with or without an emission input - and the
hole filling that keeps a graph's output finite. The per-method firefly clamp factors both forms
use live here.
"""

from __future__ import annotations

from typing import Any

import torch

from torchgi import light
from torchgi.core.check import check_option
from torchgi.filters import atrous, blend, box, guide_from, guided
from torchgi.filters.pyramid import pyramid
from torchgi.settings import ATROUS, BILATERAL, GUIDED, PIPELINE

__all__ = ["EXPORTABLE", "FIREFLY", "DeployedDenoiser", "DeployedDenoiserWithoutEmission", "deployed"]

EXPORTABLE = ("pyramid", "blend", "guided", "atrous")  # the methods Denoiser.deploy() fixes for ONNX
# fireflies are clamped at this many times their local level before each method's filter
FIREFLY = {"pyramid": GUIDED.firefly, "blend": GUIDED.firefly, "guided": GUIDED.firefly, "atrous": ATROUS.firefly, "bilateral": BILATERAL.firefly, "none": GUIDED.firefly}


def _fill_holes(tensors: list[torch.Tensor]) -> list[torch.Tensor]:
    """``tensors`` (each ``(B, C, H, W)``) with every pixel that is NaN/Inf in any channel of any
    of them made a hole: all its inputs replaced by the mean of the finite pixels within
    ``PIPELINE.hole_radius`` (normalised convolution; 0 where there is none), so nothing
    non-finite reaches the filter and the hole's output comes from its neighbours. Plain
    tensor ops (exportable); finite inputs pass unchanged."""
    ok = torch.stack([torch.isfinite(t).all(1, keepdim=True) for t in tensors]).all(0)
    w = ok.to(tensors[0].dtype)
    clean = torch.where(ok, torch.cat(tensors, 1), 0.0)  # one select, one box over every channel
    sums = box(torch.cat([clean, w], 1), PIPELINE.hole_radius)
    # 0 where no finite pixel is near (the sums are 0 there); ``clean + (1 - w) filled`` is the
    # input itself where finite, exactly, and the fill in a hole
    filled = clean + (1 - w) * (sums[:, :-1] / sums[:, -1:].clamp_min(1e-6))
    return list(filled.split([t.shape[1] for t in tensors], 1))


class DeployedDenoiser(torch.nn.Module):
    """A :class:`Denoiser` with every choice fixed, as plain tensor code for ONNX export.

    ``forward(color, emission, albedo, normal, depth)`` for "pyramid", "blend" and "guided" and
    ``forward(color, emission, albedo, normal, position)`` for "atrous", all ``(B, C, H, W)``
    (:attr:`input_names`; :class:`DeployedDenoiserWithoutEmission` takes none): the
    Denoiser's pipeline (:mod:`torchgi.denoise`'s docstring) with the fixed parameters; surfaces are the pixels
    of non-zero albedo; it takes no variance, so it does not back off toward the input
    (:func:`torchgi.light.back_off`). With an emission input (zeros when no light source is in
    view) the light sources are those pixels, as in the eager call given one; without it they
    are found from the colour, as in the eager call given none. A pixel
    that is NaN/Inf in any input is a hole (:func:`_fill_holes`): the output is finite
    everywhere and, outside the hole's filter footprint, that of the clean input (an exported
    graph cannot raise). Built by :meth:`torchgi.Denoiser.deploy`.
    """

    emission = True  # the graph's inputs include an emission layer

    def __init__(self, method: str, params: dict[str, Any], net: torch.nn.Module | None = None) -> None:
        super().__init__()
        check_option(method, "method", EXPORTABLE)
        if (net is None) != (method in ("guided", "atrous")):
            raise ValueError("net: the learned methods ('pyramid', 'blend') need their network, the others none")
        self.method, self.params, self.net = method, dict(params), net

    @property
    def input_names(self) -> tuple[str, ...]:
        last = "position" if self.method == "atrous" else "depth"
        return ("color",) + (("emission",) if self.emission else ()) + ("albedo", "normal", last)

    def forward(self, color: torch.Tensor, emission: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor,
                geometry: torch.Tensor) -> torch.Tensor:
        return self._run(*_fill_holes([color, emission, albedo, normal, geometry]))

    def _run(self, color: torch.Tensor, emission: torch.Tensor | None, albedo: torch.Tensor, normal: torch.Tensor,
             geometry: torch.Tensor) -> torch.Tensor:
        """The pipeline on hole-filled inputs (``emission`` None: light sources from the colour)."""
        surface = light.surface_mask(None, albedo)

        def filter_fn(x: torch.Tensor) -> torch.Tensor:
            if self.method == "pyramid":
                return pyramid(x, guide_from(normal, geometry, depth_scale="image"), spp=self.params["spp"],
                               net=self.net)
            if self.method == "blend":
                return blend(x, guide_from(normal, geometry, depth_scale="image"), spp=self.params["spp"], net=self.net)
            if self.method == "guided":
                return guided(x, guide_from(normal, geometry, depth_scale="image"), radius=self.params["radius"],
                              eps=self.params["eps"], subsample=self.params.get("subsample", 1))
            return atrous(x, normal, geometry, iterations=self.params["iterations"],
                          sigma_normal=self.params["sigma_normal"], sigma_position=self.params["sigma_position"],
                          sigma_color=self.params["sigma_color"])

        return light.restore(color, emission, None, albedo, surface, filter_fn, FIREFLY[self.method], box)

    def extra_repr(self) -> str:
        return f"method={self.method!r}, " + ", ".join(f"{k}={v!r}" for k, v in self.params.items()) + (
            "" if self.emission else ", emission=False")


class DeployedDenoiserWithoutEmission(DeployedDenoiser):
    """:class:`DeployedDenoiser` for renders without an emission layer: ``forward(color, albedo,
    normal, depth | position)``; the light sources are found from the colour, as the eager
    Denoiser does without one. Built by :meth:`torchgi.Denoiser.deploy` with ``emission=False``.

    Example:
        >>> import torchgi
        >>> torchgi.Denoiser("guided").deploy(emission=False).input_names
        ('color', 'albedo', 'normal', 'depth')
    """

    emission = False

    def forward(self, color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor,  # type: ignore[override]
                geometry: torch.Tensor) -> torch.Tensor:
        color, albedo, normal, geometry = _fill_holes([color, albedo, normal, geometry])
        return self._run(color, None, albedo, normal, geometry)


def deployed(method: str, params: dict[str, Any], net: torch.nn.Module | None, emission: bool) -> DeployedDenoiser:
    """The exportable module :meth:`torchgi.Denoiser.deploy` returns for ``method`` (one of
    :data:`EXPORTABLE`) with its fixed ``params`` and network: :class:`DeployedDenoiser`, or
    :class:`DeployedDenoiserWithoutEmission` when ``emission`` is False.

    Example:
        >>> deployed("guided", {"radius": 2, "eps": 1e-4}, None, emission=False)
        DeployedDenoiserWithoutEmission(method='guided', radius=2, eps=0.0001, emission=False)
    """
    if emission:
        return DeployedDenoiser(method, params, net)
    return DeployedDenoiserWithoutEmission(method, params, net)
