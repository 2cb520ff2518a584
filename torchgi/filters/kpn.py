"""A multi-resolution kernel-predicting network (Bako et al. 2017, Vogels et al. 2018), sized for
CPUs: a small U-Net at half resolution and below predicts, for every pixel of four scales (full,
1/2, 1/4, 1/8), a normalised kernel (3x3 at full resolution, 5x5 below) applied to the
demodulated irradiance through :func:`~torchgi.filters.apply_kernels`, and a weight per pixel
with which each scale replaces the low frequencies of the finer one (Vogels' scale compositor).

Inputs (:func:`kpn_features`): the noisy irradiance ``(colour - emission) / albedo`` log-scaled,
its per-pixel variance as a log relative variance, ``log2(spp)``, albedo, normal and a
per-image normalised log depth. The softmax kernels can tighten to their centre tap, and the
compositor to the finest scale, so the output can be the input where the input is clean.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from torchgi.core.check import check_same_device, check_same_floating, check_shape, is_tracing
from torchgi.core.dtypes import compute_dtype
from torchgi.filters.kernels import apply_kernels
from torchgi.filters.learned import SavedNet, shipped

__all__ = ["ALIGN", "FEATURES", "KPN", "REACH", "WEIGHTS", "KPNet", "default_net", "kpn", "kpn_denoise", "kpn_features", "log_depth_mean"]

WEIGHTS = Path(__file__).with_name("kpn_weights.json")
ALIGN = 16  # the network's H and W are multiples of it (kpn pads to it)
REACH = 80  # px: an output pixel depends on the inputs within this distance (tiles overlap by it)

FEATURES = 13  # kpn_features' channels
_ALBEDO_FLOOR = 0.02  # below it a pixel is filtered as colour, not as irradiance
_LEVELS = 4
_TAPS = (9, 25, 25, 25)  # kernel taps at full, 1/2, 1/4 and 1/8 resolution


def _luma(x: torch.Tensor) -> torch.Tensor:
    return (0.2126 * x[:, 0:1] + 0.7152 * x[:, 1:2] + 0.0722 * x[:, 2:3])


def kpn_features(
    color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor,
    emission: torch.Tensor, variance: torch.Tensor | None, spp: float | torch.Tensor,
    depth_mean: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The network's inputs and the image it filters.

    Args:
        color, albedo, normal, emission: ``(B, 3, H, W)``; depth ``(B, 1, H, W)``; variance
            ``(B, 3|1, H, W)`` of the colour's mean (None or zeros: unknown, as at 1 spp).
        spp: samples per pixel, a float or a ``(B,)`` tensor.
        depth_mean: ``(B, 1, 1, 1)`` the mean log depth the depth is centred by (None: this
            image's, :func:`log_depth_mean`; a tile passes its whole image's).

    Returns:
        ``features (B, 13, H, W)``, the irradiance ``(B, 3, H, W)`` to filter and the
        ``albedo`` it is remodulated by ``(B, 3, H, W)`` (1 where the albedo is below 0.02).

    Example:
        >>> x = torch.rand(1, 3, 8, 8)
        >>> f, irr, alb = kpn_features(x, x, x, torch.ones(1, 1, 8, 8), x * 0, None, 4.0)
        >>> f.shape, irr.shape
        (torch.Size([1, 13, 8, 8]), torch.Size([1, 3, 8, 8]))
    """
    B = color.shape[0]
    alb = torch.where(albedo < _ALBEDO_FLOOR, torch.ones_like(albedo), albedo)
    irr = (color - emission).clamp_min(0) / alb
    if variance is None:
        variance = torch.zeros_like(color[:, :1])
    var = _luma(variance) if variance.shape[1] == 3 else variance
    var_irr = var / _luma(alb).square()
    rel_var = torch.log1p(var_irr / (_luma(irr).square() + 1e-3))
    spp_t = torch.as_tensor(spp, dtype=color.dtype, device=color.device).reshape(-1, 1, 1, 1).expand(B, 1, *color.shape[2:])
    d = torch.log(depth.clamp_min(1e-6))
    hit = depth > 0
    mean = log_depth_mean(depth) if depth_mean is None else depth_mean.to(d.dtype)
    d = torch.where(hit, d - mean, torch.zeros_like(d))
    features = torch.cat([torch.log1p(irr), rel_var, torch.log2(spp_t) / 6.0, albedo, normal, d,
                          torch.log1p(_luma(emission))], 1)
    return features, irr, alb


def log_depth_mean(depth: torch.Tensor) -> torch.Tensor:
    """The mean log depth over the hits (depth > 0) of each image: ``(B, 1, 1, 1)`` (0 without one).

    Example:
        >>> log_depth_mean(torch.tensor([[[[1.0, 0.0]]]])).flatten().tolist()
        [0.0]
    """
    hit = depth > 0
    d = torch.log(depth.clamp_min(1e-6))
    return (d * hit).sum((2, 3), keepdim=True) / hit.sum((2, 3), keepdim=True).clamp_min(1)


