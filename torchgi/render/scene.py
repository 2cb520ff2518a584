"""Scenes: camera, triangle meshes with materials, and lights; loaded from YAML (docs/design.md, Scene files).

A :class:`Scene` is plain data (numpy arrays and floats). :meth:`Scene.arrays` flattens it once
into the tables the tracer reads (:class:`SceneArrays`): every triangle of every mesh in one
array, per-triangle material ids and face normals, the emissive-triangle distribution.

Conventions: right-handed world, y up; ``transform`` applies scale, then ``rotate`` (Euler
degrees about x, then y, then z), then ``translate``. BSDFs are two-sided; emission leaves the
side the face normal points to (counter-clockwise winding).
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from torchgi.core.errors import ConfigError, NonFiniteError, RangeError
from torchgi.core.registry import Registry
from torchgi.render.textures import Texture, _texture
from torchgi.render.values import _number, _vec3

__all__ = [
    "LIGHTS",
    "MATERIALS",
    "Camera",
    "CameraPath",
    "Material",
    "Mesh",
    "ObjectPath",
    "PointLight",
    "Scene",
    "SceneArrays",
    "Sky",
    "transform_matrix",
]

DIFFUSE, GLOSSY = 0, 1  # material kinds in SceneArrays.kind


@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole camera.

    Args:
        position, look_at, up: world-space points / direction (scene units).
        fov: field of view in degrees along ``fov_axis`` ("x" = image width, "y" = height).
        resolution: ``(width, height)`` in pixels, each > 0.

    Example:
        >>> Camera((0, 1, 4), (0, 1, 0), resolution=(64, 48)).resolution
        (64, 48)
    """

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov: float = 39.3
    fov_axis: str = "x"
    resolution: tuple[int, int] = (512, 512)

    def __post_init__(self) -> None:
        for name in ("position", "look_at", "up"):
            object.__setattr__(self, name, _vec3(getattr(self, name), f"camera.{name}"))
        object.__setattr__(self, "fov", _number(self.fov, "camera.fov", 0.0, 180.0))
        if self.fov_axis not in ("x", "y"):
            raise ConfigError(f"camera.fov_axis: expected 'x' or 'y', got {self.fov_axis!r}")
        res = self.resolution
        if (
            not isinstance(res, (tuple, list))
            or len(res) != 2
            or not all(isinstance(r, int) and not isinstance(r, bool) for r in res)
        ):
            raise ConfigError(f"camera.resolution: expected [width, height] ints, got {res!r}")
        if min(res) <= 0:
            raise RangeError(f"camera.resolution: expected width and height > 0, got {list(res)}")
        object.__setattr__(self, "resolution", (int(res[0]), int(res[1])))
        forward = np.subtract(self.look_at, self.position)
        if np.linalg.norm(forward) == 0 or np.linalg.norm(np.cross(forward, self.up)) == 0:
            raise ConfigError("camera: look_at must differ from position and not be parallel to up")

    def with_resolution(self, width: int, height: int) -> Camera:
        """The same camera with another resolution (the field of view is kept)."""
        return dataclasses.replace(self, resolution=(width, height))


def _segment(times: Sequence[float], time: float) -> tuple[int, int, float]:
    """The keyframes ``i, j`` around ``time`` and the weight ``w`` of ``j`` (linear between
    keyframes, held outside them)."""
    t = np.asarray(times)
    i = int(np.clip(np.searchsorted(t, time, side="right") - 1, 0, len(t) - 1))
    j = min(i + 1, len(t) - 1)
    return i, j, 0.0 if j == i else float(np.clip((time - t[i]) / (t[j] - t[i]), 0.0, 1.0))


def _lerp(a: Any, b: Any, w: float) -> tuple[float, ...]:
    return tuple(float(x) for x in (1 - w) * np.asarray(a, dtype=np.float64) + w * np.asarray(b, dtype=np.float64))


def _check_times(times: Sequence[Any], key: str) -> tuple[float, ...]:
    out = tuple(_number(t, f"{key}[{i}].time") for i, t in enumerate(times))
    if any(b <= a for a, b in itertools.pairwise(out)):
        raise ConfigError(f"{key}: keyframe times must increase, got {list(out)}")
    return out


