"""What a Denoiser method is (:class:`Method`) and the steps of the Denoiser's pipeline every
method shares: the noise level (:func:`noise_spp`), the back-off toward the input
(:func:`back_off`), the tile budget (:func:`budget`) and supersampling with guide rays
(:meth:`Method.supersample`)."""

from __future__ import annotations

import math
from typing import Any, ClassVar

import torch

from torchgi import backends, light
from torchgi.buffers import GBuffer, mean_spp, require_guides
from torchgi.core.errors import ShapeError
from torchgi.core.tiles import auto_budget
from torchgi.filters import box
from torchgi.settings import Settings
from torchgi.supersample import composite, distribute

__all__ = ["Method", "back_off", "budget", "noise_spp", "sampled_twice"]


class Method:
    """One Denoiser method: what it needs and what it is, as class attributes, and its filter.

    A method is a subclass registered by name (:func:`torchgi.methods.register`); it sets the
    attributes below and :meth:`filter` (or :meth:`run`, for a pipeline of its own), and
    :meth:`deploy` where it exports. :class:`torchgi.Denoiser` builds one per instance with its
    quality, :class:`~torchgi.settings.Settings`, filter parameters, input scale and memory budget.

    Example:
        >>> from torchgi import methods
        >>> m = methods.get("guided")
        >>> m.needs, m.exportable, m.firefly(), m.params
        ((), True, 4.0, ('radius', 'eps', 'subsample'))
    """

    name: ClassVar[str] = ""
    group: ClassVar[str] = "guided"  # its Settings group: its defaults and firefly factor
    needs: ClassVar[tuple[str, ...]] = ()  # guide layers beyond albedo and normal: refused by name without them
    params: ClassVar[tuple[str, ...]] = ()  # the filter parameters a user may give (Denoiser(**filter_params))
    filters: ClassVar[bool] = True  # False: the noisy image as it is
    unclamped: ClassVar[bool] = False  # its filter also gets the light before the firefly clamp
    tiles: ClassVar[bool] = False  # runs in tiles under a memory budget (max_memory_mb)
    learned: ClassVar[bool] = False  # a network mixes candidates: Denoiser.weights(), told the sample count
    temporal: ClassVar[bool] = False  # may be the TemporalDenoiser's spatial filter
    exportable: ClassVar[bool] = False  # Denoiser.deploy() fixes it for ONNX
    geometry: ClassVar[str] = "depth"  # the deployed graph's last guide input: "depth" or "position"
    onnx_optimize: ClassVar[bool] = True  # its exported graph goes through the ONNX optimiser
    own_pipeline: ClassVar[bool] = False  # its deployed graph is its deployed_run, not the light steps around deployed_filter

    def __init__(self, quality: str, settings: Settings, params: dict[str, Any], input_scale: float | None,
                 max_memory_mb: float | str | None) -> None:
        self.quality, self.settings, self.params = quality, settings, params
        self.input_scale, self.max_memory_mb = input_scale, max_memory_mb

    @classmethod
    def temporal_params(cls, temporal: Any) -> dict[str, Any]:
        """The filter parameters of this method as the TemporalDenoiser's spatial filter
        (``temporal``: ``Settings.temporal``); none by default (its own defaults)."""
        return {}

    @classmethod
    def firefly(cls, settings: Settings | None = None) -> float:
        """Fireflies are scaled down to this many times their local level before the filter."""
        return getattr(settings or Settings(), cls.group).firefly

    @classmethod
    def check_params(cls, params: dict[str, Any]) -> None:
        """Raise naming a filter parameter whose value this method cannot use (the names are
        checked by the Denoiser against :attr:`params`)."""

    def checks_own(self, split: bool) -> tuple[str, ...]:
        """The inputs its own pipeline checks for NaN/Inf (the Denoiser checks the others)."""
        return ()

    def run(self, gb: GBuffer, kept: torch.Tensor | None, surface: torch.Tensor, workspace: dict,
            weights: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The pipeline (:func:`torchgi.light.restore` around :meth:`filter`, then
        :func:`back_off`) on checked inputs: the ``(B, 3, H, W)`` radiance and, with ``weights``,
        what a learned method chose (None otherwise or where nothing was filtered)."""
        level = light.level(gb.color, gb.emission, kept, gb.albedo, surface)
        chosen: list[torch.Tensor | None] = [None]

        def filter_fn(x: torch.Tensor, *raw: torch.Tensor) -> torch.Tensor:
            out, chosen[0] = self.filter(x, gb, surface, *raw, workspace=workspace)
            return out

        out = light.restore(gb.color, gb.emission, kept, gb.albedo, surface, filter_fn, self.firefly(self.settings),
                            box, level, unclamped=self.unclamped)
        return back_off(out, gb, surface, level, self.settings), chosen[0]

    def filter(self, x: torch.Tensor, gb: GBuffer, surface: torch.Tensor, raw: torch.Tensor | None = None, *,
               workspace: dict | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The filter of the demodulated light ``x (B, 3, H, W)`` after its firefly clamp (``raw``:
        before it, for :attr:`unclamped` methods): the filtered light and what a learned method
        chose (else None)."""
        return x, None

    def deploy(self, spp: float, samples: float | None, frame: GBuffer | None, variance: bool,
               sigma_position: float | None) -> tuple[dict[str, Any], torch.nn.Module | None]:
        """The fixed parameters and network of :class:`torchgi.deployed.DeployedDenoiser` for a
        noise of ``spp`` samples (``samples``: the render's count, for the back-off)."""
        raise NotImplementedError(self.name)

    @staticmethod
    def deployed_filter(params: dict[str, Any], net: torch.nn.Module | None, x: torch.Tensor, normal: torch.Tensor,
                        geometry: torch.Tensor, radius: int | None = None,
                        raw: torch.Tensor | None = None) -> torch.Tensor:
        """The exported graph's filter of ``x`` with the fixed ``params`` (``radius``: one of the
        radii the guided filter chooses among, else None)."""
        raise NotImplementedError

    @staticmethod
    def deployed_run(params: dict[str, Any], net: torch.nn.Module | None, color: torch.Tensor,
                     emission: torch.Tensor | None, albedo: torch.Tensor, normal: torch.Tensor, geometry: torch.Tensor,
                     variance: torch.Tensor | None) -> torch.Tensor:
        """The exported graph of an :attr:`own_pipeline` method on hole-filled inputs (``emission``
        and ``variance`` None where the graph takes none)."""
        raise NotImplementedError

    def radius(self, spp: float, base: int) -> int:
        """Filter radius: given, or ``base · quality / sqrt(spp)`` (at least ``min_radius``) px."""
        p = self.settings.pipeline
        return self.params.get("radius", max(p.min_radius, round(p.quality_scale(self.quality) * base / math.sqrt(spp))))

    def scale(self, x: torch.Tensor, surface: torch.Tensor) -> float:
        """The input scale of the colour-weighted filters: given, or 1 / the mean light on surfaces."""
        if self.input_scale is not None:
            return self.input_scale
        mean = float(x[surface.expand_as(x)].mean()) if bool(surface.any()) else 0.0
        return 1.0 / mean if mean > 0 else 1.0

    def supersample(self, gb: GBuffer, samples: Any, filter_direct: bool, hdr: bool,
                    workspace: dict) -> torch.Tensor:
        """:meth:`torchgi.Denoiser.supersample` (its docstring) with this method's filter."""
        for name in ("emission", "direct", "indirect", "albedo", "normal", "depth"):
            if getattr(gb, name) is None:
                raise ShapeError(f"gb.{name}: required by supersample (render with render_guide_rays)")
        require_guides(gb, self.name, self.needs)
        surface = light.surface_mask(gb.hit, gb.albedo)
        albedo = light.demodulator(gb.albedo, surface)
        x = (gb.indirect + gb.direct if filter_direct else gb.indirect) / albedo
        if not self.filters:
            lit = x
        else:
            def filter_fn(v: torch.Tensor, *raw: torch.Tensor) -> torch.Tensor:
                return self.filter(v, gb, surface, *raw, workspace=workspace)[0]

            lit = light.filter_light(x, light.median_level(light.every4(x), light.every4(surface)), filter_fn,
                                     self.firefly(self.settings), box, self.unclamped)
        lit = torch.where(surface, lit, 0.0)  # no reflected light without a surface
        own, sample_own = gb.emission, samples.emission
        if not filter_direct:
            own, sample_own = own + gb.direct, sample_own + samples.direct
        out = composite(own, gb.albedo, lit, sample_own, samples.albedo, distribute(lit, gb.normal, gb.depth, samples))
        return out if hdr else out.clamp(0, 1)


def sampled_twice(gb: GBuffer, surface: torch.Tensor) -> bool:
    """Whether every ``surface`` pixel of ``gb`` has 2 samples or more (a variance of its own);
    ``gb.spp`` must be set.

    Example:
        >>> gb = GBuffer(color=torch.zeros(1, 3, 1, 2), spp=torch.tensor([[[[1, 2]]]]))
        >>> sampled_twice(gb, torch.tensor([[[[False, True]]]])), sampled_twice(gb, torch.ones(1, 1, 1, 2, dtype=torch.bool))
        (True, False)
    """
    return int(gb.spp.min()) >= 2 or not bool(((gb.spp < 2) & surface).any())


def noise_spp(gb: GBuffer, surface: torch.Tensor, settings: Settings) -> float:
    """The sample count the noise of ``gb`` corresponds to. With a measured variance (>= 2
    samples on every surface pixel): ``pipeline.rel_var_1spp`` over the mean relative variance of
    the colour on surfaces (>= 1/4), so noisier images get wider filters; otherwise the mean
    ``spp`` (>= 1; 1 without one).

    Example:
        >>> from torchgi.render import render, scenes
        >>> gb = render(scenes.cornell(16), spp=1)
        >>> noise_spp(gb, gb.hit, Settings())
        1.0
    """
    if gb.spp is None:
        return 1.0
    spp = max(mean_spp(gb.spp, surface), 1.0)
    if gb.variance is None or gb.color is None:
        return spp
    if not sampled_twice(gb, surface):
        return spp  # some surface pixel has no variance estimate
    count = int(surface.sum()) * gb.color.shape[1]
    if count == 0:
        return spp
    # (masks by where, not by indexing: no gathered copies)
    rel = float(torch.where(surface, gb.variance / (gb.color.square() + 1e-4), 0.0).sum()) / count
    return max(settings.pipeline.rel_var_1spp / max(rel, 1e-12), 0.25)


def back_off(out: torch.Tensor | list[torch.Tensor], gb: GBuffer, surface: torch.Tensor, level: torch.Tensor,
             settings: Settings, rows: slice = slice(None), cols: slice = slice(None),
             radii: tuple[int, ...] = ()) -> torch.Tensor:
    """:func:`torchgi.light.back_off` of ``out`` (the pipeline's ``(B, 3, h, w)`` output for
    ``gb[..., rows, cols]``) toward that crop of ``gb.color`` (:class:`~torchgi.backends.BackOffOp`),
    where ``gb`` has a variance from 2 samples or more and ``settings.pipeline.back_off`` holds
    (else ``out``). ``out`` a list: the outputs of the filter at ``radii``, blended first by
    :func:`torchgi.light.choose` (:class:`~torchgi.backends.ChooseOp`; one output: itself).

    Example:
        >>> from torchgi.render import render, scenes
        >>> gb = render(scenes.cornell(16), spp=1)
        >>> back_off(gb.color, gb, gb.hit, None, Settings()) is gb.color  # 1 spp: no variance to back off with
        True
    """
    c, e, a, on, v, n = (None if t is None else t[..., rows, cols]
                         for t in (gb.color, gb.emission, gb.albedo, surface, gb.variance, gb.spp))
    n = light.samples(n)
    if isinstance(out, list) and len(out) == 1:
        out = out[0]
    if v is None or (isinstance(n, float) and n < 2) or not settings.pipeline.back_off:
        return out
    emit = light.emitting(c, e, a, on, level)
    if isinstance(out, list):
        out = backends.run(backends.ChooseOp(tuple(out), radii, v, emit))
    return backends.run(backends.BackOffOp(out, c, v, n, emit))


def budget(gb: GBuffer, per_pixel: float, max_memory_mb: float | str | None, settings: Settings) -> float | None:
    """The budget (MB) of a call's tiles of ``per_pixel`` bytes per pixel: ``max_memory_mb``, or
    for "auto" the automatic one (``settings.pipeline.auto_*``); None: untiled.

    Example:
        >>> from torchgi.render import render, scenes
        >>> budget(render(scenes.cornell(16), spp=1), 480.0, "auto", Settings()) is None  # small: untiled
        True
    """
    inputs = sum(t.numel() * t.element_size() for n in GBuffer.fields() if (t := getattr(gb, n)) is not None)
    p = settings.pipeline
    return max_memory_mb if max_memory_mb != "auto" else auto_budget(
        gb.color, inputs, per_pixel, p.auto_tiles_from_mb, p.auto_budget, p.auto_floor_mb)

