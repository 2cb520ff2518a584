"""``torchgi.render``: scene + sample counts -> GBuffer, in memory-bounded chunks on all cores.

The "path" integrator runs in the compiled tracer where the C back end has it
(:class:`torchgi.backends.PathOp`: each pixel's samples in order on embree, on ``workers``
threads); otherwise, and for "basic", the torch wavefronts run: the pixels are cut into tiles;
each tile's samples are traced in chunks of at most ``chunk_size`` paths and merged into its
film; with ``workers > 1`` tiles go to a pool of processes (embreex holds the GIL while it
traces, so threads would serialise), each running torch on one thread. Random numbers are keyed
by (seed, pixel, sample, dimension) and the film merges fixed blocks of samples, so tiles,
chunks, threads and workers change no pixel.
"""

from __future__ import annotations

import atexit
import concurrent.futures
import contextlib
import dataclasses
import functools
import itertools
import multiprocessing
import os
import sys
from collections.abc import Callable, Collection, Iterator
from typing import Any

import numpy as np
import torch

from torchgi import backends
from torchgi.buffers import GBuffer
from torchgi.core.check import check_int, check_option, check_positive
from torchgi.core.errors import DeviceError, DTypeError, RangeError, ShapeError
from torchgi.render.camera import camera_rays, motion_vectors
from torchgi.render.film import BLOCK
from torchgi.render.integrators.common import CAMERA_DIMS, SKIPS, guides
from torchgi.render.sampler import sample_keys, uniform
from torchgi.render.scene import Camera, Scene, SceneArrays
from torchgi.render.scene_files import load_scene
from torchgi.render.tiles import INTEGRATORS, _context, film_tile, guide_rays_op, path_op, through_mirrors
from torchgi.supersample import EyeSamples

__all__ = [
    "INTEGRATORS", "SKIPS", "frame_seed", "process_context", "render", "render_guide_rays", "render_guides",
    "render_sequence", "worker_pool",
]

_PARALLEL_MIN_SAMPLES = 1 << 19  # below this a pool costs more than it saves (unless asked)
_TILES_PER_WORKER = 4


@dataclasses.dataclass(frozen=True)
class _Pass:
    stream: int
    record: str  # "all" | "direct" | "indirect"


@dataclasses.dataclass(frozen=True)
class _Job:
    arrays: SceneArrays
    camera: Camera
    integrator: str
    bounces: int
    seed: int
    render_pass: _Pass
    skip: frozenset[str]
    first_pixel: int
    counts: np.ndarray  # (P,) int64 samples of pixels first_pixel ... first_pixel + P - 1
    chunk_size: int
    allowed: tuple[str, ...]  # the back ends allowed where render() was called
    threads: int = 1


def _path_op(job: _Job, on_chunk: Callable[[int], None] | None = None) -> backends.PathOp:
    return path_op(job.arrays, job.camera, job.counts, bounces=job.bounces, seed=job.seed,
                   stream=job.render_pass.stream, record=job.render_pass.record, skip=job.skip,
                   first_pixel=job.first_pixel, chunk_size=job.chunk_size, threads=job.threads, on_chunk=on_chunk)


def _run_tile(job: _Job, on_chunk: Callable[[int], None] | None = None) -> tuple[np.ndarray, ...]:
    """Trace one tile (the "path" integrator through the back ends, "basic" by its torch code);
    returns its film's means of the radiance rows ``(9, P)`` and the variance of the colour mean ``(3, P)``."""
    with backends.use(*job.allowed):
        if job.integrator == "path":
            return backends.run(_path_op(job, on_chunk))
        return film_tile(_path_op(job, on_chunk), job.integrator)


