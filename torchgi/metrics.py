"""Image error metrics on ``(B, C, H, W)`` tensors: per image ``(B,)`` or reduced.

``mse``, ``relmse`` and ``psnr`` are plain torch (differentiable, any device); ``ssim`` uses
kornia's Gaussian-window SSIM with valid (cropped) borders, the same numbers as
scikit-image's ``structural_similarity(gaussian_weights=True, use_sample_covariance=False)``;
``flip`` calls NVIDIA's ``flip-evaluator`` (CPU, not differentiable). ``temporal`` scores a
sequence's flicker (tRMAE, tPSNR) from consecutive-frame differences.
"""

from __future__ import annotations

import math

import torch

from torchgi.core.check import (
    check_finite,
    check_floating,
    check_nonnegative,
    check_option,
    check_positive,
    check_range,
    check_same_device,
    check_shape,
    require,
)
from torchgi.core.errors import ShapeError

__all__ = ["flip", "mse", "psnr", "relmse", "rmae", "ssim", "summary", "temporal", "tonemap"]

_REDUCTIONS = ("mean", "none")


def _check_pair(x: torch.Tensor, ref: torch.Tensor) -> None:
    sizes = check_shape(x, "B C H W", "x")
    check_shape(ref, "B C H W", "ref", sizes)
    check_same_device({"x": x, "ref": ref})
    check_floating(x, "x")
    check_floating(ref, "ref")
    check_finite(x, "x")
    check_finite(ref, "ref")


def _reduce(per_pixel: torch.Tensor, reduction: str) -> torch.Tensor:
    check_option(reduction, "reduction", _REDUCTIONS)
    per_image = per_pixel.flatten(1).mean(1)
    return per_image.mean() if reduction == "mean" else per_image


def tonemap(x: torch.Tensor, method: str = "reinhard") -> torch.Tensor:
    """Map HDR radiance to [0, 1]: ``"reinhard"`` is ``x / (1 + x)``, ``"clamp"`` clips.

    Example:
        >>> tonemap(torch.tensor([0.0, 1.0, 3.0]))
        tensor([0.0000, 0.5000, 0.7500])
    """
    check_option(method, "tonemap", ("reinhard", "clamp"))
    x = x.clamp_min(0)
    return x / (1 + x) if method == "reinhard" else x.clamp_max(1)


def mse(x: torch.Tensor, ref: torch.Tensor, *, reduction: str = "mean") -> torch.Tensor:
    """Mean squared error.

    Args:
        x, ref: ``(B, C, H, W)`` images, same shape and device, finite.
        reduction: ``"mean"`` (a scalar) or ``"none"`` (one value per image, ``(B,)``).

    Example:
        >>> mse(torch.ones(1, 3, 2, 2), torch.zeros(1, 3, 2, 2))
        tensor(1.)
    """
    _check_pair(x, ref)
    return _reduce((x - ref).square(), reduction)


def relmse(
    x: torch.Tensor, ref: torch.Tensor, *, eps: float = 0.01, reduction: str = "mean"
) -> torch.Tensor:
    """Relative MSE, ``mean((x - ref)^2 / (ref^2 + eps))`` per channel, ``eps = 0.01``.

    Example:
        >>> relmse(torch.full((1, 1, 1, 1), 2.0), torch.ones(1, 1, 1, 1))
        tensor(0.9901)
    """
    _check_pair(x, ref)
    check_nonnegative(eps, "eps")
    return _reduce((x - ref).square() / (ref.square() + eps), reduction)


