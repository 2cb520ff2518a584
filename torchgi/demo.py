"""The demo behind ``torchgi demo``: path-trace the Cornell box at a low and a high sample count,
round-trip the buffers through multi-layer EXR, denoise with every method of the Denoiser, and
report each one's error and time in a table and a labelled picture.

Needs the ``cpu`` extra (the renderer, EXR and PNG files, FLIP).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import torch

from torchgi import methods, metrics
from torchgi.buffers import GBuffer
from torchgi.core.check import require
from torchgi.denoise import Denoiser
from torchgi.io import to_srgb8, write_png
from torchgi.render import render, scenes

__all__ = ["DEMO_FILES", "contact_sheet", "run_demo"]

DEMO_FILES = ("noisy.exr", "reference.exr", "demo.png")  # what the demo writes in its folder


def demo_metrics(x: torch.Tensor, ref: torch.Tensor) -> dict[str, float]:
    """relMSE, SSIM and FLIP of :func:`torchgi.metrics.summary`: unlike MSE, a few bright pixels
    (the light source) do not carry the whole relMSE.

    Example:
        >>> ref = torch.rand(1, 3, 16, 16)
        >>> demo_metrics(ref, ref)["relmse"]
        0.0
    """
    table = metrics.summary(x, ref)
    return {key: table[key] for key in ("relmse", "ssim", "flip")}


def contact_sheet(panels: list[torch.Tensor], labels: list[str], *, columns: int = 4) -> np.ndarray:
    """A labelled grid of images for display: each ``(3, H, W)`` linear colour panel tone-mapped to
    sRGB (:func:`torchgi.io.to_srgb8`) under a strip that prints its label (lines split at ``\\n``).
    Returns an ``(H', W', 3)`` uint8 array for :func:`torchgi.io.write_png`. Needs Pillow (the
    ``cpu`` extra, through imageio).

    Example:
        >>> sheet = contact_sheet([torch.zeros(3, 8, 8), torch.ones(3, 8, 8)], ["a", "b"], columns=2)
        >>> sheet.shape[1], sheet.dtype
        (16, dtype('uint8'))
    """
    if len(panels) != len(labels) or not panels:
        raise ValueError(f"panels, labels: one label per panel and at least one panel, got {len(panels)} and "
                         f"{len(labels)}")
    if isinstance(columns, bool) or not isinstance(columns, int) or columns < 1:
        raise ValueError(f"columns: expected an int >= 1, got {columns!r}")
    image = require("PIL.Image", "cpu")
    draw = require("PIL.ImageDraw", "cpu")
    font = require("PIL.ImageFont", "cpu").load_default()
    h, w = panels[0].shape[-2:]
    strip = 12 * max(label.count("\n") + 1 for label in labels) + 4
    rows = -(-len(panels) // columns)
    sheet = image.new("RGB", (w * min(columns, len(panels)), (h + strip) * rows), (0, 0, 0))
    pen = draw.Draw(sheet)
    for k, (panel, label) in enumerate(zip(panels, labels)):
        if panel.shape[-2:] != (h, w):
            raise ValueError(f"panels[{k}]: size {tuple(panel.shape[-2:])}, expected {(h, w)} as panels[0]")
        x, y = (k % columns) * w, (k // columns) * (h + strip)
        sheet.paste(image.fromarray(to_srgb8(panel)), (x, y + strip))
        pen.multiline_text((x + 2, y + 1), label, fill=(255, 255, 255), font=font, spacing=2)
    return np.asarray(sheet)


def _render_pair(size: int, spp: int, ref_spp: int, bounces: int, folder: Path) -> tuple[GBuffer, GBuffer, float]:
    """The noisy and reference Cornell box renders, written to EXR and read back (what a user's
    renderer hands over), and the render time in seconds."""
    t0 = time.perf_counter()
    scene = scenes.cornell(size)
    noisy = render(scene, spp=spp, bounces=bounces, seed=1)
    ref = render(scene, spp=ref_spp, bounces=bounces, seed=2)
    seconds = time.perf_counter() - t0
    noisy.to_exr(folder / DEMO_FILES[0], overwrite=True)
    ref.to_exr(folder / DEMO_FILES[1], overwrite=True)
    noisy = GBuffer.from_exr(folder / DEMO_FILES[0], required=("color", "emission", "albedo", "normal", "depth"))
    return noisy, GBuffer.from_exr(folder / DEMO_FILES[1]), seconds


def run_demo(out: str | os.PathLike = "out/demo", *, size: int = 128, spp: int = 1, ref_spp: int = 256,
             bounces: int = 1, overwrite: bool = False) -> tuple[dict[str, dict[str, float]], float]:
    """Render the Cornell box (``size`` x ``size`` px) at ``spp`` and ``ref_spp`` samples per pixel
    with ``bounces`` indirect bounces, write ``noisy.exr``, ``reference.exr`` and the labelled
    picture ``demo.png`` (noisy, every Denoiser method, reference) into the folder ``out``, and
    return ``({row: {"relmse", "ssim", "flip"[, "ms"]}}, render seconds)`` for the noisy input and
    each method with its denoising time in ms (``none`` is the noisy input itself and is left out).
    Files already there are refused unless ``overwrite``.

    Example:
        >>> import tempfile
        >>> rows, seconds = run_demo(tempfile.mkdtemp(), size=16, ref_spp=4)  # doctest: +SKIP
        >>> rows["guided"]["relmse"] < rows["noisy"]["relmse"]  # doctest: +SKIP
        True
    """
    for name, value, low in (("size", size, 11), ("spp", spp, 1), ("ref_spp", ref_spp, 1), ("bounces", bounces, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name}: expected an int >= {low}, got {value!r}")
    folder = Path(out)
    existing = [str(folder / f) for f in DEMO_FILES if (folder / f).exists()]
    if existing and not overwrite:
        raise FileExistsError(f"out: {', '.join(existing)} exist(s); pass --overwrite (overwrite=True in Python) or another "
                              "folder")
    folder.mkdir(parents=True, exist_ok=True)
    noisy, ref, render_s = _render_pair(size, spp, ref_spp, bounces, folder)
    images, ms = {}, {}
    for method in (m for m in methods.names() if methods.get(m).filters):  # every method timed before any metric runs
        den = Denoiser(method)
        den(noisy)  # once untimed: kernels compile and buffers are allocated on the first call
        t0 = time.perf_counter()
        images[method] = den(noisy)
        ms[method] = (time.perf_counter() - t0) * 1e3
    rows = {"noisy": demo_metrics(noisy.color, ref.color)}
    panels, labels = [noisy.color[0]], [f"noisy {spp} spp\nrelMSE {rows['noisy']['relmse']:.4f}"]
    for method, image in images.items():
        rows[method] = {**demo_metrics(image, ref.color), "ms": ms[method]}
        panels.append(image[0])
        labels.append(f"{method} {ms[method]:.1f} ms\nrelMSE {rows[method]['relmse']:.4f}")
    panels.append(ref.color[0])
    labels.append(f"reference {ref_spp} spp")
    write_png(folder / DEMO_FILES[2], contact_sheet(panels, labels), overwrite=True)
    return rows, render_s
