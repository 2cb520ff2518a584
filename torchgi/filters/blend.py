"""Per-pixel blend of guided-filter outputs, the weights from a small learned network (issue 17).

One filter setting cannot fit a whole image: flat walls want a wide window, shading edges,
contact shadows and thin geometry a narrow one. Following Kalantari et al. 2015 (a learned
per-pixel choice of filter parameters) and Li, Wu & Chuang 2012 (per-pixel blending of several
filter outputs), :func:`blend` filters the source with the guided filter at several radii, adds a
second guided pass whose guide also holds the log-luminance of a first-pass estimate (so shadow
and shading edges that normal and depth do not show are kept) and guided passes with a much
smaller ε (curved glossy surfaces), and mixes these *candidates* per pixel with softmax weights

    out = Σ_k w_k · c_k,   w = softmax(MLP(features)),

where the features are scale-free local statistics (log-luminance ratios between candidates,
their local disagreement, the source's local relative variance, the guide's local edge energy
and log2 of the sample count). The network is a per-pixel MLP (1x1 convolutions), a few thousand
weights, trained by ``scripts/train_blend.py`` on project-rendered scenes that are never
benchmark scenes; the weights ship beside this module (``blend_weights.json``) with their
training config, commit and data hash.

Everything is plain tensor code on top of :func:`~torchgi.filters.guided` and
:func:`~torchgi.filters.box` (so the compiled back ends run the filters): differentiable with
respect to the source, guide and the network's weights, ONNX-exportable, float16 in and out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchgi.core.check import check_floating, check_same_device, check_same_floating, check_shape, is_recording
from torchgi.core.dtypes import compute_dtype
from torchgi.core.errors import RangeError
from torchgi.filters.box import box
from torchgi.filters.guided import guided
from torchgi.filters.learned import SavedNet, shipped

__all__ = ["Blend", "BlendNet", "blend", "blend_candidates", "blend_features", "default_net"]

WEIGHTS = Path(__file__).with_name("blend_weights.json")


def _luminance(x: torch.Tensor) -> torch.Tensor:
    """``(B,1,H,W)`` channel mean of ``x (B,C,H,W)`` (light is >= 0; the mean is scale-free)."""
    return x.mean(1, keepdim=True)


def _floor(x: torch.Tensor) -> torch.Tensor:
    """``(B,1,1,1)``: 1 % of each image's mean luminance (at least 1e-6), the level below which
    log-luminance features stop resolving differences."""
    return (0.01 * x.mean(dim=(1, 2, 3), keepdim=True)).clamp_min(1e-6)


def blend_candidates(
    x: torch.Tensor, guide: torch.Tensor, *, radii: Sequence[int], eps: float, colour_radii: Sequence[int],
    colour_scale: float, fine_radii: Sequence[int] = (), fine_eps: float = 1e-6,
) -> list[torch.Tensor]:
    """The candidates :func:`blend` mixes, in this order: ``x`` itself; the guided filter of
    ``x`` at each of ``radii`` with ``eps``; the colour-guided passes at each of ``colour_radii``
    (guide: the first ``min(G, 3)`` guide channels plus ``colour_scale · log(L + floor)`` of the
    ``radii[1]`` output, ``L`` its channel mean, ``floor`` 1 % of the mean of ``x``); the guided
    filter at each of ``fine_radii`` with ``fine_eps`` (a sharper linear model, for curved glossy
    surfaces).

    Args:
        x: ``(B, C, H, W)`` source (demodulated light, >= 0).
        guide: ``(B, G, H, W)``, ``1 <= G <= 4``, as for :func:`~torchgi.filters.guided`.
        radii: guided-filter radii (px), at least 2.
        eps, fine_eps: the guided filter's ε (guide units squared).
        colour_radii, fine_radii: radii (px) of the colour-guided and the fine passes.
        colour_scale: weight of the log-luminance guide channel (guide units per e-fold).

    Returns:
        ``1 + len(radii) + len(colour_radii) + len(fine_radii)`` tensors ``(B, C, H, W)`` in the
        dtype of ``x``.

    Example:
        >>> x, g = torch.rand(1, 3, 16, 16), torch.rand(1, 4, 16, 16)
        >>> len(blend_candidates(x, g, radii=(1, 2, 4), eps=1e-4, colour_radii=(4,), colour_scale=0.1,
        ...                      fine_radii=(2,)))
        6
    """
    out = [x] + [guided(x, guide, radius=r, eps=eps) for r in radii]
    floor = _floor(x)
    lum = torch.log(_luminance(out[2]).clamp_min(0) + floor) * colour_scale
    keep = guide[:, : min(guide.shape[1], 3)]
    colour_guide = torch.cat([keep, lum], 1)
    out += [guided(x, colour_guide, radius=r, eps=eps) for r in colour_radii]
    out += [guided(x, guide, radius=r, eps=fine_eps) for r in fine_radii]
    return out


def blend_features(
    candidates: Sequence[torch.Tensor], guide: torch.Tensor, spp: float | torch.Tensor, reference: int
) -> torch.Tensor:
    """``(B, F, H, W)`` scale-free per-pixel features of the candidates (``F = K + 4`` for ``K``
    candidates): ``log`` luminance ratios of every candidate but ``reference`` to it; the local
    (3x3) relative variance of the first candidate (the source); the 5x5 disagreement of the
    second and second-to-last candidates; the guide's 3x3 edge energy; ``log2(spp)``; and a
    constant 1 (a bias the ONNX graph keeps).

    Example:
        >>> c = [torch.rand(1, 3, 8, 8) for _ in range(4)]
        >>> blend_features(c, torch.rand(1, 4, 8, 8), 4.0, reference=2).shape
        torch.Size([1, 8, 8, 8])
    """
    lums = [_luminance(c).clamp_min(0) for c in candidates]
    floor = _floor(candidates[0])
    log_ref = torch.log(lums[reference] + floor)
    feats = [torch.log(lum + floor) - log_ref for k, lum in enumerate(lums) if k != reference]
    src = lums[0]
    var = (box(src.square(), 1) - box(src, 1).square()).clamp_min(0)
    feats.append(0.5 * torch.log(var + floor.square()) - log_ref)
    diff = box((lums[1] - lums[-2]).square(), 2)
    feats.append(0.5 * torch.log(diff + floor.square()) - log_ref)
    dx = torch.nn.functional.pad((guide[..., :, 1:] - guide[..., :, :-1]).square().sum(1, keepdim=True), (0, 1))
    dy = torch.nn.functional.pad((guide[..., 1:, :] - guide[..., :-1, :]).square().sum(1, keepdim=True), (0, 0, 0, 1))
    feats.append(torch.log(box(dx + dy, 1) + 1e-4))
    ones = torch.ones_like(src)
    spp_t = torch.as_tensor(spp, dtype=src.dtype, device=src.device).reshape(-1, 1, 1, 1)
    feats.append(ones * torch.log2(spp_t.clamp_min(1)))
    feats.append(ones)
    return torch.cat(feats, 1)


class BlendNet(SavedNet):
    """The per-pixel MLP of :func:`blend`: ``features (B, F, H, W)`` → logits ``(B, K, H, W)``
    (the features and their box means at ``context`` radii, two hidden ReLU layers as 1x1
    convolutions), and the candidate set it was trained for.

    Args:
        features: ``F``, the number of input features.
        hidden: width of the two hidden layers.
        radii, eps, colour_radii, colour_scale, fine_radii, fine_eps: the candidate set
            (:func:`blend_candidates`).
        reference: index of the candidate the log-luminance features are relative to.
        context: radii (px) of the box means of the features added as further inputs.

    Example:
        >>> net = BlendNet(radii=(1, 2, 4))
        >>> net.candidates, net(torch.rand(1, net.features, 8, 8)).shape
        (8, torch.Size([1, 8, 8, 8]))
    """

    def __init__(self, *, radii: Sequence[int] = (1, 2, 4, 8), eps: float = 1e-5,
                 colour_radii: Sequence[int] = (4, 8), colour_scale: float = 0.1, reference: int = 3,
                 hidden: int = 32, context: Sequence[int] = (2, 8), fine_radii: Sequence[int] = (2, 4),
                 fine_eps: float = 1e-6) -> None:
        super().__init__()
        if len(radii) < 2 or any(int(r) != r or r < 1 for r in radii):
            raise RangeError(f"radii: expected at least two ints >= 1, got {list(radii)}")
        self.radii, self.eps = tuple(int(r) for r in radii), float(eps)
        self.colour_radii, self.colour_scale = tuple(int(r) for r in colour_radii), float(colour_scale)
        self.fine_radii, self.fine_eps = tuple(int(r) for r in fine_radii), float(fine_eps)
        self.candidates = 1 + len(self.radii) + len(self.colour_radii) + len(self.fine_radii)
        if not 0 <= reference < self.candidates:
            raise RangeError(f"reference: expected an index below {self.candidates}, got {reference}")
        self.reference, self.hidden, self.context = int(reference), int(hidden), tuple(int(r) for r in context)
        self.features = self.candidates + 4
        inputs = self.features + (self.features - 2) * len(self.context)
        self.mlp = nn.Sequential(
            nn.Conv2d(inputs, hidden, 1), nn.ReLU(), nn.Conv2d(hidden, hidden, 1), nn.ReLU(),
            nn.Conv2d(hidden, self.candidates, 1),
        )

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        # the varying features' local means (the last two are constant planes)
        parts = [features] + [box(features[:, :-2], r) for r in self.context]
        # the 1x1 convolutions as batched (out, in) x (in, pixels) products on the NCHW layout: no
        # transposes, bias and ReLU in place (the same weights; faster than mkldnn's 1x1 convolution)
        h = torch.cat(parts, 1)
        B, _, H, W = h.shape
        z = h.reshape(B, -1, H * W)
        layers = [m for m in self.mlp if isinstance(m, nn.Conv2d)]
        for i, conv in enumerate(layers):
            z = torch.baddbmm(conv.bias[None, :, None].expand(B, -1, 1), conv.weight.flatten(1).expand(B, -1, -1), z)
            z = z.relu_() if i < len(layers) - 1 else z
        return z.reshape(B, -1, H, W)

    def candidate_radii(self) -> list[int]:
        """Each candidate's window radius in px, in candidate order (the source itself: 0)."""
        return [0, *self.radii, *self.colour_radii, *self.fine_radii]

    def config(self) -> dict[str, Any]:
        """The constructor arguments (what the weights file records)."""
        return {"radii": list(self.radii), "eps": self.eps, "colour_radii": list(self.colour_radii),
                "colour_scale": self.colour_scale, "reference": self.reference, "hidden": self.hidden,
                "context": list(self.context), "fine_radii": list(self.fine_radii), "fine_eps": self.fine_eps}


