"""``torchgi.Denoiser``: what users call (docs/design.md, Denoiser pipeline), in Intel Open Image Denoise's vocabulary.

The noisy light is demodulated by albedo on surfaces (background pixels - the sky, missed rays -
are filtered as they are), filtered with the geometry-aware filter chosen by ``method`` and
remodulated. Around the filter:

* Light sources pass untouched (docs/design.md, Skips: no filtering of what carries no noise): emission far
  above the lit scene (8x the median demodulated light) over at least a 3x3 square of pixels.
  Other emission - the sky, pixels beside a light's silhouette that one sample hit, lights
  smaller than 3x3 pixels - is noisy like the rest and is filtered with it. Without an ``emission`` input, such bright coherent
  regions of ``color`` pass untouched and enter the filter at the median level, so they do not bleed.
* Fireflies: demodulated light above 4x its local level (2x for the colour-weighted filters) is
  scaled down to that bound before filtering; the excess energy of one outlier sample is dropped
  rather than spread over a window.
* The filtered light is clamped at 0 (the guided filter's local linear models can undershoot).
* With the renderer's direct/indirect split and ``filter_direct=False``, direct light is kept as
  sampled and only indirect light is filtered (the papers' setting).
* With a measured ``variance`` (>= 2 samples), the result backs off toward the input where the
  filter's residual exceeds that noise (:func:`torchgi.light.back_off`): the filter's bias is not
  left in where more samples made the input better than it, so the error falls as samples rise.
  Without a variance (1 spp, or none given) the filter's output is returned as it is.
* Method "guided" with that variance from ``GUIDED.choose_from_spp`` (3) samples on average, at
  full resolution and no ``radius`` given: the filter runs at half and at twice its radius and
  each pixel takes a blend of the two weighted by their estimated error
  (:func:`torchgi.light.choose`) before the back-off: narrow at edges and glossy highlights, wide
  on smooth light (about 2x the filter's time).

Parameters that depend on the noise level are chosen from the measured variance when every
surface pixel has one (>= 2 samples), else from ``spp``: the guided filter's and the bilateral's
radius and À-Trous' iteration count grow with the noise; ``quality`` scales them.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from torchgi import light, methods
from torchgi.buffers import (
    GBuffer,
    _noise_free,
    _warn_if_colour_normals,
    _warn_of_the_colour,
    _with_samples,
    mean_spp,
    require_guides,
)
from torchgi.core.check import check_finite, check_option, check_positive, finite_or_sanitized_all
from torchgi.core.errors import ConfigError, ShapeError
from torchgi.core.tiles import check_budget
from torchgi.deployed import DeployedDenoiser, deployed
from torchgi.methods.base import noise_spp
from torchgi.settings import DEFAULTS, Settings, check_settings
from torchgi.supersample import EyeSamples

__all__ = ["QUALITIES", "Denoiser"]

QUALITIES = ("fast", "balanced", "high")


class Denoiser(torch.nn.Module):
    """Denoise a path-traced image from its noise-free guides: the pipeline every method shares
    (inputs, light split, light sources, fireflies, back-off, tiles) around the method's filter
    (:mod:`torchgi.methods`, one class per method).

    Args:
        method: a registered method (:func:`torchgi.methods.names`): "guided" (Bauszat et al.
            2011), "pyramid" (a small network mixes guided-filter models from a pyramid of scales
            per pixel, :mod:`torchgi.filters.pyramid`), "blend" (a learned per-pixel blend of
            guided filters, :mod:`torchgi.filters.blend`: about 7x slower; both learned methods
            expect ``depth``), "atrous" (Dammertz et al. 2010), "bilateral" (brute-force
            cross-bilateral) or "none" (the noisy image, assembled).
        quality: "fast", "balanced" or "high" (radius / iterations / window scale).
        hdr: the colour is HDR (True) or in [0, 1] (False: the output is clamped to [0, 1]).
        input_scale: multiplies the demodulated signal before colour-weighted filtering (À-Trous,
            bilateral) and divides it after; None = 1 / its mean on geometry.
        filter_direct: with a direct/indirect split, filter direct light too (True: it is noisy,
            as with area lights and skies at low spp) or keep it as sampled (False: the papers'
            setting, noise-free direct light).
        sanitize: NaN/Inf in an input raises :class:`~torchgi.core.NonFiniteError` naming it
            (False) or is replaced by 0 with a warning (True).
        max_memory_mb: the most memory (MB) a call may add beyond its inputs and output (OIDN's
            ``maxMemoryMB``): methods that tile ("guided", "pyramid") run in overlapping tiles, the
            result that of one pass (to rounding); None: never in tiles; "auto": in tiles above
            ``settings.pipeline.auto_tiles_from_mb`` (docs/pipeline.md, docs/pyramid.md).
        settings: this instance's :class:`~torchgi.settings.Settings` (default
            :data:`~torchgi.settings.DEFAULTS`; ``DEFAULTS.replace(guided={"firefly": 3.0})``).
        **filter_params: override the automatic choices: ``radius``, ``eps``, ``subsample`` (guided);
            ``iterations``, ``sigma_normal``, ``sigma_position``, ``sigma_color`` (À-Trous);
            ``radius``, ``sigma_space``, ``sigma_color`` (bilateral).

    Call with a :class:`~torchgi.GBuffer` or with named ``(B, C, H, W)`` tensors: ``color``
    (or ``direct`` + ``indirect``), ``albedo``, ``normal`` (world space, [-1, 1]), and when
    available ``position``, ``depth``, ``emission``, ``variance``, ``spp``, ``hit``; a method's
    ``needs`` (``methods.get(name).needs``: "pyramid" and "blend" ``depth``, "atrous" ``position``) are
    refused by name when missing. ``spp`` may also be a number, the sample count of a render
    that recorded none (an int or float >= 1; ``den(gb, spp=4)`` is
    ``den(gb.replace(spp=torch.full((B, 1, H, W), 4)))``); without one a GBuffer without ``spp``
    is taken as 1 sample per pixel. Returns the ``(B, 3, H, W)`` denoised radiance in the input
    dtype, on the input device.

    Example:
        >>> from torchgi.render import render, scenes
        >>> gb = render(scenes.cornell(24), spp=1, bounces=1)
        >>> Denoiser("guided")(gb).shape
        torch.Size([1, 3, 24, 24])
    """

    def __init__(self, method: str = "guided", quality: str = "balanced", *, hdr: bool = True,
                 input_scale: float | None = None, filter_direct: bool = True, sanitize: bool = False,
                 max_memory_mb: float | str | None = "auto", settings: Settings = DEFAULTS, **filter_params: Any) -> None:
        super().__init__()
        kind = methods.get(method)
        check_option(quality, "quality", QUALITIES)
        for key in filter_params:
            check_option(key, f"filter parameter for method={method!r}", kind.params)
        if input_scale is not None:
            check_positive(input_scale, "input_scale")
        check_budget(max_memory_mb, method, methods.names(tiles=True))
        kind.check_params(filter_params)
        self.method, self.quality, self.hdr, self.input_scale = method, quality, hdr, input_scale
        self.filter_direct, self.sanitize, self.max_memory_mb = filter_direct, sanitize, max_memory_mb
        self.settings, self.filter_params = check_settings(settings), dict(filter_params)
        self._method = kind(quality, settings, self.filter_params, input_scale, max_memory_mb)
        self._workspace: dict = {}  # the CPU kernels' buffers, kept between calls

    @classmethod
    def from_config(cls, config: Mapping[str, Any] | str) -> Denoiser:
        """Build from ``{type: method, ...}`` (any method registered in :mod:`torchgi.methods` when
        this runs, and the constructor's other arguments) or a preset YAML path holding one."""
        method, kwargs = _config(config)
        try:
            return cls(method, **kwargs)
        except TypeError as exc:
            raise ConfigError(f"denoiser {method!r}: {exc}") from exc

    def deploy(self, *, spp: float | None = None, sigma_position: float | None = None, emission: bool = True,
               frame: GBuffer | None = None, variance: bool | None = None) -> DeployedDenoiser:
        """Fix this Denoiser's parameters for ``spp`` samples per pixel (and, for "atrous", σ_x in
        scene units squared, required unless given at construction) and return the exportable module.

        Args:
            spp: the sample count the parameters are chosen for (default 1; not with ``frame``).
            sigma_position: À-Trous' σ_x when not given at construction.
            emission: the graph takes an emission layer (as the eager call given one); False: it
                takes none and finds the light sources from the colour, as the eager call without one.
            frame: a representative :class:`GBuffer`: the choices the eager call makes from its
                data are made on it and fixed - the sample count its noise corresponds to (the
                radius or À-Trous levels follow) and, for "guided", the half or full resolution.
            variance: the graph takes the render's ``variance`` and backs off toward the input as
                the eager call given one does (:func:`torchgi.light.back_off`, for the sample count
                ``frame.spp`` or ``spp``, at least 2). None: as the eager call would on ``frame``
                (True where it has a variance from 2 samples or more), False without a frame.

        Example:
            >>> Denoiser("guided").deploy(spp=4)
            DeployedDenoiser(method='guided', radius=2, eps=0.0001)
        """
        if frame is not None and spp is not None:
            raise ValueError("spp, frame: give one of them (frame fixes the sample count from its data)")
        if spp is not None:
            check_positive(spp, "spp")
        samples = spp  # the render's sample count (the back-off's), not the one its noise corresponds to
        if frame is not None:
            spp = noise_spp(frame, light.surface_mask(frame.hit, frame.albedo), self.settings)
            samples = None if frame.spp is None else mean_spp(frame.spp)  # one count (adaptive renders: their mean)
        if variance is None:
            variance = (frame is not None and frame.variance is not None and samples is not None and samples >= 2
                        and self.settings.pipeline.back_off)
        if variance and (samples is None or samples < 2):
            raise ValueError(f"variance: the back-off needs 2 samples per pixel or more; got {samples} (spp or frame.spp)")
        if not self._method.exportable:
            raise ValueError(f"method: only {', '.join(methods.names(exportable=True))} deploy to ONNX, not "
                             f"{self.method!r}")
        params, net = self._method.deploy(1.0 if spp is None else float(spp), samples, frame, variance, sigma_position)
        count = samples if samples is not None or frame is not None else 1.0  # recorded in the graph
        return deployed(self.method, params, net, emission, variance, self._method.firefly(self.settings), count)

    def extra_repr(self) -> str:
        params = "".join(f", {k}={v!r}" for k, v in self.filter_params.items())
        memory = "" if self.max_memory_mb == "auto" else f", max_memory_mb={self.max_memory_mb!r}"
        settings = "" if self.settings == DEFAULTS else f", settings={self.settings.changes()!r}"
        return (f"method={self.method!r}, quality={self.quality!r}, hdr={self.hdr}, input_scale={self.input_scale}, "
                f"filter_direct={self.filter_direct}, sanitize={self.sanitize}{memory}{settings}{params}")

    def forward(self, gb: GBuffer | None = None, **tensors: torch.Tensor | float) -> torch.Tensor:
        count = None if isinstance(tensors.get("spp"), torch.Tensor) else tensors.pop("spp", None)
        gb = GBuffer.from_inputs(gb, tensors, by="Denoiser")
        out = self._denoise(gb if count is None else _with_samples(gb, count, "Denoiser"))
        _warn_of_the_colour(gb)  # the caller's render (a TemporalDenoiser's own calls carry reprojected history)
        return out

    def _denoise(self, gb: GBuffer) -> torch.Tensor:
        return self._run(gb)[0]

    def _run(self, gb: GBuffer, weights: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The shared pipeline: the radiance and, with ``weights``, what a learned method chose."""
        m = self._method
        if gb.color is None:
            raise ShapeError("color: required (or direct and indirect)")
        if not m.filters:
            return gb.color, None
        require_guides(gb, self.method, m.needs)
        _warn_if_colour_normals(gb.normal)
        if self.sanitize:
            names = [n for n in GBuffer.fields() if n not in ("spp", "hit") and getattr(gb, n) is not None]
            gb = gb.replace(**dict(zip(names, finite_or_sanitized_all({n: getattr(gb, n) for n in names}, True),
                                       strict=True)))
        split = gb.indirect is not None and gb.direct is not None and not self.filter_direct
        own = m.checks_own(split)
        for name in ("color", "emission", "direct", "albedo", "normal", "position", "depth", "variance"):
            if getattr(gb, name) is not None and name not in own:
                check_finite(getattr(gb, name), name)  # named here, not as the filter's input
        if _noise_free(gb) or gb.color.numel() == 0:  # nothing to filter (an empty batch included)
            return (gb.color if self.hdr else gb.color.clamp(0, 1)), None
        surface = light.surface_mask(gb.hit, gb.albedo)
        out, chosen = m.run(gb, gb.direct if split else None, surface, self._workspace, weights)  # split: direct as sampled
        return (out if self.hdr else out.clamp(0, 1)), chosen

    def supersample(self, gb: GBuffer, samples: EyeSamples) -> torch.Tensor:
        """Supersampling with guide rays (Bauszat et al. 2011 §3.2, :mod:`torchgi.supersample`):
        the guide rays' light filtered with this method and handed to every further eye ray from
        its most similar guide ray; each keeps its own emission (and, with
        ``filter_direct=False``, its own direct light). The pixel is the mean of its samples.

        Args:
            gb: the guide rays, as from :func:`torchgi.render.render_guide_rays`: ``emission``,
                ``direct``, ``indirect``, ``albedo``, ``normal``, ``depth`` (and ``position``
                for "atrous"), ``hit`` optional.
            samples: the further eye rays.

        Returns:
            ``(B, 3, H, W)`` radiance, dtype and device of ``gb``.

        Example:
            >>> from torchgi.render import render_guide_rays, scenes
            >>> gb, eye = render_guide_rays(scenes.cornell(16), spp=4)
            >>> Denoiser("guided").supersample(gb, eye).shape
            torch.Size([1, 3, 16, 16])
        """
        return self._method.supersample(gb, samples, self.filter_direct, self.hdr, self._workspace)

    def weights(self, gb: GBuffer) -> torch.Tensor:
        """A learned method's per-pixel weights of its candidates for ``gb`` (what it chose). The
        blend: ``(B, K, H, W)`` summing to 1 per pixel (radii ``BlendNet.candidate_radii()``). The
        pyramid: ``(B, K + 4, ⌈H/4⌉, ⌈W/4⌉)``, the weights of ``PyramidNet.candidates`` (summing
        to 1) then the gains in [0, 1] of the residual's four bands.

        Example:
            >>> from torchgi.render import render, scenes
            >>> Denoiser("blend").weights(render(scenes.cornell(16), spp=1)).shape
            torch.Size([1, 9, 16, 16])
        """
        if not self._method.learned:
            learned = " and ".join(repr(n) for n in methods.names(learned=True))
            raise ValueError(f"weights: only methods {learned} mix candidates, not {self.method!r}")
        chosen = self._run(gb, weights=True)[1]
        if chosen is None:
            raise ValueError("gb: its colour is noise-free or empty, so nothing was filtered")
        return chosen


def _config(config: Mapping[str, Any] | str) -> tuple[str, dict[str, Any]]:
    """A Denoiser config (a mapping or a YAML path): its registered method and other arguments."""
    if isinstance(config, str):
        import yaml

        with open(config, encoding="utf-8") as fh:
            config = yaml.safe_load(fh)
    if not isinstance(config, Mapping) or "type" not in config:
        raise ConfigError(f"denoiser config: expected a mapping with a 'type' key, got {config!r}")
    methods.get(config["type"])  # an unknown name: the registry's names at this call
    return config["type"], {k: v for k, v in config.items() if k != "type"}
