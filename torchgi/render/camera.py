"""Pinhole camera rays (world space, unit directions, as ``(3, N)`` float32 tensors)."""

from __future__ import annotations

import math

import numpy as np
import torch

from torchgi.render.scene import Camera

__all__ = ["camera_frame", "camera_rays", "motion_vectors"]


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


def _project(camera: Camera, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Image coordinates ``x, y`` (pixels, float64) of directions ``d (3, N)`` from the camera
    centre, and whether each lies in front of the camera."""
    width, height = camera.resolution
    forward, right, up, tan_x, tan_y = camera_frame(camera)
    basis = torch.tensor(np.stack([right, up, forward]), dtype=torch.float64)
    cam = basis @ d  # (3, N): along right, up, forward
    front = cam[2] > 0
    z = torch.where(front, cam[2], torch.ones_like(cam[2]))
    x = (cam[0] / z + tan_x) * (width / (2.0 * tan_x))
    y = (tan_y - cam[1] / z) * (height / (2.0 * tan_y))
    return x, y, front


def motion_vectors(camera: Camera, previous: Camera | None, position: torch.Tensor, hit: torch.Tensor) -> torch.Tensor:
    """Backward screen-space motion ``(B, 2, H, W)`` in pixels (x right, y down).

    The first-hit point seen at pixel centre ``(x+0.5, y+0.5)`` of ``camera``, at its position
    ``position`` in the previous frame (the hit itself for still geometry), projects into
    ``previous`` at ``(x+0.5+m_x, y+0.5+m_y)``; where the centre ray hit nothing, the ray's
    direction is projected (the camera's rotation alone). A point behind the previous camera
    gets a motion that leaves the image by its width and height (history cannot hold it).
    ``previous=None`` (a first frame) gives 0.

    Args:
        camera, previous: this frame's and the previous frame's camera (same resolution).
        position: ``(B, 3, H, W)`` world-space first-hit points of this frame where they were at
            the previous frame's time (``torchgi.render.engine.render_sequence`` carries moving
            meshes' points back).
        hit: ``(B, 1, H, W)`` bool, where the centre ray hit geometry.

    Returns:
        float32 ``(B, 2, H, W)`` on the CPU.

    Example:
        >>> cam = Camera((0, 0, 4), (0, 0, 0), fov=90, resolution=(4, 4))
        >>> pos, hit = torch.zeros(1, 3, 4, 4), torch.zeros(1, 1, 4, 4, dtype=torch.bool)
        >>> bool(motion_vectors(cam, cam, pos, hit).abs().max() < 1e-6)   # a still camera: no motion
        True
    """
    B, _, H, W = position.shape
    if previous is None:
        return torch.zeros(B, 2, H, W)
    if previous.resolution != camera.resolution:
        raise ValueError(f"previous: expected the resolution {camera.resolution}, got {previous.resolution}")
    _, ray = camera_rays(camera, torch.arange(H * W), None)
    points = position.double().permute(1, 0, 2, 3).reshape(3, -1)
    d_hit = points - torch.tensor(previous.position, dtype=torch.float64)[:, None]
    d = torch.where(hit.permute(1, 0, 2, 3).reshape(1, -1), d_hit, ray.double().repeat(1, B))
    x, y, front = _project(previous, d)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                            indexing="ij")
    mx = torch.where(front, x - xs.reshape(-1).repeat(B), float(W + H))
    my = torch.where(front, y - ys.reshape(-1).repeat(B), float(W + H))
    return torch.stack([mx, my]).reshape(2, B, H, W).permute(1, 0, 2, 3).float().contiguous()
