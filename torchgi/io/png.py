"""8-bit sRGB previews (contact sheets, density maps) written as PNG through imageio (the
``image`` extra, which the demo's ``all`` installs)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from torchgi.core.check import check_finite, check_positive, check_shape, require
from torchgi.core.files import temp_beside

__all__ = ["to_srgb8", "write_png"]


def to_srgb8(image: torch.Tensor, *, exposure: float = 1.0) -> np.ndarray:
    """Linear ``(C, H, W)`` radiance (C = 1 or 3) to an ``(H, W, C)`` uint8 sRGB array.

    Values are scaled by ``exposure``, clipped to [0, 1] (display only) and sRGB-encoded.

    Example:
        >>> to_srgb8(torch.ones(3, 2, 2))[0, 0].tolist()
        [255, 255, 255]
    """
    check_shape(image, "C H W", "image")
    check_finite(image, "image")
    check_positive(exposure, "exposure")
    x = (image.detach().float().cpu() * exposure).clamp(0, 1)
    srgb = torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.pow(1 / 2.4) - 0.055)
    return (srgb * 255 + 0.5).to(torch.uint8).permute(1, 2, 0).numpy()


def write_png(path: str | os.PathLike, pixels: np.ndarray, *, overwrite: bool = False) -> Path:
    """Write an ``(H, W)`` or ``(H, W, 3)`` uint8 array as a PNG file (imageio encodes it).

    Raises ``ExtraNotInstalledError`` without imageio (``pip install "torchgi[image]"``).

    Example:
        >>> import tempfile, os
        >>> p = write_png(os.path.join(tempfile.mkdtemp(), "a.png"), np.zeros((2, 3, 3), np.uint8))
        >>> p.read_bytes()[:4]
        b'\\x89PNG'
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"path: {path} exists; pass overwrite=True to replace it")
    if pixels.dtype != np.uint8 or pixels.ndim not in (2, 3) or (pixels.ndim == 3 and pixels.shape[2] != 3):
        raise ValueError(f"pixels: expected uint8 (H, W) or (H, W, 3), got {pixels.dtype} {pixels.shape}")
    iio = require("imageio.v3", "image")
    tmp = temp_beside(path)
    try:
        iio.imwrite(tmp, np.ascontiguousarray(pixels), extension=".png")
        os.replace(tmp, path)  # atomic: a reader never sees half a file
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
