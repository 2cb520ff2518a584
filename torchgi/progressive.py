"""Progressive rendering to a time budget or a target error, with the samples placed for the
Denoiser (``torchgi.render_to``; docs/design.md, Sampling). Above the Denoiser in the layers: it
denoises between rounds.

Round 0 renders ``first_spp`` samples in every pixel; each later round places its samples where
they lower the error of the denoised image most. With the per-pixel sample variance ``s²``
(3x3 box-blurred, from the rounds so far) and relMSE's weight ``w = 1 / (d² + 0.01)`` (``d`` the
denoised colour with ``target``, else the noisy colour box-blurred at radius 2), the error
``Σ_p w_p s²_p / n_p`` is least at counts ``n_p ∝ sqrt(w_p s²_p)``; a round gives each pixel its
shortfall from that share of the new total (:func:`~torchgi.sampling.allocate`, exact). With
``geometry=True`` the share is divided by the square root of the filter's support (Bauszat et
al. 2011's geometry weights, :func:`~torchgi.sampling.importance_map`). Rounds merge by
:func:`~torchgi.sampling.merge_rounds`.

``seconds``: the wall time of the renders, the planning and the final denoise together. A
render call is planned to take ``call + n · per_sample`` seconds for ``n`` samples: ``call``, its
cost beside its samples, is taken as :data:`_CALL_SPP` samples per pixel of round 0's time;
``per_sample`` from the round before (round 0's times :data:`_ADAPTIVE_COST` for the first
placed round). The final denoise is timed after round 0 on round 0's buffers given the sample
count the budget is planned to reach (and their variance scaled to it), so that a Denoiser that
does more work at more samples is planned with that work. The samples that plan, the
planning's time and the Denoiser's measured time leave go into one placed round, or, where 0.3
of them are worth at least two calls, 0.7 of them into the first placed round and the rest,
timed by its measured time per sample, into a second (each call costs; a second round corrects
the first's time per sample); a budget smaller than round 0 and one denoise is overrun by them.
With ``target`` each round doubles the samples.

``target``: the estimated relMSE of the denoised image. Every round is rendered as two halves of
independent seeds ``a`` and ``b``; each half's denoised error is estimated against the other
half's noisy colour, ``mean(w ((D(a) - x_b)² - Var(x_b)))`` (the noise of ``x_b`` is independent
of ``D(a)``, so only its variance is subtracted: the Denoiser's bias is in it), the two averaged
and divided by :data:`HALF_TO_WHOLE` (the whole's error below a half's, set on the tuning
scenes: docs/benchmarks/adaptive.md). The next round has the samples an error falling as ``n^-1/2`` reaches the
target with (at most twice those so far).
"""

from __future__ import annotations

import os
import time
from typing import TYPE_CHECKING, Any

import torch

from torchgi.core.check import check_int, check_positive
from torchgi.denoise import Denoiser
from torchgi.filters.box import box
from torchgi.sampling import allocate, geometry_importance, merge_rounds

if TYPE_CHECKING:
    from torchgi.buffers import GBuffer
    from torchgi.render.scene import Scene

__all__ = ["HALF_TO_WHOLE", "render_to"]

HALF_TO_WHOLE = 1.45  # a half's denoised relMSE over the whole's (docs/benchmarks/adaptive.md)
_EPS = 0.01  # relMSE's (torchgi.metrics.relmse)
_MIN_ROUND = 0.125  # a round of fewer samples per pixel than this is not worth its call
# a placed sample's time over a uniform one's, until a placed round is timed (they go where light
# paths are longer: 1.1-1.15x on the tuning scenes, docs/benchmarks/adaptive.md)
_ADAPTIVE_COST = 1.2
# a render call's cost beside its samples, in samples per pixel of round 0 (its buffers and its
# walk over every pixel: 0.25-0.7 spp on the tuning scenes, docs/benchmarks/adaptive.md)
_CALL_SPP = 0.5


