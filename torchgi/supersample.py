"""Supersampling with guide rays (Bauszat et al. 2011, §3.2; docs/design.md, Supersampling).

Sample 0 of every pixel is a *guide ray* through the pixel centre: the only eye ray that
estimates indirect light. That light is filtered (demodulated, geometry-aware) at the guide
rays; every further eye ray computes its own emission and direct light and takes its indirect
light (and, when direct light is filtered too, its direct light) from the filtered map at the
most similar of the 4 guide rays around it:

    s_i = sn_i · sd_i,   sn_i = 1 - |N_a - N_i|² / max_j |N_a - N_j|²,
                         sd_i = 1 - |D_a - D_i|  / max_j |D_a - D_j|        (i, j ∈ 0..3)

The pixel is the mean of its samples. The renderer side is
:func:`torchgi.render.engine.render_guide_rays`; :meth:`torchgi.Denoiser.supersample` runs the
whole scheme.
"""

from __future__ import annotations

import dataclasses

import torch

from torchgi.core.check import check_floating, check_same_device, check_shape

__all__ = ["EyeSamples", "composite", "distribute"]


@dataclasses.dataclass
class EyeSamples:
    """The eye rays after a pixel's guide ray, ``S`` per pixel, as ``(B, S, C, H, W)`` tensors.

    Attributes:
        offset: ``(B, S, 2, H, W)`` position in the pixel, x then y, in [0, 1) (0.5 = centre).
        normal: ``(B, S, 3, H, W)`` first-hit normal (facing the camera; 0 on a miss).
        depth: ``(B, S, 1, H, W)`` distance to the first hit (0 on a miss), scene units.
        albedo: ``(B, S, 3, H, W)`` first-hit albedo (0 on a miss).
        emission: ``(B, S, 3, H, W)`` light the ray meets directly (emitters, the sky).
        direct: ``(B, S, 3, H, W)`` direct light at its first hit.

    Radiance in the scene's units; all fields floating, on one device. Usually made by
    :func:`torchgi.render.render_guide_rays`.

    Example:
        >>> z = lambda c: torch.zeros(1, 3, c, 4, 4)  # B = 1, S = 3 eye rays, 4x4 pixels
        >>> EyeSamples(z(2) + 0.5, z(3), z(1), z(3), z(3), z(3)).offset.shape
        torch.Size([1, 3, 2, 4, 4])
    """

    offset: torch.Tensor
    normal: torch.Tensor
    depth: torch.Tensor
    albedo: torch.Tensor
    emission: torch.Tensor
    direct: torch.Tensor

    def __post_init__(self) -> None:
        sizes = check_shape(self.offset, "B S 2 H W", "offset")
        for name, c in (("normal", 3), ("depth", 1), ("albedo", 3), ("emission", 3), ("direct", 3)):
            t = getattr(self, name)
            check_shape(t, f"B S {c} H W", name, {k: sizes[k] for k in ("B", "S", "H", "W")})
        tensors = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        check_same_device(tensors)
        for name, t in tensors.items():
            check_floating(t, name)


