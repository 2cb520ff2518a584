"""The one embree adapter: triangles in, closest hits and occlusion out (the ``render`` extra).

Everything crossing this boundary is a contiguous float32 ``(N, 3)`` array; a miss is ``-1``.
Ray origins are pushed off the surface they leave by a scale-aware offset (:func:`offset`)
because embree's ``run`` has no ``tnear``. embreex holds the GIL while it traces, so
parallel rendering uses processes (``torchgi.render.engine``), not threads.
"""

from __future__ import annotations

import numpy as np
import torch

from torchgi import backends
from torchgi.core.check import require

__all__ = ["Accel", "offset"]

class Accel:
    """A BVH over ``triangles (T, 3, 3)`` float32.

    Example:
        >>> tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], dtype=np.float32)
        >>> acc = Accel(tri)
        >>> t, prim = acc.intersect(torch.tensor([[0.2], [0.2], [1.0]]), torch.tensor([[0.0], [0.0], [-1.0]]))
        >>> round(float(t[0]), 5), int(prim[0])
        (1.0, 0)
    """

    def __init__(self, triangles: np.ndarray) -> None:
        rtcs = require("embreex.rtcore_scene", "render")
        mesh_construction = require("embreex.mesh_construction", "render")
        backends.mark_embree_started()
        self._scene = rtcs.EmbreeScene()
        self._mesh = mesh_construction.TriangleMesh(self._scene, np.ascontiguousarray(triangles, dtype=np.float32))

    @staticmethod
    def _rows(x: torch.Tensor, n: int) -> np.ndarray:
        return np.ascontiguousarray(x.expand(3, n).T.numpy(), dtype=np.float32)

    def intersect(
        self, origin: torch.Tensor, direction: torch.Tensor, tmax: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Closest hits of rays ``origin (3, N|1)``, ``direction (3, N)`` within ``tmax (N,)``
        (None: unbounded; 0 disables a ray).

        Returns ``t (N,)`` float32 (distance in units of ``|direction|``; undefined on a miss)
        and ``prim (N,)`` int64 triangle index, -1 on a miss.
        """
        n = direction.shape[1]
        if n == 0:
            return torch.zeros(0), torch.zeros(0, dtype=torch.int64)
        # embreex writes the hit distances into ``dists``: hand it a copy, never the caller's tensor.
        dists = None if tmax is None else np.array(tmax.numpy(), dtype=np.float32)
        out = self._scene.run(self._rows(origin, n), self._rows(direction, n), dists=dists, output=1)
        return torch.from_numpy(out["tfar"]), torch.from_numpy(out["primID"]).to(torch.int64)

    def occluded(self, origin: torch.Tensor, direction: torch.Tensor, tmax: torch.Tensor | None) -> torch.Tensor:
        """True where something lies on the segment ``origin + t * direction``, ``0 < t < tmax``
        (``tmax`` None: the whole ray)."""
        n = direction.shape[1]
        if n == 0:
            return torch.zeros(0, dtype=torch.bool)
        dists = None if tmax is None else np.ascontiguousarray(tmax.numpy(), dtype=np.float32)
        hit = self._scene.run(self._rows(origin, n), self._rows(direction, n), dists=dists, query="OCCLUDED")
        return torch.from_numpy(hit) >= 0


def offset(point: torch.Tensor, normal: torch.Tensor, scale: float) -> torch.Tensor:
    """``point + eps * normal`` with ``eps = 2^-15 * scale`` (floor 1e-7): rays leaving a surface.

    ``scale`` is the scene's extent and largest coordinate (``SceneArrays.scale``), so ``eps``
    is about 256 float32 spacings of the largest coordinate: a fixed epsilon would fail either
    in millimetre scenes (self-hits) or in unit scenes (light leaks).

    Example:
        >>> offset(torch.zeros(3, 1), torch.tensor([[0.0], [1.0], [0.0]]), 2.0**15)[:, 0].tolist()
        [0.0, 1.0, 0.0]
    """
    return point + normal * max(scale * 2.0**-15, 1e-7)