def psnr(
    x: torch.Tensor,
    ref: torch.Tensor,
    *,
    data_range: float | None = None,
    tonemap_method: str | None = None,
    reduction: str = "mean",
) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB, ``10 log10(data_range^2 / mse)`` per image.

    Args:
        data_range: the value range of the data (required: HDR radiance has no natural peak).
            With ``tonemap_method`` set, both images are tone mapped first and the range is 1.
        tonemap_method: None, ``"reinhard"`` or ``"clamp"`` (see :func:`tonemap`).
        reduction: ``"mean"`` averages the per-image dB values; ``"none"`` gives ``(B,)``.

    Identical images give ``inf``.

    Example:
        >>> round(float(psnr(torch.full((1, 1, 2, 2), 0.1), torch.zeros(1, 1, 2, 2), data_range=1.0)), 4)
        20.0
    """
    if tonemap_method is not None:
        if data_range not in (None, 1, 1.0):
            raise ValueError(f"data_range: must be None or 1 with tonemap_method set, got {data_range}")
        _check_pair(x, ref)
        x, ref, data_range = tonemap(x, tonemap_method), tonemap(ref, tonemap_method), 1.0
    if data_range is None:
        raise ValueError("data_range: required (e.g. 1.0 for LDR, or the reference's peak for HDR)")
    check_positive(data_range, "data_range")
    per_image = mse(x, ref, reduction="none")
    db = 10 * torch.log10(data_range**2 / per_image)
    check_option(reduction, "reduction", _REDUCTIONS)
    return db.mean() if reduction == "mean" else db


def ssim(
    x: torch.Tensor,
    ref: torch.Tensor,
    *,
    data_range: float,
    window: int = 11,
    reduction: str = "mean",
) -> torch.Tensor:
    """Structural similarity with an 11x11 Gaussian window (sigma 1.5), valid borders.

    Args:
        x, ref: ``(B, C, H, W)``, H and W at least ``window``.
        data_range: value range of the data (e.g. 1 for tone-mapped images).
        window: odd Gaussian window size.

    Example:
        >>> x = torch.rand(1, 3, 16, 16)
        >>> float(ssim(x, x, data_range=1.0))
        1.0
    """
    _check_pair(x, ref)
    check_positive(data_range, "data_range")
    if window % 2 != 1 or window < 3:
        raise ValueError(f"window: expected an odd size >= 3, got {window}")
    if min(x.shape[-2:]) < window:
        raise ShapeError(f"x: H and W must be >= window={window}, got {tuple(x.shape[-2:])}")
    import kornia

    ssim_map = kornia.metrics.ssim(x, ref, window, max_val=float(data_range), padding="valid")
    return _reduce(ssim_map, reduction)


def flip(x: torch.Tensor, ref: torch.Tensor, *, hdr: bool = True, reduction: str = "mean") -> torch.Tensor:
    """Mean NVIDIA FLIP error (``flip-evaluator``; 0 = identical, 1 = worst).

    Args:
        x, ref: ``(B, 3, H, W)`` linear RGB; HDR in [0, inf), or LDR sRGB in [0, 1] when
            ``hdr=False``. Computed on the CPU in float32; the result is on x's device.

    Example:
        >>> x = torch.rand(1, 3, 16, 16)
        >>> float(flip(x, x))
        0.0
    """
    _check_pair(x, ref)
    check_shape(x, "B 3 H W", "x")
    check_range(x, "x", 0.0, None if hdr else 1.0)
    check_range(ref, "ref", 0.0, None if hdr else 1.0)
    fe = require("flip_evaluator", "bench")
    xs = x.detach().float().permute(0, 2, 3, 1).cpu().numpy()
    rs = ref.detach().float().permute(0, 2, 3, 1).cpu().numpy()
    values = [fe.evaluate(r.copy(), t.copy(), "HDR" if hdr else "LDR", applyMagma=False)[1] for r, t in zip(rs, xs)]
    per_image = torch.tensor(values, dtype=torch.float32, device=x.device)
    check_option(reduction, "reduction", _REDUCTIONS)
    return per_image.mean() if reduction == "mean" else per_image


def rmae(x: torch.Tensor, ref: torch.Tensor, *, reduction: str = "mean") -> torch.Tensor:
    """Relative mean absolute error ``mean(|x - ref| / (|ref| + 0.01))`` over channels and pixels.

    Example:
        >>> round(rmae(torch.full((1, 1, 1, 1), 1.5), torch.ones(1, 1, 1, 1)).item(), 4)   # 0.5 / 1.01
        0.495
    """
    _check_pair(x, ref)
    return _reduce((x - ref).abs() / (ref.abs() + 0.01), reduction)


def temporal(frames: torch.Tensor, refs: torch.Tensor, *, warmup: int = 0) -> dict[str, float]:
    """Flicker of a sequence against its reference (the noisebase project's temporal metrics).

    With ``Δx_t = x_t - x_{t-1}`` and ``Δy_t = y_t - y_{t-1}`` for ``t > warmup``: ``trmae`` is the mean
    over those frames of :func:`rmae` ``(Δx_t, Δy_t)`` on the HDR radiance, and ``tpsnr`` the PSNR
    (peak 1) of the Reinhard-tone-mapped frames' differences, from their MSE over all those
    frames. A still reference makes them the output's own flicker.

    Args:
        frames, refs: ``(T, B, C, H, W)`` outputs and references, ``T > warmup + 1``.
        warmup: leading frames left out (the first difference used is ``x_{warmup+1} - x_warmup``).

    Returns:
        ``{"trmae": float, "tpsnr": float}`` (tPSNR is ``inf`` for identical differences).

    Example:
        >>> ref = torch.ones(4, 1, 3, 8, 8)
        >>> temporal(ref + 0.1 * torch.arange(4.0).view(4, 1, 1, 1, 1) % 2, ref)["trmae"] > 0
        True
    """
    if frames.dim() != 5 or refs.shape != frames.shape:
        raise ShapeError(f"frames, refs: expected equal (T, B, C, H, W) shapes, got {tuple(frames.shape)} and "
                         f"{tuple(refs.shape)}")
    if isinstance(warmup, bool) or not isinstance(warmup, int) or not 0 <= warmup < frames.shape[0] - 1:
        raise ValueError(f"warmup: expected an int in [0, T - 1) for T = {frames.shape[0]}, got {warmup!r}")
    x, y = frames[warmup:], refs[warmup:]
    for name, t in (("frames", x), ("refs", y)):
        check_floating(t, name)
        check_finite(t, name)
    dx, dy = (x[1:] - x[:-1]).flatten(0, 1), (y[1:] - y[:-1]).flatten(0, 1)
    tx, ty = tonemap(x), tonemap(y)
    err = float(((tx[1:] - tx[:-1]) - (ty[1:] - ty[:-1])).double().square().mean())
    return {"trmae": float(rmae(dx, dy)), "tpsnr": float("inf") if err == 0 else 10 * math.log10(1 / err)}


def summary(x: torch.Tensor, ref: torch.Tensor) -> dict[str, float]:
    """The standard table for HDR images ``(B, 3, H, W)`` against ``ref``: ``mse``, ``relmse``,
    ``psnr_db`` and ``ssim`` (both on Reinhard-tone-mapped values, range 1; SSIM only from 11
    px, its window) and HDR-``flip`` (of the values clamped at 0). Means over the batch.

    Example:
        >>> ref = torch.rand(1, 3, 16, 16)
        >>> sorted(summary(ref, ref))
        ['flip', 'mse', 'psnr_db', 'relmse', 'ssim']
    """
    out = {"mse": float(mse(x, ref)), "relmse": float(relmse(x, ref)),
           "psnr_db": float(psnr(x, ref, tonemap_method="reinhard"))}
    if min(x.shape[-2:]) >= 11:
        out["ssim"] = float(ssim(tonemap(x), tonemap(ref), data_range=1.0))
    out["flip"] = float(flip(x.clamp_min(0), ref.clamp_min(0)))
    return out