@dataclasses.dataclass(frozen=True)
class CameraPath:
    """Camera keyframes: ``position``, ``look_at`` and ``fov`` at increasing ``times`` (seconds),
    linearly interpolated between keyframes and held outside them; ``up``, ``fov_axis`` and
    ``resolution`` are the scene camera's.

    Example:
        >>> path = CameraPath((0.0, 1.0), ((0, 0, 4), (2, 0, 4)), ((0, 0, 0), (0, 0, 0)), (40.0, 40.0))
        >>> path.at(Camera((0, 0, 4), (0, 0, 0)), 0.25).position
        (0.5, 0.0, 4.0)
    """

    times: tuple[float, ...]
    positions: tuple[tuple[float, float, float], ...]
    look_ats: tuple[tuple[float, float, float], ...]
    fovs: tuple[float, ...]

    def __post_init__(self) -> None:
        n = len(self.times)
        if n == 0 or not len(self.positions) == len(self.look_ats) == len(self.fovs) == n:
            raise ConfigError(f"camera.path: expected one or more keyframes with time, position and look_at "
                              f"each, got {n} time(s)")
        object.__setattr__(self, "times", _check_times(self.times, "camera.path"))
        object.__setattr__(self, "positions", tuple(_vec3(p, f"camera.path[{i}].position")
                                                    for i, p in enumerate(self.positions)))
        object.__setattr__(self, "look_ats", tuple(_vec3(p, f"camera.path[{i}].look_at")
                                                   for i, p in enumerate(self.look_ats)))
        object.__setattr__(self, "fovs", tuple(_number(f, f"camera.path[{i}].fov", 0.0, 180.0)
                                               for i, f in enumerate(self.fovs)))

    @property
    def duration(self) -> tuple[float, float]:
        """The first and the last keyframe's time."""
        return self.times[0], self.times[-1]

    def at(self, camera: Camera, time: float) -> Camera:
        """``camera`` moved to the path's pose at ``time`` (seconds)."""
        i, j, w = _segment(self.times, time)
        fov = (1 - w) * self.fovs[i] + w * self.fovs[j]
        return dataclasses.replace(camera, position=_lerp(self.positions[i], self.positions[j], w),
                                   look_at=_lerp(self.look_ats[i], self.look_ats[j], w), fov=fov)


@dataclasses.dataclass(frozen=True)
class ObjectPath:
    """A mesh's keyframed motion: ``scales``, ``rotates`` (Euler degrees about x, then y, then z)
    and ``translates`` at increasing ``times`` (seconds), each linearly interpolated between
    keyframes and held outside them, composed as :func:`transform_matrix` does and applied after
    the mesh's own ``transform``. Lights move with it when the mesh emits.

    Example:
        >>> path = ObjectPath((0.0, 2.0), ((1, 1, 1),) * 2, ((0, 0, 0), (0, 90, 0)), ((0, 0, 0), (4, 0, 0)))
        >>> np.round(path.matrix(1.0) @ [1, 0, 0, 1], 6).tolist()   # half way: 45 degrees, 2 along x
        [2.707107, 0.0, -0.707107, 1.0]
    """

    times: tuple[float, ...]
    scales: tuple[tuple[float, float, float], ...]
    rotates: tuple[tuple[float, float, float], ...]
    translates: tuple[tuple[float, float, float], ...]
    key: str = "path"  # the scene-file key, for messages

    def __post_init__(self) -> None:
        n = len(self.times)
        if n == 0 or not len(self.scales) == len(self.rotates) == len(self.translates) == n:
            raise ConfigError(f"{self.key}: expected one or more keyframes, each with a time, got {n} time(s)")
        object.__setattr__(self, "times", _check_times(self.times, self.key))
        for name in ("scales", "rotates", "translates"):
            object.__setattr__(self, name, tuple(_vec3(v, f"{self.key}[{i}].{name[:-1]}")
                                                 for i, v in enumerate(getattr(self, name))))

    def matrix(self, time: float | None) -> np.ndarray:
        """The 4x4 float64 transform at ``time`` (None: the first keyframe's)."""
        i, j, w = _segment(self.times, self.times[0] if time is None else time)
        return transform_matrix(_lerp(self.scales[i], self.scales[j], w), _lerp(self.rotates[i], self.rotates[j], w),
                                _lerp(self.translates[i], self.translates[j], w))


