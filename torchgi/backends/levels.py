"""The À-Trous level loop every back end shares (:func:`iterate_levels`) and what a level needs
of the op: the guides scaled by their σ's, the SVGF variance blur and the colour weight's scale."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchgi.backends.base import ATrousOp

__all__ = ["LevelFn", "blur3", "colour_scale", "iterate_levels", "scaled_guides"]

LevelFn = Callable[[torch.Tensor, torch.Tensor | None, torch.Tensor | None, int],
                   tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]]


def iterate_levels(desc: ATrousOp, level: LevelFn) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The À-Trous level loop every back end shares: ``level(c, var, valid, i)`` filters level
    ``i`` (step ``2^i``) and returns the colour, the propagated variance and the weight sum;
    in-painted pixels (weight > 0) become sources. Returns the colour and the details.

    Example:
        >>> c = torch.ones(1, 1, 4, 4)
        >>> desc = ATrousOp(c, None, None, None, None, torch.ones(1, 1, 1, 1), None, None, iterations=3)
        >>> out, _ = iterate_levels(desc, lambda c, var, valid, i: (c * 2, var, torch.ones_like(c)))
        >>> float(out.max())   # three levels, each doubling
        8.0
    """
    c, var, valid = desc.color, desc.variance, desc.valid
    details = []
    for i in range(desc.iterations):
        c_next, var, den = level(c, var, valid, i)
        if desc.return_details:
            details.append(c_next - c)
        c = c_next
        if valid is not None:
            valid = den > 0
    return c, details


def scaled_guides(desc: ATrousOp) -> list[tuple[torch.Tensor, torch.Tensor, bool]]:
    """The geometry guides of ``desc`` as ``(guide (B,3,H,W), 1/√σ (B,1,1,1), per_step)``: normal
    (its distances also divided by the level's step², ``per_step``) and position, centred per
    image (offsets cancel in differences; centring keeps them small). Absent weights are left out.

    Example:
        >>> n = torch.zeros(1, 3, 2, 2); x = torch.full((1, 3, 2, 2), 5.0)
        >>> desc = ATrousOp(torch.ones(1, 1, 2, 2), n, x, None, None, torch.ones(1, 1, 1, 1), None,
        ...                 torch.full((1, 1, 1, 1), 4.0), iterations=1)
        >>> [(float(g.abs().max()), float(s), per_step) for g, s, per_step in scaled_guides(desc)]
        [(0.0, 2.0, False)]
    """
    x = desc.position
    if x is not None:
        x = x - x.mean(dim=(2, 3), keepdim=True)
    return ([(desc.normal, desc.inv_normal.sqrt(), True)] if desc.inv_normal is not None else []) + \
        ([(x, desc.inv_position.sqrt(), False)] if desc.inv_position is not None else [])


def blur3(v: torch.Tensor) -> torch.Tensor:
    """3x3 binomial blur ([1,2,1]/4 ⊗ [1,2,1]/4) of ``v (B, C, H, W)`` with edge replication, by
    shifted views.

    Example:
        >>> v = torch.zeros(1, 1, 3, 3); v[..., 1, 1] = 16.0
        >>> blur3(v)[0, 0].tolist()
        [[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]]
    """
    p = torch.nn.functional.pad(v, (1, 1, 1, 1), mode="replicate")
    H, W = v.shape[-2], v.shape[-1]
    rows = 0.25 * p[..., :, 0:W] + 0.5 * p[..., :, 1 : W + 1] + 0.25 * p[..., :, 2 : W + 2]
    return 0.25 * rows[..., 0:H, :] + 0.5 * rows[..., 1 : H + 1, :] + 0.25 * rows[..., 2 : H + 2, :]


def colour_scale(desc: ATrousOp, i: int, var: torch.Tensor | None, factor_only: bool = False) -> torch.Tensor | float | None:
    """Level ``i``'s colour-weight scale: None (off), ``1 / (σ² · blur(Var))`` summed over channels
    ``(B,1,H,W)`` with a variance, else ``2^i / σ_rt`` ``(B,1,1,1)`` — or the factor ``2^i`` alone
    (``factor_only``: a kernel that multiplies by ``1/σ_rt`` itself).

    Example:
        >>> desc = ATrousOp(torch.ones(1, 1, 2, 2), None, None, None, None, torch.full((1, 1, 1, 1), 0.5), None,
        ...                 None, iterations=3, fill=1)
        >>> colour_scale(desc, 0, None), float(colour_scale(desc, 2, None)), colour_scale(desc, 2, None, True)
        (None, 2.0, 4.0)
    """
    if not desc.color_weight or i < desc.fill:
        return None
    if var is not None:
        return desc.inv_color / (blur3(var).sum(1, keepdim=True) + 1e-12)
    return 2.0**i if factor_only else desc.inv_color * (2.0**i)
