"""The network of the learned pyramid (:mod:`torchgi.filters.pyramid`): a small U-Net at 1/4
resolution from the pyramid's features to its per-pixel parameters, and the shipped weights."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchgi.backends.torch_code.filter_box import block_mean
from torchgi.backends.torch_code.pyramid import up2
from torchgi.core.errors import RangeError
from torchgi.filters.learned import SavedNet, shipped

__all__ = ["BANDS", "WEIGHTS", "PyramidNet", "default_net"]

WEIGHTS = Path(__file__).with_name("pyramid_weights.json")
BANDS = (1, 2, 4, 8)  # the residual's bands (the last one its low-pass), one gain each


def _triples(values: Sequence[Sequence[float]], name: str) -> tuple[tuple[int, int, float], ...]:
    """Checked ``(scale, radius, eps)`` triples: scale a power of two in [1, 64], radius an int
    >= 1, eps > 0."""
    out = []
    for c in values:
        s, r, e = int(c[0]), int(c[1]), float(c[2])
        if not 1 <= s <= 64 or s & (s - 1) or r < 1 or c[1] != r or not 0 < e < math.inf:
            raise RangeError(f"{name}: expected (scale: a power of two in [1, 64], radius: int >= 1, "
                             f"eps > 0), got {tuple(c)}")
        out.append((s, r, e))
    return tuple(out)


class PyramidNet(SavedNet):
    """The network of :func:`pyramid`: features ``(B, F, h, w)`` at 1/4 resolution → ``(B, K +
    4, h, w)`` (``K + 9`` with ``direct``): logits over the ``K`` candidates (``candidates`` then
    ``colour``), then the gain logits of the residual's bands (:data:`BANDS`), then with
    ``direct`` the correction ``δ`` (3) and the logits of the clamped light's gains at 1/4 and
    1/16; and the candidate set it was trained for.

    Args:
        candidates: ``(scale, radius, eps)`` per candidate on the guide: the pyramid scale (2, 4,
            8, ...: a power of two >= 2), the window radius in pixels of that scale and ε (guide
            units²).
        colour: the same for the colour candidates (module docstring; none by default).
        colour_scale: λ, the colour channel's guide units per e-fold of luminance.
        widths: channels of the U-Net's three levels (1/4, 1/8, 1/16 resolution).
        direct: the direct term (module docstring): two more features, five more outputs.

    Example:
        >>> net = PyramidNet()
        >>> net(torch.rand(1, net.features, 16, 16)).shape
        torch.Size([1, 13, 16, 16])
        >>> PyramidNet(direct=True).features, PyramidNet(direct=True).head.out_channels
        (21, 18)
    """

    def __init__(self, *, candidates: Sequence[Sequence[float]] = ((2, 1, 1e-5), (2, 2, 1e-5), (2, 2, 1e-6),
                                                                    (4, 2, 1e-5), (4, 4, 1e-5), (8, 2, 1e-5),
                                                                    (8, 4, 1e-5), (1, 1, 1e-5), (1, 2, 1e-6)),
                 colour: Sequence[Sequence[float]] = (),
                 colour_scale: float = 0.1, widths: Sequence[int] = (16, 24, 32), direct: bool = False) -> None:
        super().__init__()
        self.geometric = _triples(candidates, "candidates")
        self.colour = _triples(colour, "colour")
        self.candidates = self.geometric + self.colour
        if not self.geometric or len(widths) != 3 or not 0 < colour_scale < math.inf:
            raise RangeError(f"candidates, widths, colour_scale: expected at least one candidate, three widths and "
                             f"a scale > 0, got {len(self.geometric)}, {list(widths)} and {colour_scale!r}")
        self.colour_scale = float(colour_scale)
        self.widths = tuple(int(w) for w in widths)
        self.direct = bool(direct)
        self.top = max(s for s, _, _ in self.candidates)
        self.features = 10 + len(self.candidates) + 2 * self.direct
        w1, w2, w3 = self.widths
        conv = lambda i, o, k=3: nn.Conv2d(i, o, k, padding=k // 2)
        self.enc1 = nn.Sequential(conv(self.features, w1), nn.ReLU(), conv(w1, w1), nn.ReLU())
        self.enc2 = nn.Sequential(conv(w1, w2), nn.ReLU(), conv(w2, w2), nn.ReLU())
        self.enc3 = nn.Sequential(conv(w2, w3), nn.ReLU(), conv(w3, w3), nn.ReLU())
        self.dec2 = nn.Sequential(conv(w3 + w2, w2), nn.ReLU())
        self.dec1 = nn.Sequential(conv(w2 + w1, w1), nn.ReLU())
        # candidate logits, then gain logits, then (direct) a low-frequency correction per channel
        # and the gains of the clamped-away light at 1/4 and 1/16
        self.head = conv(w1, len(self.candidates) + len(BANDS) + 5 * self.direct, 1)
        if self.direct:  # no correction to begin with
            with torch.no_grad():
                self.head.weight[-5:].zero_()
                self.head.bias[-5:-2].zero_()
                self.head.bias[-2:].fill_(-4.0)
        # the features' standardisation, set from the training data (scripts/train_pyramid.py)
        self.register_buffer("shift", torch.zeros(self.features))
        self.register_buffer("scale", torch.ones(self.features))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        e1 = self.enc1((features - self.shift[:, None, None]) * self.scale[:, None, None])
        e2 = self.enc2(block_mean(e1, 2))
        e3 = self.enc3(block_mean(e2, 2))
        d2 = self.dec2(torch.cat([up2(e3, e2.shape[-2:]), e2], 1))
        d1 = self.dec1(torch.cat([up2(d2, e1.shape[-2:]), e1], 1))
        return self.head(d1)

    def config(self) -> dict[str, Any]:
        """The constructor arguments (what the weights file records)."""
        return {"candidates": [list(c) for c in self.geometric], "colour": [list(c) for c in self.colour],
                "colour_scale": self.colour_scale, "widths": list(self.widths), "direct": self.direct}


_DEFAULT: dict[torch.device, PyramidNet] = {}


def default_net(device: torch.device | str = "cpu") -> PyramidNet:
    """The shipped network (``pyramid_weights.json``) on ``device``: read once per process, one
    copy per device."""
    return shipped(PyramidNet, WEIGHTS, device, _DEFAULT, "the pyramid's weights", "scripts/train_pyramid.py")
