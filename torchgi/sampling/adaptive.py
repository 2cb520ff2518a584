"""Adaptive sampling wired into the renderer (Bauszat et al. 2011; docs/design.md, Sampling), and beyond it.

1. Render the noise-free guides (one ray per pixel centre).
2. Importance from the filter's own geometry weights (:func:`importance_map`), background excluded.
3. Apportion ``rate x (pixels on geometry)`` samples exactly (:func:`allocate`).
4. Render: each pixel's whole light with its count (the GBuffer's ``spp`` and ``variance`` are
   those of the colour the Denoiser filters).

Beyond the paper: ``variance_share > 0`` keeps that share of the budget for a second round,
handed out in proportion to the first round's per-pixel variance of the colour's mean after a
3x3 box blur (where the filter will still see noise), and the two rounds are merged per pixel by
their sample counts. The result is filtered with either À-Trous or the guided filter (the
paper's stated future work) by the caller (see ``scripts/repro_adaptive.py``).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

import torch

from torchgi.buffers import GBuffer
from torchgi.core.check import check_int, check_positive
from torchgi.core.errors import RangeError
from torchgi.filters.box import box
from torchgi.geometry import sigma_position_rule
from torchgi.sampling.allocate import MAX_BUDGET, allocate
from torchgi.sampling.importance import importance_map

if TYPE_CHECKING:  # the renderer imports its scene types lazily (embree is an extra)
    from torchgi.render.scene import Scene

__all__ = ["adaptive_counts", "adaptive_render", "geometry_importance", "merge_rounds"]

# σ_x of the importance map, in pixel footprints: the map compares neighbours at step 1 over a
# 4 px window, where the filter's σ_x (4 footprints, settings.ATROUS) would see no edge
IMPORTANCE_FOOTPRINTS = 2.0


def adaptive_counts(
    guides: GBuffer,
    rate: float,
    *,
    window: int = 4,
    sigma_normal: float = 0.1,
    sigma_position: float | None = None,
    min_samples: int = 1,
) -> torch.Tensor:
    """Indirect samples per pixel: ``round(rate x pixels on geometry)`` in all, at least
    ``min_samples`` on geometry, none on background, the rest by geometric importance.

    Args:
        guides: a GBuffer with ``normal``, ``position`` and ``hit`` (e.g. ``render_guides``).
        rate: average samples per pixel on geometry, a finite number > 0.
        sigma_position: σ_x in scene units squared; None = :func:`sigma_position_rule` with 2 footprints.

    Returns:
        ``(B, 1, H, W)`` int64 counts.

    Example:
        >>> n = torch.zeros(1, 3, 4, 4); n[:, 2] = 1; n[..., 2:] = torch.tensor([1.0, 0, 0])[:, None, None]
        >>> g = GBuffer(normal=n, position=torch.zeros(1, 3, 4, 4), hit=torch.ones(1, 1, 4, 4, dtype=torch.bool))
        >>> c = adaptive_counts(g, 2.0)
        >>> int(c.sum()), int(c.min()) >= 1, int(c[..., 1:3].sum()) > int(c[..., [0, 3]].sum())
        (32, True, True)
    """
    check_positive(rate, "rate")
    check_int(min_samples, "min_samples")
    hit = guides.hit
    imp = geometry_importance(guides, window=window, sigma_normal=sigma_normal, sigma_position=sigma_position)
    budget = round(rate * int(hit.flatten(1).sum(1).max()))
    if budget > MAX_BUDGET:
        raise RangeError(f"rate: {rate!r} samples per pixel make {budget} samples per image, more than 2**52")
    return allocate(imp, budget, min_samples=min_samples, mask=hit)


def geometry_importance(guides: GBuffer, *, window: int = 4, sigma_normal: float = 0.1,
                        sigma_position: float | None = None) -> torch.Tensor:
    """:func:`importance_map` of ``guides``' normal, position and hit with the σ_x rule of adaptive
    sampling: ``q = 1 - (the filter's geometry support) / window²``, ``(B, 1, H, W)`` in [0, 1].

    Args:
        guides: a GBuffer with ``normal``, ``position`` and ``hit``.
        sigma_position: σ_x in scene units squared; None = :func:`sigma_position_rule` with 2 footprints.

    Example:
        >>> n = torch.zeros(1, 3, 4, 4); n[:, 2] = 1
        >>> g = GBuffer(normal=n, position=torch.zeros(1, 3, 4, 4), hit=torch.ones(1, 1, 4, 4, dtype=torch.bool))
        >>> float(geometry_importance(g).max())   # a flat plane: full support everywhere
        0.0
    """
    if sigma_position is None:
        sigma_position = sigma_position_rule(guides.position, guides.hit, IMPORTANCE_FOOTPRINTS)
    return importance_map(guides.normal, guides.position, window=window, sigma_normal=sigma_normal,
                          sigma_position=sigma_position, hit=guides.hit)


def adaptive_render(
    scene: Scene | str | os.PathLike,
    rate: float = 4.0,
    bounces: int = 1,
    seed: int = 0,
    *,
    window: int = 4,
    sigma_normal: float = 0.1,
    sigma_position: float | None = None,
    min_samples: int = 1,
    variance_share: float = 0.0,
    **render_kwargs: Any,
) -> tuple[GBuffer, torch.Tensor]:
    """Render ``scene`` with adaptively apportioned samples.

    Args:
        scene: a Scene, YAML path or built-in name.
        rate: samples per pixel on geometry, on average (the budget is exact); a
            finite number > 0.
        bounces, seed: as :func:`torchgi.render`.
        window, sigma_normal, sigma_position, min_samples: as :func:`adaptive_counts`.
        variance_share: in [0, 1): the share of the budget kept for a second, variance-driven
            round (0 = the paper's single round).
        render_kwargs: passed on to :func:`torchgi.render` (``workers``, ``progress``...).

    Returns:
        The GBuffer (``spp``: each pixel's samples, 1 where it got none: :func:`torchgi.render`)
        and the counts ``(1, 1, H, W)``.

    Example:
        >>> from torchgi.render import scenes
        >>> gb, counts = adaptive_render(scenes.cornell(16), rate=2.0, bounces=1)
        >>> int(counts.sum()) == round(2.0 * int(gb.hit.sum())), torch.equal(gb.spp, counts.clamp_min(1))
        (True, True)
    """
    from torchgi.render import load_scene, render, render_guides

    check_positive(rate, "rate")
    if isinstance(variance_share, bool) or not isinstance(variance_share, (int, float)) or not 0 <= variance_share < 1:
        raise RangeError(f"variance_share: expected a number in [0, 1), got {variance_share!r}")
    if isinstance(scene, str):
        scene = load_scene(scene)
    g = render_guides(scene)
    hit = g.hit
    total = round(rate * int(hit.sum()))
    first_rate = rate * (1 - variance_share)
    counts = adaptive_counts(g, first_rate, window=window, sigma_normal=sigma_normal,
                             sigma_position=sigma_position, min_samples=min_samples)
    gb = render(scene, counts, bounces, seed, **render_kwargs)
    rest = total - int(counts.sum())
    if variance_share == 0 or rest <= 0:
        return gb, counts
    # Second round: the rest of the budget where the (blurred) variance of the mean is highest.
    # (the prefix-sum box filter can leave -1e-10 where the variance is 0: not a variance)
    var = box(gb.variance.mean(1, keepdim=True), 1).clamp_min(0) * hit
    second = allocate(var, rest, min_samples=0, mask=hit)
    gb2 = render(scene, second, bounces, (seed + 0x5BD1E995) & 0xFFFFFFFF, **render_kwargs)
    return merge_rounds(gb, counts, gb2, second), counts + second


def merge_rounds(a: GBuffer, counts_a: torch.Tensor, b: GBuffer, counts_b: torch.Tensor) -> GBuffer:
    """Two independent renders of one scene and camera (``render(scene, counts_*)`` with different
    seeds) merged per pixel as one render of ``counts_a + counts_b`` samples: the light fields
    weighted by the counts, the variance of the mean pooled exactly (the sums of squared
    deviations of the two rounds and of their means, Chan et al. 1979), ``spp`` the sum. A pixel
    with no samples in a round (``counts = 0``: that render holds nothing there, or with
    ``fill_empty`` one sample of emission and direct light) takes the other round's values;
    guides are ``a``'s.

    Args:
        a, b: GBuffers from :func:`torchgi.render` with per-pixel counts (``variance`` and ``spp`` set).
        counts_a, counts_b: ``(B, 1, H, W)`` int64, the counts each was rendered with.

    Returns:
        The merged GBuffer.

    Example:
        >>> from torchgi.render import render, scenes
        >>> scene = scenes.cornell(8)
        >>> one = torch.ones(1, 1, 8, 8, dtype=torch.int64)
        >>> gb = merge_rounds(render(scene, one, seed=1), one, render(scene, one, seed=2), one)
        >>> int(gb.spp.max()), bool((gb.variance > 0).any())  # two single samples: a variance
        (2, True)
    """
    n1, n2 = counts_a.to(a.color.dtype), counts_b.to(a.color.dtype)
    n = n1 + n2
    safe = n.clamp_min(1)
    fields = {}
    for name in ("emission", "direct", "indirect"):
        x, y = getattr(a, name), getattr(b, name)
        fields[name] = torch.where(n2 == 0, x, torch.where(n1 == 0, y, (x * n1 + y * n2) / safe))

    def m2(gb: GBuffer, k: torch.Tensor) -> torch.Tensor:  # Σ (x - mean)² of a round's colour samples
        return gb.variance * k * (k - 1).clamp_min(0)

    delta = b.color - a.color
    pooled = m2(a, n1) + m2(b, n2) + delta.square() * (n1 * n2 / safe)
    variance = torch.where(n > 1, pooled / (n * (n - 1)).clamp_min(1), 0.0)
    variance = torch.where(n2 == 0, a.variance, torch.where(n1 == 0, b.variance, variance))
    spp = torch.where(n2 == 0, a.spp, torch.where(n1 == 0, b.spp, counts_a + counts_b))
    return GBuffer(**{k: v for k, v in a.items() if k not in (*fields, "variance", "spp", "color")}, **fields,
                   variance=variance, spp=spp)
