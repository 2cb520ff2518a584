"""The temporal denoiser's ops at the back-end seam, in the order :func:`torchgi.temporal.temporal_step`
runs them: the reprojection and accumulation (:class:`AccumulateOp`), the change test and what the
spatial filter is given (:class:`ChangeOp`), the output history (:class:`HistoryOp`); and the
planes of the first two's packed results by name (:class:`Accumulated`, :class:`Changed`: their
layouts are defined there only). Re-exported by :mod:`torchgi.backends.base`."""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["LUMA", "AccumulateOp", "Accumulated", "ChangeOp", "Changed", "HistoryOp"]

LUMA = (0.2126, 0.7152, 0.0722)  # the luminance AccumulateOp returns and moments are of (Rec. 709 weights)


@dataclass(eq=False, slots=True)
class AccumulateOp:
    """One frame of :mod:`torchgi.temporal`'s reprojection and accumulation for the light
    ``x (B,3,H,W)`` (scaled down to ``bound (B,1,H,W)`` where its channel maximum exceeds it),
    ``motion (B,2,H,W)``, this frame's ``normal (B,3)``, ``depth (B,1)``,
    ``surface (B,1)`` bool, and the history ``light (B,3)``, ``output (B,3)``, ``moments (B,2)``,
    ``length (B,1)``, ``prev_normal (B,3)``, ``prev_depth (B,1)``, ``prev_surface (B,1)`` (1.0 on
    geometry), all of one float dtype and device but ``surface``; ``alpha``, ``max_history``,
    ``normal_tolerance``, ``depth_tolerance`` as in ``settings.TemporalSettings``. Returns
    ``(B,13,H,W)``, its planes named by :class:`Accumulated` (the layout). ``workspace``:
    a dict the CPU kernels keep their result's buffer in between calls (each call overwrites the
    last one's), or None: a new tensor."""

    x: torch.Tensor
    bound: torch.Tensor
    motion: torch.Tensor
    normal: torch.Tensor
    depth: torch.Tensor
    surface: torch.Tensor
    light: torch.Tensor
    output: torch.Tensor
    moments: torch.Tensor
    length: torch.Tensor
    prev_normal: torch.Tensor
    prev_depth: torch.Tensor
    prev_surface: torch.Tensor
    alpha: float
    max_history: int
    normal_tolerance: float
    depth_tolerance: float
    workspace: dict | None = None

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.x, self.bound, self.motion, self.normal, self.depth, self.light, self.output, self.moments, self.length,
                self.prev_normal, self.prev_depth, self.prev_surface)


@dataclass(frozen=True, eq=False)
class Accumulated:
    """:class:`AccumulateOp`'s ``(B,13,H,W)`` result (``packed``, what :class:`ChangeOp` takes as
    ``step``) by name: each plane a view of it (no copy). The layout is defined here only; every
    back end writes it in this order."""

    packed: torch.Tensor

    @property
    def light(self) -> torch.Tensor:
        """``(B,3)`` the accumulated light (channels 0-2)."""
        return self.packed[:, 0:3]

    @property
    def output(self) -> torch.Tensor:
        """``(B,3)`` the reprojected output history (3-5)."""
        return self.packed[:, 3:6]

    @property
    def moments(self) -> torch.Tensor:
        """``(B,2)`` the accumulated luminance moments, mean and mean square (6-7)."""
        return self.packed[:, 6:8]

    @property
    def length(self) -> torch.Tensor:
        """``(B,1)`` the new history length (8)."""
        return self.packed[:, 8:9]

    @property
    def prev_length(self) -> torch.Tensor:
        """``(B,1)`` the reprojected history length (9; 0: no history)."""
        return self.packed[:, 9:10]

    @property
    def variance(self) -> torch.Tensor:
        """``(B,1)`` the moments' variance (10)."""
        return self.packed[:, 10:11]

    @property
    def frames(self) -> torch.Tensor:
        """``(B,1)`` the number of frames averaged (11)."""
        return self.packed[:, 11:12]

    @property
    def luminance(self) -> torch.Tensor:
        """``(B,1)`` the luminance (:data:`LUMA`) of this frame's light after its firefly clamp (12)."""
        return self.packed[:, 12:13]