def _tiles(counts: torch.Tensor, pieces: int) -> list[tuple[int, int]]:
    """Split pixels ``[0, P)`` into about ``pieces`` ranges of similar sample counts."""
    cum = torch.cumsum(counts, 0)
    total = int(cum[-1]) if cum.numel() else 0
    if pieces <= 1 or total == 0:
        return [(0, counts.numel())]
    targets = torch.linspace(0, total, pieces + 1, dtype=torch.float64)[1:-1].to(torch.int64)
    cuts = sorted({0, *torch.searchsorted(cum, targets, right=True).tolist(), counts.numel()})
    return [(a, b) for a, b in itertools.pairwise(cuts) if b > a]


_POOL: concurrent.futures.ProcessPoolExecutor | None = None
_POOL_SIZE = 0


def _shutdown_pool() -> None:
    global _POOL
    if _POOL is not None:
        _POOL.shutdown(wait=True, cancel_futures=True)
        _POOL = None


atexit.register(_shutdown_pool)


def _init_worker() -> None:
    torch.set_num_threads(1)


def process_context() -> multiprocessing.context.BaseContext:
    """The start method for worker processes (renders and data generation).

    ``fork`` while this process has not built a BVH yet: fast. Afterwards ``forkserver``
    (``spawn`` where that is missing): embree's TBB threads do not survive a fork, and a forked
    child that builds a BVH can deadlock (a CI run hung so, in ``Accel.intersect``). Pools from
    :func:`worker_pool` start those workers without running the user's ``__main__`` script again.
    """
    methods = multiprocessing.get_all_start_methods()
    if "fork" in methods and not backends.embree_started():
        return multiprocessing.get_context("fork")
    if "forkserver" in methods:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["torchgi.render.engine"])
        return ctx
    return multiprocessing.get_context("spawn")


@contextlib.contextmanager
def _main_hidden() -> Iterator[None]:
    """While worker processes start by forkserver / spawn, hide ``__main__``'s file and spec:
    multiprocessing would otherwise run the user's script again in every worker (which then
    renders again, or fails without a main guard); the workers only need torchgi."""
    main = sys.modules.get("__main__")
    saved = {k: main.__dict__[k] for k in ("__file__", "__spec__") if main is not None and k in main.__dict__}
    try:
        if main is not None:
            main.__dict__.pop("__file__", None)
            main.__dict__["__spec__"] = None
        yield
    finally:
        if main is not None:
            main.__dict__.pop("__spec__", None)
            main.__dict__.update(saved)


def worker_pool(workers: int, initializer: Callable[[], None] | None = None) -> concurrent.futures.ProcessPoolExecutor:
    """A process pool of ``workers`` (see :func:`process_context`), all started now; with
    forkserver / spawn they start without re-running ``__main__``, so scripts need no main guard.

    Example:
        >>> with worker_pool(2) as pool:
        ...     sorted(pool.map(abs, [-1, 2]))
        [1, 2]
    """
    ctx = process_context()
    pool = concurrent.futures.ProcessPoolExecutor(workers, mp_context=ctx, initializer=initializer)
    if ctx.get_start_method() != "fork":
        with _main_hidden():
            pool._launch_processes()  # private, stable since 3.9: every worker now, while __main__ is hidden
    return pool


def _pool(workers: int) -> concurrent.futures.ProcessPoolExecutor:
    """A persistent pool of ``workers`` single-threaded processes (see :func:`worker_pool`)."""
    global _POOL, _POOL_SIZE
    if _POOL is None or _POOL_SIZE != workers:
        if _POOL is not None:
            _POOL.shutdown()
        _POOL = worker_pool(workers, _init_worker)
        _POOL_SIZE = workers
    return _POOL


def _progress_bar(total: int, enabled: bool | None, desc: str) -> Any:
    from tqdm.auto import tqdm

    show = sys.stderr.isatty() if enabled is None else enabled
    return tqdm(total=total, disable=not show, delay=1.0, unit="spp", unit_scale=True, desc=desc, leave=False)


