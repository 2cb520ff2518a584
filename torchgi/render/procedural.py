"""Procedural scenes: a new scene for every seed, for training data at scale (issue: learn from
thousands of scenes).

:func:`procedural` draws, from one seed, a ground under the open sky or a room; 1-20 objects
(the shipped Stanford meshes, spheres, boxes, thin slats, grids of thin bars, tilted panels) at
random places, scales and rotations; materials from Lambert through rough to near-mirror GGX,
40 % of them with a solid albedo texture (checker, stripes or value noise at 0.7-30 cells a
metre); one to three lights among area lights from 3 cm to 2.5 m across, point lights, a
constant sky and a sun (a distant point light), sometimes an emitter in view; and a camera that
looks at the objects with a field of view of 25-80 degrees. Units are metres; y is up.

The draw uses only numpy's ``default_rng`` keyed by the seed and the package's meshes, so a seed
is the same scene on every machine. Spot lights are not drawn: the tracer has none.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from torchgi.core.check import check_int
from torchgi.io.mesh import mesh_root, read_mesh
from torchgi.render.scene import MATERIALS, Camera, Material, Mesh, PointLight, Scene, Sky
from torchgi.render.scene import transform_matrix as _matrix
from torchgi.render.shapes import block, sphere
from torchgi.render.textures import TEXTURES, Texture

__all__ = ["MESHES", "procedural"]

# the shipped meshes a scene may place (torchgi/meshes/README.md) and the rotation that stands each upright
MESHES = {
    "bunny": ("stanford_bunny/stanford-bunny.ply", (0, 0, 0)),
    "dragon": ("stanford_dragon/dragon.ply", (0, 0, 0)),
    "armadillo": ("stanford_armadillo/armadillo.obj", (0, 180, 0)),
    "lucy": ("stanford_lucy/lucy.ply", (-90, 0, 0)),
}
_KINDS = ("sphere", "box", "slats", "grid", "panel", "mesh")
_KIND_P = (0.2, 0.22, 0.12, 0.08, 0.1, 0.28)
_KEY = 0x70726F63  # "proc": the draw's stream, apart from every other generator keyed by a seed


@functools.cache
def _unit_mesh(name: str) -> tuple[np.ndarray, np.ndarray]:
    """A shipped mesh stood upright, centred over the origin, its base at y = 0, height 1."""
    path, rotate = MESHES[name]
    v, f = read_mesh(str(mesh_root() / path))
    v = v @ _matrix(rotate=rotate)[:3, :3].T
    lo, hi = v.min(0), v.max(0)
    v = (v - [(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2]) / (hi[1] - lo[1])
    return v, f


def _colour(rng: np.random.Generator, low: float = 0.05, high: float = 0.9) -> tuple[float, float, float]:
    """A random albedo: a hue at a random saturation, its largest channel in [low, high]."""
    hue = rng.uniform(0, 1)
    sat = rng.uniform(0, 1) ** 2.5
    rgb = np.clip(np.abs(((hue * 6 + np.array([0, 4, 2])) % 6) - 3) - 1, 0, 1)
    rgb = (1 - sat) + sat * rgb
    return tuple(float(x) for x in rgb * rng.uniform(low, high))


def _material(rng: np.random.Generator, textured: bool) -> Material:
    """Lambert (half), rough or near-mirror GGX; a solid texture on 40 % when ``textured``."""
    albedo = _colour(rng)
    texture = None
    if rng.uniform() < 0.4:  # drawn with or without textures, so that both draw the same scene
        kind = TEXTURES[int(rng.integers(len(TEXTURES)))]
        texture = Texture(kind, _colour(rng), float(np.exp(rng.uniform(math.log(0.7), math.log(30.0)))))
        texture = texture if textured else None
    if rng.uniform() < 0.5:
        return MATERIALS.get("diffuse")(albedo, texture=texture)
    roughness = float(np.exp(rng.uniform(math.log(0.01), math.log(1.0))))
    return MATERIALS.get("glossy")(albedo, roughness, texture=texture)


def _object(rng: np.random.Generator, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """An object's vertices and faces in a unit frame: standing on y = 0, about 1 high."""
    if kind == "sphere":
        return sphere((0.0, 0.5, 0.0), 0.5, rings=int(rng.integers(12, 33)))
    if kind == "box":
        sx, sz = rng.uniform(0.3, 1.0, 2)
        return block([[-sx, -sz], [sx, -sz], [sx, sz], [-sx, sz]], float(rng.uniform(0.2, 1.0)))
    if kind in ("slats", "grid"):
        n = int(rng.integers(3, 12))
        width = float(rng.uniform(0.01, 0.06))
        parts = []
        for i in range(n):  # upright slats along x; a grid adds bars along y
            x = -0.5 + (i + 0.5) / n
            parts.append(block([[x - width, -width], [x + width, -width], [x + width, width], [x - width, width]], 1.0))
        if kind == "grid":
            for i in range(n):
                y = (i + 0.5) / n
                v, f = block([[-0.5, -width], [0.5, -width], [0.5, width], [-0.5, width]], 2 * width)
                parts.append((v + [0, y - width, 0.0], f))
        return _merge(parts)
    if kind == "panel":
        v = np.array([[-0.5, 0, -0.5], [0.5, 0, -0.5], [0.5, 0, 0.5], [-0.5, 0, 0.5]], dtype=np.float64)
        v = v @ _matrix(rotate=(float(rng.uniform(20, 90)), 0, 0))[:3, :3].T + [0, 0.5, 0]
        return v, np.array([[0, 2, 1], [0, 3, 2]])
    return _unit_mesh(list(MESHES)[int(rng.integers(len(MESHES)))])


