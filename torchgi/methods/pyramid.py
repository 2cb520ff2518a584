"""Method "pyramid": a small network at 1/4 resolution mixes guided-filter models from a pyramid
of scales per pixel (:mod:`torchgi.filters.pyramid`), inside the steps of
:func:`torchgi.light.restore` (``backends.LightInOp`` / ``LightOutOp``, fused in the C back
end), then the back-off; under a memory budget in tiles that overlap by the pipeline's reach and
the pyramid's (:data:`torchgi.filters.pyramid.REACH`), after a first pass over tiles that sums the
image statistics the pyramid centres and scales by."""

from __future__ import annotations

from typing import Any

import torch

from torchgi import backends, light
from torchgi.buffers import GBuffer
from torchgi.core.dtypes import compute_dtype
from torchgi.core.tiles import tile_side, tiles
from torchgi.filters import guide_from
from torchgi.filters.guided import depth_scales
from torchgi.filters.pyramid import ALIGN, FEATURE_SCALE, REACH, default_net, pyramid, pyramid_stats
from torchgi.methods.base import Method, back_off, budget, noise_spp

__all__ = ["Pyramid"]

# bytes per pixel and image that a tile of the pyramid's pipeline holds (measured: docs/pyramid.md)
_PYRAMID_BYTES = 480


class Pyramid(Method):
    """``Denoiser("pyramid")``: no parameters; expects ``depth`` (the guide it was trained with);
    noisier renders than 1 spp are fed to it as 1 spp.

    Example:
        >>> from torchgi import Denoiser
        >>> from torchgi.render import render, scenes
        >>> Denoiser("pyramid").weights(render(scenes.cornell(16), spp=1)).shape
        torch.Size([1, 13, 4, 4])
    """

    name = "pyramid"
    needs = ("depth",)
    unclamped = tiles = learned = temporal = exportable = True

    def run(self, gb: GBuffer, kept: torch.Tensor | None, surface: torch.Tensor, workspace: dict,
            weights: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        level = light.level(gb.color, gb.emission, kept, gb.albedo, surface)
        spp = max(noise_spp(gb, surface, self.settings), 1.0)  # noisier renders than 1 spp are fed as 1 spp
        depth_scale = None if gb.depth is None else depth_scales(gb.depth)  # its guide as in training
        chosen: list[torch.Tensor] = []  # each tile's weights

        def op(rows: slice = slice(None), cols: slice = slice(None), workspace: dict | None = None,
               stats: dict[str, torch.Tensor] | None = None, sums: list | None = None) -> torch.Tensor | None:
            """The pipeline on ``gb[..., rows, cols]``; with ``sums`` only the statistics of the core
            ``sums[0] = (rows, cols)`` (relative to the tile), added into ``sums[1]``."""
            c, e, k, a, hit, n, d = (None if t is None else t[..., rows, cols]
                                     for t in (gb.color, gb.emission, kept, gb.albedo, gb.hit, gb.normal, gb.depth))
            guide = guide_from(n, d, depth_scale=depth_scale, workspace=workspace)
            # light.restore's steps around the filter, fused in the C back end
            x, raw, lights = backends.run(backends.LightInOp(c, e, k, a, hit, level, self.firefly(self.settings),
                                                             workspace))
            if sums is not None:  # the first pass: only the core's statistics
                core = (..., *sums[0])
                ct = compute_dtype(x.dtype)
                part = pyramid_stats(x[core].to(ct), guide[core].to(ct))
                weight = x[core][0, 0].numel() / (gb.color.shape[-2] * gb.color.shape[-1])
                for key, v in part.items():
                    sums[1][key] = sums[1].get(key, 0) + weight * v
                return None
            out, w = pyramid(x, guide, spp=spp, raw=raw, return_weights=True, workspace=workspace, stats=stats)
            if weights:
                chosen.append(w)
            out = backends.run(backends.LightOutOp(out, c, e, k, a, hit, lights, inplace=True))
            return back_off(out, gb, surface, level, self.settings, rows, cols)

        per_pixel = _PYRAMID_BYTES * gb.color.shape[0] * torch.finfo(compute_dtype(gb.color.dtype)).bits / 32
        mb = budget(gb, per_pixel, self.max_memory_mb, self.settings)
        if mb is None:
            out = op(workspace=workspace)
            return out, chosen[0] if weights else None
        p = self.settings.pipeline
        reach = p.firefly_radius + 2 * (p.light_square // 2)  # the light's before the filter
        halo = -(-(reach + REACH + p.backoff_radius) // ALIGN) * ALIGN
        side = tile_side(gb.color, mb, per_pixel, halo, ALIGN)
        stats: dict[str, torch.Tensor] = {}
        for rows, cols, core_rows, core_cols, _, _ in tiles(*gb.color.shape[-2:], side, reach, ALIGN):
            op(rows, cols, sums=[(core_rows, core_cols), stats])
        out = torch.empty_like(gb.color)
        placed = []
        for rows, cols, core_rows, core_cols, out_rows, out_cols in tiles(*gb.color.shape[-2:], side, halo, ALIGN):
            out[..., out_rows, out_cols] = op(rows, cols, stats=stats)[..., core_rows, core_cols]
            placed.append((core_rows, core_cols, out_rows, out_cols))
        return out, _stitched(chosen, placed, gb.color.shape[-2:]) if weights else None

    def filter(self, x: torch.Tensor, gb: GBuffer, surface: torch.Tensor, raw: torch.Tensor | None = None, *,
               workspace: dict | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        # its guide as in training; noisier renders than 1 spp fed as 1 spp
        return pyramid(x, guide_from(gb.normal, gb.depth, depth_scale="image"),
                       spp=max(noise_spp(gb, surface, self.settings), 1.0), raw=raw, return_weights=True,
                       workspace=workspace)

    def deploy(self, spp: float, samples: float | None, frame: GBuffer | None, variance: bool,
               sigma_position: float | None) -> tuple[dict[str, Any], torch.nn.Module]:
        return {"spp": max(spp, 1.0), **({"samples": float(samples)} if variance else {})}, default_net()

    @staticmethod
    def deployed_filter(params: dict[str, Any], net: torch.nn.Module | None, x: torch.Tensor, normal: torch.Tensor,
                        geometry: torch.Tensor, radius: int | None = None,
                        raw: torch.Tensor | None = None) -> torch.Tensor:
        return pyramid(x, guide_from(normal, geometry, depth_scale="image"), spp=params["spp"], net=net, raw=raw)


def _stitched(parts: list[torch.Tensor], placed: list[tuple[slice, ...]], size: torch.Size) -> torch.Tensor:
    """The tiles' weights at 1/4 resolution, stitched as the output is."""
    B, K = parts[0].shape[:2]
    w = parts[0].new_empty(B, K, *(-(-n // FEATURE_SCALE) for n in size))

    def q(sl: slice) -> slice:
        return slice(sl.start // FEATURE_SCALE, -(-sl.stop // FEATURE_SCALE))

    for part, (core_rows, core_cols, out_rows, out_cols) in zip(parts, placed, strict=True):
        w[..., q(out_rows), q(out_cols)] = part[..., q(core_rows), q(core_cols)]
    return w
