"""Rendering: a batched embree path tracer that emits GBuffer tensors.

``torchgi.render`` is both this package and the render function: ``torchgi.render(scene, spp,
bounces, seed)`` calls :func:`torchgi.render.engine.render`.

Modules: ``scene`` (materials, lights, cameras), ``scene_files`` (YAML, the mesh root), ``scenes`` (built-ins), ``camera``, ``sampler``,
``accel`` (the embree adapter), ``materials``, ``lights``, ``film``, ``integrators/{basic,path}``,
``engine`` (chunks, workers), ``mitsuba`` (Mitsuba 3 export and reference renders).
"""

import sys
import types
from typing import Any

from torchgi.io.mesh import mesh_root
from torchgi.render import scenes
from torchgi.render.engine import render, render_guide_rays, render_guides, render_sequence
from torchgi.render.scene import Camera, CameraPath, Material, Mesh, ObjectPath, PointLight, Scene, Sky
from torchgi.render.scene_files import load_scene
from torchgi.render.textures import Texture

__all__ = [
    "Camera",
    "CameraPath",
    "Material",
    "Mesh",
    "ObjectPath",
    "PointLight",
    "Scene",
    "Sky",
    "Texture",
    "load_scene",
    "mesh_root",
    "render",
    "render_guide_rays",
    "render_guides",
    "render_sequence",
    "scenes",
]


class _CallableModule(types.ModuleType):
    """Lets ``torchgi.render(...)`` call :func:`render` while ``torchgi.render.x`` stays a module."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return render(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