def _neighbours(offset: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For samples at ``offset (B,S,2,H,W)``, the row and column index ``(B,S,4,H,W)`` of the 4
    guide rays (pixel centres) around each, clamped to the image, in the order
    (top-left, top-right, bottom-left, bottom-right)."""
    H, W = offset.shape[-2:]
    ys = torch.arange(H, device=offset.device).view(1, 1, H, 1)
    xs = torch.arange(W, device=offset.device).view(1, 1, 1, W)
    # the centre left of / above the sample: this pixel's if the offset is past 0.5, else the previous
    x0 = xs - (offset[:, :, 0] < 0.5).long()
    y0 = ys - (offset[:, :, 1] < 0.5).long()
    cols = torch.stack([x0, x0 + 1, x0, x0 + 1], 2).clamp(0, W - 1)
    rows = torch.stack([y0, y0, y0 + 1, y0 + 1], 2).clamp(0, H - 1)
    return rows, cols


def _gather(image: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """``image (B,C,H,W)`` at ``rows, cols (B,S,K,H,W)`` -> ``(B,S,K,C,H,W)``."""
    B, C, H, W = image.shape
    S, K = rows.shape[1], rows.shape[2]
    index = (rows * W + cols).reshape(B, 1, -1).expand(B, C, -1)
    return image.reshape(B, C, H * W).gather(2, index).reshape(B, C, S, K, H, W).permute(0, 2, 3, 1, 4, 5)


def distribute(
    filtered: torch.Tensor, guide_normal: torch.Tensor, guide_depth: torch.Tensor, samples: EyeSamples
) -> torch.Tensor:
    """Indirect light for each eye ray from the filtered map at its most similar guide ray.

    Args:
        filtered: ``(B, C, H, W)`` filtered (demodulated) indirect light at the guide rays.
        guide_normal: ``(B, 3, H, W)`` guide rays' first-hit normals.
        guide_depth: ``(B, 1, H, W)`` guide rays' first-hit depths (scene units).
        samples: the further eye rays (their ``offset``, ``normal``, ``depth`` are read).

    Returns:
        ``(B, S, C, H, W)``: for each eye ray, ``filtered`` at the guide ray among the 4 around
        it with the largest ``s_i`` (module docstring; where all 4 are alike in normal or depth
        that factor is 1; ties go to the first in the order top-left, top-right, bottom-left,
        bottom-right). Differentiable with respect to ``filtered``.

    Example:
        >>> B, S, H, W = 1, 2, 4, 4
        >>> eye = EyeSamples(torch.full((B, S, 2, H, W), 0.75), torch.zeros(B, S, 3, H, W), torch.ones(B, S, 1, H, W),
        ...                  torch.ones(B, S, 3, H, W), torch.zeros(B, S, 3, H, W), torch.zeros(B, S, 3, H, W))
        >>> light = torch.arange(16.0).view(1, 1, 4, 4)
        >>> distribute(light, torch.zeros(1, 3, 4, 4), torch.ones(1, 1, 4, 4), eye)[0, 0, 0, 0].tolist()
        [0.0, 1.0, 2.0, 3.0]
    """
    sizes = check_shape(filtered, "B C H W", "filtered")
    hw = {"B": sizes["B"], "H": sizes["H"], "W": sizes["W"]}
    check_shape(guide_normal, "B 3 H W", "guide_normal", hw)
    check_shape(guide_depth, "B 1 H W", "guide_depth", hw)
    check_shape(samples.offset, "B S 2 H W", "samples.offset", hw)
    check_same_device({"filtered": filtered, "guide_normal": guide_normal, "guide_depth": guide_depth,
                       "samples": samples.offset})
    rows, cols = _neighbours(samples.offset)
    n4 = _gather(guide_normal, rows, cols)  # (B,S,4,3,H,W)
    d4 = _gather(guide_depth, rows, cols)  # (B,S,4,1,H,W)
    dn = (samples.normal[:, :, None] - n4).square().sum(3)  # (B,S,4,H,W)
    dd = (samples.depth[:, :, None] - d4).abs().sum(3)

    def similarity(d: torch.Tensor) -> torch.Tensor:
        top = d.amax(2, keepdim=True)
        return torch.where(top > 0, 1 - d / torch.where(top > 0, top, 1), 1)

    score = similarity(dn) * similarity(dd)  # (B,S,4,H,W)
    # the first best of 4, by comparisons (faster than argmax over a size-4 middle dimension)
    best = torch.zeros_like(score[:, :, :1], dtype=torch.long)
    top = score[:, :, :1]
    for k in range(1, 4):
        better = score[:, :, k : k + 1] > top
        best = torch.where(better, k, best)
        top = torch.where(better, score[:, :, k : k + 1], top)
    r = rows.gather(2, best)
    c = cols.gather(2, best)
    return _gather(filtered, r, c)[:, :, 0]


def composite(
    guide_radiance: torch.Tensor, guide_albedo: torch.Tensor, filtered: torch.Tensor, sample_radiance: torch.Tensor,
    sample_albedo: torch.Tensor, distributed: torch.Tensor,
) -> torch.Tensor:
    """Pixel colours: the mean over the guide ray and the further eye rays of their own radiance
    (emission, and direct light when it is not filtered) + albedo x filtered light.

    Args:
        guide_radiance: ``(B, 3, H, W)`` the guide rays' own radiance.
        guide_albedo: ``(B, 3, H, W)`` the guide rays' albedo.
        filtered: ``(B, 3, H, W)`` filtered demodulated light at the guide rays.
        sample_radiance: ``(B, S, 3, H, W)`` the eye rays' own radiance.
        sample_albedo: ``(B, S, 3, H, W)`` their albedo.
        distributed: ``(B, S, 3, H, W)`` their share of ``filtered``, from :func:`distribute`.

    Returns:
        ``(B, 3, H, W)`` radiance.

    Example:
        >>> ones = torch.ones(1, 3, 2, 2)
        >>> sample = torch.ones(1, 1, 3, 2, 2)
        >>> composite(ones, ones, ones, sample, sample, 3 * sample)[0, :, 0, 0].tolist()
        [3.0, 3.0, 3.0]
    """
    total = guide_radiance + guide_albedo * filtered + (sample_radiance + sample_albedo * distributed).sum(1)
    return total / (1 + distributed.shape[1])