@dataclasses.dataclass(frozen=True)
class Material:
    """A two-sided BSDF with optional one-sided emission.

    ``diffuse``: Lambert, ``albedo / pi``. ``glossy``: GGX microfacet reflector, Fresnel 1
    tinted by ``albedo``, ``roughness`` = GGX alpha in (0, 1]. ``emission``: radiance
    (linear RGB, >= 0) leaving the front face.
    """

    type: str
    albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
    emission: tuple[float, float, float] = (0.0, 0.0, 0.0)
    roughness: float = 0.0
    texture: Texture | None = None

    def __post_init__(self) -> None:
        if self.type not in ("diffuse", "glossy"):
            raise ConfigError(f"material.type: expected 'diffuse' or 'glossy', got {self.type!r}")
        if max(_vec3(self.albedo, "material.albedo", low=0.0)) > 1:
            raise ConfigError(f"material.albedo: expected values in [0, 1], got {self.albedo!r}")
        _vec3(self.emission, "material.emission", low=0.0)
        if self.type == "glossy" and _number(self.roughness, "material.roughness", 0.0, None) > 1:
            raise ConfigError(f"material.roughness: expected a GGX alpha in (0, 1], got {self.roughness!r}")
        if self.texture is not None and not isinstance(self.texture, Texture):
            raise ConfigError(f"material.texture: expected a Texture, got {type(self.texture).__name__}")

    @property
    def emissive(self) -> bool:
        return max(self.emission) > 0


MATERIALS: Registry[Material] = Registry("material")


@MATERIALS.register("diffuse")
def diffuse(albedo: Any = (0.8, 0.8, 0.8), emission: Any = (0, 0, 0), texture: Any = None) -> Material:
    """A Lambertian material (``albedo`` in [0, 1], ``emission`` radiance >= 0, ``texture`` a
    :class:`Texture` or its mapping ``{type, albedo2, scale}`` that varies the albedo)."""
    albedo = _vec3(albedo, "material.albedo", low=0.0)
    if max(albedo) > 1:
        raise ConfigError(f"material.albedo: expected values in [0, 1], got {list(albedo)}")
    return Material("diffuse", albedo, _vec3(emission, "material.emission", low=0.0), texture=_texture(texture))


@MATERIALS.register("glossy")
def glossy(
    albedo: Any = (0.8, 0.8, 0.8), roughness: float = 0.2, emission: Any = (0, 0, 0), texture: Any = None
) -> Material:
    """A GGX reflector (``roughness`` = alpha in (0, 1], Fresnel 1 tinted by ``albedo``, which a
    ``texture`` varies as in :func:`diffuse`)."""
    base = diffuse(albedo, emission, texture)
    alpha = _number(roughness, "material.roughness", 0.0, None)
    if alpha > 1:
        raise ConfigError(f"material.roughness: expected a GGX alpha in (0, 1], got {roughness!r}")
    return Material("glossy", base.albedo, base.emission, alpha, base.texture)


@dataclasses.dataclass(frozen=True)
class PointLight:
    """An isotropic point light: ``intensity`` in radiance units x area (W/sr per channel);
    ``path`` moves its ``position`` as a mesh's path moves its vertices (None: still)."""

    position: tuple[float, float, float]
    intensity: tuple[float, float, float]
    path: ObjectPath | None = None

    def __post_init__(self) -> None:
        _vec3(self.position, "light.position")
        _vec3(self.intensity, "light.intensity", low=0.0)

    def posed(self, time: float | None) -> PointLight:
        """The still light at its position at ``time`` (None: the first keyframe's).

        Example:
            >>> p = ObjectPath((0.0, 1.0), ((1, 1, 1),) * 2, ((0, 0, 0),) * 2, ((0, 0, 0), (2, 0, 0)))
            >>> PointLight((0, 3, 0), (1, 1, 1), p).posed(0.5).position
            (1.0, 3.0, 0.0)
        """
        if self.path is None:
            return self
        m = self.path.matrix(time)
        return PointLight(tuple(float(v) for v in m[:3, :3] @ np.asarray(self.position) + m[:3, 3]), self.intensity)