_DEFAULT: dict[torch.device, BlendNet] = {}


def default_net(device: torch.device | str = "cpu") -> BlendNet:
    """The shipped network (``blend_weights.json``) on ``device``: read once per process, one
    copy per device."""
    return shipped(BlendNet, WEIGHTS, device, _DEFAULT, "the blend's weights", "scripts/train_blend.py")


def _weights(net: BlendNet, candidates: Sequence[torch.Tensor], guide: torch.Tensor,
             spp: float | torch.Tensor) -> torch.Tensor:
    """``(B, K, H, W)`` softmax blend weights (computed in the network's dtype)."""
    feats = blend_features(candidates, guide, spp, net.reference)
    p = next(net.parameters())
    return torch.softmax(net(feats.to(p.dtype)), 1)


_LARGEST = 2.0**60  # the features square box means of the light: keep them within float32
_SMALLEST = 1e-4  # below this mean light, 1 % of it is under _floor's bound of 1e-6


def _exponent_shift(x: torch.Tensor) -> int:
    """``k`` such that ``x * 2^-k`` is of order 1 when ``x (B,C,H,W)`` holds values above
    :data:`_LARGEST` (whose squares would overflow the features' float32) or its mean lies below
    :data:`_SMALLEST` (where :func:`_floor`'s lower bound would stop being 1 % of the mean),
    else 0 (traced or exported graphs: 0)."""
    if is_recording() or x.numel() == 0:
        return 0
    peak, mean = float(x.detach().abs().amax()), float(x.detach().mean())  # (a scale choice, not differentiated)
    if not math.isfinite(peak):
        return 0
    if peak > _LARGEST:
        return math.frexp(peak)[1]
    return math.frexp(mean)[1] if 0 < mean < _SMALLEST else 0


