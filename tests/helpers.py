"""What every test file shares: the relative error against an oracle, and which back end ran."""

from __future__ import annotations

import numpy as np
import torch

from torchgi import backends


def rel_error(out: torch.Tensor, ref: torch.Tensor | np.ndarray, scale: str = "max") -> float:
    """``max |out - ref|`` over ``max |ref|`` (``scale="max"``) or over ``max ref - min ref``
    (``"range"``: for outputs whose offset is arbitrary, like a guided filter of offset guides)."""
    ref = torch.as_tensor(np.asarray(ref) if not torch.is_tensor(ref) else ref).double().cpu()
    diff = float((out.detach().double().cpu() - ref).abs().max())
    return diff / float(ref.abs().max() if scale == "max" else ref.max() - ref.min())


def last_backend(op: str) -> str:
    """The back end that computed the last ``op`` ("box", "guided", "atrous", "importance", "allocate")."""
    return backends.status()["last"][op]["ran"]


def rel_range(out: torch.Tensor, ref: torch.Tensor | np.ndarray) -> float:
    """:func:`rel_error` over the range of ``ref``."""
    return rel_error(out, ref, "range")


def scene_fingerprint(scene) -> tuple[tuple, frozenset]:
    """A scene's camera (position, target, up, field of view, to 1e-6) and its geometry (one
    SHA-256 per mesh of its world-space vertices to 1e-5 and its faces), independent of file
    names, materials and resolution: two scenes are the same shot when either part matches."""
    import hashlib

    cam = scene.camera
    camera = tuple(round(float(v), 6) for v in (*cam.position, *cam.look_at, *cam.up, cam.fov)) + (cam.fov_axis,)
    geometry = frozenset(
        hashlib.sha256(np.round(np.asarray(m.vertices, np.float64), 5).tobytes()
                       + np.asarray(m.faces, np.int64).tobytes()).hexdigest()
        for m in scene.meshes)
    return camera, geometry
