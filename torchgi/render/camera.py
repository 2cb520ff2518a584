"""Pinhole camera rays (world space, unit directions, as ``(3, N)`` float32 tensors)."""

from __future__ import annotations

import math

import numpy as np
import torch

from torchgi.render.scene import Camera

__all__ = ["camera_frame", "camera_rays"]


def camera_frame(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """``forward, right, up`` unit vectors and the tangents of the half field of view (x, y).

    Image x grows along ``right = forward x up`` and image y (rows) against ``up``.

    Example:
        >>> f, r, u, tx, ty = camera_frame(Camera((0, 0, 0), (0, 0, -1), fov=90, resolution=(4, 2)))
        >>> (r + 0.0).tolist(), round(tx, 6), round(ty, 6)
        ([1.0, 0.0, 0.0], 1.0, 0.5)
    """
    forward = np.subtract(camera.look_at, camera.position).astype(np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, camera.up)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    width, height = camera.resolution
    tan = math.tan(math.radians(camera.fov) / 2)
    if camera.fov_axis == "x":
        tan_x, tan_y = tan, tan * height / width
    else:
        tan_x, tan_y = tan * width / height, tan
    return forward, right, up, tan_x, tan_y


def camera_rays(camera: Camera, pixel: torch.Tensor, jitter: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through ``pixel`` (index ``y*W + x``, any batch offset removed) at ``jitter``.

    Args:
        camera: the scene camera.
        pixel: ``(N,)`` int64 pixel index within one image.
        jitter: ``(2, N)`` offsets in [0, 1) inside the pixel (x, y); None = pixel centre.

    Returns:
        ``origin (3, 1)`` (broadcasts) and unit ``direction (3, N)``, float32.

    Example:
        >>> cam = Camera((0, 0, 0), (0, 0, -1), fov=90, resolution=(2, 2))
        >>> o, d = camera_rays(cam, torch.tensor([0]), None)  # top-left pixel: left, up, forward
        >>> torch.round(d[:, 0] / d[:, 0].abs().max(), decimals=5).tolist()
        [-0.5, 0.5, -1.0]
    """
    width, height = camera.resolution
    forward, right, up, tan_x, tan_y = camera_frame(camera)
    x = (pixel % width).to(torch.float32)
    y = torch.div(pixel, width, rounding_mode="floor").to(torch.float32)
    if jitter is None:
        x, y = x + 0.5, y + 0.5
    else:
        x, y = x + jitter[0], y + jitter[1]
    sx = (2.0 * tan_x / width) * x - tan_x
    sy = tan_y - (2.0 * tan_y / height) * y
    basis = torch.tensor(np.stack([right, up, forward]), dtype=torch.float32)  # (3 axes, xyz)
    d = basis[0, :, None] * sx + basis[1, :, None] * sy + basis[2, :, None]
    d = d * torch.rsqrt((d * d).sum(0, keepdim=True))
    origin = torch.tensor(camera.position, dtype=torch.float32).reshape(3, 1)
    return origin, d
