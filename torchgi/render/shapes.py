"""Triangle meshes of simple shapes (vertices ``(V, 3)`` float64, faces ``(F, 3)`` int64, faces
pointing outwards) for the built-in and procedural scenes."""

from __future__ import annotations

import numpy as np

__all__ = ["block", "ground", "quads", "sphere"]


def quads(corners: list[list[list[float]]]) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of quads ``[v0, v1, v2, v3]`` (two triangles each, same winding).

    Example:
        >>> [a.shape for a in quads([[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]])]
        [(4, 3), (2, 3)]
    """
    v = np.asarray(corners, dtype=np.float64).reshape(-1, 3)
    base = 4 * np.arange(len(corners))[:, None]
    f = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return v, f


def block(footprint: list[list[float]], height: float) -> tuple[np.ndarray, np.ndarray]:
    """A prism of ``height`` over a 4-point floor ``footprint`` (x, z), faces pointing outwards.

    Example:
        >>> block([[0, 0], [1, 0], [1, 1], [0, 1]], 2.0)[1].shape   # six quads
        (12, 3)
    """
    fp = np.asarray(footprint, dtype=np.float64)
    bottom = [[x, 0.0, z] for x, z in fp]
    top = [[x, height, z] for x, z in fp]
    sides = [top[::-1], bottom]
    for i in range(4):
        j = (i + 1) % 4
        sides.append([bottom[i], bottom[j], top[j], top[i]])
    v, f = quads(sides)
    centre = np.array([fp[:, 0].mean(), height / 2, fp[:, 1].mean()])
    tri = v[f]
    outward = np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(1) - centre)
    f[outward < 0] = f[outward < 0][:, ::-1]
    return v, f


def sphere(centre: tuple[float, float, float], radius: float, rings: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere of ``rings`` rings (``2 rings`` segments each) with outward faces.

    Example:
        >>> v, f = sphere((0, 0, 0), 2.0, rings=4)
        >>> float(abs(np.linalg.norm(v, axis=1) - 2).max()) < 1e-12
        True
    """
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, 2 * rings, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    cols = 2 * rings
    faces = []
    for i in range(rings):
        for j in range(cols):
            a, b = i * cols + j, i * cols + (j + 1) % cols
            c, d = a + cols, b + cols
            faces += [[a, b, d], [a, d, c]]
    f = np.asarray(faces)
    tri = v[f]
    f = f[np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) > 1e-12]  # poles
    tri = v[f]
    outward = np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(1))
    f[outward < 0] = f[outward < 0][:, ::-1]
    return v * radius + np.asarray(centre), f


def ground(size: float) -> tuple[np.ndarray, np.ndarray]:
    """A square at y = 0 from ``-size`` to ``size`` in x and z, facing up.

    Example:
        >>> ground(1.0)[0][:, 1].tolist()
        [0.0, 0.0, 0.0, 0.0]
    """
    return quads([[[-size, 0, -size], [-size, 0, size], [size, 0, size], [size, 0, -size]]])
