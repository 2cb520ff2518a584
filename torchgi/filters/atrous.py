"""Edge-avoiding À-Trous wavelet filter (Dammertz et al. 2010), docs/design.md, À-Trous.

Iteration ``i = 0..N-1`` with step ``s = 2^i`` over the 25 taps of ``h = b ⊗ b``::

    c_{i+1}(p) = Σ_q h(q) w(p,q) c_i(q) / Σ_q h(q) w(p,q)
    w = w_rt · w_n · w_x,  w_rt = exp(-|c_i(p)-c_i(q)|² / σ_rt,i),
    w_n = exp(-|n(p)-n(q)|² / (s² σ_n)),  w_x = exp(-|x(p)-x(q)|² / σ_x),  σ_rt,i = 2^-i σ_rt

(the paper's shader form: squared distances over σ). The three exponentials are one
``exp(-(d_rt + d_n + d_x))``. Beyond the paper: sub-sampled input with in-painting, global
energy post-normalisation (the paper's stated fix), and an SVGF-style variance-guided colour
weight (Schied et al. 2017) that replaces the tie of σ_rt to the image maximum.

The levels run in the back end :mod:`torchgi.backends` picks: a level per kernel (compiled C
on the CPU, Triton on CUDA) for eager float32 calls, else the torch code (autograd, tracing
and export, float64, no compiler; :mod:`torchgi.backends.torch_code`).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from torchgi import backends
from torchgi.core.check import (
    check_int,
    check_positive,
    check_range,
    check_same_device,
    check_same_floating,
    check_shape,
    finite_or_sanitized_later,
)
from torchgi.core.dtypes import compute_dtype
from torchgi.core.errors import RangeError, ShapeError
from torchgi.filters.learned import inverse_power, register_positive

__all__ = ["ATrous", "atrous"]

MAX_ITERATIONS = 30  # level i steps 2^(i-1) px: past 30 levels the steps pass any image


def atrous(
    color: torch.Tensor,
    normal: torch.Tensor | None = None,
    position: torch.Tensor | None = None,
    *,
    iterations: int = 5,
    sigma_color: float | torch.Tensor | None = None,
    sigma_normal: float | torch.Tensor | None = 0.1,
    sigma_position: float | torch.Tensor | None = 0.1,
    variance: torch.Tensor | None = None,
    color_weight: bool = True,
    subsample: int = 1,
    energy: bool = False,
    return_details: bool = False,
    sanitize: bool = False,
    fused: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, list[torch.Tensor]]:
    """Edge-avoiding À-Trous filter of ``color`` guided by ``normal`` and ``position``.

    Args:
        color: ``(B, C, H, W)`` HDR radiance (or demodulated irradiance) in [0, inf).
        normal: ``(B, 3, H, W)`` world-space normals in [-1, 1]; None switches ``w_n`` off.
        position: ``(B, 3, H, W)`` world-space positions, scene units; None switches ``w_x`` off.
        iterations: N >= 1 levels; the footprint is ``4·2^N + 1`` pixels wide.
        sigma_color: σ_rt in colour units squared, float, ``(B,)`` or a ``(B, 1, H, W)`` map
            (per pixel: a pixel's own σ weighs its neighbours; gradients reach the map); None =
            the paper's default, the image's maximum (per image; differentiated too: its
            gradient reaches the brightest pixel). With ``variance`` it is the
            number of standard deviations instead (None = 4, as SVGF).
        sigma_normal, sigma_position: σ_n (normal distance squared) and σ_x (scene units
            squared), float or ``(B,)``; None switches the weight off.
        variance: ``(B, 1|C, H, W)`` per-pixel variance of ``color``: the colour weight becomes
            ``exp(-|Δc|² / (σ² · blur3x3(Var)))`` and the variance is filtered along (SVGF).
        color_weight: False switches ``w_rt`` off (paper Table 2: any subset of weights).
        subsample: 1, 2, 4, ...: only every ``subsample``-th pixel in x and y carries a sample
            (the paper's sub-sampling); holes are no source until filled, and the colour
            weight stays off for the first ``log2(subsample)`` iterations.
        energy: rescale the result so each image and channel keeps the input's total (the
            paper's post-normalisation fix for energy loss at edges).
        return_details: also return the detail coefficients ``d_i = c_{i+1} - c_i``.
        sanitize: replace NaN/Inf inputs by 0 (with a warning) instead of raising.
        fused: run the torch code of each level through ``torch.compile`` (one fused loop per
            level). The first call in a process compiles (about a minute on 2 cores; inductor
            caches it on disk for later processes); new sizes and steps reuse it. float32
            (and float16/bfloat16) calls without autograd or tracing run each level in one
            kernel instead, whatever ``fused`` says (:mod:`torchgi.backends`: C on the CPU,
            Triton on CUDA; timings in the README).

    Returns:
        ``(B, C, H, W)`` filtered colour in the input's dtype (float16/bfloat16 computed in
        float32), or ``(out, [d_0, ..., d_{N-1}])``. Differentiable.

    Example:
        >>> c = torch.rand(1, 3, 16, 16)
        >>> n = torch.nn.functional.normalize(torch.randn(1, 3, 16, 16), dim=1)
        >>> atrous(c, n, torch.rand(1, 3, 16, 16), iterations=3).shape
        torch.Size([1, 3, 16, 16])
        >>> flat = torch.full((1, 3, 8, 8), 0.5)
        >>> torch.equal(atrous(flat, iterations=2), flat)   # a constant image stays constant
        True
    """
    _check_atrous_args(color, normal, position, variance, iterations, subsample)
    B = color.shape[0]
    named = {"color": color, "normal": normal, "position": position, "variance": variance}
    values, check_finite_inputs = finite_or_sanitized_later(named, sanitize)  # read back before returning
    c, n, x, var = (None if t is None else t.to(compute_dtype(color.dtype)) for t in values)
    if var is not None:
        check_range(var, "variance", 0.0)
        if var.shape[1] == 1 and c.shape[1] > 1:
            var = var.expand(-1, c.shape[1], -1, -1)
    valid = None
    if subsample > 1:
        H, W = c.shape[-2:]
        ys = torch.arange(H, device=c.device) % subsample == 0
        xs = torch.arange(W, device=c.device) % subsample == 0
        valid = (ys[:, None] & xs[None, :]).expand(B, 1, H, W)
        c = c * valid.to(c.dtype)
    if var is not None:  # variance-guided: σ_rt counts standard deviations
        inv_c = inverse_power(4.0 if sigma_color is None else sigma_color, "sigma_color", B, c, power=2, per_pixel=True)
    elif sigma_color is None:  # the paper's default: the image's maximum
        inv_c = 1.0 / c.flatten(1).amax(1).clamp_min(torch.finfo(c.dtype).tiny).reshape(B, 1, 1, 1)
    else:
        inv_c = inverse_power(sigma_color, "sigma_color", B, c, per_pixel=True)
    op = backends.ATrousOp(
        c, n, x, var, valid, inv_c,
        inverse_power(sigma_normal, "sigma_normal", B, c) if n is not None else None,
        inverse_power(sigma_position, "sigma_position", B, c) if x is not None else None,
        iterations, fill=int(math.log2(subsample)), color_weight=color_weight, return_details=return_details,
        fused=fused)
    total_in = c.sum(dim=(2, 3), keepdim=True) if energy else None
    c, details = backends.run(op)
    if energy:
        total_out = c.sum(dim=(2, 3), keepdim=True)
        c = c * torch.where(total_out != 0, total_in / torch.where(total_out != 0, total_out, 1.0), 1.0)
    out = c.to(color.dtype).contiguous()
    check_finite_inputs()
    if return_details:
        return out, [d.to(color.dtype) for d in details]
    return out


def _check_atrous_args(
    color: torch.Tensor, normal: torch.Tensor | None, position: torch.Tensor | None, variance: torch.Tensor | None,
    iterations: int, subsample: int,
) -> None:
    """Shapes, devices, dtypes and integer arguments of :func:`atrous`."""
    sizes = check_shape(color, "B C H W", "color")
    named = {"color": color, "normal": normal, "position": position, "variance": variance}
    for name in ("normal", "position"):
        if named[name] is not None:
            check_shape(named[name], "B 3 H W", name, sizes)
    if variance is not None:
        check_shape(variance, "B V H W", "variance", sizes)
        if variance.shape[1] not in (1, color.shape[1]):
            raise ShapeError(f"variance: expected 1 or {color.shape[1]} channels, got {variance.shape[1]}")
    check_same_device(named)
    check_same_floating(named)
    _check_levels(iterations, subsample)


def _check_levels(iterations: int, subsample: int) -> None:
    """``iterations`` an int in [1, MAX_ITERATIONS], ``subsample`` a power of two >= 1."""
    check_int(iterations, "iterations", 1)
    if iterations > MAX_ITERATIONS:
        raise RangeError(f"iterations: expected an int in [1, {MAX_ITERATIONS}] (level i steps 2^(i-1) px: past "
                         f"{MAX_ITERATIONS} levels the steps pass any image), got {iterations!r}")
    if not isinstance(subsample, int) or isinstance(subsample, bool) or subsample < 1 or subsample & (subsample - 1):
        raise ValueError(f"subsample: expected a power of two >= 1, got {subsample!r}")


class ATrous(nn.Module):
    """Module form of :func:`atrous`; σ's are buffers, or with ``learnable=True`` learnable
    parameters that stay > 0 (``self.sigma_color`` reads the σ, the optimiser updates
    ``parametrizations.sigma_color.original``, ``σ = softplus(original)``); a σ given as None
    stays None (``sigma_color=None``: from each image's maximum, not learned).

    Example:
        >>> f = ATrous(iterations=3, sigma_color=1.0)
        >>> f(torch.rand(2, 3, 16, 16), torch.zeros(2, 3, 16, 16), torch.rand(2, 3, 16, 16)).shape
        torch.Size([2, 3, 16, 16])
    """

    def __init__(
        self,
        iterations: int = 5,
        sigma_color: float | None = None,
        sigma_normal: float | None = 0.1,
        sigma_position: float | None = 0.1,
        *,
        color_weight: bool = True,
        subsample: int = 1,
        energy: bool = False,
        fused: bool = False,
        learnable: bool = False,
    ) -> None:
        super().__init__()
        _check_levels(iterations, subsample)
        self.iterations, self.color_weight, self.subsample, self.energy = iterations, color_weight, subsample, energy
        self.fused = fused
        for name, value in (("sigma_color", sigma_color), ("sigma_normal", sigma_normal),
                            ("sigma_position", sigma_position)):
            if value is None:
                setattr(self, name, None)
                continue
            if not isinstance(value, torch.Tensor):  # a 0-d tensor is checked where the call reads it
                check_positive(value, name)
            if learnable:
                register_positive(self, name, torch.tensor(float(value)))
            else:
                self.register_buffer(name, torch.tensor(float(value)))

    def forward(
        self, color: torch.Tensor, normal: torch.Tensor | None = None, position: torch.Tensor | None = None,
        variance: torch.Tensor | None = None,
    ) -> torch.Tensor:
        def cast(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t.to(compute_dtype(color.dtype))

        return atrous(
            color, normal, position, iterations=self.iterations, sigma_color=cast(self.sigma_color),
            sigma_normal=cast(self.sigma_normal), sigma_position=cast(self.sigma_position), variance=variance,
            color_weight=self.color_weight, subsample=self.subsample, energy=self.energy, fused=self.fused,
        )

    def extra_repr(self) -> str:
        def val(t: torch.Tensor | None) -> str:
            return "None" if t is None else f"{float(t.detach()):g}"

        return (f"iterations={self.iterations}, sigma_color={val(self.sigma_color)}, "
                f"sigma_normal={val(self.sigma_normal)}, sigma_position={val(self.sigma_position)}, "
                f"color_weight={self.color_weight}, subsample={self.subsample}, energy={self.energy}, "
                f"fused={self.fused}")