@dataclasses.dataclass(frozen=True)
class Sky:
    """A constant environment: every ray that leaves the scene sees ``radiance``."""

    radiance: tuple[float, float, float]

    def __post_init__(self) -> None:
        _vec3(self.radiance, "light.radiance", low=0.0)


LIGHTS: Registry[Any] = Registry("light")


@LIGHTS.register("point")
def point(position: Any, intensity: Any) -> PointLight:
    """A point light at ``position`` with ``intensity`` >= 0."""
    return PointLight(_vec3(position, "light.position"), _vec3(intensity, "light.intensity", low=0.0))


@LIGHTS.register("sky")
def sky(radiance: Any) -> Sky:
    """A constant sky of ``radiance`` >= 0."""
    return Sky(_vec3(radiance, "light.radiance", low=0.0))


def transform_matrix(scale: Any = 1.0, rotate: Any = (0, 0, 0), translate: Any = (0, 0, 0)) -> np.ndarray:
    """A 4x4 float64 matrix: scale, then rotate (degrees about x, then y, then z), then translate.

    Example:
        >>> m = transform_matrix(2.0, (0, 90, 0), (1, 0, 0))
        >>> np.round(m @ [1, 0, 0, 1], 6).tolist()
        [1.0, 0.0, -2.0, 1.0]
    """
    s = np.diag(list(_vec3(scale, "transform.scale")) + [1.0])
    ax, ay, az = np.radians(_vec3(rotate, "transform.rotate"))
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rz @ ry @ rx
    m[:3, 3] = _vec3(translate, "transform.translate")
    return m @ s


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in world space with one material.

    Args:
        vertices: ``(V, 3)`` float positions, finite.
        faces: ``(F, 3)`` int vertex indices (counter-clockwise = front).
        material: its :class:`Material`.
        name: a label used in messages.
        path: its keyframed motion (:class:`ObjectPath`, applied to ``vertices``), None = still.
    """

    vertices: np.ndarray
    faces: np.ndarray
    material: Material
    name: str = "mesh"
    path: ObjectPath | None = None

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=np.float64)
        f = np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ConfigError(f"{self.name}: vertices must be (V, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
            raise ConfigError(f"{self.name}: faces must be (F, 3) integers, got {f.shape} {f.dtype}")
        bad = ~np.isfinite(v).all(axis=1)
        if bad.any():
            raise NonFiniteError(f"{self.name}: {int(bad.sum())} of {len(v)} vertices are NaN or Inf")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ConfigError(f"{self.name}: face indices must lie in [0, {len(v)})")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f.astype(np.int64))

    def transformed(self, matrix: np.ndarray) -> Mesh:
        """This mesh with ``matrix`` (4x4) applied to its vertices; a mirroring matrix keeps
        the faces' front sides by reversing their winding."""
        v = self.vertices @ matrix[:3, :3].T + matrix[:3, 3]
        faces = self.faces[:, ::-1] if np.linalg.det(matrix[:3, :3]) < 0 else self.faces
        return Mesh(v, faces, self.material, self.name, self.path)

    def matrix(self, time: float | None) -> np.ndarray:
        """The 4x4 transform of its :attr:`path` at ``time`` (identity for a still mesh)."""
        return np.eye(4) if self.path is None else self.path.matrix(time)

    def posed(self, time: float | None) -> Mesh:
        """The still mesh in its pose at ``time`` (None: the first keyframe's)."""
        return self if self.path is None else dataclasses.replace(self.transformed(self.matrix(time)), path=None)


