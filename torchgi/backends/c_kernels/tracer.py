"""The C back end's path tracer (``tracer.c`` on embree 4): a tile of a render pass and the
guide rays, on OpenMP threads, BVHs held per call."""

from __future__ import annotations

import contextlib
import ctypes
from collections.abc import Iterator

import torch

from torchgi.backends.base import (
    GuideRaysOp,
    PathOp,
    chunks,
)
from torchgi.backends.c_kernels import build
from torchgi.backends.c_kernels.build import _F, _I, _L, _P
from torchgi.backends.c_kernels.embree import embree_functions


class _Render(ctypes.Structure):
    """``pt_render`` of tracer.c."""

    _fields_ = [("tri", _P), ("light", _P), ("cdf", _P), ("points", _P), ("intensities", _P), ("sky", _P),
                ("T", _L), ("L", _I), ("P", _I), ("any_glossy", _I), ("eps", _F), ("origin", _F * 3),
                ("basis", _F * 9), ("tan_x", _F), ("tan_y", _F), ("width", _I), ("height", _I), ("bounces", _I),
                ("roulette_from", _I), ("record", _I), ("head", ctypes.c_uint32), ("profile", _P)]


_RECORD = {"all": 0, "direct": 1, "indirect": 2}
_embree_status: str | None = None  # None: not tried yet; "": loaded
_SCENES_KEPT = 2  # BVHs a process keeps between calls
_scenes: dict[str, list] = {}  # scene key -> [BVH handle, its tables, calls tracing it]; least recently used first


def _path_support(desc: PathOp | GuideRaysOp) -> str | None:
    """Why the compiled tracer cannot take ``desc``, or None."""
    if isinstance(desc, PathOp) and not desc.setup.every_skip:
        return "the compiled tracer applies every skip of docs/design.md (Skips); with one off the torch code runs"
    width, height = desc.camera.resolution
    if desc.arrays.triangles.shape[0] >= 2**31 or width * height >= 2**31:
        return "the compiled tracer takes fewer than 2^31 triangles and pixels"
    if build.library() is None:
        return build._status
    global _embree_status
    if _embree_status is None:
        with build._lock:
            if _embree_status is None:
                try:
                    build.library().torchgi_embree_init((ctypes.c_void_p * 13)(*embree_functions()))
                    _embree_status = ""
                except Exception as err:  # noqa: BLE001 - no embree 4 library: the torch code runs
                    _embree_status = f"compiled tracer unavailable: {err}"
    return _embree_status or None


@contextlib.contextmanager
def _bvh(arrays, tables) -> Iterator[tuple[int, tuple[torch.Tensor | None, ...]]]:
    """This scene's embree BVH (built once per process) and its tables laid out one row per
    triangle / light, held for the ``with`` block: beyond :data:`_SCENES_KEPT` scenes the least
    recently used one is freed, but never while a call (another thread's) still traces it."""
    lib = build.library()
    with build._lock:
        entry = _scenes.pop(arrays.key, None)
        if entry is None:
            tri = torch.from_numpy(arrays.triangles).to(torch.float32).contiguous()
            handle = lib.torchgi_scene_new(tri.data_ptr(), tri.shape[0])
            if not handle:
                raise RuntimeError("embree could not build the BVH")
            keep = (tables.tri.T.contiguous(), tables.light.T.contiguous(), tables.light_cdf.contiguous(),
                    tables.points.to(torch.float32).contiguous(), tables.intensities.to(torch.float32).contiguous(),
                    None if tables.sky is None else tables.sky.reshape(3).to(torch.float32).contiguous())
            entry = [handle, keep, 0]
        _scenes[arrays.key] = entry  # the most recently used last
        entry[2] += 1
        _evict(lib)
    try:
        yield entry[0], entry[1]
    finally:
        with build._lock:
            entry[2] -= 1
            _evict(lib)


def _evict(lib: ctypes.CDLL) -> None:
    """Free the least recently used idle BVHs beyond :data:`_SCENES_KEPT` (under ``build._lock``)."""
    while len(_scenes) > _SCENES_KEPT:
        idle = next((key for key, entry in _scenes.items() if entry[2] == 0), None)
        if idle is None:
            return
        lib.torchgi_scene_free(_scenes.pop(idle)[0])