def blend(
    x: torch.Tensor, guide: torch.Tensor, *, spp: float | torch.Tensor = 1.0, net: BlendNet | None = None,
    return_weights: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Blend the guided-filter candidates of ``x`` per pixel with learned weights.

    Args:
        x: ``(B, C, H, W)`` source, >= 0 (the Denoiser's demodulated, firefly-clamped light).
        guide: ``(B, G, H, W)``, ``1 <= G <= 4``, same dtype and device (e.g.
            :func:`~torchgi.filters.guide_from`).
        spp: samples per pixel the noise corresponds to, a float or ``(B,)`` tensor (>= 1).
        net: the network, on ``x``'s device; None = the shipped one there (:func:`default_net`).
        return_weights: also return the ``(B, K, H, W)`` weights (the per-pixel choice).

    Returns:
        ``(B, C, H, W)`` in the dtype and on the device of ``x`` (float16 is computed in float32),
        and the weights when asked.

    Example:
        >>> x, g = torch.rand(1, 3, 16, 16), torch.rand(1, 4, 16, 16)
        >>> out, w = blend(x, g, spp=1.0, return_weights=True)
        >>> out.shape, w.shape, bool(torch.allclose(w.sum(1), torch.ones(1, 16, 16)))
        (torch.Size([1, 3, 16, 16]), torch.Size([1, 9, 16, 16]), True)
    """
    check_shape(x, "B C H W", "x")
    check_floating(x, "x")
    check_same_device({"x": x, "guide": guide})
    check_same_floating({"x": x, "guide": guide})
    if isinstance(spp, bool) or isinstance(spp, (int, float)) and not (math.isfinite(spp) and spp >= 1):
        raise RangeError(f"spp: expected a finite number >= 1, got {spp!r}")
    net = default_net(x.device) if net is None else net
    if next(net.parameters()).device != x.device:
        raise ValueError(f"net: on {next(net.parameters()).device}, x on {x.device} (move one of them)")
    ct = compute_dtype(x.dtype)
    xs, gs = x.to(ct), guide.to(ct)
    shift = _exponent_shift(xs)
    if shift:  # a power of two: exact, and the blend is scale-equivariant (its features are scale-free)
        xs = xs * 2.0**-shift
    cands = blend_candidates(xs, gs, radii=net.radii, eps=net.eps, colour_radii=net.colour_radii,
                             colour_scale=net.colour_scale, fine_radii=net.fine_radii,
                             fine_eps=net.fine_eps)
    w = _weights(net, cands, gs, spp).to(ct)
    out = sum(w[:, k : k + 1] * c for k, c in enumerate(cands))
    out = (out * 2.0**shift if shift else out).to(x.dtype)
    return (out, w.to(x.dtype)) if return_weights else out


class Blend(nn.Module):
    """Module form of :func:`blend`; the network is a submodule (moves with ``.to()``).

    Example:
        >>> Blend()(torch.rand(1, 3, 8, 8), torch.rand(1, 4, 8, 8), spp=2.0).shape
        torch.Size([1, 3, 8, 8])
    """

    def __init__(self, net: BlendNet | None = None) -> None:
        super().__init__()
        self.net = net if net is not None else BlendNet.load(WEIGHTS)

    def forward(self, x: torch.Tensor, guide: torch.Tensor, spp: float | torch.Tensor = 1.0) -> torch.Tensor:
        return blend(x, guide, spp=spp, net=self.net)
