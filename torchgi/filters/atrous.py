"""Edge-avoiding À-Trous wavelet filter (Dammertz et al. 2010), DESIGN §3.1.

Iteration ``i = 0..N-1`` with step ``s = 2^i`` over the 25 taps of ``h = b ⊗ b``::

    c_{i+1}(p) = Σ_q h(q) w(p,q) c_i(q) / Σ_q h(q) w(p,q)
    w = w_rt · w_n · w_x,  w_rt = exp(-|c_i(p)-c_i(q)|² / σ_rt,i),
    w_n = exp(-|n(p)-n(q)|² / (s² σ_n)),  w_x = exp(-|x(p)-x(q)|² / σ_x),  σ_rt,i = 2^-i σ_rt

(the paper's shader form: squared distances over σ). The three exponentials are one
``exp(-(d_rt + d_n + d_x))``. Beyond the paper: sub-sampled input with in-painting, global
energy post-normalisation (the paper's stated fix), and an SVGF-style variance-guided colour
weight (Schied et al. 2017) that replaces the tie of σ_rt to the image maximum.

Where it applies a level runs in one kernel — compiled C on the CPU
(:mod:`torchgi.filters.native`), Triton on CUDA (:mod:`torchgi.filters.gpu`) — else in the
torch code below (autograd, tracing and export, float64, no compiler).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from torchgi.core.check import (
    check_floating,
    check_int,
    check_range,
    check_same_device,
    check_same_floating,
    check_shape,
    finite_or_sanitized_later,
    is_recording,
)
from torchgi.core.errors import RangeError, ShapeError
from torchgi.filters import gpu, native
from torchgi.filters.box import compute_dtype
from torchgi.filters.taps import Padded, kernel_5x5

__all__ = ["ATrous", "atrous"]

_TAPS = kernel_5x5()


def _inverse(value: float | torch.Tensor | None, name: str, B: int, like: torch.Tensor, power: int = 1) -> torch.Tensor | None:
    """``value^-power`` of a float or ``(B,)`` tensor parameter as ``(B, 1, 1, 1)`` in ``like``'s
    dtype/device. A float is checked and inverted on the host and filled in on the device (one
    launch, no synchronisation)."""
    if value is None:
        return None
    if isinstance(value, torch.Tensor):
        check_same_device({name: value, "color": like})
        check_floating(value, name)
        if value.shape not in ((), (1,), (B,)):
            raise ShapeError(f"{name}: expected a float or shape ({B},), got {tuple(value.shape)}")
        t = value.to(like.dtype)
        if not is_recording() and bool((~torch.isfinite(t) | (t <= 0)).any()):
            raise RangeError(f"{name}: expected finite values > 0 (a float or a ({B},) tensor), got "
                             f"{t.flatten().tolist()[:4]}")
        return t.pow(-power).reshape(-1, 1, 1, 1).expand(B, 1, 1, 1)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise RangeError(f"{name}: expected finite values > 0 (a float or a ({B},) tensor), got {value!r}")
    return torch.full((B, 1, 1, 1), float(value) ** -power, dtype=like.dtype, device=like.device)


def _blur3(v: torch.Tensor) -> torch.Tensor:
    """3x3 binomial blur ([1,2,1]/4 ⊗ [1,2,1]/4) with edge replication, by shifted views."""
    p = torch.nn.functional.pad(v, (1, 1, 1, 1), mode="replicate")
    H, W = v.shape[-2], v.shape[-1]
    rows = 0.25 * p[..., :, 0:W] + 0.5 * p[..., :, 1 : W + 1] + 0.25 * p[..., :, 2 : W + 2]
    return 0.25 * rows[..., 0:H, :] + 0.5 * rows[..., 1 : H + 1, :] + 0.25 * rows[..., 2 : H + 2, :]


def _sqdist(a: list[torch.Tensor], b: list[torch.Tensor]) -> torch.Tensor:
    """Σ (a - b)² over channels ``(B,1,H,W)``: either one ``(B,C,H,W)`` tensor each (a channel
    reduction: few ops, compact ONNX graphs) or lists of ``(B,1,H,W)`` planes (pointwise only:
    what ``torch.compile`` fuses into one loop)."""
    out = (a[0] - b[0]).square().sum(1, keepdim=True)
    for u, v in zip(a[1:], b[1:]):
        out = out + (u - v).square()
    return out


def _planes(t: torch.Tensor, split: bool) -> list[torch.Tensor]:
    """``t (B,C,H,W)`` as a list of channel planes (``split``) or as ``[t]``."""
    return [t[:, k : k + 1] for k in range(t.shape[1])] if split else [t]


def _iteration(
    c: torch.Tensor, feat: torch.Tensor | None, var: torch.Tensor | None, valid: torch.Tensor | None,
    step: int, colour_scale: torch.Tensor | None, split: bool = False,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """One À-Trous level.

    ``feat`` ``(B,F,H,W)`` holds the geometry guides already divided by the square roots of
    their σ's (normal also by the step), so ``w_n · w_x = exp(-|f(p) - f(q)|²``); None: no
    geometry weight. ``colour_scale`` is ``1/σ_rt,i`` ``(B,1,1,1)`` or, variance-guided,
    ``1/(σ² · blur(Var))`` ``(B,1,H,W)``; None: no colour weight. ``valid`` ``(B,1,H,W)``
    marks pixels that may act as sources (None: all). Returns the filtered colour, the
    propagated variance and the weight sum.

    With ``split`` every channel is its own plane and the level is pure pointwise arithmetic
    over shifted views, which ``torch.compile`` fuses into one loop (the ``fused=True`` path);
    without it channels are reduced with ``sum`` (fewer ops for eager code and ONNX).
    """
    pad = 2 * step
    pc = Padded(c, pad)
    pf = Padded(feat, pad) if feat is not None else None
    pv = Padded(torch.ones_like(c[:, :1]) if valid is None else valid.to(c.dtype), pad)  # 0 outside / on holes
    pvar = Padded(var, pad) if var is not None else None
    cc = _planes(c, split)
    ff = _planes(feat, split) if feat is not None else []
    num: list[torch.Tensor] = []
    var_num: list[torch.Tensor] = []
    den = torch.zeros_like(c[:, :1])
    for dy, dx, h in _TAPS:
        oy, ox = dy * step, dx * step
        cq = _planes(pc.at(oy, ox), split)
        d = None
        if colour_scale is not None:
            d = _sqdist(cc, cq) * colour_scale
        if pf is not None:
            dg = _sqdist(ff, _planes(pf.at(oy, ox), split))
            d = dg if d is None else d + dg
        w = pv.at(oy, ox) * h
        if d is not None:
            w = w * torch.exp(-d)
        num = [w * q for q in cq] if not num else [a + w * q for a, q in zip(num, cq)]
        den = den + w
        if pvar is not None:
            w2 = w.square()
            vq = _planes(pvar.at(oy, ox), split)
            var_num = [w2 * q for q in vq] if not var_num else [a + w2 * q for a, q in zip(var_num, vq)]
    ok = den > 0
    safe = torch.where(ok, den, torch.ones_like(den))
    out = torch.where(ok, torch.cat(num, 1) / safe, c)  # no weight at all: keep the centre pixel
    var_out = torch.where(ok, torch.cat(var_num, 1) / safe.square(), var) if var is not None else None
    return out, var_out, den


_fused_iteration = None


def _compiled_iteration():
    """``torch.compile(_iteration, dynamic=True)``, built on first use (one compile serves
    every size and step)."""
    global _fused_iteration
    if _fused_iteration is None:
        _fused_iteration = torch.compile(_iteration, dynamic=True)
    return _fused_iteration


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
        sigma_color: σ_rt in colour units squared, float or ``(B,)``; None = the paper's
            default, the image's maximum (per image). With ``variance`` it is the number of
            standard deviations instead (None = 4, as SVGF).
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
            kernel instead, whatever ``fused`` says: on the CPU the compiled C kernel of
            :mod:`torchgi.filters.native` (1024x768, 5 levels, 3 weights: 83 ms against 211
            fused and 2100 eager), on CUDA the Triton kernel of :mod:`torchgi.filters.gpu`.

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
    check_int(iterations, "iterations", 1)
    if not isinstance(subsample, int) or subsample < 1 or subsample & (subsample - 1):
        raise ValueError(f"subsample: expected a power of two >= 1, got {subsample!r}")
    ct = compute_dtype(color.dtype)
    B = color.shape[0]
    values, check_finite_inputs = finite_or_sanitized_later(named, sanitize)  # read back before returning
    c, n, x, var = (None if t is None else t.to(ct) for t in values)
    if var is not None:
        check_range(var, "variance", 0.0)
    if var is not None and var.shape[1] == 1 and c.shape[1] > 1:
        var = var.expand(-1, c.shape[1], -1, -1)

    valid = None
    fill = 0
    if subsample > 1:
        H, W = c.shape[-2], c.shape[-1]
        ys = torch.arange(H, device=c.device) % subsample == 0
        xs = torch.arange(W, device=c.device) % subsample == 0
        valid = (ys[:, None] & xs[None, :]).expand(B, 1, H, W)
        c = c * valid.to(ct)
        fill = int(math.log2(subsample))

    if var is not None:
        inv_c = _inverse(4.0 if sigma_color is None else sigma_color, "sigma_color", B, c, power=2)
    elif sigma_color is None:
        peak = c.detach().flatten(1).amax(1).clamp_min(torch.finfo(ct).tiny)
        inv_c = 1.0 / peak.reshape(B, 1, 1, 1)
    else:
        inv_c = _inverse(sigma_color, "sigma_color", B, c)
    inv_n = _inverse(sigma_normal, "sigma_normal", B, c) if n is not None else None
    inv_x = _inverse(sigma_position, "sigma_position", B, c) if x is not None else None

    details = []
    total_in = c.sum(dim=(2, 3), keepdim=True) if energy else None
    level = _compiled_iteration() if fused else _iteration
    # a whole level in one kernel: compiled C on the CPU, Triton on CUDA; else the torch code
    kernel = native if native.applies(c, n, x, var, inv_c, inv_n, inv_x) else \
        gpu if gpu.applies(c, n, x, var, inv_c, inv_n, inv_x) and c.shape[1] <= gpu.MAX_CHANNELS else None
    if kernel is gpu:  # raw guides and the images' inverse σ's: the kernel scales the distances
        inv = torch.stack([torch.ones(B, dtype=ct, device=c.device) if t is None else t.reshape(B)
                           for t in (inv_c, inv_n, inv_x)], 1)
        n, x = (n if inv_n is not None else None), (x if inv_x is not None else None)
    elif x is not None:
        x = x - x.mean(dim=(2, 3), keepdim=True)  # offsets cancel in differences; keep them small
    # w_n · w_x = exp(-|f(p) - f(q)|²) with f = (n / (s·√σ_n), x / √σ_x): the guides divided
    # by √σ here, normals also by the step s of each level
    guides = [] if kernel is gpu else (([(n, inv_n.sqrt(), True)] if inv_n is not None else []) +
        ([(x, inv_x.sqrt(), False)] if inv_x is not None else []))
    if kernel is native and guides:  # built once: the kernel scales the normals' distances by 1 / s²
        feat = native.empty_planes(c, 3 * len(guides))
        for k, (g, s, _) in enumerate(guides):
            torch.mul(g, s, out=feat[:, 3 * k : 3 * k + 3])
    for i in range(iterations):
        step = 2**i
        scale = None
        if color_weight and i >= fill:
            # variance-guided: 1 / (σ² · blurred per-pixel variance summed over channels)
            if var is not None:
                scale = inv_c / (_blur3(var).sum(1, keepdim=True) + 1e-12)
            else:  # the Triton kernel takes the factor and multiplies σ_rt's inverse itself
                scale = 2.0**i if kernel is gpu else inv_c * (2.0**i)
        if kernel is gpu:
            c_next, var, den = gpu.atrous_level(c, n, x, inv, var, valid, step, scale)
        elif kernel is not None:
            c_next, var, den = kernel.atrous_level(
                c, feat if guides else None, [1.0 / step**2 if per_step else 1.0 for _, _, per_step in guides], var,
                valid, step, scale)
        else:
            feat = torch.cat([g * (s / step if per_step else s) for g, s, per_step in guides], 1) if guides else None
            c_next, var, den = level(c, feat, var, valid, step, scale, fused)
        if return_details:
            details.append(c_next - c)
        c = c_next
        if valid is not None:
            valid = den > 0  # in-painted pixels become sources
    if energy:
        total_out = c.sum(dim=(2, 3), keepdim=True)
        c = c * torch.where(total_out != 0, total_in / torch.where(total_out != 0, total_out, 1.0), 1.0)
    out = c.to(color.dtype).contiguous()
    check_finite_inputs()
    if return_details:
        return out, [d.to(color.dtype) for d in details]
    return out


class ATrous(nn.Module):
    """Module form of :func:`atrous`; σ's are buffers, or Parameters with ``learnable=True``.

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
        self.iterations, self.color_weight, self.subsample, self.energy = iterations, color_weight, subsample, energy
        self.fused = fused
        for name, value in (("sigma_color", sigma_color), ("sigma_normal", sigma_normal),
                            ("sigma_position", sigma_position)):
            if value is None:
                setattr(self, name, None)
            elif learnable:
                setattr(self, name, nn.Parameter(torch.tensor(float(value))))
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
            return "None" if t is None else f"{float(t):g}"

        return (f"iterations={self.iterations}, sigma_color={val(self.sigma_color)}, "
                f"sigma_normal={val(self.sigma_normal)}, sigma_position={val(self.sigma_position)}, "
                f"color_weight={self.color_weight}, subsample={self.subsample}, energy={self.energy}, "
                f"fused={self.fused}")
