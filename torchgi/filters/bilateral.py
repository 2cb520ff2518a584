"""Brute-force cross (joint) bilateral filter: the "perfect geometry-aware filter" baseline of
Bauszat et al. 2011 and a test oracle. Cost grows with ``(2r+1)²``."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from torchgi.backends.torch_code import channel_planes, squared_distance
from torchgi.core.check import (
    check_int,
    check_positive,
    check_same_device,
    check_same_floating,
    check_shape,
    finite_or_sanitized_all,
)
from torchgi.core.dtypes import compute_dtype
from torchgi.core.taps import Padded
from torchgi.filters.learned import inverse_power

__all__ = ["CrossBilateral", "cross_bilateral"]


def cross_bilateral(
    color: torch.Tensor,
    guides: Sequence[torch.Tensor] = (),
    *,
    radius: int,
    sigma_space: float | torch.Tensor,
    sigma_color: float | torch.Tensor | None,
    sigma_guides: Sequence[float | torch.Tensor] = (),
    sanitize: bool = False,
) -> torch.Tensor:
    """Joint bilateral filter over a ``(2r+1)²`` window with colour and guide range kernels.

    ``w(p,q) = exp(-|p-q|²/2σ_s²) · exp(-|c_p-c_q|²/2σ_c²) · Π_g exp(-|g_p-g_q|²/2σ_g²)``,
    ``out(p) = Σ w c_q / Σ w`` over the taps inside the image (the centre always counts).

    Every σ is a float, a ``(B,)`` tensor (one per image) or a per-pixel ``(B, 1, H, W)`` map
    (the centre pixel's σ weighs its neighbours); tensors are differentiable.

    Args:
        color: ``(B, C, H, W)`` image to filter.
        guides: ``(B, G_k, H, W)`` tensors (e.g. normal, depth), same dtype and device.
        radius: window radius ``r >= 0`` in pixels.
        sigma_space: spatial σ in pixels (> 0).
        sigma_color: colour σ in colour units (> 0), or None for no colour term (cross only).
        sigma_guides: one σ per guide, in that guide's units (> 0).
        sanitize: replace NaN/Inf by 0 (with a warning) instead of raising.

    Returns:
        ``(B, C, H, W)`` in the input dtype (float16/bfloat16 computed in float32). Differentiable.

    Example:
        >>> c = torch.rand(1, 3, 12, 12)
        >>> out = cross_bilateral(c, [torch.rand(1, 1, 12, 12)], radius=2, sigma_space=2.0,
        ...                       sigma_color=0.5, sigma_guides=[0.1])
        >>> out.shape
        torch.Size([1, 3, 12, 12])
    """
    sizes = check_shape(color, "B C H W", "color")
    if len(guides) != len(sigma_guides):
        raise ValueError(f"sigma_guides: expected one σ per guide ({len(guides)}), got {len(sigma_guides)}")
    named = {"color": color} | {f"guides[{k}]": g for k, g in enumerate(guides)}
    for k, g in enumerate(guides):
        check_shape(g, "B G H W", f"guides[{k}]", {"B": sizes["B"], "H": sizes["H"], "W": sizes["W"]})
    check_same_device(named)
    check_same_floating(named)
    check_int(radius, "radius")
    ct = compute_dtype(color.dtype)
    c, *gs = (t.to(ct) for t in finite_or_sanitized_all(named, sanitize))
    B = c.shape[0]
    half_inv = [None if v is None else 0.5 * inverse_power(v, name, B, c, power=2, per_pixel=True)
                for name, v in [("sigma_space", sigma_space), ("sigma_color", sigma_color)]
                + [(f"sigma_guides[{k}]", v) for k, v in enumerate(sigma_guides)]]  # 1 / 2σ²
    pc = Padded(c, radius)
    pv = Padded(torch.ones_like(c[:, :1]), radius)
    pg = [Padded(g, radius) for g in gs]
    cc, gg = channel_planes(c, False), [channel_planes(g, False) for g in gs]
    num: list[torch.Tensor] = []
    den = torch.zeros_like(c[:, :1])
    for oy in range(-radius, radius + 1):
        for ox in range(-radius, radius + 1):
            cq = channel_planes(pc.at(oy, ox), False)
            expo = (-(oy * oy + ox * ox) * half_inv[0]).expand_as(den)
            if half_inv[1] is not None:
                expo = expo - squared_distance(cc, cq) * half_inv[1]
            for g, p, h in zip(gg, pg, half_inv[2:]):
                expo = expo - squared_distance(g, channel_planes(p.at(oy, ox), False)) * h
            w = pv.at(oy, ox) * torch.exp(expo)
            num = [w * q for q in cq] if not num else [a + w * q for a, q in zip(num, cq)]
            den = den + w
    return (torch.cat(num, 1) / den).to(color.dtype)


def _check_numbers(radius: int, sigma_space: float, sigma_color: float | None, sigma_guides: Sequence[float]) -> None:
    """The Module's settings: the radius an int >= 0, every σ given a finite float > 0 (each named)."""
    check_int(radius, "radius")
    for name, v in [("sigma_space", sigma_space), ("sigma_color", sigma_color)] + [
        (f"sigma_guides[{k}]", v) for k, v in enumerate(sigma_guides)
    ]:
        if v is not None:
            check_positive(v, name)


class CrossBilateral(nn.Module):
    """Module form of :func:`cross_bilateral` (settings as attributes).

    Example:
        >>> CrossBilateral(radius=1, sigma_space=1.0, sigma_color=None)(torch.rand(1, 3, 5, 5)).shape
        torch.Size([1, 3, 5, 5])
    """

    def __init__(self, radius: int, sigma_space: float, sigma_color: float | None,
                 sigma_guides: Sequence[float] = ()) -> None:
        super().__init__()
        _check_numbers(radius, sigma_space, sigma_color, tuple(sigma_guides))
        self.radius, self.sigma_space, self.sigma_color = radius, sigma_space, sigma_color
        self.sigma_guides = tuple(sigma_guides)

    def forward(self, color: torch.Tensor, *guides: torch.Tensor) -> torch.Tensor:
        return cross_bilateral(color, guides, radius=self.radius, sigma_space=self.sigma_space,
                               sigma_color=self.sigma_color, sigma_guides=self.sigma_guides)

    def extra_repr(self) -> str:
        return (f"radius={self.radius}, sigma_space={self.sigma_space}, sigma_color={self.sigma_color}, "
                f"sigma_guides={self.sigma_guides}")
