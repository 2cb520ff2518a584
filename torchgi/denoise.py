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
* Method "guided" with that variance from ``GUIDED.choose_from_spp`` (4) samples on average, at
  full resolution and no ``radius`` given: the filter runs at half and at twice its radius and
  each pixel takes a blend of the two weighted by their estimated error
  (:func:`torchgi.light.choose`) before the back-off: narrow at edges and glossy highlights, wide
  on smooth light (about 2x the filter's time).

Parameters that depend on the noise level are chosen from the measured variance when every
surface pixel has one (>= 2 samples), else from ``spp``: the guided filter's and the bilateral's
radius and À-Trous' iteration count grow with the noise; ``quality`` scales them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch

from torchgi import backends, light
from torchgi.buffers import GBuffer, _mean_spp, _noise_free, _require_guides, _warn_if_colour_normals, _with_samples
from torchgi.core.check import check_finite, check_nonnegative, check_option, check_positive, finite_or_sanitized_all
from torchgi.core.dtypes import compute_dtype
from torchgi.core.errors import ShapeError
from torchgi.core.registry import Registry
from torchgi.core.tiles import auto_budget, check_budget, guided_bytes, tile_side, tiled, tiles
from torchgi.deployed import EXPORTABLE, FIREFLY, UNCLAMPED, DeployedDenoiser, DeployedDenoiserWithoutEmission, deployed
from torchgi.filters import atrous, box, cross_bilateral, guide_from, guided
from torchgi.filters.blend import blend, default_net
from torchgi.filters.guided import depth_scales
from torchgi.filters.pyramid import ALIGN, FEATURE_SCALE, REACH, pyramid, pyramid_stats
from torchgi.filters.pyramid import default_net as pyramid_net
from torchgi.geometry import sigma_position_rule
from torchgi.settings import ATROUS, BILATERAL, GUIDED, PIPELINE
from torchgi.supersample import EyeSamples

__all__ = ["DENOISERS", "EXPORTABLE", "METHODS", "QUALITIES", "Denoiser", "DeployedDenoiser", "DeployedDenoiserWithoutEmission"]

# bytes per pixel and image that a tile of the pyramid's pipeline holds (measured: docs/pyramid.md)
_PYRAMID_BYTES = 480
METHODS = ("pyramid", "blend", "guided", "atrous", "bilateral", "none")
QUALITIES = ("fast", "balanced", "high")
# the guide layers a method cannot run without, beyond albedo and normal (its call refuses an input without them)
NEEDS = {"pyramid": ("depth",), "blend": ("depth",), "atrous": ("position",)}


class Denoiser(torch.nn.Module):
    """Denoise a path-traced image from its noise-free guides.

    Args:
        method: "guided" (Bauszat et al. 2011), "pyramid" (a small network at 1/4 resolution
            mixes guided-filter models from a pyramid of scales per pixel,
            :mod:`torchgi.filters.pyramid`), "blend" (a learned per-pixel blend of guided
            filters, :mod:`torchgi.filters.blend`: more accurate, about 7x slower; both learned
            methods expect ``depth`` for the guide they were trained with), "atrous" (Dammertz et al. 2010),
            "bilateral" (brute-force cross-bilateral) or "none" (the noisy image, assembled).
        quality: "fast", "balanced" or "high" (radius / iterations / window scale).
        hdr: the colour is HDR (True) or in [0, 1] (False: the output is clamped to [0, 1]).
        input_scale: multiplies the demodulated signal before colour-weighted filtering (À-Trous,
            bilateral) and divides it after; None = 1 / its mean on geometry.
        filter_direct: with a direct/indirect split, filter direct light too (True: it is noisy,
            as with area lights and skies at low spp) or keep it as sampled (False: the papers'
            setting, noise-free direct light).
        sanitize: NaN/Inf in an input raises :class:`~torchgi.core.NonFiniteError` naming it
            (False) or is replaced by 0 with a warning (True).
        max_memory_mb: the most memory (MB) a call may add beyond its inputs, the output
            included (OIDN's ``maxMemoryMB``): methods "guided" and "pyramid" then run in tiles
            whose overlap covers their footprint, the result that of one pass (to rounding); None:
            never in tiles; "auto": in tiles where the untiled call is estimated above 2 GB (the
            pyramid from about 4.4 Mpx per image, "guided" from 12 Mpx), within twice the inputs'
            memory (``PIPELINE.auto_*``; docs/pipeline.md, docs/pyramid.md: the time it costs).
        **filter_params: override the automatic choices: ``radius``, ``eps``, ``subsample`` (guided);
            ``iterations``, ``sigma_normal``, ``sigma_position``, ``sigma_color`` (À-Trous);
            ``radius``, ``sigma_space``, ``sigma_color`` (bilateral).

    Call with a :class:`~torchgi.GBuffer` or with named ``(B, C, H, W)`` tensors: ``color``
    (or ``direct`` + ``indirect``), ``albedo``, ``normal`` (world space, [-1, 1]), and when
    available ``position``, ``depth``, ``emission``, ``variance``, ``spp``, ``hit``; "pyramid" and
    "blend" need ``depth``, "atrous" ``position`` (:data:`NEEDS`: refused by name without them).
    ``spp`` may also be a number, the sample count of a render that recorded none (an int or
    float >= 1; ``den(gb, spp=4)`` is ``den(gb.replace(spp=torch.full((B, 1, H, W), 4)))``);
    without one a GBuffer without ``spp`` is taken as 1 sample per pixel. Returns the
    ``(B, 3, H, W)`` denoised radiance in the input dtype, on the input device.

    Example:
        >>> from torchgi.render import render, scenes
        >>> gb = render(scenes.cornell(24), spp=1, bounces=1)
        >>> Denoiser("guided")(gb).shape
        torch.Size([1, 3, 24, 24])
    """

    def __init__(
        self,
        method: str = "guided",
        quality: str = "balanced",
        *,
        hdr: bool = True,
        input_scale: float | None = None,
        filter_direct: bool = True,
        sanitize: bool = False,
        max_memory_mb: float | str | None = "auto",
        **filter_params: Any,
    ) -> None:
        super().__init__()
        check_option(method, "method", METHODS)
        check_option(quality, "quality", QUALITIES)
        known = {
            "pyramid": (),
            "blend": (),
            "guided": ("radius", "eps", "subsample"),
            "atrous": ("iterations", "sigma_normal", "sigma_position", "sigma_color"),
            "bilateral": ("radius", "sigma_space", "sigma_color"),
            "none": (),
        }[method]
        for key in filter_params:
            check_option(key, f"filter parameter for method={method!r}", known)
        if input_scale is not None:
            check_positive(input_scale, "input_scale")
        check_budget(max_memory_mb, method, ("guided", "pyramid"))
        eps = filter_params.get("eps", GUIDED.eps)
        if method == "guided":
            check_nonnegative(eps, "eps")
        self.method, self.quality, self.hdr, self.input_scale = method, quality, hdr, input_scale
        self.filter_direct, self.sanitize, self.max_memory_mb = filter_direct, sanitize, max_memory_mb
        self.filter_params = dict(filter_params)
        self._workspace: dict = {}  # the guided filter's (the pyramid's fits') CPU buffers, kept between calls
        self._capture: dict | None = None  # set by weights()

    @classmethod
    def from_config(cls, config: Mapping[str, Any] | str) -> Denoiser:
        """Build from ``{type: method, quality: ..., ...}`` or a preset YAML path
        (``configs/denoise/*.yaml``) through :data:`DENOISERS`."""
        if isinstance(config, str):
            import yaml

            with open(config, encoding="utf-8") as fh:
                config = yaml.safe_load(fh)
        return DENOISERS.build(config)

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
            surface = light.surface_mask(frame.hit, frame.albedo)
            spp = self._spp(frame, surface)
            samples = None if frame.spp is None else _mean_spp(frame.spp)  # one count (adaptive renders: their mean)
        if variance is None:
            variance = frame is not None and frame.variance is not None and samples is not None and samples >= 2
        if variance and (samples is None or samples < 2):
            raise ValueError(f"variance: the back-off needs 2 samples per pixel or more; got {samples} (spp or frame.spp)")
        spp = 1.0 if spp is None else float(spp)
        p = self.filter_params
        extra = {"samples": float(samples)} if variance else {}
        if self.method == "blend":
            return deployed("blend", {"spp": max(spp, 1.0), **extra}, default_net(), emission, variance)
        if self.method == "pyramid":
            return deployed("pyramid", {"spp": max(spp, 1.0), **extra}, pyramid_net(), emission, variance)
        if self.method == "guided":
            params = {"radius": self._radius(spp, GUIDED.radius), "eps": p.get("eps", GUIDED.eps), **extra}
            subsample = p.get("subsample", 1)
            if frame is not None:
                spec, _ = self._guide_spec(frame)
                subsample = self._subsample(spec, *frame.color.shape[-2:], frame.spp)
            if subsample > 1:
                params["subsample"] = subsample
            elif variance and "radius" not in p and samples >= GUIDED.choose_from_spp:  # as the eager _radii
                params["radii"] = _choice_radii(params["radius"])
        elif self.method == "atrous":
            sigma_x = p.get("sigma_position", sigma_position)
            if sigma_x is None:
                raise ValueError("sigma_position: an exported À-Trous needs a fixed σ_x (scene units squared)")
            params = {
                "iterations": self._iterations(spp),
                "sigma_normal": p.get("sigma_normal", ATROUS.sigma_normal), "sigma_position": sigma_x,
                "sigma_color": p.get("sigma_color", ATROUS.deployed_sigma_color), **extra,
            }
        else:
            raise ValueError(f"method: only {', '.join(EXPORTABLE)} deploy to ONNX, not {self.method!r}")
        return deployed(self.method, params, None, emission, variance)

    def extra_repr(self) -> str:
        params = "".join(f", {k}={v!r}" for k, v in self.filter_params.items())
        memory = "" if self.max_memory_mb == "auto" else f", max_memory_mb={self.max_memory_mb!r}"
        return (f"method={self.method!r}, quality={self.quality!r}, hdr={self.hdr}, input_scale={self.input_scale}, "
                f"filter_direct={self.filter_direct}, sanitize={self.sanitize}{memory}{params}")

    # ------------------------------------------------------------------------------ call
    def forward(self, gb: GBuffer | None = None, **tensors: torch.Tensor | float) -> torch.Tensor:
        count = None if isinstance(tensors.get("spp"), torch.Tensor) else tensors.pop("spp", None)
        gb = GBuffer.from_inputs(gb, tensors, by="Denoiser")
        return self._denoise(gb if count is None else _with_samples(gb, count, "Denoiser"))

    def _denoise(self, gb: GBuffer) -> torch.Tensor:
        if gb.color is None:
            raise ShapeError("color: required (or direct and indirect)")
        if self.method == "none":
            return gb.color
        if gb.albedo is None or gb.normal is None:
            raise ShapeError("albedo and normal: required by every method but 'none'")
        _require_guides(gb, self.method, NEEDS.get(self.method, ()))
        _warn_if_colour_normals(gb.normal)
        if self.sanitize:
            names = [n for n in GBuffer.fields() if n not in ("spp", "hit") and getattr(gb, n) is not None]
            gb = gb.replace(**dict(zip(names, finite_or_sanitized_all({n: getattr(gb, n) for n in names}, True),
                                       strict=True)))
        split = gb.indirect is not None and gb.direct is not None and not self.filter_direct
        # the fused guided pipeline checks what it reads itself (normal, depth: its guide statistics)
        read = ("color", "emission", "albedo", "normal", "depth") + (("direct",) if split else ())
        for name in ("color", "emission", "direct", "albedo", "normal", "position", "depth", "variance"):
            if getattr(gb, name) is not None and not (self.method == "guided" and name in read):
                check_finite(getattr(gb, name), name)  # named here, not as the filter's input
        if _noise_free(gb) or gb.color.numel() == 0:  # nothing to filter (an empty batch included)
            return gb.color if self.hdr else gb.color.clamp(0, 1)
        surface = light.surface_mask(gb.hit, gb.albedo)
        kept = gb.direct if split else None  # the papers' split: direct light as sampled
        if self.method == "guided":
            out = self._guided_pipeline(gb, kept, surface)
        elif self.method == "pyramid":
            out = self._pyramid_pipeline(gb, kept, surface)
        else:
            level = light.level(gb.color, gb.emission, kept, gb.albedo, surface)
            out = light.restore(gb.color, gb.emission, kept, gb.albedo, surface,
                                lambda x, *raw: self._filter(x, gb, surface, *raw), FIREFLY[self.method], box, level,
                                unclamped=self.method in UNCLAMPED)
            out = _back_off(out, gb, surface, level)
        return out if self.hdr else out.clamp(0, 1)

    def _guided_pipeline(self, gb: GBuffer, kept: torch.Tensor | None, surface: torch.Tensor) -> torch.Tensor:
        """Method "guided": the whole pipeline as one :class:`~torchgi.backends.RestoreOp` (fused
        in the compiled back ends)."""
        spec, guide_means = self._guide_spec(gb)
        H, W = gb.color.shape[-2:]
        level = light.level(gb.color, gb.emission, kept, gb.albedo, surface)
        radius, s = self._radius(self._spp(gb, surface), GUIDED.radius), self._subsample(spec, H, W, gb.spp)
        radii = self._radii(radius, s, gb)

        def op(rows: slice = slice(None), cols: slice = slice(None), workspace: dict | None = None) -> torch.Tensor:
            def cut(t: torch.Tensor | None) -> torch.Tensor | None:
                return None if t is None else t[..., rows, cols]

            tile = backends.GuideSpec(cut(spec.normal), cut(spec.depth), spec.channels, spec.scale, spec.offset)
            outs = [backends.run(backends.RestoreOp(cut(gb.color), cut(gb.emission), cut(kept), cut(gb.albedo),
                                                    cut(gb.hit), tile, level, r,
                                                    self.filter_params.get("eps", GUIDED.eps), s, GUIDED.firefly,
                                                    workspace, centres[0], centres[1]))
                    for r in radii]
            return _back_off(outs, gb, surface, level, rows, cols, radii)

        # light and guide centred by constants of each image, so that tiles compute the untiled sums
        centres = (light.centre(gb.color, gb.emission, kept, gb.albedo, surface, GUIDED.firefly * level), guide_means)

        per_pixel = guided_bytes(gb.color.shape[0], kept is not None, gb.variance is not None, len(radii))
        budget = self._budget(gb, per_pixel)
        if budget is None:
            return op(workspace=self._workspace)
        return tiled(op, gb.color, budget, _footprint(max(radii), s, len(radii) > 1), s, per_pixel)

    def _pyramid_pipeline(self, gb: GBuffer, kept: torch.Tensor | None, surface: torch.Tensor) -> torch.Tensor:
        """Method "pyramid": the steps of :func:`torchgi.light.restore` (``backends.LightInOp`` /
        ``LightOutOp``) around :func:`pyramid`, then the back-off; with ``max_memory_mb`` in tiles that overlap by the pipeline's reach and the
        pyramid's (:data:`torchgi.filters.pyramid.REACH`), after a first pass over tiles that
        sums the image statistics the pyramid centres and scales by (pixel-weighted
        :func:`~torchgi.filters.pyramid.pyramid_stats` of each tile's core)."""
        level = light.level(gb.color, gb.emission, kept, gb.albedo, surface)
        spp = max(self._spp(gb, surface), 1.0)  # noisier renders than 1 spp are fed as 1 spp
        depth_scale = None if gb.depth is None else depth_scales(gb.depth)  # its guide as in training

        def op(rows: slice = slice(None), cols: slice = slice(None), workspace: dict | None = None,
               stats: dict[str, torch.Tensor] | None = None, sums: list | None = None) -> torch.Tensor | None:
            """The pipeline on ``gb[..., rows, cols]``; with ``sums`` only the statistics of the core
            ``sums[0] = (rows, cols)`` (relative to the tile), added into ``sums[1]``."""
            c, e, k, a, hit, n, d = (None if t is None else t[..., rows, cols]
                                     for t in (gb.color, gb.emission, kept, gb.albedo, gb.hit, gb.normal, gb.depth))
            guide = guide_from(n, d, depth_scale=depth_scale, workspace=workspace)
            # light.restore's steps around the filter, fused in the C back end
            x, raw, lights = backends.run(backends.LightInOp(c, e, k, a, hit, level, FIREFLY["pyramid"], workspace))
            if sums is not None:  # the first pass: only the core's statistics
                core = (..., *sums[0])
                ct = compute_dtype(x.dtype)
                part = pyramid_stats(x[core].to(ct), guide[core].to(ct))
                weight = x[core][0, 0].numel() / (gb.color.shape[-2] * gb.color.shape[-1])
                for key, v in part.items():
                    sums[1][key] = sums[1].get(key, 0) + weight * v
                return None
            out, w = pyramid(x, guide, spp=spp, raw=raw, return_weights=True, workspace=workspace, stats=stats)
            if self._capture is not None:
                self._capture.setdefault("tiles", []).append(w)
            out = backends.run(backends.LightOutOp(out, c, e, k, a, hit, lights, inplace=True))
            return _back_off(out, gb, surface, level, rows, cols)

        per_pixel = _PYRAMID_BYTES * gb.color.shape[0] * torch.finfo(compute_dtype(gb.color.dtype)).bits / 32
        budget = self._budget(gb, per_pixel)
        if budget is None:
            out = op(workspace=self._workspace)
            if self._capture is not None:
                self._capture["weights"] = self._capture.pop("tiles")[0]
            return out
        reach = PIPELINE.firefly_radius + 2 * (PIPELINE.light_square // 2)  # the light's before the filter
        halo = -(-(reach + REACH + PIPELINE.backoff_radius) // ALIGN) * ALIGN
        side = tile_side(gb.color, budget, per_pixel, halo, ALIGN)
        stats: dict[str, torch.Tensor] = {}
        for rows, cols, core_rows, core_cols, _, _ in tiles(*gb.color.shape[-2:], side, reach, ALIGN):
            op(rows, cols, sums=[(core_rows, core_cols), stats])
        out = torch.empty_like(gb.color)
        placed = []
        for rows, cols, core_rows, core_cols, out_rows, out_cols in tiles(*gb.color.shape[-2:], side, halo, ALIGN):
            out[..., out_rows, out_cols] = op(rows, cols, stats=stats)[..., core_rows, core_cols]
            placed.append((core_rows, core_cols, out_rows, out_cols))
        if self._capture is not None:  # the weights at 1/4 resolution, stitched as the output
            parts = self._capture.pop("tiles")
            B, K = parts[0].shape[:2]
            w = parts[0].new_empty(B, K, *(-(-n // FEATURE_SCALE) for n in gb.color.shape[-2:]))
            q = lambda sl: slice(sl.start // FEATURE_SCALE, -(-sl.stop // FEATURE_SCALE))
            for part, (core_rows, core_cols, out_rows, out_cols) in zip(parts, placed, strict=True):
                w[..., q(out_rows), q(out_cols)] = part[..., q(core_rows), q(core_cols)]
            self._capture["weights"] = w
        return out

    def _budget(self, gb: GBuffer, per_pixel: float) -> float | None:
        """The budget (MB) of this call's tiles of ``per_pixel`` bytes per pixel; None: untiled."""
        inputs = sum(t.numel() * t.element_size() for n in GBuffer.fields() if (t := getattr(gb, n)) is not None)
        return self.max_memory_mb if self.max_memory_mb != "auto" else auto_budget(
            gb.color, inputs, per_pixel, PIPELINE.auto_tiles_from_mb, PIPELINE.auto_budget, PIPELINE.auto_floor_mb)

    def _radii(self, radius: int, s: int, gb: GBuffer) -> tuple[int, ...]:
        """The guided filter's radii: ``(radius,)``, or ``(radius // 2 (>= 1), 2 radius)``
        for :func:`torchgi.light.choose` where the radius is not given, the filter runs at full
        resolution and every pixel has a variance from 2 samples or more, ``GUIDED.choose_from_spp``
        on average."""
        if ("radius" in self.filter_params or s > 1 or gb.variance is None or gb.spp is None
                or float(gb.spp.min()) < 2 or _mean_spp(gb.spp) < GUIDED.choose_from_spp):
            return (radius,)
        return _choice_radii(radius)

    def _guide_spec(self, gb: GBuffer) -> tuple[backends.GuideSpec, torch.Tensor]:
        """:func:`~torchgi.filters.guide_from_gbuffer`'s guide (normal to [0, 1], depth over the
        largest depth on hit pixels, channels constant over the batch dropped) as planes and
        factors, and each image's guide means ``(B, n)`` float64 (``RestoreOp.centre_guide``), from
        one statistics walk; raises naming ``normal`` or ``depth`` if it holds NaN/Inf."""
        st = backends.run(backends.GuideStatsOp(gb.normal, gb.depth, gb.hit))
        for name, col in (("normal", 9), ("depth", 10)):
            if bool(st[:, col].any()):
                check_finite(getattr(gb, name), name)
        depth_scale = float(st[:, 8].max())
        depth_scale = depth_scale if depth_scale > 0 else 1.0  # (-inf: no hit pixel)
        scale = torch.tensor([0.5, 0.5, 0.5, 1.0 / depth_scale], dtype=gb.normal.dtype)
        offset = torch.tensor([0.5, 0.5, 0.5, 0.0], dtype=gb.normal.dtype)
        lo = st[:, :4].amin(0).to(gb.normal.dtype) * scale + offset  # the guide's extremes, rounded as its values
        hi = st[:, 4:8].amax(0).to(gb.normal.dtype) * scale + offset
        varying = [c for c in range(3 if gb.depth is None else 4) if bool(hi[c] > lo[c])] or [0]
        spec = backends.GuideSpec(gb.normal, gb.depth, tuple(varying), tuple(float(scale[c]) for c in varying),
                                  tuple(float(offset[c]) for c in varying))
        H, W = gb.normal.shape[-2:]
        means = st[:, 11:][:, varying] / max(H * W, 1) * scale.double()[varying] + offset.double()[varying]
        return spec, means

    def supersample(self, gb: GBuffer, samples: EyeSamples) -> torch.Tensor:
        """Supersampling with guide rays (Bauszat et al. 2011 §3.2, :mod:`torchgi.supersample`).

        The guide rays' light is demodulated, filtered with this Denoiser's method (fireflies
        clamped, as in a call) and handed to every further eye ray from its most similar guide
        ray; every eye ray keeps its own emission. With ``filter_direct=False`` (the papers'
        setting: noise-free direct light) only indirect light is filtered and each eye ray keeps
        its own direct light; with ``filter_direct=True`` the guide rays' direct light is
        filtered with it. The pixel is the mean of its samples.

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
        from torchgi.supersample import composite, distribute

        for name in ("emission", "direct", "indirect", "albedo", "normal", "depth"):
            if getattr(gb, name) is None:
                raise ShapeError(f"gb.{name}: required by supersample (render with render_guide_rays)")
        _require_guides(gb, self.method, NEEDS.get(self.method, ()))
        surface = light.surface_mask(gb.hit, gb.albedo)
        albedo = light.demodulator(gb.albedo, surface)
        x = (gb.indirect + gb.direct if self.filter_direct else gb.indirect) / albedo
        if self.method == "none":
            lit = x
        else:
            lit = light.filter_light(x, light.median_level(light.every4(x), light.every4(surface)),
                                     lambda v, *raw: self._filter(v, gb, surface, *raw), FIREFLY[self.method], box,
                                     self.method in UNCLAMPED)
        lit = torch.where(surface, lit, 0.0)  # no reflected light without a surface
        own, sample_own = gb.emission, samples.emission
        if not self.filter_direct:
            own, sample_own = own + gb.direct, sample_own + samples.direct
        out = composite(own, gb.albedo, lit, sample_own, samples.albedo,
                        distribute(lit, gb.normal, gb.depth, samples))
        return out if self.hdr else out.clamp(0, 1)

    def weights(self, gb: GBuffer) -> torch.Tensor:
        """Methods "blend" and "pyramid": the per-pixel weights it gives its candidates for ``gb``
        (what it chose). The blend: ``(B, K, H, W)`` summing to 1 per pixel, the candidates' radii
        in px ``BlendNet.candidate_radii()`` of :func:`torchgi.filters.blend.default_net`. The
        pyramid: ``(B, K + 4, ⌈H/4⌉, ⌈W/4⌉)``, the weights of ``PyramidNet.candidates`` of
        :func:`torchgi.filters.pyramid.default_net` (summing to 1) then the gains in [0, 1] of the
        residual's four bands.

        Example:
            >>> from torchgi.render import render, scenes
            >>> Denoiser("blend").weights(render(scenes.cornell(16), spp=1)).shape
            torch.Size([1, 9, 16, 16])
        """
        if self.method not in ("blend", "pyramid"):
            raise ValueError(f"weights: only methods 'blend' and 'pyramid' mix candidates, not {self.method!r}")
        self._capture = {}
        try:
            self._denoise(gb)
            captured = self._capture
        finally:
            self._capture = None
        if "weights" not in captured:
            raise ValueError("gb: its colour is noise-free or empty, so nothing was filtered")
        return captured["weights"]

    def _radius(self, spp: float, base: int) -> int:
        """Filter radius: given, or ``base · quality / sqrt(spp)`` (at least 2) px."""
        scale = PIPELINE.quality_scale(self.quality)
        return self.filter_params.get("radius", max(PIPELINE.min_radius, round(scale * base / math.sqrt(spp))))

    def _iterations(self, spp: float) -> int:
        """À-Trous levels: given, or enough for a ``16 · quality / sqrt(spp)`` px footprint (2..8)."""
        q = PIPELINE.quality_scale(self.quality)
        levels = round(math.log2(ATROUS.footprint * q / math.sqrt(spp)) + 2)
        return self.filter_params.get("iterations", max(ATROUS.min_iterations, min(ATROUS.max_iterations, levels)))

    def _spp(self, gb: GBuffer, surface: torch.Tensor) -> float:
        """The sample count the noise corresponds to. With a measured variance (>= 2 samples on
        every surface pixel): ``PIPELINE.rel_var_1spp`` over the mean relative variance of the colour on
        surfaces (>= 1/4), so noisier images get wider filters; otherwise the mean ``spp`` (>= 1)."""
        if gb.spp is None:
            return 1.0
        spp = max(_mean_spp(gb.spp), 1.0)
        if gb.variance is None or gb.color is None:
            return spp
        if int(gb.spp.min()) < 2 and bool(((gb.spp < 2) & surface).any()):
            return spp  # some surface pixel has no variance estimate
        count = int(surface.sum()) * gb.color.shape[1]
        if count == 0:
            return spp
        # (masks by where, not by indexing: no gathered copies)
        rel = float(torch.where(surface, gb.variance / (gb.color.square() + 1e-4), 0.0).sum()) / count
        return max(PIPELINE.rel_var_1spp / max(rel, 1e-12), 0.25)

    def _subsample(self, spec: backends.GuideSpec, H: int, W: int, spp: torch.Tensor | None) -> int:
        """Guided filter's subsampling: given, or 2 where half resolution is worth its bias, else 1.
        Half resolution needs >= 256 px on the short side, fewer than ``GUIDED.full_from_spp``
        samples per pixel on average (``spp``; None: 1), quality "fast"/"balanced", and a guide
        that is smooth at the pixel scale: fewer than 10 % of (every other row's) horizontal
        neighbours differing by more than 0.1 in the guide (``settings.GUIDED``; the measurements
        behind it in docs/calibration.md)."""
        if "subsample" in self.filter_params:
            return self.filter_params["subsample"]
        mean_spp = 1.0 if spp is None else _mean_spp(spp)
        if min(H, W) < GUIDED.subsample_from or self.quality == "high" or mean_spp >= GUIDED.full_from_spp:
            return 1
        return 2 if backends.run(backends.EdgeShareOp(spec, GUIDED.edge)) < GUIDED.edge_share else 1

    def _filter(self, x: torch.Tensor, gb: GBuffer, surface: torch.Tensor, raw: torch.Tensor | None = None,
                ) -> torch.Tensor:
        """The method's filter of the clamped light ``x`` (``raw``: before the clamp; the pyramid's)."""
        p = self.filter_params
        spp = self._spp(gb, surface)
        if self.method == "pyramid":  # its guide as in training; noisier renders than 1 spp fed as 1 spp
            out, w = pyramid(x, guide_from(gb.normal, gb.depth, depth_scale="image"), spp=max(spp, 1.0), raw=raw,
                             return_weights=True, workspace=self._workspace)
            if self._capture is not None:
                self._capture["weights"] = w
            return out
        if self.method == "blend":
            # depth over each image's largest, as in training and in the exported form
            # (its network knows 1 spp and more: noisier renders than 1 spp are fed to it as 1 spp)
            out, w = blend(x, guide_from(gb.normal, gb.depth, depth_scale="image"), spp=max(spp, 1.0),
                           return_weights=True)
            if self._capture is not None:
                self._capture["weights"] = w
            return out
        if self.method == "guided":  # the workspace of the CPU path is kept between calls
            spec = self._guide_spec(gb)[0]
            return guided(x, spec.build(), radius=self._radius(spp, GUIDED.radius), eps=p.get("eps", GUIDED.eps),
                          subsample=self._subsample(spec, *x.shape[-2:], gb.spp), workspace=self._workspace)
        scale = self.input_scale
        if scale is None:
            mean = float(x[surface.expand_as(x)].mean()) if bool(surface.any()) else 0.0
            scale = 1.0 / mean if mean > 0 else 1.0
        if self.method == "atrous":
            iterations = self._iterations(spp)
            sigma_x = p.get("sigma_position")
            if sigma_x is None and gb.position is not None:
                sigma_x = sigma_position_rule(gb.position, surface, ATROUS.sigma_position_footprints)
            out = atrous(x * scale, gb.normal, gb.position, iterations=iterations,
                         sigma_normal=p.get("sigma_normal", ATROUS.sigma_normal), sigma_position=sigma_x,
                         sigma_color=p.get("sigma_color"))
            return out / scale
        radius = self._radius(spp, BILATERAL.radius)
        guides = [gb.normal] + ([gb.depth / gb.depth.amax().clamp_min(1e-12)] if gb.depth is not None else [])
        out = cross_bilateral(x * scale, guides, radius=radius, sigma_space=p.get("sigma_space", radius / 2),
                              sigma_color=p.get("sigma_color", BILATERAL.sigma_color),
                              sigma_guides=[BILATERAL.sigma_guide] * len(guides))
        return out / scale


def _choice_radii(radius: int) -> tuple[int, int]:
    """The radii :func:`torchgi.light.choose` blends in place of ``radius``: half (>= 1) and twice it."""
    return (max(1, radius // 2), 2 * radius)


def _back_off(out: torch.Tensor | list[torch.Tensor], gb: GBuffer, surface: torch.Tensor, level: torch.Tensor,
              rows: slice = slice(None), cols: slice = slice(None), radii: tuple[int, ...] = ()) -> torch.Tensor:
    """:func:`torchgi.light.back_off` of ``out`` (the pipeline's output for ``gb[..., rows, cols]``)
    toward that crop of ``gb.color`` (:class:`~torchgi.backends.BackOffOp`, compiled in the C back
    end), where ``gb`` has a variance from 2 samples or more (else ``out``). ``out`` a list: the
    outputs of the filter at ``radii``, blended first by :func:`torchgi.light.choose`
    (:class:`~torchgi.backends.ChooseOp`, compiled in the C back end; one output: itself)."""
    c, e, a, on, v, n = (None if t is None else t[..., rows, cols]
                         for t in (gb.color, gb.emission, gb.albedo, surface, gb.variance, gb.spp))
    n = light.samples(n)
    if isinstance(out, list) and len(out) == 1:
        out = out[0]
    if v is None or (isinstance(n, float) and n < 2):
        return out
    emit = light.emitting(c, e, a, on, level)
    if isinstance(out, list):
        out = backends.run(backends.ChooseOp(tuple(out), radii, v, emit))
    return backends.run(backends.BackOffOp(out, c, v, n, emit))


def _footprint(radius: int, s: int, chosen: bool = False) -> int:
    """How far (px) the guided pipeline's output reaches into its input: the firefly window, the
    light-source opening, the guided filter's two box passes at radius r (r / s at 1 / s
    resolution, plus the s x s blocks and the bilinear taps), the window of the choice among radii
    (``chosen``) and the back-off's window, rounded up to a multiple of s."""
    r_low = radius if s == 1 else round(radius / s)
    reach = PIPELINE.firefly_radius + 2 * (PIPELINE.light_square // 2) + s * (2 * r_low + 2) + s
    reach += PIPELINE.backoff_radius * (1 + chosen)  # the back-off's window (and the choice's)
    return -(-reach // s) * s


DENOISERS: Registry[Denoiser] = Registry("denoiser")
for _method in METHODS:
    DENOISERS.register(_method)(lambda _m=_method, **kw: Denoiser(_m, **kw))