def _merge(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One vertex and face array from several meshes."""
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    return np.concatenate([v for v, _ in parts]), np.concatenate([f + o for (_, f), o in zip(parts, offsets)])


def _quad(centre, size: float, normal_down: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A horizontal square of side ``size`` at ``centre``, facing down (or up)."""
    h = size / 2
    c = np.asarray(centre, dtype=np.float64)
    v = c + np.array([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]])
    f = np.array([[0, 1, 2], [0, 2, 3]]) if normal_down else np.array([[0, 2, 1], [0, 3, 2]])
    return v, f


def _room(rng: np.random.Generator, textured: bool) -> tuple[list[Mesh], float, bool]:
    """A floor under the sky (ceiling False) or a room; returns its meshes, half-size and ceiling."""
    half = float(rng.uniform(2.5, 5.0))
    floor_v = np.array([[-half, 0, -half], [-half, 0, half], [half, 0, half], [half, 0, -half]], dtype=np.float64)
    meshes = [Mesh(floor_v, np.array([[0, 1, 2], [0, 2, 3]]), _material(rng, textured), "floor")]
    if rng.uniform() < 0.5:
        return meshes, half, False
    height = float(rng.uniform(2.2, 4.0))
    walls = [i for i in range(4) if rng.uniform() < 0.8]
    for i in walls:  # walls facing in
        a = np.array([[-half, 0, -half], [half, 0, -half], [half, height, -half], [-half, height, -half]])
        v = a @ _matrix(rotate=(0, 90 * i, 0))[:3, :3].T
        meshes.append(Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]), _material(rng, textured), f"wall_{i}"))
    ceiling = len(walls) == 4 or rng.uniform() < 0.5
    if ceiling:
        v, f = _quad((0, height, 0), 2 * half)
        meshes.append(Mesh(v, f, MATERIALS.get("diffuse")(_colour(rng, 0.5, 0.9)), "ceiling"))
    return meshes, half, ceiling


def _lights(rng: np.random.Generator, half: float, ceiling: bool, top: float) -> tuple[list, list[Mesh]]:
    """One to three lights (a room with a ceiling has no sky or sun) and their emitting meshes."""
    lights: list = []
    meshes: list[Mesh] = []
    kinds = ["area", "point"] if ceiling else ["area", "point", "sky", "sun"]
    for k in range(int(rng.integers(1, 4))):
        kind = kinds[int(rng.integers(len(kinds)))]
        if kind == "sky" and not any(isinstance(li, Sky) for li in lights):
            tint = np.asarray(_colour(rng, 0.6, 1.0))
            lights.append(Sky(tuple(float(x) for x in tint * np.exp(rng.uniform(math.log(0.2), math.log(1.5))))))
        elif kind == "sun" or kind == "sky":
            direction = np.array([rng.normal(), rng.uniform(0.3, 1.5), rng.normal()])
            direction /= np.linalg.norm(direction)
            irradiance = float(np.exp(rng.uniform(math.log(0.8), math.log(6.0))))
            lights.append(PointLight(tuple(float(x) for x in direction * 100.0),
                                     tuple(float(x) for x in np.asarray(_colour(rng, 0.9, 1.0)) * irradiance * 1e4)))
        elif kind == "point":
            p = (rng.uniform(-0.8, 0.8) * half, rng.uniform(0.5, 1.0) * top, rng.uniform(-0.8, 0.8) * half)
            power = float(np.exp(rng.uniform(math.log(8.0), math.log(150.0))))
            colour = np.asarray(_colour(rng, 0.9, 1.0)) * power
            lights.append(PointLight(tuple(float(x) for x in p), tuple(float(x) for x in colour)))
        else:
            size = float(np.exp(rng.uniform(math.log(0.03), math.log(2.5))))
            y = top - 1e-3 if ceiling else float(rng.uniform(1.5, 4.0))
            v, f = _quad((rng.uniform(-0.6, 0.6) * half, y, rng.uniform(-0.6, 0.6) * half), size)
            power = float(np.exp(rng.uniform(math.log(10.0), math.log(150.0))))
            emission = np.asarray(_colour(rng, 0.9, 1.0)) * power / (size * size)
            meshes.append(Mesh(v, f, MATERIALS.get("diffuse")((0.8, 0.8, 0.8), tuple(float(x) for x in emission)),
                               f"light_{k}"))
    return lights, meshes


