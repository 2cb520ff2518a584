"""Temporal denoising of animated sequences (SVGF class, Schied et al. 2017), around the guided filter.

Each frame, inside the Denoiser's pipeline (demodulation by albedo, light sources passed
untouched, fireflies clamped at ``GUIDED.firefly`` x their local level, remodulation):

1. **Reprojection**: the history is read at ``pixel + motion`` with bilinear taps; a tap counts
   only inside the image, on the same kind of pixel (surface / background), with a normal within
   ``TEMPORAL.normal_tolerance`` (cosine) and a depth within ``TEMPORAL.depth_tolerance``
   (relative) of the pixel's; the counted taps' weights are renormalised. No counted tap: the
   pixel is new (disoccluded, or after a cut) and its history length restarts at 1.
2. **Accumulation**: exponential averages, with weight ``max(1 / length, TEMPORAL.alpha)`` for
   the new frame, of the demodulated light and of its luminance moments; the history length is
   capped at ``TEMPORAL.max_history``.
3. **Variance** of the accumulated light: from the moments (``E[l²] - E[l]²``, over the number
   of frames averaged) once ``TEMPORAL.variance_history`` frames are in, else a spatial estimate
   (the ``7x7`` window of the current frame).
4. **Spatial filter**, guided by that variance: the guided filter (normal + depth guide) at the
   radius the Denoiser would give the samples averaged (``4 / sqrt(n)`` px); where the
   accumulated light differs from the filtered one by more than its noise explains (a shading
   edge the guide does not see), the accumulated light is kept in proportion (a per-pixel
   Wiener gain, luminance ``noise² / difference²`` over a ``3x3`` window).
5. **Feedback**: the result is the next frame's light history.

The state is plain tensors (:class:`TemporalState`), so :func:`temporal_step` and
:class:`DeployedTemporal` export to ONNX; :class:`TemporalDenoiser` keeps the state between calls.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from torchgi.buffers import GBuffer
from torchgi.core.check import finite_or_sanitized_all, is_recording
from torchgi.core.errors import ShapeError
from torchgi.settings import GUIDED, TEMPORAL

__all__ = ["DeployedTemporal", "TemporalDenoiser", "TemporalState", "temporal_step"]

_LUMA = (0.2126, 0.7152, 0.0722)
_INPUTS = ("color", "albedo", "normal", "depth", "motion", "emission", "hit")


@dataclasses.dataclass
class TemporalState:
    """What :func:`temporal_step` carries from one frame to the next, all ``(B, C, H, W)``:
    ``light`` (3: the accumulated demodulated light), ``output`` (3: the filtered one, the
    output's history), ``moments`` (2: luminance mean and mean square), ``length`` (1: frames in the history, 0 = none), ``normal`` (3), ``depth`` (1) and
    ``surface`` (1: 1.0 on geometry) of the frame they belong to."""

    light: torch.Tensor
    output: torch.Tensor
    moments: torch.Tensor
    length: torch.Tensor
    normal: torch.Tensor
    depth: torch.Tensor
    surface: torch.Tensor

    @classmethod
    def empty(cls, like: torch.Tensor) -> TemporalState:
        """No history (every pixel new), shaped after ``like (B, C, H, W)``.

        Example:
            >>> TemporalState.empty(torch.zeros(1, 3, 4, 4)).length.shape
            torch.Size([1, 1, 4, 4])
        """
        B, _, H, W = like.shape

        def z(c: int) -> torch.Tensor:
            return like.new_zeros(B, c, H, W)

        return cls(z(3), z(3), z(2), z(1), z(3), z(1), z(1))

    def tensors(self) -> tuple[torch.Tensor, ...]:
        """The fields in order (the exported graph's state inputs and outputs)."""
        return tuple(getattr(self, f.name) for f in dataclasses.fields(self))


def _luminance(x: torch.Tensor) -> torch.Tensor:
    w = torch.tensor(_LUMA, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return (x * w).sum(1, keepdim=True)


def _reproject(state: TemporalState, motion: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor,
               surface: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The history at ``pixel + motion``: light ``(B,3)``, moments ``(B,2)`` and length ``(B,1)``
    (0 where no tap counts), from the bilinear taps that pass the consistency tests."""
    B, _, H, W = normal.shape
    dt = normal.dtype
    ys = torch.arange(H, dtype=dt, device=normal.device).view(1, H, 1)
    xs = torch.arange(W, dtype=dt, device=normal.device).view(1, 1, W)
    px, py = xs + motion[:, 0], ys + motion[:, 1]  # (B, H, W): pixel-centre coordinates in the previous frame
    x0, y0 = torch.floor(px), torch.floor(py)
    fx, fy = px - x0, py - y0
    values = torch.cat([state.light, state.output, state.moments, state.length], 1).flatten(2)  # (B, 9, HW)
    tests = torch.cat([state.normal, state.depth, state.surface], 1).flatten(2)  # (B, 5, HW)
    acc = torch.zeros(B, 9, H, W, dtype=dt, device=normal.device)
    total = torch.zeros(B, 1, H, W, dtype=dt, device=normal.device)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        tx, ty = x0 + dx, y0 + dy
        w = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
        inside = (tx >= 0) & (tx <= W - 1) & (ty >= 0) & (ty <= H - 1)
        index = (ty.clamp(0, H - 1) * W + tx.clamp(0, W - 1)).to(torch.int64).flatten(1)  # (B, HW)
        t = tests.gather(2, index[:, None].expand(-1, 5, -1)).view(B, 5, H, W)
        same_kind = (t[:, 4:5] > 0.5) == surface
        close = ((t[:, :3] * normal).sum(1, keepdim=True) >= TEMPORAL.normal_tolerance) & (
            (t[:, 3:4] - depth).abs() <= TEMPORAL.depth_tolerance * depth.abs())
        ok = inside[:, None] & same_kind & (close | ~surface)
        w = torch.where(ok, w[:, None], 0.0)
        acc = acc + w * values.gather(2, index[:, None].expand(-1, 9, -1)).view(B, 9, H, W)
        total = total + w
    found = total > 1e-3
    acc = torch.where(found, acc / torch.where(found, total, 1.0), 0.0)
    return acc[:, :3], acc[:, 3:6], acc[:, 6:8], torch.where(found, torch.round(acc[:, 8:9]), 0.0)


def _fresh(out: torch.Tensor, acc: torch.Tensor, guide: torch.Tensor, length: torch.Tensor, radius: int,
           eps: float) -> torch.Tensor:
    """``out`` where the history is long; where it is shorter than ``TEMPORAL.variance_history``
    frames, blended towards the guided filter of ``acc`` at the per-frame Denoiser's ``radius``
    (weight 1 for a new pixel). Eager calls filter only the rows and columns around such pixels."""
    from torchgi.filters import guided

    w = ((TEMPORAL.variance_history - length) / max(TEMPORAL.variance_history - 1, 1)).clamp(0, 1)
    if is_recording():
        return out + w * (guided(acc, guide, radius=radius, eps=eps) - out)
    rows, cols = w.amax((0, 1, 3)) > 0, w.amax((0, 1, 2)) > 0
    if not bool(rows.any()):
        return out
    halo = 2 * radius + 2  # the filter's reach: the box of the box
    r = rows.nonzero()[:, 0]
    c = cols.nonzero()[:, 0]
    H, W = out.shape[-2:]
    r0, r1 = max(int(r[0]) - halo, 0), min(int(r[-1]) + halo + 1, H)
    c0, c1 = max(int(c[0]) - halo, 0), min(int(c[-1]) + halo + 1, W)
    win = (..., slice(r0, r1), slice(c0, c1))
    wide = guided(acc[win].contiguous(), guide[win].contiguous(), radius=radius, eps=eps)
    out = out.clone()
    out[win] = out[win] + w[win] * (wide - out[win])
    return out


def temporal_step(
    color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, motion: torch.Tensor,
    state: TemporalState | None = None, *, emission: torch.Tensor | None = None, hit: torch.Tensor | None = None,
    radius: int = TEMPORAL.radius, radius_fresh: int = GUIDED.radius, eps: float = TEMPORAL.eps,
) -> tuple[torch.Tensor, TemporalState]:
    """One frame of temporal denoising (module docstring), stateless: ``(output, next_state)``.

    Args:
        color: ``(B,3,H,W)`` noisy HDR radiance of this frame.
        albedo, normal: ``(B,3,H,W)`` first-hit albedo in [0, 1] and world-space normal.
        depth: ``(B,1,H,W)`` distance along the camera ray (scene units).
        motion: ``(B,2,H,W)`` backward motion in pixels (``GBuffer.motion``).
        state: the previous call's ``next_state``; None = no history (a first frame, a cut).
        emission: ``(B,3,H,W)`` emitted radiance (light sources pass untouched), or None.
        hit: ``(B,1,H,W)`` bool surface mask; None = non-zero albedo.
        radius: the guided filter's radius in px (``TEMPORAL.radius``).
        radius_fresh: its radius where the history is short (new pixels: the per-frame Denoiser's).
        eps: the guided filter's ε (``TEMPORAL.eps``).

    Returns:
        The ``(B,3,H,W)`` denoised radiance (input dtype and device) and the state for the next frame.

    Example:
        >>> from torchgi.render import render_sequence, scenes
        >>> state = None
        >>> for gb in render_sequence(scenes.cornell(16), 2):
        ...     out, state = temporal_step(gb.color, gb.albedo, gb.normal, gb.depth, gb.motion, state)
        >>> out.shape, int(state.length.max())
        (torch.Size([1, 3, 16, 16]), 2)
    """
    from torchgi.denoise import _restore, _surface
    from torchgi.filters import box, guide_from, guided

    surface = _surface(hit, albedo)
    state = TemporalState.empty(color) if state is None else state
    kept: dict[str, Any] = {}

    def filter_fn(x: torch.Tensor) -> torch.Tensor:
        hist_light, hist_out, hist_moments, hist_length = _reproject(state, motion, normal, depth, surface)
        length = torch.where(hist_length > 0, (hist_length + 1).clamp_max(TEMPORAL.max_history), 1.0)
        a = torch.maximum(1.0 / length, torch.full((), TEMPORAL.alpha, dtype=x.dtype, device=x.device))
        acc = hist_light + a * (x - hist_light)
        lum = _luminance(x)
        moments = hist_moments + a * (torch.cat([lum, lum * lum], 1) - hist_moments)
        temporal_var = (moments[:, 1:2] - moments[:, :1].square()).clamp_min(0)
        m = box(torch.cat([lum, lum * lum], 1), TEMPORAL.variance_radius)
        spatial_var = (m[:, 1:2] - m[:, :1].square()).clamp_min(0)
        var = torch.where(length >= TEMPORAL.variance_history, temporal_var, spatial_var)
        # frames averaged: 1/length while the weights are equal, (2 - α)/α once the average is exponential
        frames = torch.minimum(length, (2 - a) / a)
        guide = guide_from(normal, depth, depth_scale="image")
        out = _fresh(guided(acc, guide, radius=radius, eps=eps), acc, guide, length, radius_fresh, eps)
        # the output history, within sqrt(clamp x the noise variance of acc) of this frame's result
        sigma = torch.sqrt(TEMPORAL.clamp * box(var / frames, 1))
        h = torch.maximum(torch.minimum(hist_out, out + sigma), out - sigma)
        beta = torch.maximum(1.0 / length, torch.full((), TEMPORAL.output_alpha, dtype=x.dtype, device=x.device))
        out = torch.where(hist_length > 0, h + beta * (out - h), out)
        kept["state"] = TemporalState(acc, out, moments, length, normal, depth, surface.to(x.dtype))
        return out

    out = _restore(color, emission, None, albedo, surface, filter_fn, GUIDED.firefly)
    return out, kept["state"]


def _check_inputs(tensors: dict[str, torch.Tensor]) -> GBuffer:
    unknown = sorted(set(tensors) - set(_INPUTS))
    if unknown:
        raise ValueError(f"unknown input(s) {', '.join(unknown)}; known: {', '.join(_INPUTS)}")
    for name in ("color", "albedo", "normal", "depth", "motion"):
        if tensors.get(name) is None:
            raise ShapeError(f"{name}: required by the TemporalDenoiser")
    return GBuffer(**tensors)  # shapes, one device, one dtype; guides (motion included) finite


class TemporalDenoiser(torch.nn.Module):
    """Denoise an animated sequence frame by frame, carrying a history (module docstring).

    Call once per frame, in order, with a :class:`~torchgi.GBuffer` (as from
    :func:`torchgi.render_sequence`) or named ``(B, C, H, W)`` tensors: ``color``, ``albedo``,
    ``normal``, ``depth``, ``motion`` and when available ``emission`` and ``hit``. Returns that
    frame's ``(B, 3, H, W)`` denoised radiance in the input dtype and device. :meth:`reset`
    forgets the history (call it at a cut; a cut the motion does not explain is also caught by the
    consistency tests, pixel by pixel). A change of shape, dtype or device starts a new history.

    Args:
        sanitize: NaN/Inf in ``color`` or ``emission`` raises :class:`~torchgi.core.NonFiniteError`
            naming it (False) or is replaced by 0 with a warning (True); the guides must be finite.

    Example:
        >>> from torchgi.render import render_sequence, scenes
        >>> den = TemporalDenoiser()
        >>> outs = [den(gb) for gb in render_sequence(scenes.cornell(16), 3)]
        >>> outs[-1].shape
        torch.Size([1, 3, 16, 16])
    """

    def __init__(self, *, sanitize: bool = False) -> None:
        super().__init__()
        self.sanitize = sanitize
        self.state: TemporalState | None = None

    def reset(self) -> None:
        """Forget the history: the next frame is filtered as a first frame."""
        self.state = None

    def extra_repr(self) -> str:
        return f"sanitize={self.sanitize}"

    def forward(self, gb: GBuffer | None = None, **tensors: torch.Tensor) -> torch.Tensor:
        if gb is not None and tensors:
            raise ValueError("pass a GBuffer or named tensors, not both")
        if gb is None:
            gb = _check_inputs(tensors)
        else:
            gb = _check_inputs({k: getattr(gb, k) for k in _INPUTS if getattr(gb, k) is not None})
        color, emission = finite_or_sanitized_all({"color": gb.color, "emission": gb.emission}, self.sanitize)
        s = self.state
        if s is not None and (s.light.shape != color.shape or s.light.dtype != color.dtype
                              or s.light.device != color.device):
            s = None
        out, self.state = temporal_step(color, gb.albedo, gb.normal, gb.depth, gb.motion, s, emission=emission,
                                        hit=gb.hit)
        return out


class DeployedTemporal(torch.nn.Module):
    """:func:`temporal_step` as plain tensor code for ONNX export.

    ``forward(color, emission, albedo, normal, depth, motion, light, history, moments, length,
    prev_normal, prev_depth, prev_surface)`` returns ``(output, light, history, moments, length,
    surface)``: the next frame passes these five as ``light, history, moments, length,
    prev_surface`` and this frame's ``normal`` and ``depth`` inputs as ``prev_normal, prev_depth``
    (``history`` is :attr:`TemporalState.output`). The first frame passes
    :meth:`TemporalState.empty`. Surfaces are the pixels of non-zero albedo; ``emission`` is
    required (zeros when no light source is in view).

    Example:
        >>> m = DeployedTemporal()
        >>> x = torch.rand(1, 3, 8, 8)
        >>> out = m(x, x * 0, x, x, x[:, :1] + 1, x[:, :2] * 0, *TemporalState.empty(x).tensors())
        >>> [t.shape[1] for t in out]
        [3, 3, 3, 2, 1, 1]
    """

    input_names = ("color", "emission", "albedo", "normal", "depth", "motion", "light", "history", "moments",
                   "length", "prev_normal", "prev_depth", "prev_surface")
    output_names = ("output", "next_light", "next_history", "next_moments", "next_length", "next_surface")

    def forward(self, color: torch.Tensor, emission: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor,
                depth: torch.Tensor, motion: torch.Tensor, light: torch.Tensor, history: torch.Tensor,
                moments: torch.Tensor, length: torch.Tensor, prev_normal: torch.Tensor, prev_depth: torch.Tensor,
                prev_surface: torch.Tensor) -> tuple[torch.Tensor, ...]:
        state = TemporalState(light, history, moments, length, prev_normal, prev_depth, prev_surface)
        out, nxt = temporal_step(color, albedo, normal, depth, motion, state, emission=emission)
        return out, nxt.light, nxt.output, nxt.moments, nxt.length, nxt.surface