def _counts(spp: int | torch.Tensor, camera: Camera) -> torch.Tensor:
    width, height = camera.resolution
    if isinstance(spp, torch.Tensor):
        if spp.dtype in (torch.bool,) or spp.is_floating_point() or spp.is_complex():
            raise DTypeError(f"spp: expected an integer tensor, got {spp.dtype}")
        if spp.device.type != "cpu":
            raise DeviceError(f"spp: the renderer runs on the CPU; pass a CPU tensor (got {spp.device})")
        if spp.dim() != 4 or spp.shape[1] != 1 or tuple(spp.shape[2:]) != (height, width):
            raise ShapeError(f"spp: expected (B, 1, {height}, {width}) for this camera, got {tuple(spp.shape)}")
        if spp.numel() and int(spp.min()) < 0:
            raise RangeError(f"spp: expected counts >= 0, found {int(spp.min())}")
        return spp.to(torch.int64)
    check_int(spp, "spp", 1)
    return torch.full((1, 1, height, width), spp, dtype=torch.int64)


def render_guides(scene: Scene | str | os.PathLike[str], *, chunk_size: int = 1 << 15) -> GBuffer:
    """The noise-free guides alone: one ray through each pixel centre (no shading).

    Returns a GBuffer (B = 1, CPU, float32) with ``albedo``, ``normal`` (facing the camera),
    ``position``, ``depth (1,1,H,W)`` (distance along the ray) and ``hit``; 0 on background.
    What adaptive sampling reads before it spends any sample.

    Example:
        >>> from torchgi.render import scenes
        >>> g = render_guides(scenes.cornell(8))
        >>> g.normal.shape, g.color is None
        (torch.Size([1, 3, 8, 8]), True)
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    check_int(chunk_size, "chunk_size", 1)
    return _guides(scene, chunk_size, torch.get_num_threads())


def _guides(scene: Scene, chunk_size: int, threads: int, mirror_guides: float | None = None) -> GBuffer:
    width, height = scene.camera.resolution
    arrays = scene.arrays()
    g = backends.run(guide_rays_op(arrays, scene.camera, chunk_size, threads))
    if mirror_guides is not None:
        g["albedo"], g["normal"] = through_mirrors(arrays, scene.camera, mirror_guides, g["albedo"], g["normal"],
                                                   chunk_size)
    return GBuffer(**{k: v.reshape(1, -1, height, width) for k, v in g.items()})


def _check_mirror_guides(mirror_guides: float | None) -> None:
    """``mirror_guides``: None or a roughness in (0, 1], else the error naming it."""
    if mirror_guides is None:
        return
    check_positive(mirror_guides, "mirror_guides")
    if mirror_guides > 1:
        raise RangeError(f"mirror_guides: expected None or a roughness in (0, 1], got {mirror_guides!r}")


def render_guide_rays(
    scene: Scene | str | os.PathLike[str],
    spp: int = 4,
    bounces: int = 1,
    seed: int = 0,
    *,
    integrator: str = "path",
    chunk_size: int = 1 << 15,
) -> tuple[GBuffer, EyeSamples]:
    """Render for supersampling with guide rays (Bauszat et al. 2011 §3.2; :mod:`torchgi.supersample`).

    Sample 0 of each pixel is a guide ray through its centre, the only path that estimates
    indirect light; the ``spp - 1`` further eye rays are jittered in the pixel and compute only
    emission and direct light, plus their first-hit guides. One process (no workers).

    Args:
        scene: a :class:`Scene`, a YAML path or a built-in name.
        spp: eye rays per pixel, >= 1 (the guide ray included).
        bounces: indirect bounces of the guide rays' paths, >= 0.
        seed: in [0, 2^32).
        integrator: "path" or "basic".
        chunk_size: rays traced at once, >= 1.

    Returns:
        The guide rays' GBuffer (B = 1, CPU, float32): ``emission``, ``direct``, ``indirect``
        of one path per pixel centre, its first-hit ``albedo``, ``normal``, ``position``,
        ``depth``, ``hit`` and ``spp`` (1); and the :class:`~torchgi.supersample.EyeSamples` of
        the other eye rays, ``S = spp - 1``.

    Example:
        >>> from torchgi.render import scenes
        >>> gb, eye = render_guide_rays(scenes.cornell(8), spp=3)
        >>> gb.indirect.shape, eye.direct.shape
        (torch.Size([1, 3, 8, 8]), torch.Size([1, 2, 3, 8, 8]))
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    check_int(spp, "spp", 1)
    check_int(bounces, "bounces", 0)
    _check_seed(seed)
    check_option(integrator, "integrator", tuple(INTEGRATORS))
    check_int(chunk_size, "chunk_size", 1)
    width, height = scene.camera.resolution
    P, S = width * height, spp - 1
    ctx = _context(scene.arrays(), scene.camera, bounces, seed)
    radiance = INTEGRATORS[integrator]
    rows = torch.zeros(9, P)
    for start in range(0, P, chunk_size):
        pixel = torch.arange(start, min(start + chunk_size, P))
        rows[:, start : start + pixel.numel()] = radiance(ctx, pixel, torch.zeros_like(pixel), centre=True)
    eye = {k: torch.zeros(c, S * P) for k, c in (("offset", 2), ("normal", 3), ("depth", 1), ("albedo", 3),
                                                 ("emission", 3), ("direct", 3))}
    for start in range(0, S * P, chunk_size):
        index = torch.arange(start, min(start + chunk_size, S * P))
        pixel, sample = index % P, index // P + 1
        jitter = uniform(sample_keys(seed, pixel, sample, 0), CAMERA_DIMS)
        g = guides(ctx, pixel, jitter)
        values = radiance(ctx, pixel, sample, record="direct")
        chunk = slice(start, start + index.numel())
        eye["offset"][:, chunk] = jitter
        for k in ("normal", "depth", "albedo"):
            eye[k][:, chunk] = g[k]
        eye["emission"][:, chunk] = values[0:3]
        eye["direct"][:, chunk] = values[3:6]
    g = render_guides(scene, chunk_size=chunk_size)

    def image(x: torch.Tensor) -> torch.Tensor:  # (C, P) -> (1, C, H, W)
        return x.reshape(1, -1, height, width)

    samples = EyeSamples(**{k: v.reshape(v.shape[0], S, height, width).permute(1, 0, 2, 3)[None].contiguous()
                            for k, v in eye.items()})
    gb = GBuffer(emission=image(rows[0:3]), direct=image(rows[3:6]), indirect=image(rows[6:9]), albedo=g.albedo,
                 normal=g.normal, position=g.position, depth=g.depth, hit=g.hit,
                 spp=torch.ones(1, 1, height, width, dtype=torch.int64))
    return gb, samples