def render_to(
    scene: Scene | str | os.PathLike,
    *,
    seconds: float | None = None,
    target: float | None = None,
    bounces: int = 1,
    seed: int = 0,
    denoiser: Any = None,
    first_spp: int = 2,
    max_spp: float = 4096.0,
    adaptive: bool = True,
    geometry: bool = False,
    progress: bool | None = None,
    **render_kwargs: Any,
) -> GBuffer:
    """Render ``scene`` in rounds until ``seconds`` of wall time are used or the estimated relMSE
    of the denoised image is at most ``target``, each round's samples where they lower the
    denoised error most (module docstring).

    Args:
        scene: a Scene, YAML path or built-in name.
        seconds: the wall-time budget in seconds (renders, planning and the final denoise), > 0.
        target: the estimated relMSE to reach, > 0 (give exactly one of ``seconds`` and ``target``).
        bounces, seed: as :func:`torchgi.render`; a seed and a ``target`` give the same rounds
            every time (with ``seconds`` the round sizes follow the measured times).
        denoiser: the Denoiser the samples are placed for and the error estimated with (None:
            ``Denoiser()``).
        first_spp: samples of round 0 in every pixel, an int >= 2 (a variance needs two).
        max_spp: stop before the mean samples per pixel pass this, > 0.
        adaptive: place each round's samples (module docstring); False: every round uniform
            (a time budget or a target without placement).
        geometry: divide each pixel's share by the square root of the filter's support.
        progress: print a line per round (None: only on a terminal).
        render_kwargs: passed on to :func:`torchgi.render` (``workers``, ``chunk_size``).

    Returns:
        The merged GBuffer: ``spp (1, 1, H, W)`` each pixel's samples, ``variance`` that of its
        colour; ``Denoiser()(gb)`` is the result.

    Example:
        >>> from torchgi.render import scenes
        >>> gb = render_to(scenes.cornell(16), seconds=0.5, bounces=1)
        >>> int(gb.spp.min()) >= 2
        True
    """
    from torchgi.render import load_scene

    start = time.perf_counter()
    _check_args(seconds, target, first_spp, max_spp)
    scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
    run = _Run(scene, bounces, seed, target is not None, render_kwargs, None if seconds is None else start + seconds)
    denoiser = Denoiser() if denoiser is None else denoiser
    show = progress if progress is not None else os.isatty(2)
    W, H = scene.camera.resolution
    pixels = H * W
    first = torch.full((1, 1, H, W), first_spp, dtype=torch.int64)
    acc, whole, per_sample, call_s, denoised, denoise_s = run.first(first, denoiser, _ADAPTIVE_COST if adaptive else 1.0)
    total = int(first.sum())
    support = _support(whole[0]) if geometry else None
    r, overhead, history = 0, 0.0, []
    while True:
        t_plan = time.perf_counter()
        n = total  # with a target the next round doubles the samples
        estimate = None
        if target is not None:
            estimate = _estimate(acc, whole, denoised, denoiser)
            history.append((total, estimate))
            if estimate <= target:
                break
            n = _samples_to(history, target)
        if seconds is not None:  # what is left after this round's planning and the final denoise
            n = _samples_left(seconds - (time.perf_counter() - start) - overhead - denoise_s, call_s, per_sample, r)
        n = min(n, int(max_spp * pixels) - total)
        if show:
            _report(r, total / pixels, time.perf_counter() - start, estimate)
        if n < _MIN_ROUND * pixels:
            break
        r += 1
        counts = _counts(whole[0], whole[1], denoised if target is not None else None, n, support, adaptive)
        t0 = time.perf_counter()
        parts = run.round(counts, r)
        t_render = time.perf_counter() - t0
        per_sample = max(t_render - len(parts) * call_s, t_render / 2) / n
        acc = [(merge_rounds(a, ca, b, cb), ca + cb) for (a, ca), (b, cb) in zip(acc, parts)]
        total += n
        whole = _merged(acc)
        if target is not None:
            denoised = denoiser(whole[0])  # the estimate's reference and the next round's weights
        overhead = time.perf_counter() - t_plan - t_render  # a round's work beside its render
    return whole[0]