@dataclasses.dataclass(frozen=True)
class SceneArrays:
    """A scene flattened for the tracer (float32 numpy arrays; built by :meth:`Scene.arrays`).

    ``triangles (T,3,3)``, unit face ``normals (T,3)``, ``material (T,)`` index into the
    per-material tables ``albedo (M,3)``, ``emission (M,3)``, ``roughness (M,)``, ``kind (M,)``
    (0 diffuse, 1 glossy), ``texture (M,)`` (0 none, else :attr:`Texture.code`), its
    ``texture_scale (M,)`` and second colour ``albedo2 (M,3)``. ``light_tris (L,)`` are the emissive triangles, chosen with
    probability ``light_prob (L,)`` (area x emitted luminance), ``light_pdf (T,)`` is the area
    density of light sampling on each triangle (0 off lights). ``points`` ``(P,3)`` and
    ``intensities (P,3)`` are the point lights; ``sky (3,)`` is None without a sky.
    ``scale`` is the scene's extent (for ray offsets); ``skipped`` counts zero-area triangles;
    ``mesh (T,)`` is each triangle's index in :attr:`Scene.meshes`.
    """

    triangles: np.ndarray
    normals: np.ndarray
    material: np.ndarray
    albedo: np.ndarray
    emission: np.ndarray
    roughness: np.ndarray
    kind: np.ndarray
    texture: np.ndarray
    texture_scale: np.ndarray
    albedo2: np.ndarray
    light_tris: np.ndarray
    light_prob: np.ndarray
    light_pdf: np.ndarray
    points: np.ndarray
    intensities: np.ndarray
    sky: np.ndarray | None
    mesh: np.ndarray
    scale: float
    skipped: int
    key: str  # SHA-256 of the arrays: what the tracers' caches are keyed by


@dataclasses.dataclass(eq=False)
class Scene:
    """Camera, meshes and lights (:func:`load_scene` reads one from YAML; ``torchgi.render.scenes``
    builds the built-in ones).

    Example:
        >>> tri = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]),
        ...            MATERIALS.build({"type": "diffuse"}))
        >>> scene = Scene(Camera((0.3, 0.3, 2), (0.3, 0.3, 0), resolution=(8, 8)), [tri],
        ...               [Sky((1, 1, 1))])
        >>> scene.arrays().triangles.shape
        (1, 3, 3)
    """

    camera: Camera
    meshes: list[Mesh]
    lights: list[Any] = dataclasses.field(default_factory=list)
    name: str = "scene"
    path: CameraPath | None = None  # camera animation (render_sequence), None = a still camera
    time: float | None = None  # the moving meshes' pose (Mesh.path); None = each one's first keyframe

    def __post_init__(self) -> None:
        if not self.meshes:
            raise ConfigError("meshes: a scene needs at least one mesh")
        self._arrays: SceneArrays | None = None

    def with_camera(self, camera: Camera) -> Scene:
        """The same scene (its tables and BVH shared, not rebuilt) seen by ``camera``."""
        out = Scene(camera, self.meshes, self.lights, self.name, self.path, self.time)
        out._arrays = self._arrays
        return out

    @property
    def moving(self) -> list[int]:
        """The indices of the meshes with a :attr:`Mesh.path`."""
        return [i for i, m in enumerate(self.meshes) if m.path is not None]

    @property
    def duration(self) -> tuple[float, float] | None:
        """The first and last keyframe time over the camera's, the meshes' and the point lights'
        paths (None: nothing moves)."""
        paths = [p for p in [self.path, *(m.path for m in self.meshes), *(getattr(li, "path", None)
                                                                        for li in self.lights)] if p is not None]
        if not paths:
            return None
        return min(p.times[0] for p in paths), max(p.times[-1] for p in paths)

    def times_of(self, frames: int) -> list[float]:
        """The times of ``frames`` frames spread evenly over :attr:`duration` (0 for a still scene).

        Example:
            >>> from torchgi.render import scenes
            >>> scenes.cornell(8).times_of(3)
            [0.0, 0.0, 0.0]
        """
        if self.duration is None:
            return [0.0] * frames
        a, b = self.duration
        return [a] if frames == 1 else [a + (b - a) * k / (frames - 1) for k in range(frames)]

    def with_resolution(self, width: int, height: int) -> Scene:
        """The same scene seen by the same camera at another resolution."""
        return self.with_camera(self.camera.with_resolution(width, height))

    def at(self, time: float) -> Scene:
        """The scene at ``time``: its camera on :attr:`path` (the camera itself without one), its
        moving meshes and point lights posed (:attr:`time`); a scene where only the camera moves
        shares the tables and BVH."""
        out = self if self.path is None else self.with_camera(self.path.at(self.camera, time))
        if self.moving or any(getattr(li, "path", None) is not None for li in self.lights):
            out = Scene(out.camera, self.meshes, self.lights, self.name, self.path, time)
        return out

    def arrays(self) -> SceneArrays:
        """The flattened tables (built once, then cached); warns once about zero-area triangles."""
        if self._arrays is None:
            self._arrays = _flatten(self)
            if self._arrays.skipped:
                warnings.warn(
                    f"scene {self.name!r}: skipped {self._arrays.skipped} zero-area triangle(s)", stacklevel=2
                )
        return self._arrays


