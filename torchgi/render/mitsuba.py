"""Mitsuba 3 as a reference renderer (the ``ref`` extra, variant ``scalar_rgb``).

``to_mitsuba`` writes a torchgi :class:`~torchgi.render.Scene` as a Mitsuba 3 scene dict (meshes
as PLY files with face normals, ``twosided`` BSDFs, one-sided area emitters, a box pixel
filter so each sample stays in its pixel, as torchgi's film does); ``render_mitsuba`` renders
one with ``max_depth = bounces + 2``. ``render_gbuffer`` renders a Mitsuba scene dict with an
AOV integrator and returns a :class:`~torchgi.GBuffer` with torchgi's conventions.
"""

from __future__ import annotations

import os
import tempfile
from typing import Any

import numpy as np
import torch

from torchgi.buffers import GBuffer
from torchgi.core.check import check_int, check_option, require
from torchgi.core.errors import ConfigError
from torchgi.render.scene import Material, PointLight, Scene, Sky

__all__ = ["cornell_box", "load_mitsuba", "render_gbuffer", "render_mitsuba", "scene_gbuffer", "to_mitsuba"]


def _rgb(value: Any) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def _bsdf(material: Material) -> dict:
    if material.texture is not None:
        raise ConfigError(f"material: a {material.texture.kind!r} texture has no Mitsuba 3 counterpart here (torchgi's "
                          f"textures are solid, Mitsuba's need UVs); convert a scene without textures "
                          f"(torchgi.scenes.procedural(seed, textures=False))")
    if material.type == "glossy":
        inner = {
            "type": "roughconductor",
            "material": "none",
            "distribution": "ggx",
            "alpha": material.roughness,
            "specular_reflectance": _rgb(material.albedo),
        }
    else:
        inner = {"type": "diffuse", "reflectance": _rgb(material.albedo)}
    return {"type": "twosided", "bsdf": inner}


def to_mitsuba(scene: Scene, directory: str | os.PathLike[str], *, bounces: int = 1) -> dict:
    """A Mitsuba 3 scene dict for ``scene``; its meshes are written to ``directory`` as
    ``mesh_<i>.ply`` (an existing file is never overwritten: FileExistsError). A textured
    material raises :class:`~torchgi.core.ConfigError` (solid textures do not map to Mitsuba's).

    Args:
        scene: a torchgi scene.
        directory: where the PLY files go (created if missing); keep it until the dict is loaded.
        bounces: the integrator's indirect bounces (``max_depth = bounces + 2``).

    Example:
        >>> import tempfile
        >>> from torchgi.render import scenes
        >>> with tempfile.TemporaryDirectory() as d:
        ...     sorted(to_mitsuba(scenes.cornell(16), d))[:3]
        ['integrator', 'mesh_0', 'mesh_1']
    """
    check_int(bounces, "bounces", 0)
    trimesh = require("trimesh", "render")
    os.makedirs(directory, exist_ok=True)
    cam = scene.camera
    width, height = cam.resolution
    out: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": bounces + 2},
        "sensor": {
            "type": "perspective",
            "fov": cam.fov,
            "fov_axis": cam.fov_axis,
            "to_world": _look_at(cam.position, cam.look_at, cam.up),
            "sampler": {"type": "independent"},
            "film": {
                "type": "hdrfilm",
                "width": width,
                "height": height,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
            },
        },
    }
    for i, mesh in enumerate(scene.meshes):
        mesh = mesh.posed(scene.time)
        path = os.path.join(os.fspath(directory), f"mesh_{i}.ply")
        if os.path.exists(path):
            raise FileExistsError(f"directory: {path} exists; pass an empty directory")
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(path)
        entry: dict[str, Any] = {"type": "ply", "filename": path, "face_normals": True, "bsdf": _bsdf(mesh.material)}
        if mesh.material.emissive:
            entry["emitter"] = {"type": "area", "radiance": _rgb(mesh.material.emission)}
        out[f"mesh_{i}"] = entry
    for i, light in enumerate(scene.lights):
        if isinstance(light, PointLight):
            light = light.posed(scene.time)
            out[f"light_{i}"] = {"type": "point", "position": list(light.position), "intensity": _rgb(light.intensity)}
        elif isinstance(light, Sky):
            out[f"light_{i}"] = {"type": "constant", "radiance": _rgb(light.radiance)}
    return out


def _load_in_order(scene: dict) -> Any:
    """``mi.load_dict`` with its shapes loaded one by one first: Mitsuba loads files in parallel and
    lists the shapes (so their emitters, which its light sampling picks by index) in the order the
    loads finish, so the same seed would render other samples from one run to the next."""
    mi = load_mitsuba()
    return mi.load_dict({k: mi.load_dict(v) if isinstance(v, dict) and v.get("type") in ("ply", "obj") else v
                         for k, v in scene.items()})


def _look_at(origin: Any, target: Any, up: Any) -> Any:
    mi = load_mitsuba()
    return mi.ScalarTransform4f().look_at(origin=list(origin), target=list(target), up=list(up))


def render_mitsuba(scene: Scene, *, spp: int, bounces: int = 1, seed: int = 0) -> torch.Tensor:
    """Render a torchgi scene with Mitsuba 3's path tracer: ``(1, 3, H, W)`` float32 colour.

    ``bounces`` counts indirect bounces as torchgi does (``max_depth = bounces + 2``); pass
    ``bounces=-1`` for ``max_depth = 1`` (emitters seen directly).

    Example:
        >>> from torchgi.render import scenes
        >>> render_mitsuba(scenes.cornell(8), spp=4).shape
        torch.Size([1, 3, 8, 8])
    """
    check_int(spp, "spp", 1)
    check_int(bounces, "bounces", -1)
    mi = load_mitsuba()
    with tempfile.TemporaryDirectory() as tmp:
        loaded = _load_in_order(to_mitsuba(scene, tmp, bounces=max(bounces, 0)))
    integrator = mi.load_dict({"type": "path", "max_depth": bounces + 2})
    img = np.array(mi.render(loaded, integrator=integrator, spp=spp, seed=seed), dtype=np.float32)
    return torch.from_numpy(img[..., :3].copy()).permute(2, 0, 1)[None].contiguous()