def _conv(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.LeakyReLU(0.1, inplace=True))


class KPNet(SavedNet):
    """The predictor: features ``(B, 13, H, W)`` (H, W multiples of 16) to each scale's kernel
    logits and compositor weights.

    Args:
        widths: channels at 1/2, 1/4 and 1/8 resolution.

    Example:
        >>> net = KPNet((8, 8, 8))
        >>> [k.shape[1] for k in net(torch.rand(1, 13, 16, 16))[0]]
        [9, 25, 25, 25]
    """

    def __init__(self, widths: tuple[int, int, int] | list[int] = (24, 32, 48)) -> None:
        super().__init__()
        self.widths = tuple(int(w) for w in widths)
        w1, w2, w3 = self.widths
        self.enc1 = nn.Sequential(_conv(4 * FEATURES, w1), _conv(w1, w1))
        self.enc2 = nn.Sequential(_conv(w1, w2), _conv(w2, w2))
        self.enc3 = nn.Sequential(_conv(w2, w3), _conv(w3, w3))
        self.dec2 = _conv(w2 + w3, w2)
        self.dec1 = _conv(w1 + w2, w1)
        self.head1 = nn.Conv2d(w1, 4 * _TAPS[0] + _TAPS[1] + 2, 1)  # full-res kernels (shuffled), 1/2 kernel, 2 weights
        self.head2 = nn.Conv2d(w2, _TAPS[2] + 1, 1)
        self.head3 = nn.Conv2d(w3, _TAPS[3] + 1, 1)

    def config(self) -> dict[str, Any]:
        return {"widths": list(self.widths)}

    def forward(self, features: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Kernel logits per scale ``(B, taps, H / 2^s, W / 2^s)`` and compositor weights in
        (0, 1) for scales 0-2 ``(B, 1, H / 2^s, W / 2^s)``."""
        e1 = self.enc1(F.pixel_unshuffle(features, 2))
        e2 = self.enc2(F.avg_pool2d(e1, 2))
        e3 = self.enc3(F.avg_pool2d(e2, 2))
        d2 = self.dec2(torch.cat([e2, F.interpolate(e3, scale_factor=2.0, mode="nearest")], 1))
        d1 = self.dec1(torch.cat([e1, F.interpolate(d2, scale_factor=2.0, mode="nearest")], 1))
        h1, h2, h3 = self.head1(d1), self.head2(d2), self.head3(e3)
        n0 = 4 * _TAPS[0]
        k0 = F.pixel_shuffle(h1[:, :n0], 2)
        k1 = h1[:, n0:n0 + _TAPS[1]]
        a0 = F.interpolate(torch.sigmoid(h1[:, -2:-1]), scale_factor=2.0, mode="bilinear", align_corners=False)
        a1 = torch.sigmoid(h1[:, -1:])
        k2, a2 = h2[:, :_TAPS[2]], torch.sigmoid(h2[:, -1:])
        k3 = h3[:, :_TAPS[3]]
        return [k0, k1, k2, k3], [a0, a1, a2]


def _down(x: torch.Tensor) -> torch.Tensor:
    return F.avg_pool2d(x, 2)


def _up(x: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)


def kpn_denoise(net: KPNet, features: torch.Tensor, irradiance: torch.Tensor,
                return_weights: bool = False) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """The filtered irradiance ``(B, 3, H, W)``: each scale's kernels applied to the irradiance
    box-downsampled to that scale, then composited coarse to fine,
    ``f_s <- f_s + a_s (up(f_{s+1}) - up(down(f_s)))`` (Vogels et al. 2018).

    Args:
        net: the predictor; features: ``(B, 13, H, W)``; irradiance: ``(B, 3, H, W)``, with
            H and W multiples of 16.
        return_weights: also return the compositor weights ``a_0, a_1, a_2`` in (0, 1),
            upsampled (bilinear) to ``(B, 3, H, W)``: how much of each coarser scale's low
            frequencies each pixel took.

    Example:
        >>> f, irr, _ = kpn_features(*(torch.rand(1, 3, 16, 16),) * 3, torch.ones(1, 1, 16, 16),
        ...                          torch.zeros(1, 3, 16, 16), None, 1.0)
        >>> kpn_denoise(KPNet((8, 8, 8)), f, irr).shape
        torch.Size([1, 3, 16, 16])
    """
    kernels, weights = net(features)
    images = [irradiance]
    for _ in range(_LEVELS - 1):
        images.append(_down(images[-1]))
    filtered = [apply_kernels(img, torch.softmax(k, 1), normalize=True) for img, k in zip(images, kernels)]
    out = filtered[-1]
    for s in range(_LEVELS - 2, -1, -1):
        f = filtered[s]
        out = f + weights[s] * (_up(out) - _up(_down(f)))
    if not return_weights:
        return out
    return out, torch.cat([weights[0], _up(weights[1]), _up(_up(weights[2]))], 1)


_DEFAULT: dict[torch.device, KPNet] = {}


def default_net(device: torch.device | str = "cpu") -> KPNet:
    """The shipped network (``kpn_weights.json``, ``scripts/train_kpn.py``) on ``device``: read
    once per process, one copy per device."""
    return shipped(KPNet, WEIGHTS, device, _DEFAULT, "the kpn's weights", "scripts/train_kpn.py")


def kpn(
    color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, *,
    emission: torch.Tensor | None = None, variance: torch.Tensor | None = None, spp: float | torch.Tensor = 1.0,
    net: KPNet | None = None, return_weights: bool = False, depth_mean: torch.Tensor | None = None,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """The denoised colour ``(B, 3, H, W)`` (same units, dtype and device as ``color``): the
    kernel-predicting network on the demodulated irradiance, remodulated by the albedo, with the
    light seen directly (``emission``) added back unfiltered. Any H and W (padded by edge
    replication to multiples of :data:`ALIGN` for the network, then cropped).

    Args:
        color: ``(B, 3, H, W)`` noisy radiance (the mean of ``spp`` samples), >= 0.
        albedo, normal: ``(B, 3, H, W)`` guides; depth ``(B, 1, H, W)`` (0 where nothing was hit).
        emission: ``(B, 3, H, W)`` light seen directly (None: none).
        variance: ``(B, 3|1, H, W)`` of the colour's mean (None or zeros: unknown, as at 1 spp).
        spp: samples per pixel, a float or a ``(B,)`` tensor (what the network was told in training).
        net: the predictor (None: the shipped one, on ``color``'s device).
        return_weights: also return the compositor weights ``(B, 3, H, W)`` (:func:`kpn_denoise`).
        depth_mean: ``(B, 1, 1, 1)``, for a tile: its whole image's :func:`log_depth_mean` (None:
            this image's). A tile whose origin is on multiples of :data:`ALIGN` px with
            :data:`REACH` px of the image around its core gives the untiled output there.

    Example:
        >>> x = torch.rand(1, 3, 20, 24)
        >>> kpn(x, x, x, torch.ones(1, 1, 20, 24), spp=4.0, net=KPNet((8, 8, 8))).shape
        torch.Size([1, 3, 20, 24])
    """
    sizes = check_shape(color, "B 3 H W", "color")
    same = {"B": sizes["B"], "H": sizes["H"], "W": sizes["W"]}
    for name, t, c in (("albedo", albedo, "3"), ("normal", normal, "3"), ("depth", depth, "1"),
                       ("emission", emission, "3")):
        if t is not None:
            check_shape(t, f"B {c} H W", name, same)
    if variance is not None:
        check_shape(variance, "B C H W", "variance", same)
    named = {"color": color, "albedo": albedo, "normal": normal, "depth": depth, "emission": emission,
             "variance": variance}
    check_same_device(named)
    check_same_floating(named)
    net = default_net(color.device) if net is None else net
    ct = next(net.parameters()).dtype
    H, W = sizes["H"], sizes["W"]
    pad = (0, (ALIGN - W % ALIGN) % ALIGN, 0, (ALIGN - H % ALIGN) % ALIGN)
    padded = is_tracing() or any(pad)  # (a graph pads always: its sizes are symbolic)

    def prep(t: torch.Tensor | None) -> torch.Tensor | None:
        if t is None:
            return None
        t = t.to(compute_dtype(t.dtype)).to(ct)
        return F.pad(t, pad, mode="replicate") if padded else t

    c, a, n, d, v = (prep(t) for t in (color, albedo, normal, depth, variance))
    e = prep(emission) if emission is not None else torch.zeros_like(c)
    f, irr, alb = kpn_features(c, a, n, d, e, v, spp, log_depth_mean(depth.to(ct)) if depth_mean is None else depth_mean)
    out, weights = kpn_denoise(net, f, irr, return_weights=True)
    out = (out * alb + e)[..., :H, :W].to(color.dtype)
    return (out, weights[..., :H, :W].to(color.dtype)) if return_weights else out


class KPN(nn.Module):
    """Module form of :func:`kpn`; the network is a submodule (moves with ``.to()``; None: the
    shipped one).

    Example:
        >>> x = torch.rand(1, 3, 16, 16)
        >>> KPN(KPNet((8, 8, 8)))(x, x, x, torch.ones(1, 1, 16, 16), spp=2.0).shape
        torch.Size([1, 3, 16, 16])
    """

    def __init__(self, net: KPNet | None = None) -> None:
        super().__init__()
        self.net = net if net is not None else KPNet.load(WEIGHTS)

    def forward(self, color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, *,
                emission: torch.Tensor | None = None, variance: torch.Tensor | None = None,
                spp: float | torch.Tensor = 1.0) -> torch.Tensor:
        return kpn(color, albedo, normal, depth, emission=emission, variance=variance, spp=spp, net=self.net)
