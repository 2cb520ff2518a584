"""Method "guided": the guided filter on normal + depth guides (Bauszat et al. 2011), its whole
pipeline fused as one :class:`~torchgi.backends.RestoreOp` (compiled in the C and Triton back
ends), at full or half resolution, in tiles under a memory budget, and with a measured variance
a per-pixel choice between half and twice its radius (:func:`torchgi.light.choose`)."""

from __future__ import annotations

from typing import Any

import torch

from torchgi import backends, light
from torchgi.buffers import GBuffer, mean_spp
from torchgi.core.check import check_finite, check_nonnegative
from torchgi.core.tiles import guided_bytes, tiled
from torchgi.filters import guide_from, guided
from torchgi.methods.base import Method, back_off, budget, noise_spp, sampled_twice
from torchgi.settings import Settings

__all__ = ["Guided", "choice_radii", "footprint", "guide_spec"]


class Guided(Method):
    """``Denoiser("guided")``: parameters ``radius`` (px), ``eps`` (guide units squared),
    ``subsample`` (1 or 2); settings ``Settings.guided``.

    Example:
        >>> from torchgi import Denoiser
        >>> from torchgi.render import render, scenes
        >>> Denoiser("guided")(render(scenes.cornell(24), spp=1)).shape
        torch.Size([1, 3, 24, 24])
    """

    name = "guided"
    params = ("radius", "eps", "subsample")
    tiles = temporal = exportable = True

    @classmethod
    def check_params(cls, params: dict[str, Any]) -> None:
        if "eps" in params:
            check_nonnegative(params["eps"], "eps")

    @classmethod
    def temporal_params(cls, temporal: Any) -> dict[str, Any]:
        """Inside the TemporalDenoiser: the radius and ε of ``Settings.temporal``, full resolution
        (the accumulated history has less noise than one frame)."""
        return {"radius": temporal.radius, "eps": temporal.eps, "subsample": 1}

    def checks_own(self, split: bool) -> tuple[str, ...]:
        # the fused guided pipeline checks what it reads itself (normal, depth: its guide statistics)
        return ("color", "emission", "albedo", "normal", "depth") + (("direct",) if split else ())

    def run(self, gb: GBuffer, kept: torch.Tensor | None, surface: torch.Tensor, workspace: dict,
            weights: bool = False) -> tuple[torch.Tensor, None]:
        g = self.settings.guided
        spec, guide_means = guide_spec(gb)
        H, W = gb.color.shape[-2:]
        level = light.level(gb.color, gb.emission, kept, gb.albedo, surface)
        radius = self.radius(noise_spp(gb, surface, self.settings), g.radius)
        s = self.subsample(spec, H, W, gb.spp, surface)
        radii = self.radii(radius, s, gb, surface)
        eps = self.params.get("eps", g.eps)

        def op(rows: slice = slice(None), cols: slice = slice(None), workspace: dict | None = None) -> torch.Tensor:
            def cut(t: torch.Tensor | None) -> torch.Tensor | None:
                return None if t is None else t[..., rows, cols]

            tile = backends.GuideSpec(cut(spec.normal), cut(spec.depth), spec.channels, spec.scale, spec.offset)
            outs = [backends.run(backends.RestoreOp(cut(gb.color), cut(gb.emission), cut(kept), cut(gb.albedo),
                                                    cut(gb.hit), tile, level, r, eps, s, g.firefly, workspace,
                                                    centres[0], centres[1]))
                    for r in radii]
            return back_off(outs, gb, surface, level, self.settings, rows, cols, radii)

        # light and guide centred by constants of each image, so that tiles compute the untiled sums
        centres = (light.centre(gb.color, gb.emission, kept, gb.albedo, surface, g.firefly * level), guide_means)
        per_pixel = guided_bytes(gb.color.shape[0], kept is not None, gb.variance is not None, len(radii))
        mb = budget(gb, per_pixel, self.max_memory_mb, self.settings)
        if mb is None:
            return op(workspace=workspace), None
        return tiled(op, gb.color, mb, footprint(max(radii), s, self.settings, len(radii) > 1), s, per_pixel), None

    def filter(self, x: torch.Tensor, gb: GBuffer, surface: torch.Tensor, raw: torch.Tensor | None = None, *,
               workspace: dict | None = None) -> tuple[torch.Tensor, None]:
        g = self.settings.guided
        spec = guide_spec(gb)[0]  # the workspace of the CPU path is kept between calls
        return guided(x, spec.build(), radius=self.radius(noise_spp(gb, surface, self.settings), g.radius),
                      eps=self.params.get("eps", g.eps), subsample=self.subsample(spec, *x.shape[-2:], gb.spp, surface),
                      workspace=workspace), None

    def deploy(self, spp: float, samples: float | None, frame: GBuffer | None, variance: bool,
               sigma_position: float | None) -> tuple[dict[str, Any], None]:
        g = self.settings.guided
        params = {"radius": self.radius(spp, g.radius), "eps": self.params.get("eps", g.eps),
                  **({"samples": float(samples)} if variance else {})}
        subsample = self.params.get("subsample", 1)
        if frame is not None:
            spec, _ = guide_spec(frame)
            subsample = self.subsample(spec, *frame.color.shape[-2:], frame.spp,
                                       light.surface_mask(frame.hit, frame.albedo))
        if subsample > 1:
            params["subsample"] = subsample
        elif (variance and "radius" not in self.params and samples >= g.choose_from_spp
              and self.settings.pipeline.back_off):  # as the eager radii()
            params["radii"] = choice_radii(params["radius"])
        return params, None

    @staticmethod
    def deployed_filter(params: dict[str, Any], net: torch.nn.Module | None, x: torch.Tensor, normal: torch.Tensor,
                        geometry: torch.Tensor, radius: int | None = None,
                        raw: torch.Tensor | None = None) -> torch.Tensor:
        return guided(x, guide_from(normal, geometry, depth_scale="image"), radius=radius or params["radius"],
                      eps=params["eps"], subsample=params.get("subsample", 1))

    def radii(self, radius: int, s: int, gb: GBuffer, surface: torch.Tensor) -> tuple[int, ...]:
        """``(radius,)``, or :func:`choice_radii` for :func:`torchgi.light.choose` where the radius
        is not given, the filter runs at full resolution, the back-off is on and every surface pixel
        has a variance from 2 samples or more, ``guided.choose_from_spp`` on average on surfaces."""
        if ("radius" in self.params or s > 1 or gb.variance is None or gb.spp is None or not self.settings.pipeline.back_off
                or not sampled_twice(gb, surface)
                or mean_spp(gb.spp, surface) < self.settings.guided.choose_from_spp):
            return (radius,)
        return choice_radii(radius)

    def subsample(self, spec: backends.GuideSpec, H: int, W: int, spp: torch.Tensor | None,
                  surface: torch.Tensor | None = None) -> int:
        """Given, or 2 where half resolution is worth its bias, else 1. Half resolution needs
        ``guided.subsample_from`` px on the short side, fewer than ``guided.full_from_spp`` samples
        per pixel on average on ``surface`` (``spp``; None: 1), quality "fast"/"balanced", and a guide that is
        smooth at the pixel scale: fewer than ``guided.edge_share`` of (every other row's)
        horizontal neighbours differing by more than ``guided.edge`` in the guide (the
        measurements behind it in docs/calibration.md)."""
        if "subsample" in self.params:
            return self.params["subsample"]
        g = self.settings.guided
        mean = 1.0 if spp is None else mean_spp(spp, surface)
        if min(H, W) < g.subsample_from or self.quality == "high" or mean >= g.full_from_spp:
            return 1
        return 2 if backends.run(backends.EdgeShareOp(spec, g.edge)) < g.edge_share else 1