def procedural(seed: int, resolution: int = 256, *, textures: bool = True) -> Scene:
    """A random scene drawn from ``seed`` (the module docstring lists what it draws).

    Args:
        seed: any int >= 0; each is a different scene, the same on every machine.
        resolution: the camera's width and height in pixels.
        textures: False draws the same scene without albedo textures (for renderers that have
            no solid textures, such as the Mitsuba 3 conversion).

    Returns:
        A :class:`~torchgi.render.Scene` named ``procedural_<seed>``.

    Example:
        >>> s = procedural(3, 32)
        >>> s.name, s.camera.resolution, procedural(3, 32).arrays().key == s.arrays().key
        ('procedural_3', (32, 32), True)
    """
    check_int(seed, "seed", 0)
    check_int(resolution, "resolution", 1)
    rng = np.random.default_rng([_KEY, seed])
    meshes, half, ceiling = _room(rng, textures)
    top = max(m.vertices[:, 1].max() for m in meshes) if ceiling else 4.0
    spread = float(rng.uniform(0.8, 2.2))
    placed = []
    for i in range(int(rng.integers(1, 21))):
        kind = _KINDS[int(rng.choice(len(_KINDS), p=_KIND_P))]
        v, f = _object(rng, kind)
        scale = float(np.exp(rng.uniform(math.log(0.15), math.log(1.1))))
        lift = 0.0 if rng.uniform() < 0.8 else float(rng.uniform(0.1, 1.0))
        tilt = (0.0, 0.0) if rng.uniform() < 0.7 else tuple(rng.uniform(-40, 40, 2))
        centre = (rng.uniform(-spread, spread), lift, rng.uniform(-spread, spread))
        m = _matrix(scale, (tilt[0], rng.uniform(0, 360), tilt[1]), centre)
        emitter = rng.uniform() < 0.05
        material = (MATERIALS.get("diffuse")((0.8, 0.8, 0.8), tuple(float(x) for x in
                    np.asarray(_colour(rng, 0.9, 1.0)) * float(np.exp(rng.uniform(0.0, math.log(20.0))))))
                    if emitter else _material(rng, textures))
        placed.append(Mesh(v, f, material, f"{kind}_{i}").transformed(m))
    lights, emitters = _lights(rng, half, ceiling, top)
    meshes += placed + emitters
    camera = _camera(rng, placed, half, top if ceiling else 6.0, resolution)
    return Scene(camera, meshes, lights, f"procedural_{seed}")


def _camera(rng: np.random.Generator, placed: list[Mesh], half: float, top: float, resolution: int) -> Camera:
    """A camera that looks at the objects: outside their bounds, inside the room, at a random fov."""
    points = np.concatenate([m.vertices for m in placed])
    lo, hi = points.min(0), points.max(0)
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 0.2)
    fov = float(rng.uniform(25.0, 80.0))
    distance = radius / math.tan(math.radians(fov) / 2) * float(rng.uniform(0.6, 1.3))
    azimuth = rng.uniform(0, 2 * math.pi)
    elevation = rng.uniform(math.radians(3), math.radians(50))
    offset = distance * np.array([math.cos(elevation) * math.cos(azimuth), math.sin(elevation),
                                  math.cos(elevation) * math.sin(azimuth)])
    position = centre + offset
    position[[0, 2]] = np.clip(position[[0, 2]], -0.95 * half, 0.95 * half)
    position[1] = float(np.clip(position[1], 0.1, 0.95 * top))
    look_at = centre + rng.normal(size=3) * 0.1 * radius
    return Camera(tuple(position.tolist()), tuple(look_at.tolist()), (0, 1, 0), fov, "x", (resolution, resolution))
