"""Built-in procedural scenes, available without any download.

* :func:`cornell` - the Cornell box with Cornell's published coordinates (millimetres) and
  camera, Mitsuba 3's RGB reflectances and light radiance; the light is lowered 0.5 mm
  below the ceiling as in Mitsuba's ``cbox.xml``.
* :func:`cornell_glossy` - the same box with two GGX blocks.
* :func:`sky` - a box, a sphere and a slab on a ground plane under a blue sky with a point sun.
* :func:`grass` - thousands of thin, leaning grass blades (6000 blades, 18k triangles) on a
  ground plane under sky and sun: the geometrically complex case adaptive sampling exists for.
* :func:`procedural` - a new random scene for every seed, with textures (``render/procedural.py``);
  ``load_scene("procedural:<seed>")`` names one.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from torchgi.render.procedural import procedural
from torchgi.render.scene import MATERIALS, Camera, Mesh, PointLight, Scene, Sky, transform_matrix
from torchgi.render.shapes import block, ground, quads, sphere

__all__ = ["BUILTINS", "PROCEDURAL", "cornell", "cornell_glossy", "grass", "procedural", "sky"]

PROCEDURAL = "procedural:"  # load_scene's prefix of a procedural scene's seed

# Cornell Box Data (http://www.graphics.cornell.edu/online/box/data.html), mm, as quads.
_CORNELL = {
    "floor": [[552.8, 0, 0], [0, 0, 0], [0, 0, 559.2], [549.6, 0, 559.2]],
    "ceiling": [[556, 548.8, 0], [556, 548.8, 559.2], [0, 548.8, 559.2], [0, 548.8, 0]],
    "back": [[549.6, 0, 559.2], [0, 0, 559.2], [0, 548.8, 559.2], [556, 548.8, 559.2]],
    "green": [[0, 0, 559.2], [0, 0, 0], [0, 548.8, 0], [0, 548.8, 559.2]],
    "red": [[552.8, 0, 0], [549.6, 0, 559.2], [556, 548.8, 559.2], [556, 548.8, 0]],
    "light": [[343, 548.3, 227], [343, 548.3, 332], [213, 548.3, 332], [213, 548.3, 227]],
}
_SHORT_BLOCK = ([[130, 65], [82, 225], [240, 272], [290, 114]], 165.0)
_TALL_BLOCK = ([[423, 247], [265, 296], [314, 456], [472, 406]], 330.0)
_WHITE = (0.885809, 0.698859, 0.666422)
_GREEN = (0.105421, 0.37798, 0.076425)
_RED = (0.570068, 0.0430135, 0.0443706)
_LIGHT = (18.387, 13.9873, 6.75357)


def cornell(resolution: int = 512, glossy_blocks: bool = False) -> Scene:
    """The Cornell box (published geometry, millimetres), camera at (278, 273, -800).

    Example:
        >>> scene = cornell(64)
        >>> scene.camera.resolution, len(scene.meshes)
        ((64, 64), 8)
    """
    diffuse = MATERIALS.get("diffuse")
    materials = {
        "floor": diffuse(_WHITE),
        "ceiling": diffuse(_WHITE),
        "back": diffuse(_WHITE),
        "green": diffuse(_GREEN),
        "red": diffuse(_RED),
        "light": diffuse(_WHITE, _LIGHT),
    }
    meshes = [Mesh(*quads([quad]), materials[name], name) for name, quad in _CORNELL.items()]
    # Walls face into the box; the light faces down. Cornell's data wind some quads the other way.
    centre = np.array([278.0, 274.4, 279.6])
    for i, mesh in enumerate(meshes):
        tri = mesh.vertices[mesh.faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        if np.einsum("ij,ij->i", normal, centre - tri.mean(1)).mean() < 0:
            meshes[i] = Mesh(mesh.vertices, mesh.faces[:, ::-1], mesh.material, mesh.name)
    if glossy_blocks:
        short_mat = MATERIALS.get("glossy")(_WHITE, 0.3)
        tall_mat = MATERIALS.get("glossy")((0.9, 0.9, 0.9), 0.1)
    else:
        short_mat = tall_mat = materials["floor"]
    meshes.append(Mesh(*block(*_SHORT_BLOCK), short_mat, "short_block"))
    meshes.append(Mesh(*block(*_TALL_BLOCK), tall_mat, "tall_block"))
    camera = Camera((278, 273, -800), (278, 273, -799), (0, 1, 0), 39.3077, "x", (resolution, resolution))
    return Scene(camera, meshes, [], "cornell_glossy" if glossy_blocks else "cornell")


def cornell_glossy(resolution: int = 512) -> Scene:
    """The Cornell box with GGX blocks (short: roughness 0.3, tall: 0.1)."""
    return cornell(resolution, glossy_blocks=True)


_SUN = PointLight((8.0, 12.0, 6.0), (300.0, 280.0, 250.0))
_SKY = Sky((0.5, 0.6, 0.8))


def sky(resolution: int = 512) -> Scene:
    """Objects on a ground plane (metres) under a constant sky and a point-light sun.

    Example:
        >>> len(sky(32).lights)
        2
    """
    diffuse, glossy = MATERIALS.get("diffuse"), MATERIALS.get("glossy")
    box_v, box_f = block([[-0.4, -0.4], [0.4, -0.4], [0.4, 0.4], [-0.4, 0.4]], 0.8)
    box_v = box_v @ transform_matrix(rotate=(0, 30, 0))[:3, :3].T + [-0.9, 0, 0.2]
    slab_v, slab_f = block([[-0.6, -0.25], [0.6, -0.25], [0.6, 0.25], [-0.6, 0.25]], 0.15)
    slab_v = slab_v + [0.9, 0, 0.6]
    meshes = [
        Mesh(*ground(20.0), diffuse((0.5, 0.45, 0.4)), "ground"),
        Mesh(box_v, box_f, diffuse((0.7, 0.3, 0.2)), "box"),
        Mesh(*sphere((0.5, 0.5, -0.3), 0.5), glossy((0.9, 0.9, 0.9), 0.15), "sphere"),
        Mesh(slab_v, slab_f, diffuse((0.2, 0.5, 0.7)), "slab"),
    ]
    camera = Camera((0, 1.6, 4.5), (0, 0.4, 0), (0, 1, 0), 45.0, "x", (resolution, resolution))
    return Scene(camera, meshes, [_SUN, _SKY], "sky")


def grass(resolution: int = 512, blades: int = 6000, seed: int = 7) -> Scene:
    """A patch of ``blades`` thin grass blades (three triangles each, leaning, random heights).

    Example:
        >>> grass(32, blades=100).arrays().triangles.shape
        (302, 3, 3)
    """
    rng = np.random.default_rng(seed)
    n = blades
    root = np.stack([rng.uniform(-1.5, 1.5, n), np.zeros(n), rng.uniform(-1.5, 1.0, n)], -1)
    height = rng.uniform(0.15, 0.45, n)
    width = rng.uniform(0.008, 0.02, n)
    yaw = rng.uniform(0, 2 * np.pi, n)
    lean = rng.uniform(0.0, 0.5, n)  # radians
    side = np.stack([np.cos(yaw), np.zeros(n), np.sin(yaw)], -1)
    bend = np.stack([-np.sin(yaw), np.zeros(n), np.cos(yaw)], -1)
    mid = root + (np.cos(lean / 2)[:, None] * [0, 1, 0] + np.sin(lean / 2)[:, None] * bend) * (height / 2)[:, None]
    tip = mid + (np.cos(lean)[:, None] * [0, 1, 0] + np.sin(lean)[:, None] * bend) * (height / 2)[:, None]
    half = (width / 2)[:, None] * side
    v = np.stack([root - half, root + half, mid + 0.6 * half, mid - 0.6 * half, tip], 1).reshape(-1, 3)
    base = 5 * np.arange(n)[:, None]
    f = np.concatenate([base + [0, 1, 2], base + [0, 2, 3], base + [3, 2, 4]])
    diffuse = MATERIALS.get("diffuse")
    meshes = [
        Mesh(*ground(20.0), diffuse((0.35, 0.28, 0.2)), "ground"),
        Mesh(v, f, diffuse((0.25, 0.55, 0.15)), "blades"),
    ]
    camera = Camera((0, 0.9, 2.6), (0, 0.15, 0), (0, 1, 0), 50.0, "x", (resolution, resolution))
    return Scene(camera, meshes, [_SUN, _SKY], "grass")


BUILTINS: dict[str, Callable[..., Scene]] = {
    "cornell": cornell,
    "cornell_glossy": cornell_glossy,
    "sky": sky,
    "grass": grass,
}