def choice_radii(radius: int) -> tuple[int, int]:
    """The radii :func:`torchgi.light.choose` blends in place of ``radius``: half (>= 1) and twice it.

    Example:
        >>> choice_radii(3)
        (1, 6)
    """
    return (max(1, radius // 2), 2 * radius)


def guide_spec(gb: GBuffer) -> tuple[backends.GuideSpec, torch.Tensor]:
    """:func:`~torchgi.filters.guide_from_gbuffer`'s guide (normal to [0, 1], depth over the
    largest depth on hit pixels, channels constant over the batch dropped) as planes and factors,
    and each image's guide means ``(B, n)`` float64 (``RestoreOp.centre_guide``), from one
    statistics walk (:class:`~torchgi.backends.GuideStats`); raises naming ``normal`` or
    ``depth`` if it holds NaN/Inf.

    Example:
        >>> from torchgi.render import render, scenes
        >>> spec, means = guide_spec(render(scenes.cornell(16), spp=1))
        >>> spec.channels, means.shape
        ((0, 1, 2, 3), torch.Size([1, 4]))
    """
    st = backends.GuideStats(backends.run(backends.GuideStatsOp(gb.normal, gb.depth, gb.hit)))
    for name, bad in (("normal", st.nonfinite_normal), ("depth", st.nonfinite_depth)):
        if bool(bad.any()):
            check_finite(getattr(gb, name), name)
    depth_scale = float(st.depth_max.max())
    depth_scale = depth_scale if depth_scale > 0 else 1.0  # (-inf: no hit pixel)
    scale = torch.tensor([0.5, 0.5, 0.5, 1.0 / depth_scale], dtype=gb.normal.dtype)
    offset = torch.tensor([0.5, 0.5, 0.5, 0.0], dtype=gb.normal.dtype)
    lo = st.minima.amin(0).to(gb.normal.dtype) * scale + offset  # the guide's extremes, rounded as its values
    hi = st.maxima.amax(0).to(gb.normal.dtype) * scale + offset
    varying = [c for c in range(3 if gb.depth is None else 4) if bool(hi[c] > lo[c])] or [0]
    spec = backends.GuideSpec(gb.normal, gb.depth, tuple(varying), tuple(float(scale[c]) for c in varying),
                              tuple(float(offset[c]) for c in varying))
    H, W = gb.normal.shape[-2:]
    means = st.sums[:, varying] / max(H * W, 1) * scale.double()[varying] + offset.double()[varying]
    return spec, means


def footprint(radius: int, s: int, settings: Settings, chosen: bool = False) -> int:
    """How far (px) the guided pipeline's output reaches into its input: the firefly window, the
    light-source opening, the guided filter's two box passes at radius r (r / s at 1 / s
    resolution, plus the s x s blocks and the bilinear taps), the window of the choice among radii
    (``chosen``) and the back-off's window, rounded up to a multiple of s.

    Example:
        >>> footprint(4, 1, Settings())
        24
    """
    p = settings.pipeline
    r_low = radius if s == 1 else round(radius / s)
    reach = p.firefly_radius + 2 * (p.light_square // 2) + s * (2 * r_low + 2) + s
    reach += p.backoff_radius * (1 + chosen)  # the back-off's window (and the choice's)
    return -(-reach // s) * s