def _flatten(scene: Scene) -> SceneArrays:
    materials: list[Material] = []
    index: dict[Material, int] = {}
    tris, mats = [], []
    skipped = 0
    owner = []
    for m, mesh in enumerate(scene.meshes):
        mesh = mesh.posed(scene.time)
        t = mesh.vertices[mesh.faces]  # (F, 3, 3) float64
        area2 = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
        keep = area2 > 0
        skipped += int((~keep).sum())
        if mesh.material not in index:
            index[mesh.material] = len(materials)
            materials.append(mesh.material)
        tris.append(t[keep])
        mats.append(np.full(int(keep.sum()), index[mesh.material], dtype=np.int64))
        owner.append(np.full(int(keep.sum()), m, dtype=np.int64))
    triangles = np.concatenate(tris)
    if len(triangles) == 0:
        raise ConfigError("meshes: the scene has no triangle with a non-zero area")
    material = np.concatenate(mats)
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normals = cross / (2 * area[:, None])
    albedo = np.array([m.albedo for m in materials])
    emission = np.array([m.emission for m in materials])
    lum = emission @ np.array([0.2126, 0.7152, 0.0722])
    power = area * lum[material]
    light_tris = np.flatnonzero(power > 0)
    light_prob = power[light_tris] / power[light_tris].sum() if len(light_tris) else np.zeros(0)
    light_pdf = np.zeros(len(triangles))
    light_pdf[light_tris] = light_prob / area[light_tris]
    points = [light.posed(scene.time) for light in scene.lights if isinstance(light, PointLight)]
    skies = [light for light in scene.lights if isinstance(light, Sky)]
    if len(skies) > 1:
        raise ConfigError("lights: at most one sky")
    lo, hi = triangles.reshape(-1, 3).min(0), triangles.reshape(-1, 3).max(0)
    scale = float(max(np.abs(lo).max(), np.abs(hi).max(), (hi - lo).max()))
    f32 = np.float32
    fields = {
        "triangles": np.ascontiguousarray(triangles, dtype=f32),
        "normals": normals.astype(f32),
        "material": material,
        "albedo": albedo.astype(f32),
        "emission": emission.astype(f32),
        "roughness": np.array([m.roughness for m in materials], dtype=f32),
        "kind": np.array([GLOSSY if m.type == "glossy" else DIFFUSE for m in materials], dtype=np.int64),
        "texture": np.array([0 if m.texture is None else m.texture.code for m in materials], dtype=np.int64),
        "texture_scale": np.array([1.0 if m.texture is None else m.texture.scale for m in materials], dtype=f32),
        "albedo2": np.array([m.albedo if m.texture is None else m.texture.albedo2 for m in materials], dtype=f32),
        "light_tris": light_tris,
        "light_prob": light_prob.astype(np.float64),
        "light_pdf": light_pdf.astype(f32),
        "points": np.array([p.position for p in points], dtype=f32).reshape(-1, 3),
        "intensities": np.array([p.intensity for p in points], dtype=f32).reshape(-1, 3),
        "sky": np.array(skies[0].radiance, dtype=f32) if skies and max(skies[0].radiance) > 0 else None,
        "mesh": np.concatenate(owner),
    }
    # the tracers' caches are keyed by content: a scene object's id is reused after it is freed
    digest = hashlib.sha256()
    for name, value in fields.items():
        digest.update(name.encode() + (b"-" if value is None else np.ascontiguousarray(value).tobytes()))
    return SceneArrays(**fields, scale=scale, skipped=skipped, key=digest.hexdigest())
