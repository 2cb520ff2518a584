"""A tile of a render pass as the back ends take it: the scene's tables and embreex BVH (built
once per process), the :class:`~torchgi.backends.TraceSetup` the renderer hands the back ends
(camera frame, sampler key, roulette start, skips, the torch wavefronts), the op builders
:func:`path_op` / :func:`guide_rays_op`, and :func:`film_tile`, the torch integrators' tile
(the torch back end's reference for the compiled tracer).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Collection
from typing import Any

import numpy as np
import torch

from torchgi import backends
from torchgi.render.accel import Accel
from torchgi.render.camera import camera_frame
from torchgi.render.film import BLOCK, Film
from torchgi.render.integrators import basic, common, path
from torchgi.render.integrators.common import RR_START, SKIPS, Context, guides
from torchgi.render.lights import Tables
from torchgi.render.sampler import key_head
from torchgi.render.scene import Camera, SceneArrays

__all__ = ["INTEGRATORS", "film_tile", "guide_rays_op", "path_op", "through_mirrors", "trace_setup"]

INTEGRATORS: dict[str, Callable[..., torch.Tensor]] = {"path": path.radiance, "basic": basic.radiance}


_CONTEXTS: dict[str, tuple[Tables, Accel | None]] = {}
_CONTEXTS_LOCK = threading.Lock()  # renders on several Python threads at once share the cache


def _tables(arrays: SceneArrays, bvh: bool = True) -> tuple[Tables, Accel | None]:
    """The scene's tables and (``bvh``) its embreex BVH, each built once per process (the last
    scene's kept); safe on several threads: a thread never reads another thread's entry."""
    with _CONTEXTS_LOCK:
        entry = _CONTEXTS.get(arrays.key)
        if entry is None:
            _CONTEXTS.clear()
            entry = (Tables.from_arrays(arrays), None)
        if bvh and entry[1] is None:
            entry = (entry[0], Accel(arrays.triangles))
        _CONTEXTS[arrays.key] = entry
        return entry


def _context(
    arrays: SceneArrays, camera: Camera, bounces: int, seed: int, skip: frozenset[str] = frozenset(SKIPS)
) -> Context:
    """A render context; the BVH of a scene is built once per process."""
    tables, accel = _tables(arrays)
    return Context(tables, accel, camera, bounces, seed, skip)


def trace_setup(camera: Camera, seed: int = 0, stream: int = 0, skip: Collection[str] = SKIPS,
                wavefronts: Callable[[Any], Any] | None = None) -> backends.TraceSetup:
    """What the back ends need to trace ``camera``'s view (:class:`torchgi.backends.TraceSetup`):
    its frame, the pass's sampler key head from ``seed`` and ``stream``, the Russian-roulette start,
    whether every skip is on, and the torch wavefronts (``wavefronts``; default: the "path"
    integrator's film, :func:`film_tile`).

    Example:
        >>> from torchgi.render import scenes
        >>> trace_setup(scenes.cornell(4).camera).roulette_from
        3
    """
    forward, right, up, tan_x, tan_y = camera_frame(camera)
    return backends.TraceSetup(tuple(float(v) for v in camera.position),
                               tuple(float(v) for v in (*right, *up, *forward)), tan_x, tan_y, key_head(seed, stream),
                               RR_START, frozenset(skip) == frozenset(SKIPS), wavefronts or _path_wavefronts)


def path_op(arrays: SceneArrays, camera: Camera, counts: np.ndarray, *, bounces: int, seed: int, stream: int = 0,
            record: str = "all", skip: Collection[str] = SKIPS, first_pixel: int = 0, chunk_size: int = 1 << 15,
            threads: int = 1, on_chunk: Callable[[int], None] | None = None,
            profile: torch.Tensor | None = None) -> backends.PathOp:
    """A :class:`torchgi.backends.PathOp`: ``counts (P,)`` samples of the pixels ``first_pixel ...``
    of the scene ``arrays`` seen by ``camera`` (the other arguments as in the op).

    Example:
        >>> from torchgi.render import scenes
        >>> s = scenes.cornell(4)
        >>> backends.run(path_op(s.arrays(), s.camera, np.full(16, 2), bounces=1, seed=0))[0].shape
        (9, 16)
    """
    return backends.PathOp(arrays, _tables(arrays, bvh=False)[0], camera, bounces, seed, stream, record,
                           frozenset(skip), first_pixel, counts, chunk_size, trace_setup(camera, seed, stream, skip),
                           threads, on_chunk, profile)


def guide_rays_op(arrays: SceneArrays, camera: Camera, chunk_size: int = 1 << 15,
                  threads: int = 1) -> backends.GuideRaysOp:
    """A :class:`torchgi.backends.GuideRaysOp`: one ray through each pixel centre of ``camera``.

    Example:
        >>> from torchgi.render import scenes
        >>> s = scenes.cornell(4)
        >>> backends.run(guide_rays_op(s.arrays(), s.camera))["hit"].shape
        torch.Size([1, 16])
    """
    return backends.GuideRaysOp(arrays, _tables(arrays, bvh=False)[0], camera,
                                trace_setup(camera, wavefronts=_guide_wavefronts), chunk_size, threads)


def _path_wavefronts(op: backends.PathOp) -> tuple[np.ndarray, np.ndarray]:
    """The torch code of :class:`~torchgi.backends.PathOp` (the torch back end calls it)."""
    return film_tile(op, "path")


def _guide_wavefronts(op: backends.GuideRaysOp) -> dict[str, torch.Tensor]:
    """The torch code of :class:`~torchgi.backends.GuideRaysOp`: embreex and
    :func:`~torchgi.render.integrators.common.guides`, ``chunk_size`` rays at a time."""
    width, height = op.camera.resolution
    ctx = _context(op.arrays, op.camera, 0, 0)
    channels = {"albedo": 3, "normal": 3, "position": 3, "depth": 1, "hit": 1}
    g = {k: torch.zeros(c, width * height, dtype=torch.bool if k == "hit" else torch.float32)
         for k, c in channels.items()}
    for start in range(0, width * height, op.chunk_size):
        pixel = torch.arange(start, min(start + op.chunk_size, width * height))
        for k, v in guides(ctx, pixel).items():
            g[k][:, start : start + pixel.numel()] = v
    return g


def through_mirrors(arrays: SceneArrays, camera: Camera, max_roughness: float, albedo: torch.Tensor,
                    normal: torch.Tensor, chunk_size: int = 1 << 15) -> tuple[torch.Tensor, torch.Tensor]:
    """The guides ``albedo``, ``normal`` ``(3, H·W)`` of ``camera``'s pixel centres with those of
    the first non-specular hit where the first hit is a mirror (roughness below ``max_roughness``:
    :func:`~torchgi.render.integrators.common.through_mirrors`, embreex and the torch code,
    ``chunk_size`` rays at a time); new tensors.

    Example:
        >>> from torchgi.render import scenes
        >>> s = scenes.cornell(4)
        >>> g = backends.run(guide_rays_op(s.arrays(), s.camera))
        >>> a, n = through_mirrors(s.arrays(), s.camera, 0.1, g["albedo"], g["normal"])
        >>> torch.equal(a, g["albedo"])   # no glossy surface: the first hit's guides
        True
    """
    width, height = camera.resolution
    ctx = _context(arrays, camera, 0, 0)
    albedo, normal = albedo.clone(), normal.clone()
    for start in range(0, width * height, chunk_size):
        pixel = torch.arange(start, min(start + chunk_size, width * height))
        a, n, found = common.through_mirrors(ctx, pixel, max_roughness)
        part = slice(start, start + pixel.numel())
        albedo[:, part] = torch.where(found, a, albedo[:, part])
        normal[:, part] = torch.where(found, n, normal[:, part])
    return albedo, normal


def film_tile(op: backends.PathOp, integrator: str) -> tuple[np.ndarray, np.ndarray]:
    """A tile of a render pass by the torch integrator ``integrator`` ("path": the wavefronts of
    :mod:`~torchgi.render.integrators.path`; "basic"), chunk by chunk into a film.

    Args:
        op: the tile (:class:`torchgi.backends.PathOp`; ``threads`` is not used: one process, one thread).
        integrator: a key of :data:`INTEGRATORS`.

    Returns:
        float64 numpy ``mean (9, P)`` (emission, direct, indirect radiance) and ``variance (3, P)``
        of the colour's mean.

    Example:
        >>> from torchgi.render import scenes
        >>> s = scenes.cornell(4); a = s.arrays()
        >>> film_tile(path_op(a, s.camera, np.full(16, 2), bounces=1, seed=0, chunk_size=4096), "basic")[0].shape
        (9, 16)
    """
    ctx = _context(op.arrays, op.camera, op.bounces, op.seed, op.skip)
    radiance = INTEGRATORS[integrator]
    counts = torch.from_numpy(op.counts)
    film = Film(counts.numel(), rows=12)
    # Blocks: each pixel's samples cut at multiples of BLOCK (see film.py).
    nblocks = torch.div(counts + BLOCK - 1, BLOCK, rounding_mode="floor")
    block_pixel = torch.repeat_interleave(torch.arange(counts.numel()), nblocks)
    first_block = torch.cumsum(nblocks, 0) - nblocks
    block_rank = torch.arange(block_pixel.numel()) - first_block[block_pixel]
    block_start = block_rank * BLOCK
    block_count = torch.minimum(counts[block_pixel] - block_start, torch.tensor(BLOCK))
    for a, b in backends.chunks(block_count, op.chunk_size):
        cnt = block_count[a:b]
        offsets = torch.cumsum(cnt, 0) - cnt
        n = int(cnt.sum())
        within = torch.arange(n) - torch.repeat_interleave(offsets, cnt)
        local = torch.repeat_interleave(block_pixel[a:b], cnt)
        sample = torch.repeat_interleave(block_start[a:b], cnt) + within
        values = radiance(ctx, local + op.first_pixel, sample, stream=op.stream, record=op.record)
        color = values[0:3] + values[3:6] + values[6:9]
        film.add_blocks(torch.cat([values, color]), block_pixel[a:b], cnt, slice(9, 12))
        if op.on_chunk is not None:
            op.on_chunk(n)
    return film.mean[:9].numpy(), film.variance_of_mean().numpy()
