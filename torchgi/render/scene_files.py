"""Scene files (docs/design.md, Scene files): YAML with a camera (and its ``path`` of keyframes),
meshes with their materials, transforms and ``path`` of keyframed transforms (moving objects), and
lights (a point light may have a ``path`` too), built into a :class:`~torchgi.render.scene.Scene`.
A mesh names its file relative to the scene file (``file:``, the project's own meshes) or relative
to the mesh root (``mesh:``, the meshes made by others that ship in ``torchgi/meshes``; the
environment variable ``TORCHGI_MESHES`` overrides it; :func:`mesh_root`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from torchgi.core.errors import ConfigError
from torchgi.core.registry import Registry
from torchgi.io.mesh import PACKAGE_MESHES, mesh_root, read_mesh
from torchgi.render import scenes
from torchgi.render.scene import (
    LIGHTS,
    MATERIALS,
    Camera,
    CameraPath,
    Mesh,
    ObjectPath,
    PointLight,
    Scene,
    transform_matrix,
)
from torchgi.render.values import _no_unknown_keys

__all__ = ["load_scene", "scene_from_dict"]

_TOP_KEYS = ("camera", "meshes", "lights")
_CAMERA_KEYS = ("position", "look_at", "up", "fov", "fov_axis", "resolution", "path")
_KEYFRAME_KEYS = ("time", "position", "look_at", "fov")
_MESH_KEYS = ("file", "mesh", "material", "transform", "path", "name")
_TRANSFORM_KEYS = ("scale", "rotate", "translate")
_MESH_KEYFRAME_KEYS = ("time", *_TRANSFORM_KEYS)


def _mesh_path(m: Mapping[str, Any], root: str, key: str) -> str:
    """The file of mesh entry ``m``: ``file`` relative to the scene file's folder ``root``, or
    ``mesh`` relative to :func:`mesh_root` (a missing one raises, saying how to set the root)."""
    if ("file" in m) == ("mesh" in m):
        raise ConfigError(f"{key}: exactly one of 'file' (relative to the scene file) or 'mesh' (relative to the "
                          f"mesh root, $TORCHGI_MESHES) is required")
    if "file" in m:
        return os.path.join(root, str(m["file"]))
    base = mesh_root()
    path = base / str(m["mesh"])
    if not path.is_file():
        if os.environ.get("TORCHGI_MESHES"):
            where = (f"the mesh root {str(base)!r} named by the environment variable TORCHGI_MESHES (unset, it "
                     f"is the package's {str(PACKAGE_MESHES)!r})")
        else:
            where = (f"the mesh root {str(base)!r} (the package's meshes; the environment variable "
                     f"TORCHGI_MESHES overrides it)")
        raise FileNotFoundError(f"{key}.mesh: {m['mesh']!r} is not under {where}")
    return str(path)


def _load_mesh_file(path: str, key: str) -> tuple[np.ndarray, np.ndarray]:
    try:
        return read_mesh(path)
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"{key}: {exc}") from None
    except ConfigError as exc:
        raise ConfigError(f"{key}: {exc}") from exc


def _build(registry: Registry[Any], cfg: Any, key: str) -> Any:
    if not isinstance(cfg, Mapping) or "type" not in cfg:
        raise ConfigError(f"{key}: expected a mapping with a 'type' ({', '.join(registry.names())})")
    try:
        return registry.build(dict(cfg))
    except ConfigError as exc:
        raise ConfigError(f"{key}: {exc}") from None
    except TypeError as exc:  # unexpected / missing keyword
        raise ConfigError(f"{key}: {exc}") from None


def scene_from_dict(cfg: Mapping[str, Any], root: str = ".", name: str = "scene") -> Scene:
    """Build a :class:`Scene` from a parsed YAML mapping (docs/design.md, Scene files): a mesh's
    ``file`` is relative to ``root``, its ``mesh`` to :func:`mesh_root`.

    Example:
        >>> cfg = {"camera": {"position": [0, 0, 3], "look_at": [0, 0, 0], "resolution": [8, 8]},
        ...        "meshes": [{"file": "configs/scenes/meshes/sphere.obj", "material": {"type": "diffuse"}}]}
        >>> len(scene_from_dict(cfg, str(PACKAGE_MESHES.parents[1])).meshes)
        1
    """
    _no_unknown_keys(cfg, "scene", _TOP_KEYS)
    if "camera" not in cfg or "meshes" not in cfg:
        raise ConfigError("scene: 'camera' and 'meshes' are required")
    cam = cfg["camera"]
    _no_unknown_keys(cam, "camera", _CAMERA_KEYS)
    cam = dict(cam)
    path = _camera_path(cam.pop("path"), cam.get("fov", Camera.fov)) if "path" in cam else None
    if path is not None:  # the base pose defaults to the first keyframe's
        cam.setdefault("position", path.positions[0])
        cam.setdefault("look_at", path.look_ats[0])
    for required in ("position", "look_at"):
        if required not in cam:
            raise ConfigError(f"camera.{required}: required")
    if "resolution" in cam:
        cam["resolution"] = tuple(cam["resolution"]) if isinstance(cam["resolution"], list) else cam["resolution"]
    camera = Camera(**cam)
    if not isinstance(cfg["meshes"], list):
        raise ConfigError("meshes: expected a list")
    meshes = []
    for i, m in enumerate(cfg["meshes"]):
        key = f"meshes[{i}]"
        _no_unknown_keys(m, key, _MESH_KEYS)
        if "material" not in m:
            raise ConfigError(f"{key}: 'material' is required")
        material = _build(MATERIALS, m["material"], f"{key}.material")
        file_key = "file" if "file" in m else "mesh"
        v, f = _load_mesh_file(_mesh_path(m, root, key), f"{key}.{file_key}")
        mesh = Mesh(v, f, material, str(m.get("name", m.get("file", m.get("mesh")))))
        if "transform" in m:
            _no_unknown_keys(m["transform"], f"{key}.transform", _TRANSFORM_KEYS)
            mesh = mesh.transformed(transform_matrix(**m["transform"]))
        if "path" in m:
            mesh = dataclasses.replace(mesh, path=_object_path(m["path"], f"{key}.path"))
        meshes.append(mesh)
    lights_cfg = cfg.get("lights") or []
    if not isinstance(lights_cfg, list):
        raise ConfigError("lights: expected a list")
    lights = [_light(light, f"lights[{i}]") for i, light in enumerate(lights_cfg)]
    return Scene(camera, meshes, lights, name, path)


def _light(cfg: Any, key: str) -> Any:
    """A light entry; a point light may have a ``path`` (as a mesh's: it moves its position)."""
    if not isinstance(cfg, Mapping) or "path" not in cfg:
        return _build(LIGHTS, cfg, key)
    light = _build(LIGHTS, {k: v for k, v in cfg.items() if k != "path"}, key)
    if not isinstance(light, PointLight):
        raise ConfigError(f"{key}.path: only a point light moves (an emissive mesh with a path is a moving area "
                          f"light); this one is {cfg.get('type')!r}")
    return dataclasses.replace(light, path=_object_path(cfg["path"], f"{key}.path"))


def _camera_path(cfg: Any, fov: float) -> CameraPath:
    """``camera.path``: a list of ``{time, position, look_at, fov}`` keyframes (fov defaults to the camera's)."""
    if not isinstance(cfg, list) or not cfg:
        raise ConfigError(f"camera.path: expected a non-empty list of keyframes, got {cfg!r}")
    for i, key in enumerate(cfg):
        _no_unknown_keys(key, f"camera.path[{i}]", _KEYFRAME_KEYS)
        for required in ("time", "position", "look_at"):
            if required not in key:
                raise ConfigError(f"camera.path[{i}].{required}: required")
    return CameraPath(tuple(k["time"] for k in cfg), tuple(k["position"] for k in cfg),
                      tuple(k["look_at"] for k in cfg), tuple(k.get("fov", fov) for k in cfg))


def _object_path(cfg: Any, key: str) -> ObjectPath:
    """A mesh's ``path``: a list of ``{time, scale, rotate, translate}`` keyframes (scale 1,
    rotate and translate 0 where left out), applied after its ``transform``."""
    if not isinstance(cfg, list) or not cfg:
        raise ConfigError(f"{key}: expected a non-empty list of keyframes, got {cfg!r}")
    for i, k in enumerate(cfg):
        _no_unknown_keys(k, f"{key}[{i}]", _MESH_KEYFRAME_KEYS)
        if "time" not in k:
            raise ConfigError(f"{key}[{i}].time: required")
    return ObjectPath(tuple(k["time"] for k in cfg), tuple(k.get("scale", 1.0) for k in cfg),
                      tuple(k.get("rotate", 0.0) for k in cfg), tuple(k.get("translate", 0.0) for k in cfg), key)


def load_scene(path: str | os.PathLike[str]) -> Scene:
    """Load a scene from a YAML file (docs/design.md, Scene files), or a built-in one by name.

    Args:
        path: a ``.yaml`` file, one of ``torchgi.render.scenes.BUILTINS`` ("cornell", ...) or
            ``"procedural:<seed>"`` (:func:`torchgi.render.scenes.procedural`).

    Raises:
        ConfigError: malformed YAML or a bad value (the message names the key).
        FileNotFoundError: the file or a mesh it names does not exist.

    Example:
        >>> load_scene("cornell").camera.resolution
        (512, 512)
    """
    path = os.fspath(path)
    if path in scenes.BUILTINS:
        return scenes.BUILTINS[path]()
    if path.startswith(scenes.PROCEDURAL):
        seed = path[len(scenes.PROCEDURAL):]
        if not seed.isdigit():
            raise ConfigError(f"scene {path!r}: expected {scenes.PROCEDURAL}<seed>, the seed an int >= 0")
        return scenes.procedural(int(seed))
    if not os.path.isfile(path):
        raise FileNotFoundError(
            f"scene {path!r} does not exist (built-in scenes: {', '.join(sorted(scenes.BUILTINS))})"
        )
    import yaml

    with open(path, encoding="utf-8") as fh:
        try:
            cfg = yaml.safe_load(fh)
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: malformed YAML: {exc}") from None
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"{path}: expected a mapping with 'camera' and 'meshes' at the top")
    return scene_from_dict(cfg, os.path.dirname(os.path.abspath(path)), os.path.splitext(os.path.basename(path))[0])