def _render_struct(desc: PathOp | GuideRaysOp, tables: tuple[torch.Tensor | None, ...]) -> _Render:
    """The ``pt_render`` of a call: the tables, the camera, the pass."""
    tri, light, cdf, points, intensities, sky = tables
    setup = desc.setup
    width, height = desc.camera.resolution
    path_op = isinstance(desc, PathOp)
    record = desc.record if path_op else "direct"
    return _Render(tri.data_ptr(), light.data_ptr(), cdf.data_ptr(), points.data_ptr(), intensities.data_ptr(),
                   None if sky is None else sky.data_ptr(), tri.shape[0], light.shape[0], points.shape[0],
                   int(desc.tables.any_glossy), max(desc.tables.scale * 2.0**-15, 1e-7),
                   (_F * 3)(*setup.origin), (_F * 9)(*setup.basis), setup.tan_x, setup.tan_y, width, height,
                   desc.bounces if path_op and record != "direct" else 0, setup.roulette_from, _RECORD[record],
                   setup.key_head if path_op else 0,
                   desc.profile.data_ptr() if path_op and desc.profile is not None else None)


def path(desc: PathOp) -> tuple:
    """:class:`~torchgi.backends.base.PathOp` by the compiled tracer (``tracer.c``): each
    pixel's samples in order on one of ``desc.threads`` OpenMP threads, the film merged there.

    Example:
        >>> from torchgi.render import scenes
        >>> from torchgi.render.tiles import path_op
        >>> import numpy as np
        >>> s = scenes.cornell(4)
        >>> op = path_op(s.arrays(), s.camera, np.full(16, 2), bounces=1, seed=0)
        >>> _path_support(op) is not None or path(op)[0].shape == (9, 16)
        True
    """
    why = _path_support(desc)
    if why is not None:
        raise RuntimeError(why)
    with _bvh(desc.arrays, desc.tables) as (handle, tables):
        return _trace_pixels(desc, handle, _render_struct(desc, tables))


def _trace_pixels(desc: PathOp, handle: int, r: _Render) -> tuple:
    counts = torch.from_numpy(desc.counts).to(torch.int64).contiguous()
    n = counts.numel()
    mean = torch.empty(9, n, dtype=torch.float64)  # every element written by the kernel
    var = torch.empty(3, n, dtype=torch.float64)
    # pieces of at most chunk_size samples per thread (>= 1 pixel), so that progress is reported as it goes
    for a, b in chunks(counts, desc.chunk_size * desc.threads):
        build.library().torchgi_render_pixels(handle, ctypes.byref(r), desc.first_pixel + a, counts[a:].data_ptr(), b - a,
                                              n, mean[:, a:].data_ptr(), var[:, a:].data_ptr(), desc.threads)
        if desc.on_chunk is not None:
            desc.on_chunk(int(counts[a:b].sum()))
    return mean.numpy(), var.numpy()


def guide_rays(desc: GuideRaysOp) -> dict[str, torch.Tensor]:
    """:class:`~torchgi.backends.base.GuideRaysOp` by the compiled tracer, on ``desc.threads`` threads.

    Example:
        >>> from torchgi.render import scenes
        >>> from torchgi.render.tiles import guide_rays_op
        >>> s = scenes.cornell(4)
        >>> op = guide_rays_op(s.arrays(), s.camera)
        >>> _path_support(op) is not None or guide_rays(op)["hit"].dtype == torch.bool
        True
    """
    why = _path_support(desc)
    if why is not None:
        raise RuntimeError(why)
    width, height = desc.camera.resolution
    out = torch.empty(11, width * height, dtype=torch.float32)
    with _bvh(desc.arrays, desc.tables) as (handle, tables):
        build.library().torchgi_render_guides(handle, ctypes.byref(_render_struct(desc, tables)), width * height,
                                        out.data_ptr(), desc.threads)
    return {"albedo": out[0:3], "normal": out[3:6], "position": out[6:9], "depth": out[9:10], "hit": out[10:11] > 0}