@dataclass(eq=False, slots=True)
class ChangeOp:
    """:func:`torchgi.temporal.temporal_step` after the accumulation: where the light changed, the
    history dropped (its change test, module docstring of :mod:`torchgi.temporal`), the variance
    chosen, and the spatial filter's input remodulated. ``x (B,3,H,W)`` the demodulated light
    before its firefly clamp at ``bound (B,1,H,W)``; ``step (B,13,H,W)`` :class:`AccumulateOp`'s
    result (:attr:`Accumulated.packed`); ``spatial_var (B,1,H,W)`` this frame's spatial variance of the luminance; ``near`` and
    ``wide`` ``(B,3,H,W)`` the box means at ``radii[0]`` and ``radii[1]`` of (this frame's
    luminance, the accumulated light's, ``spatial_var``), or None for no change test;
    ``threshold`` in sigmas of the window mean's noise; below it, the history's light and moments are
    scaled so that its window means move toward this frame's by the gain ``d² / (d² + (follow
    sigma)²)`` of their change ``d`` (per radius, the scales multiplied; 0: not); ``variance_history`` frames from which the
    moments' variance replaces the spatial one; ``albedo (B,3)``, ``surface (B,1)`` bool and
    ``emission (B,3)`` to remodulate. All of one float dtype and device but ``surface``. Returns
    ``(B,11,H,W)``, its planes named by :class:`Changed` (the layout). ``workspace`` as
    :class:`AccumulateOp`'s."""

    x: torch.Tensor
    bound: torch.Tensor
    step: torch.Tensor
    spatial_var: torch.Tensor
    near: torch.Tensor | None
    wide: torch.Tensor | None
    albedo: torch.Tensor
    surface: torch.Tensor
    emission: torch.Tensor
    radii: tuple[int, int]
    threshold: float
    variance_history: int
    follow: float = 0.0
    workspace: dict | None = None

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.x, self.bound, self.step, self.spatial_var, self.near, self.wide, self.albedo, self.emission)


@dataclass(frozen=True, eq=False)
class Changed:
    """:class:`ChangeOp`'s ``(B,11,H,W)`` result (``packed``) by name: the history after the
    change test's drop, each plane a view of it (no copy). The layout is defined here only; every
    back end writes it in this order."""

    packed: torch.Tensor

    @property
    def light(self) -> torch.Tensor:
        """``(B,3)`` the accumulated light after the drop (channels 0-2)."""
        return self.packed[:, 0:3]

    @property
    def moments(self) -> torch.Tensor:
        """``(B,2)`` the luminance moments after the drop (3-4)."""
        return self.packed[:, 3:5]

    @property
    def length(self) -> torch.Tensor:
        """``(B,1)`` the history length after the drop (5)."""
        return self.packed[:, 5:6]

    @property
    def frames(self) -> torch.Tensor:
        """``(B,1)`` the frames averaged after the drop (6)."""
        return self.packed[:, 6:7]

    @property
    def spread(self) -> torch.Tensor:
        """``(B,1)`` the variance over the frames averaged (7: the moments' variance from
        ``variance_history`` frames on, else ``spatial_var``, divided by the frames)."""
        return self.packed[:, 7:8]

    @property
    def color(self) -> torch.Tensor:
        """``(B,3)`` the spatial filter's colour input, the light remodulated (8-10)."""
        return self.packed[:, 8:11]


@dataclass(eq=False, slots=True)
class HistoryOp:
    """:func:`torchgi.temporal.temporal_step`'s output history: the spatial filter's output ``out
    (B,3,H,W)`` demodulated (``emission (B,3)`` taken away, divided by the demodulator of ``albedo
    (B,3)`` and ``surface (B,1)`` bool), the reprojected output history ``hist_out (B,3)`` clamped
    to within ``sqrt(clamp x spread)`` of it (``spread (B,1)``: the box mean of the variance over
    the frames averaged) and averaged with weight ``max(1 / kept, output_alpha)`` for this frame
    where ``hist_length (B,1)`` > 0 (``kept (B,1)``: the history length after the change test).
    All of one float dtype and device but ``surface``. Returns two ``(B,3,H,W)`` tensors: the next
    output history (demodulated; in ``workspace``, as :class:`AccumulateOp`'s) and the frame's image
    (remodulated; always a new tensor)."""

    out: torch.Tensor
    emission: torch.Tensor
    albedo: torch.Tensor
    surface: torch.Tensor
    spread: torch.Tensor
    hist_out: torch.Tensor
    kept: torch.Tensor
    hist_length: torch.Tensor
    clamp: float
    output_alpha: float
    workspace: dict | None = None

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.out, self.emission, self.albedo, self.spread, self.hist_out, self.kept, self.hist_length)