class _Run:
    """How a round renders: one render, or with ``halves`` two of independent seeds; after round
    0 without the sample of what a miss shows on pixels it skips and without guide rays. With a
    ``deadline`` (``time.perf_counter()`` seconds), round 0's denoise is timed as the final one's."""

    def __init__(self, scene: Scene, bounces: int, seed: int, halves: bool, kwargs: dict[str, Any],
                 deadline: float | None = None) -> None:
        self.scene, self.bounces, self.seed, self.halves, self.kwargs = scene, bounces, seed, halves, kwargs
        self.deadline = deadline

    def first(self, counts: torch.Tensor, denoiser: Any, cost: float) -> tuple[
            list[tuple[GBuffer, torch.Tensor]], tuple[GBuffer, torch.Tensor], float, float, torch.Tensor, float]:
        """Round 0: its parts, the whole, the seconds a sample of the next round is expected to
        take (round 0's, less its call's cost, times ``cost``), the seconds a render call costs
        beside its samples (module docstring), the denoised whole and the seconds the denoise
        took; with the run's ``deadline`` the denoise is of the whole as the budget's final
        render (module docstring), not the whole itself."""
        t0 = time.perf_counter()
        acc = self.round(counts, 0)
        t_render = time.perf_counter() - t0
        samples = float(counts.sum())
        spp = samples / counts.numel()
        call_s = t_render * _CALL_SPP / (spp + len(acc) * _CALL_SPP)  # per call (two with halves)
        per_sample = (t_render - len(acc) * call_s) / samples * cost
        whole = _merged(acc)
        gb = whole[0]
        if self.deadline is not None:  # time the denoise of the render the budget is planned to reach
            final = spp + max(self.deadline - time.perf_counter() - call_s, 0.0) / per_sample / counts.numel()
            if final >= spp + 1:
                gb = gb.replace(spp=torch.full_like(gb.spp, round(final)), variance=gb.variance * (spp / final))
        t0 = time.perf_counter()
        denoised = denoiser(gb)
        return acc, whole, per_sample, call_s, denoised, time.perf_counter() - t0

    def round(self, counts: torch.Tensor, r: int) -> list[tuple[GBuffer, torch.Tensor]]:
        """Round ``r`` of ``counts``: its parts (the render, or the two halves) with their counts."""
        from torchgi.render import render

        parts = [counts] if not self.halves else [counts // 2, counts - counts // 2]
        return [(render(self.scene, c, self.bounces, _round_seed(self.seed, r, k), fill_empty=r == 0, guides=r == 0,
                        **self.kwargs), c) for k, c in enumerate(parts)]


def _check_args(seconds: float | None, target: float | None, first_spp: int, max_spp: float) -> None:
    """Exactly one of ``seconds`` and ``target``, > 0; ``first_spp`` an int >= 2; ``max_spp`` > 0."""
    if (seconds is None) == (target is None):
        raise ValueError(f"seconds, target: give exactly one of them, got seconds={seconds!r}, target={target!r}")
    if seconds is not None:
        check_positive(seconds, "seconds")
    if target is not None:
        check_positive(target, "target")
    check_int(first_spp, "first_spp", 2)
    check_positive(max_spp, "max_spp")


def _round_seed(seed: int, r: int, half: int) -> int:
    """The seed of round ``r``'s half ``half``: ``seed`` itself for the first render."""
    return seed if r == 0 and half == 0 else (seed + 0x9E3779B1 * (2 * r + half)) & 0xFFFFFFFF


def _merged(acc: list[tuple[GBuffer, torch.Tensor]]) -> tuple[GBuffer, torch.Tensor]:
    """The whole render: the one accumulated render, or its two halves merged."""
    if len(acc) == 1:
        return acc[0]
    (a, ca), (b, cb) = acc
    return merge_rounds(a, ca, b, cb), ca + cb


def _support(gb: GBuffer) -> torch.Tensor:
    """The filter's support per pixel from its geometry weights, in [1/16, 1]: ``1 - q`` of
    :func:`~torchgi.sampling.geometry_importance`, background 1."""
    q = geometry_importance(gb)
    return torch.where(gb.hit, 1 - q, 1.0).clamp_min(1 / 16)


def _report(r: int, spp: float, seconds: float, estimate: float | None) -> None:
    """``progress``' line for round ``r``."""
    print(f"render_to: round {r}, {spp:.2f} spp, {seconds:.2f} s"
          + ("" if estimate is None else f", estimated relMSE {estimate:.3g}"), flush=True)


def _counts(gb: GBuffer, counts: torch.Tensor, denoised: torch.Tensor | None, n: int,
            support: torch.Tensor | None, adaptive: bool = True) -> torch.Tensor:
    """The next round's ``n`` samples: each pixel's shortfall from its share ``∝ sqrt(w s²)`` of
    the new total (module docstring), or without ``adaptive`` spread evenly."""
    if not adaptive:
        return allocate(torch.ones_like(counts, dtype=torch.float32), n, min_samples=0)
    k = counts.to(gb.variance.dtype)
    s2 = box(gb.variance * k, 1).clamp_min(0)  # per-sample variance, blurred (box may leave -1e-10)
    ref = box(gb.color if denoised is None else denoised, 2).clamp_min(0)  # (prefix sums: -1e-10)
    w = 1 / (ref.square() + _EPS)
    share = (s2 * w).sum(1, keepdim=True).sqrt()
    if support is not None:
        share = share / support.sqrt()
    total = float(counts.sum()) + n
    if float(share.sum()) == 0:
        return allocate(torch.ones_like(share), n, min_samples=0)
    want = share * (total / float(share.sum()))
    shortfall = (want - k).clamp_min(0)
    if float(shortfall.sum()) == 0:
        shortfall = share
    return allocate(shortfall, n, min_samples=0)


def _estimate(acc: list[tuple[GBuffer, torch.Tensor]], whole: tuple[GBuffer, torch.Tensor], denoised: torch.Tensor,
              denoiser: Any) -> float:
    """The estimated relMSE of the denoised whole (module docstring): each half's denoised error
    against the other half's colour, less that colour's variance (the whole's per-sample variance
    over the half's counts, so that a half of one sample has one), averaged, over
    :data:`HALF_TO_WHOLE`."""
    w = 1 / (denoised.square() + _EPS)
    per_sample = whole[0].variance * whole[1]
    errors = []
    for (a, _), (b, cb) in (acc, acc[::-1]):
        var_b = per_sample / cb.clamp_min(1)
        errors.append(float((((denoiser(a) - b.color).square() - var_b) * w).mean()))
    return max(sum(errors) / 2, 0.0) / HALF_TO_WHOLE


def _samples_left(left: float, call_s: float, per_sample: float, r: int) -> int:
    """The samples of the next round with ``left`` seconds for its render call: all of them, or,
    after round 0 where 0.3 of them are worth two calls, 0.7 of them (the rest goes into a second
    round, timed by the first's measured time per sample)."""
    n = (left - call_s) / per_sample
    return int(n * 0.7 if r == 0 and n * 0.3 >= 2 * call_s / per_sample else n)


def _samples_to(history: list[tuple[int, float]], target: float) -> int:
    """The samples of the next round: what an error falling as ``n^-1/2`` reaches ``target``
    with, at least an eighth and at most twice the samples so far."""
    n, e = history[-1]
    return int(min(max(n * ((e / target) ** 2 - 1), n / 8), 2 * n))