def render(
    scene: Scene | str | os.PathLike[str],
    spp: int | torch.Tensor = 1,
    bounces: int = 1,
    seed: int = 0,
    *,
    integrator: str = "path",
    workers: int | None = None,
    chunk_size: int = 1 << 15,
    progress: bool | None = None,
    skip_unneeded: bool | Collection[str] = True,
    mirror_guides: float | None = None,
    fill_empty: bool = True,
    guides: bool = True,
) -> GBuffer:
    """Path-trace a scene into a :class:`~torchgi.GBuffer` (CPU, float32).

    Args:
        scene: a :class:`Scene`, a YAML path or a built-in name ("cornell", ...).
        spp: samples per pixel, an int > 0; or a per-pixel ``(B, 1, H, W)`` int tensor >= 0
            (adaptive sampling): each pixel's whole light (emission, direct and indirect) gets
            its count of samples; a pixel given 0 gets one sample of emission and direct light
            and no indirect light (what a background pixel shows), and counts as 1 in the
            returned ``spp`` (with ``fill_empty=False`` it stays 0, ``spp`` 0: a round that
            :func:`~torchgi.sampling.merge_rounds` adds to another); B > 1 renders B
            independent images.
        bounces: indirect bounces >= 0 (0 = direct light only; Mitsuba's ``max_depth`` is
            ``bounces + 2``).
        seed: in [0, 2^32); the same seed gives the same image, bit for bit.
        integrator: "path" (fast: MIS, compaction, Russian roulette) or "basic" (readable).
        workers: threads of the compiled tracer (None: ``torch.get_num_threads()``); where it
            does not run (no C compiler, a skip turned off, ``integrator="basic"``), processes
            (None: all available cores for renders of >= 2^19 samples; see
            :func:`process_context` for how they start; no main guard is needed).
        chunk_size: paths the torch wavefronts trace at once per worker (memory bound); the
            compiled tracer's progress step per thread; >= 1024.
        progress: a progress bar (shown after 1 s); None = only on a terminal.
        skip_unneeded: skip work the scene does not need (docs/design.md, Skips): True = every skip,
            False = none, or the names to keep from ``SKIPS`` ("absent_lights", "dead_paths",
            "last_vertex_rays"). Skips change no pixel beyond noise; turning them off is for
            benchmarks and tests.
        mirror_guides: None (the guides of the first hit), or a roughness in (0, 1]: on glossy
            surfaces rougher than none of it (near-mirrors) the ``albedo`` and ``normal`` are
            those of the first hit the mirror reflection meets that is not one (up to 4
            reflections; a mirror that shows the background keeps its own), as Intel Open Image
            Denoise asks of its guides; ``position``, ``depth`` and ``hit`` stay the first hit's.
        fill_empty: see ``spp``.
        guides: False: no guide rays; ``albedo``, ``normal``, ``position``, ``depth`` and ``hit``
            are None (a later round merged into one that has them).

    Returns:
        GBuffer with ``color = emission + direct + indirect``, ``emission``, ``direct``,
        ``indirect`` ``(B,3,H,W)`` radiance; ``albedo``, ``normal`` (facing the camera),
        ``position``, ``depth (B,1,H,W)`` and ``hit`` from a ray through each pixel centre
        (0 on background); ``variance (B,3,H,W)``, the variance of the colour estimate (of the
        mean; 0 where fewer than 2 samples); ``spp (B,1,H,W)`` int64, the samples of each pixel.

    Example:
        >>> from torchgi.render import scenes
        >>> gb = render(scenes.cornell(resolution=16), spp=2, bounces=1)
        >>> gb.color.shape, bool(gb.hit.any())
        (torch.Size([1, 3, 16, 16]), True)
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    skips = _check_render_args(bounces, seed, integrator, skip_unneeded, chunk_size, workers)
    _check_mirror_guides(mirror_guides)
    camera = scene.camera
    width, height = camera.resolution
    counts = _counts(spp, camera)
    batch = counts.shape[0]
    flat = counts.reshape(-1)
    passes = [(_Pass(0, "all"), flat)]
    if fill_empty and isinstance(spp, torch.Tensor) and bool((flat == 0).any()):  # one sample of what a miss shows
        passes.append((_Pass(1, "direct"), (flat == 0).to(flat.dtype)))
    total = sum(int(c.sum()) for _, c in passes)
    allowed = tuple(name for name in backends.NAMES if backends.enabled(name))
    jobs = functools.partial(_Job, scene.arrays(), camera, integrator, bounces, seed)
    with _progress_bar(total, progress, f"render {scene.name}") as bar:
        rows = _trace(jobs, passes, skips, chunk_size, workers, total, allowed, bar)
    g = _guides(scene, chunk_size, workers or torch.get_num_threads(), mirror_guides) if guides else None

    def image(x: torch.Tensor) -> torch.Tensor:  # (C, B*H*W) -> (B, C, H, W)
        return x.reshape(x.shape[0], batch, height, width).permute(1, 0, 2, 3).contiguous()

    def guide(x: torch.Tensor | None) -> torch.Tensor | None:  # (1, C, H, W), the same for every image
        return None if x is None else x.expand(batch, -1, -1, -1).contiguous()

    return GBuffer(
        emission=image(rows[0:3]),
        direct=image(rows[3:6]),
        indirect=image(rows[6:9]),
        **{k: guide(getattr(g, k) if g is not None else None) for k in ("albedo", "normal", "position", "depth", "hit")},
        variance=image(rows[9:12]),
        spp=counts.clamp_min(1) if fill_empty else counts.clone(),
    )


def _check_seed(seed: int) -> None:
    """``seed``: an int in [0, 2^32), else the error naming it."""
    check_int(seed, "seed", 0)
    if seed >= 1 << 32:
        raise RangeError(f"seed: expected an int in [0, 2^32), got {seed}")


def frame_seed(seed: int, frame: int) -> int:
    """The seed :func:`render_sequence` gives frame ``frame`` of a sequence started with ``seed``
    (a golden-ratio step modulo 2^32, so neighbouring sequences do not share frames' noise).

    Example:
        >>> frame_seed(0, 0), frame_seed(0, 1)
        (0, 2654435769)
    """
    return (seed + 0x9E3779B9 * frame) % (1 << 32)


def render_sequence(
    scene: Scene | str | os.PathLike[str],
    frames: int,
    spp: int | torch.Tensor = 1,
    bounces: int = 1,
    seed: int = 0,
    **render_args: Any,
) -> Iterator[GBuffer]:
    """Render the frames of an animation (the camera's ``scene.path``, YAML ``camera.path``, and
    the meshes' ``path``), one by one.

    Frame ``k`` is at time ``t0 + k (t1 - t0) / (frames - 1)`` over every path's keyframes
    (:meth:`Scene.times_of`), rendered by :func:`render` with seed ``frame_seed(seed, k)``; the
    BVH of still geometry is built once, that of moving meshes once per frame. A still scene
    gives ``frames`` renders of its still camera (noise differs, motion is 0).

    Args:
        scene: a :class:`Scene`, a YAML path or a built-in name.
        frames: number of frames, >= 1.
        spp, bounces, seed, render_args: as for :func:`render`.

    Yields:
        One GBuffer per frame, :func:`render`'s fields plus ``motion (B,2,H,W)``: the backward
        screen-space motion in pixels (:func:`torchgi.render.camera.motion_vectors`; 0 in the
        first frame). On a moving mesh, the pixel-centre hit is carried back through the mesh's
        motion to where that point of the mesh was in the previous frame, then projected by the
        previous camera.

    Example:
        >>> from torchgi.render import scenes
        >>> [gb.motion.shape for gb in render_sequence(scenes.cornell(8), 2)]
        [torch.Size([1, 2, 8, 8]), torch.Size([1, 2, 8, 8])]
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    check_int(frames, "frames", 1)
    _check_seed(seed)
    times = scene.times_of(frames)
    previous: Scene | None = None
    for k, time in enumerate(times):
        frame = scene.at(time)
        gb = render(frame, spp, bounces, frame_seed(seed, k), **render_args)
        points = gb.position
        if previous is not None and scene.moving:
            points = _carried_back(frame, previous.time, gb.position, gb.hit)
        yield gb.replace(motion=motion_vectors(frame.camera, None if previous is None else previous.camera, points,
                                               gb.hit))
        previous = frame


def _carried_back(frame: Scene, before: float | None, position: torch.Tensor, hit: torch.Tensor) -> torch.Tensor:
    """The first-hit points ``position (B, 3, H, W)`` of ``frame`` (a scene at its :attr:`Scene.time`)
    where they were at time ``before``: a point on a moving mesh through ``M(before) M(now)^-1``
    of its path, other points unchanged. The mesh of each pixel is that of its centre ray's hit."""
    width, height = frame.camera.resolution
    arrays = frame.arrays()
    origin, direction = camera_rays(frame.camera, torch.arange(width * height), None)
    _, prim = _context(arrays, frame.camera, 0, 0).accel.intersect(origin, direction)
    owner = torch.where(prim >= 0, torch.from_numpy(arrays.mesh)[prim.clamp(min=0)], -1).reshape(1, 1, height, width)
    out = position.double()
    for i in frame.moving:
        mesh = frame.meshes[i]
        m = torch.from_numpy(mesh.matrix(before) @ np.linalg.inv(mesh.matrix(frame.time)))
        moved = torch.einsum("ij,bjhw->bihw", m[:3, :3], out) + m[:3, 3].reshape(1, 3, 1, 1)
        out = torch.where((owner == i) & hit, moved, out)
    return out


def _check_render_args(
    bounces: int, seed: int, integrator: str, skip_unneeded: bool | Collection[str], chunk_size: int,
    workers: int | None,
) -> frozenset[str]:
    """Validate :func:`render`'s arguments; returns the skips to apply."""
    check_int(bounces, "bounces", 0)
    _check_seed(seed)
    check_option(integrator, "integrator", tuple(INTEGRATORS))
    if isinstance(skip_unneeded, bool):
        skips = frozenset(SKIPS) if skip_unneeded else frozenset()
    else:
        skips = frozenset(skip_unneeded)
        for name in skips:
            check_option(name, "skip_unneeded", tuple(SKIPS))
    check_int(chunk_size, "chunk_size", BLOCK)
    if workers is not None:
        check_int(workers, "workers", 1)
    return skips


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _trace(
    jobs: Callable[..., _Job], passes: list, skips: frozenset[str], chunk_size: int, workers: int | None, total: int,
    allowed: tuple[str, ...], bar,
) -> torch.Tensor:
    """Trace every pass in tiles into radiance rows 0-8 (emission, direct, indirect) and the
    colour variance 9-11, float32 ``(12, pixels)``: by the compiled tracer on ``workers`` threads
    (None: every core) where it takes the render, else here or on ``workers`` processes (None:
    every core from 2^19 samples); each tile is merged as soon as it arrives, so only one tile's
    film is held at a time."""
    rows = torch.empty(12, passes[0][1].numel())  # the first pass's tiles cover every pixel
    probe = jobs(passes[0][0], skips, 0, passes[0][1][:1].numpy(), chunk_size, allowed)
    with backends.use(*allowed):
        compiled = probe.integrator == "path" and backends.select(_path_op(probe))[0] == "c"
    if compiled:
        threads, workers = workers or torch.get_num_threads(), 1
    else:
        threads = 1
        workers = workers or (_cores() if total >= _PARALLEL_MIN_SAMPLES else 1)
    for index, (render_pass, pass_counts) in enumerate(passes):
        tiles = _tiles(pass_counts, workers * _TILES_PER_WORKER if workers > 1 else 1)
        tile_jobs = [jobs(render_pass, skips, a, pass_counts[a:b].numpy(), chunk_size, allowed, threads)
                     for a, b in tiles]
        if workers > 1:
            futures = {_pool(workers).submit(_run_tile, job): tile for job, tile in zip(tile_jobs, tiles)}
            done = ((futures[f], f.result()) for f in concurrent.futures.as_completed(futures))
        else:
            done = ((tile, _run_tile(job, bar.update)) for job, tile in zip(tile_jobs, tiles))
        for (a, b), (mean, variance) in done:
            if index == 0:
                rows[:9, a:b].copy_(torch.from_numpy(mean))
                rows[9:, a:b].copy_(torch.from_numpy(variance))
            else:
                rows[:9, a:b] += torch.from_numpy(mean)
                rows[9:, a:b] += torch.from_numpy(variance)  # (independent passes: their variances add)
            if workers > 1:
                bar.update(int(pass_counts[a:b].sum()))
    return rows