_AOVS = "albedo:albedo,nn:sh_normal,pp:position,dd:depth"


def load_mitsuba(variant: str = "scalar_rgb") -> Any:
    """Import Mitsuba 3 and select ``variant``; error naming the ``ref`` extra if absent."""
    mi = require("mitsuba", "ref")
    mi.set_variant(variant)
    return mi


def cornell_box(resolution: int = 128, *, pixel_filter: str = "box") -> dict:
    """Mitsuba's built-in Cornell box scene dict at ``resolution``² pixels.

    ``pixel_filter`` is the film's reconstruction filter: "box" (default here) gives each
    sample to its own pixel, so pixel noise is independent, as denoisers expect; Mitsuba's
    own default "gaussian" spreads each sample over neighbours and correlates the noise.

    Example:
        >>> cornell_box(32)["sensor"]["film"]["width"]
        32
    """
    mi = load_mitsuba()
    scene = mi.cornell_box()
    scene["sensor"]["film"]["width"] = resolution
    scene["sensor"]["film"]["height"] = resolution
    check_option(pixel_filter, "pixel_filter", ("box", "gaussian", "tent"))
    scene["sensor"]["film"]["rfilter"] = {"type": pixel_filter}
    return scene


def render_gbuffer(scene: dict, *, spp: int, bounces: int = 1, seed: int = 0) -> GBuffer:
    """Render a Mitsuba scene dict to a GBuffer (B = 1, float32, CPU).

    Args:
        scene: a Mitsuba 3 scene dict with one sensor (its integrator is replaced).
        spp: samples per pixel, > 0.
        bounces: indirect bounces (``max_depth = bounces + 2``); 0 is direct light only.
        seed: Mitsuba's sampler seed.

    Returns:
        GBuffer with ``color (1,3,H,W)``, its ``variance`` (of the mean, from Mitsuba's
        ``moment`` integrator; 0 at 1 spp), ``emission`` (light seen directly: a path tracer
        with ``max_depth = 1`` on the same camera samples), ``albedo``, ``normal``,
        ``position``, ``depth (1,1,H,W)``, ``hit (1,1,H,W)`` and ``spp``. Guides are Mitsuba's AOVs, which average
        over the pixel's samples (not a single centre ray).

    Example:
        >>> render_gbuffer(cornell_box(16), spp=4).hit.all().item()
        True
    """
    check_int(spp, "spp", 1)
    check_int(bounces, "bounces", 0)
    mi = load_mitsuba()
    scene = dict(scene)
    # One pass, two nested integrators on the same camera samples: the colour and the light seen
    # directly (max_depth 1), so ``color - emission`` is exact per sample (a second render would
    # trace other camera rays and leave light-source edges in the difference).
    # Around them, the moment integrator: each layer's mean ("nested.*") and second moment
    # ("m2_nested.*"), from which the colour's variance comes.
    # A fixed block size: Mitsuba derives it from its thread count otherwise, and seeds its sampler
    # per block, so the same seed would give other samples on a machine with other cores.
    scene["integrator"] = {"type": "moment", "block_size": 16, "nested": {
        "type": "aov",
        "aovs": _AOVS,
        "color": {"type": "path", "max_depth": bounces + 2},
        "emission": {"type": "path", "max_depth": 1},
    }}
    loaded = _load_in_order(scene)
    mi.render(loaded, spp=spp, seed=seed)
    parts = {
        name: torch.from_numpy(np.array(bmp, dtype=np.float32).reshape(bmp.height(), bmp.width(), -1))
        .permute(2, 0, 1)[None]
        .contiguous()
        for name, bmp in loaded.sensors()[0].film().bitmap(raw=False).split()
    }
    color, emission = parts["nested.color"][:, :3].contiguous(), parts["nested.emission"][:, :3].contiguous()
    # the sample variance over n = spp samples, of their mean: (E[x²] - E[x]²) / (n - 1) (the
    # difference clamped at 0: it rounds below where all samples agree); 0 below 2 samples
    variance = ((parts["m2_nested.color"][:, :3] - color.square()).clamp_min(0) / (spp - 1) if spp > 1
                else torch.zeros_like(color))
    albedo, normal, position, depth = (parts[f"nested.{k}"] for k in ("albedo", "nn", "pp", "dd"))
    hit = depth > 0
    return GBuffer(
        color=color,
        emission=emission,
        albedo=albedo,
        normal=normal,
        position=position,
        depth=depth,
        hit=hit,
        variance=variance.contiguous(),
        spp=torch.full_like(depth, spp, dtype=torch.int64),
    )


def scene_gbuffer(scene: Scene, *, spp: int, bounces: int = 1, seed: int = 0) -> GBuffer:
    """A torchgi scene converted (:func:`to_mitsuba`) and rendered by Mitsuba 3 to a GBuffer
    (:func:`render_gbuffer`; ``seed`` taken modulo 2^31).

    Example:
        >>> from torchgi.render import scenes
        >>> scene_gbuffer(scenes.cornell(8), spp=2).color.shape
        torch.Size([1, 3, 8, 8])
    """
    with tempfile.TemporaryDirectory() as tmp:  # the PLY files live while Mitsuba loads them
        return render_gbuffer(to_mitsuba(scene, tmp, bounces=bounces), spp=spp, bounces=bounces, seed=seed & 0x7FFFFFFF)
