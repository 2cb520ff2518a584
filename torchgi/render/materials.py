"""BSDFs, vectorised over ``(3, N)`` world-space vectors: two-sided Lambert and a GGX reflector.

All functions take the shading normal already flipped to the side of ``wi`` (two-sided
surfaces), unit ``wi`` (towards the previous vertex) and unit ``wo`` (towards the next).

GGX (Walter et al. 2007) with alpha = ``roughness``, Fresnel 1, separable Smith masking,
as Mitsuba 3's ``roughconductor`` with ``material: none``:
``f = albedo * D(h) G1(wi) G1(wo) / (4 cos_i cos_o)``. Sampling draws ``h`` from
``D(h) cos(theta_h)``, so ``pdf(wo) = D(h) cos(theta_h) / (4 |wo . h|)``.
"""

from __future__ import annotations

import math

import torch

__all__ = ["bsdf_eval", "bsdf_sample", "cosine_hemisphere", "dot", "frame", "ggx_d", "ggx_g1", "to_world"]


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise dot product of ``(3, N)`` vectors -> ``(N,)``."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit tangents completing ``n (3, N)`` to an orthonormal basis (Duff et al. 2017)."""
    sign = torch.where(n[2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    t = torch.stack([1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]])
    s = torch.stack([b, sign + n[1] * n[1] * a, -n[1]])
    return t, s


def to_world(
    local: torch.Tensor, n: torch.Tensor, tangents: tuple[torch.Tensor, torch.Tensor] | None = None
) -> torch.Tensor:
    """Local ``(3, N)`` (x, y along the tangents, z along ``n``) -> world space; ``tangents``
    is ``frame(n)`` when the caller already has it."""
    t, s = frame(n) if tangents is None else tangents
    return t * local[0] + s * local[1] + n * local[2]


def cosine_hemisphere(u: torch.Tensor) -> torch.Tensor:
    """Cosine-weighted local directions ``(3, N)`` from ``u (2, N)``; pdf = z / pi."""
    r = torch.sqrt(u[0])
    phi = (2.0 * math.pi) * u[1]
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), torch.sqrt((1.0 - u[0]).clamp_(min=0.0))])


def ggx_d(cos_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX normal distribution ``D(h)`` for ``cos(theta_h)``."""
    a2 = alpha * alpha
    c2 = cos_h * cos_h
    denom = c2 * (a2 - 1.0) + 1.0
    return torch.where(cos_h > 0, a2 / (math.pi * denom * denom), 0.0)


def ggx_g1(cos_v: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Smith masking ``G1(v)`` for GGX, ``2 / (1 + sqrt(1 + alpha^2 tan^2 theta_v))``."""
    c2 = (cos_v * cos_v).clamp_(min=1e-12)
    tan2 = (1.0 - c2).clamp_(min=0.0) / c2
    return 2.0 / (1.0 + torch.sqrt(1.0 + alpha * alpha * tan2))


def bsdf_eval(
    glossy: torch.Tensor | None,
    albedo: torch.Tensor,
    alpha: torch.Tensor,
    n: torch.Tensor,
    wi: torch.Tensor,
    wo: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``f * cos_o`` ``(3, N)`` and the sampling pdf of ``wo`` (solid angle) ``(N,)``.

    Args:
        glossy: ``(N,)`` bool, True for GGX vertices; None when no vertex is glossy.
        albedo: ``(3, N)``; alpha: ``(N,)`` roughness (ignored where not glossy).
        n, wi, wo: ``(3, N)`` unit vectors; ``n`` faces ``wi``.
    """
    cos_o = dot(n, wo).clamp_(min=0.0)
    value = cos_o * (1.0 / math.pi)
    if glossy is None:
        return albedo * value, value
    above = cos_o > 0
    cos_i = dot(n, wi).clamp(min=1e-7)
    h = wi + wo
    h = h * torch.rsqrt((h * h).sum(0).clamp_(min=1e-20))
    cos_h = dot(n, h)
    d = ggx_d(cos_h, alpha)
    spec = d * ggx_g1(cos_i, alpha) * ggx_g1(cos_o, alpha) / (4.0 * cos_i)
    spec_pdf = d * cos_h / (4.0 * dot(wo, h).abs().clamp_(min=1e-7))
    value = torch.where(above, torch.where(glossy, spec, value), 0.0)
    pdf = torch.where(above, torch.where(glossy, spec_pdf, value), 0.0)
    return albedo * value, pdf


def bsdf_sample(
    glossy: torch.Tensor | None,
    albedo: torch.Tensor,
    alpha: torch.Tensor,
    n: torch.Tensor,
    wi: torch.Tensor,
    u: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sample ``wo``: returns ``wo (3, N)``, weight ``f cos_o / pdf (3, N)`` (0 where the sample
    falls below the surface) and ``pdf (N,)`` (solid angle)."""
    local = cosine_hemisphere(u)
    if glossy is None:
        wo = to_world(local, n)
        return wo, albedo.clone(), local[2] * (1.0 / math.pi)
    a2 = alpha * alpha
    cos2 = (1.0 - u[0]) / (1.0 + (a2 - 1.0) * u[0])
    sin_h = torch.sqrt((1.0 - cos2).clamp_(min=0.0))
    phi = (2.0 * math.pi) * u[1]
    tangents = frame(n)  # one frame for both lobes
    h = to_world(torch.stack([sin_h * torch.cos(phi), sin_h * torch.sin(phi), torch.sqrt(cos2)]), n, tangents)
    spec_wo = 2.0 * dot(wi, h) * h - wi
    wo = torch.where(glossy, spec_wo, to_world(local, n, tangents))
    f_cos, pdf = bsdf_eval(glossy, albedo, alpha, n, wi, wo)
    weight = torch.where(pdf > 0, f_cos / pdf.clamp(min=1e-20), 0.0)
    return wo, weight, pdf

