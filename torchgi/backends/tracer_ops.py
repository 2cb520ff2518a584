"""The renderer's ops at the back-end seam: what a back end needs to trace a pass
(:class:`TraceSetup`), one tile of a render pass (:class:`PathOp`) and the first-hit guides
(:class:`GuideRaysOp`), how the tracers cut a tile's samples (:func:`chunks`), and whether this
process has started embree. Re-exported by :mod:`torchgi.backends.base`."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["GuideRaysOp", "PathOp", "TraceSetup", "chunks", "embree_started", "mark_embree_started"]


@dataclass(frozen=True, slots=True)
class TraceSetup:
    """What a back end needs from the renderer to trace a pass, beyond the scene's tables (the
    back ends sit below :mod:`torchgi.render` and import nothing of it; the renderer builds this,
    ``torchgi.render.tiles.trace_setup``): the camera's ``origin`` (3 floats), its ``basis``
    (right, up, forward: 9 floats), the tangents of its half field of view ``tan_x``, ``tan_y``;
    the pass's sampler ``key_head`` (an unsigned 32-bit int), ``roulette_from`` (bounces before
    Russian roulette may end a path), ``every_skip`` (every skip of docs/design.md, Skips, is on), and
    ``wavefronts(op)``: the renderer's torch code for the op, the torch back end's reference."""

    origin: tuple[float, ...]
    basis: tuple[float, ...]
    tan_x: float
    tan_y: float
    key_head: int
    roulette_from: int
    every_skip: bool
    wavefronts: Callable[[Any], Any]


@dataclass(eq=False, slots=True)
class PathOp:
    """One tile of a render pass of :mod:`torchgi.render`'s "path" integrator: ``counts (P,)``
    int64 samples (numpy) of the pixels ``first_pixel ... first_pixel + P - 1`` (global index
    ``b*H*W + y*W + x``) of the scene ``arrays`` (``SceneArrays``) and its ``tables`` (``Tables``)
    seen by ``camera``; ``bounces``, ``seed``, the pass's random ``stream`` and ``record``
    ("all" / "direct" / "indirect"), the skips (docs/design.md, Skips) that are on (``skip``), paths per
    chunk (``chunk_size``), the renderer's :class:`TraceSetup`, ``threads`` (>= 1) and
    ``on_chunk(samples)`` (progress, or None); ``profile``: None, or a zeroed float64
    ``(threads, 4)`` tensor into which the compiled tracer adds, per thread, its seconds in
    embree's closest-hit and occlusion queries and their counts. Returns numpy float64
    ``mean (9, P)`` (emission, direct, indirect) and ``variance (3, P)`` of the colour's mean (0
    below 2 samples). Built by ``torchgi.render.tiles.path_op``."""

    arrays: Any
    tables: Any
    camera: Any
    bounces: int
    seed: int
    stream: int
    record: str
    skip: frozenset[str]
    first_pixel: int
    counts: Any
    chunk_size: int
    setup: TraceSetup
    threads: int = 1
    on_chunk: Callable[[int], None] | None = None
    profile: torch.Tensor | None = None  # (threads, 4) float64: the compiled tracer adds embree's seconds there

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return ()


@dataclass(eq=False, slots=True)
class GuideRaysOp:
    """The first-hit guides of one ray through each pixel centre of ``camera`` in the scene
    ``arrays`` / ``tables`` (as :class:`PathOp`, with its :class:`TraceSetup`), on ``threads``
    threads. Returns ``albedo, normal, position (3, H*W)``, ``depth (1, H*W)`` float32 and
    ``hit (1, H*W)`` bool (the normal faces the camera; everything 0 on a miss). Built by
    ``torchgi.render.tiles.guide_rays_op``."""

    arrays: Any
    tables: Any
    camera: Any
    setup: TraceSetup
    chunk_size: int = 1 << 15
    threads: int = 1

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return ()


def chunks(counts: torch.Tensor, size: int) -> Iterator[tuple[int, int]]:
    """Consecutive index ranges ``[a, b)`` of ``counts (N,)`` int64 holding at most ``size`` in
    total each (at least one index each): how the tracers cut a tile's samples into pieces.

    Example:
        >>> list(chunks(torch.tensor([2, 2, 5, 1]), 4))
        [(0, 2), (2, 3), (3, 4)]
    """
    ends = torch.cumsum(counts, 0)
    a, total = 0, len(counts)
    while a < total:
        done = int(ends[a - 1]) if a else 0
        b = int(torch.searchsorted(ends, done + size, right=True))
        b = max(b, a + 1)
        yield a, b
        a = b


_EMBREE_STARTED = [False]


def embree_started() -> bool:
    """True once this process has built an embree BVH (by the compiled tracer or embreex):
    embree's TBB worker threads then exist, and a process forked from this one must not use
    embree (``torchgi.render.engine.process_context``).

    Example:
        >>> isinstance(embree_started(), bool)
        True
    """
    return _EMBREE_STARTED[0]


def mark_embree_started() -> None:
    """Record that this process has started embree (see :func:`embree_started`).

    Example:
        >>> mark_embree_started(); embree_started()
        True
    """
    _EMBREE_STARTED[0] = True
