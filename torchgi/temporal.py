"""Temporal denoising of animated sequences (SVGF class, Schied et al. 2017), around the guided filter.

Each frame, on the light demodulated by albedo (``(color - emission) / albedo`` on surfaces):

1. **Fireflies** above ``GUIDED.firefly`` x their local level are scaled down to it (as the
   Denoiser does) before they enter the history.
2. **Reprojection**: the history is read at ``pixel + motion`` with bilinear taps; a tap counts
   only inside the image, on the same kind of pixel (surface / background), with a normal within
   ``TEMPORAL.normal_tolerance`` (cosine) and a depth within ``TEMPORAL.depth_tolerance``
   (relative) of the pixel's; the counted taps' weights are renormalised. No counted tap: the
   pixel is new (disoccluded, or after a cut) and its history length restarts at 1.
3. **Accumulation**: exponential averages, with weight ``max(1 / length, TEMPORAL.alpha)`` for
   the new frame, of the light and of its luminance moments; the history length is capped at
   ``TEMPORAL.max_history``. Variance: from the moments once ``TEMPORAL.variance_history``
   frames are in, else the spatial estimate of the current frame's ``7x7`` window. **Where the
   light changed** (moving shadows and highlights, a moving light: what the motion cannot
   explain) the history is dropped: this frame's mean luminance in ``9x9`` and ``33x33`` windows
   (``TEMPORAL.change_radius``, ``change_scale``) against the accumulated light's, beyond
   ``TEMPORAL.change_threshold`` sigmas of the window mean's noise. Below that, the history is
   scaled so that its window means follow this frame's by the gain ``d² / (d² + (TEMPORAL.follow
   sigma)²)`` of their change ``d``: a light changing a little each frame does not lag.
4. **Spatial filter**: the guided Denoiser pipeline (normal + depth guide, light sources passed
   untouched) on the accumulated light, at ``TEMPORAL.radius`` and ``TEMPORAL.eps``: the light
   averages several frames, so a narrower, sharper filter than the per-frame Denoiser's. Where
   the history is shorter than ``TEMPORAL.variance_history`` frames the result is blended (weight
   1 for a new pixel) towards the per-frame Denoiser's in images below ``GUIDED.subsample_from``
   px on the short side and in frames where at least ``TEMPORAL.fresh_share`` of the pixels are
   new (a first frame, a cut), so a revealed region is filtered as a single frame would be; in
   the other frames towards the same guided filter at ``TEMPORAL.short_radius``.
5. **Output history**: the filtered light of the previous frame, reprojected as in 2, clamped to
   within ``sqrt(TEMPORAL.clamp x variance / frames)`` of this frame's filtered light (the noise
   the accumulated light still has), then averaged with weight ``max(1 / length,
   TEMPORAL.output_alpha)`` for this frame (``length`` after the drop of 3): flicker the filter leaves is averaged out, and a
   change larger than the noise (a moving highlight) passes through.

``TEMPORAL``, ``GUIDED`` and ``PIPELINE`` above name the groups ``temporal``, ``guided`` and
``pipeline`` of the :class:`~torchgi.settings.Settings` given (``settings=``, default
:data:`~torchgi.settings.DEFAULTS`).

The accumulated light (not the filtered one) is the light history: feeding the filtered light
back (SVGF's choice) blurred shading over frames on the tuning sequence (docs/temporal.md). The
state is plain tensors (:class:`TemporalState`), so :func:`temporal_step` and
:class:`DeployedTemporal` export to ONNX; :class:`TemporalDenoiser` keeps the state between calls.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import torch

from torchgi import backends, light, methods
from torchgi.buffers import GBuffer
from torchgi.core.check import check_option, finite_or_sanitized_all, is_recording
from torchgi.core.errors import DTypeError, ShapeError
from torchgi.denoise import Denoiser
from torchgi.filters import box
from torchgi.settings import DEFAULTS, Settings, check_settings

__all__ = ["DeployedTemporal", "TemporalDenoiser", "TemporalState", "temporal_step"]



@dataclasses.dataclass
class TemporalState:
    """What :func:`temporal_step` carries from one frame to the next, all ``(B, C, H, W)``:
    ``light`` (3: the accumulated demodulated light), ``output`` (3: the filtered one, the
    output's history), ``moments`` (2: luminance mean and mean square), ``length`` (1: frames in
    the history, 0 = none), ``normal`` (3), ``depth`` (1) and ``surface`` (1: 1.0 on geometry) of
    the frame they belong to."""

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


Spatial = Callable[..., torch.Tensor]


def _blend_fresh(out: torch.Tensor, length: torch.Tensor, inputs: dict[str, torch.Tensor | None],
                 fresh: Spatial, share: float, short: Spatial | None, settings: Settings) -> torch.Tensor:
    """``out`` where the history is long; where it is shorter than ``settings.temporal.variance_history``
    frames, blended towards ``fresh`` (the per-frame Denoiser) of the same inputs, weight 1 for a
    new pixel; only when at least ``share`` of the pixels are new (0: always), else towards
    ``short`` (None: not blended). Eager calls filter only the rows and columns around such pixels
    (and the filter's reach)."""
    t = settings.temporal
    recording = is_recording()
    if not recording and share > 0 and float((length == 1).float().mean()) < share:  # most frames
        if short is None:
            return out
        fresh = short
    w = ((t.variance_history - length) / max(t.variance_history - 1, 1)).clamp(0, 1)
    if recording:
        return out + w * (fresh(**inputs) - out)
    rows, cols = w.amax((0, 1, 3)) > 0, w.amax((0, 1, 2)) > 0
    if not bool(rows.any()):
        return out
    # the box of the box of the wider of the two filters, the firefly window
    halo = 4 * max(settings.guided.radius, t.short_radius) + 2 * settings.pipeline.firefly_radius + 4
    r, c = rows.nonzero().flatten(), cols.nonzero().flatten()  # the rows and columns to filter
    H, W = out.shape[-2:]
    r0, r1 = max(int(r[0]) - halo, 0), min(int(r[-1]) + halo + 1, H)
    c0, c1 = max(int(c[0]) - halo, 0), min(int(c[-1]) + halo + 1, W)
    if 2 * (r1 - r0) * (c1 - c0) >= H * W:  # copying the inputs' window would cost more than the rest of the frame
        return torch.lerp(out, fresh(**inputs), w)
    win = (..., slice(r0, r1), slice(c0, c1))
    wide = fresh(**{k: None if v is None else v[win] for k, v in inputs.items()})
    out = out.clone()
    out[win] = torch.lerp(out[win], wide, w[win])
    return out


# temporal_step's stages, in the order it runs them (module docstring, 1-5)
def _demodulated(color: torch.Tensor, emission: torch.Tensor, albedo: torch.Tensor, surface: torch.Tensor,
                 settings: Settings) -> tuple[torch.Tensor, torch.Tensor]:
    """1: this frame's demodulated light and its firefly bound, ``settings.guided.firefly`` x its local level (as
    the Denoiser's), which the accumulation scales it down to before it enters the history: ``(x, bound)``."""
    demod = light.demodulator(albedo, surface)
    x = (color - emission) / demod
    level = light.level(color, emission, None, albedo, surface)
    return x, light.firefly_bound(x.amax(1, keepdim=True), level, settings.guided.firefly, box)


def _reproject_and_accumulate(x: torch.Tensor, bound: torch.Tensor, motion: torch.Tensor, normal: torch.Tensor,
                              depth: torch.Tensor, surface: torch.Tensor, state: TemporalState, settings: Settings,
                              workspace: dict | None) -> backends.Accumulated:
    """2-3: the light ``x`` (clamped at ``bound``) averaged into ``state``'s history reprojected by ``motion`` where
    the guides agree; returns the accumulation's planes by name."""
    t = settings.temporal
    return backends.Accumulated(backends.run(backends.AccumulateOp(
        x, bound, motion, normal, depth, surface, *state.tensors(), t.alpha, t.max_history, t.normal_tolerance,
        t.depth_tolerance, workspace)))


def _drop_changed_history(x: torch.Tensor, bound: torch.Tensor, acc: backends.Accumulated, albedo: torch.Tensor,
                          surface: torch.Tensor, emission: torch.Tensor, settings: Settings,
                          workspace: dict | None) -> backends.Changed:
    """3, the change test: ``acc``'s history dropped where the light changed, made to follow this frame's below that;
    returns the history kept, its variance and the spatial filter's colour input by name."""
    t = settings.temporal
    lum = acc.luminance
    mean, mean_square = box(torch.cat([lum, lum * lum], 1), t.variance_radius).split(1, 1)
    spatial_var = (mean_square - mean.square()).clamp_min(0)
    near = wide = None
    radii = (t.change_radius, t.change_radius * t.change_scale)
    if t.change_threshold > 0:  # the light changed (module docstring): boxes of this frame's and the history's luminance
        luma = torch.tensor(backends.base.LUMA, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        planes = torch.cat([lum, (acc.light * luma).sum(1, keepdim=True), spatial_var], 1)
        near, wide = (box(planes, r) for r in radii)
    return backends.Changed(backends.run(backends.ChangeOp(
        x, bound, acc.packed, spatial_var, near, wide, albedo, surface, emission, radii, t.change_threshold,
        t.variance_history, t.follow, workspace)))


def _filter(kept: backends.Changed, guides: dict[str, torch.Tensor | None], spatial: Spatial, fresh: Spatial | None,
            fresh_share: float, short: Spatial | None, spatial_spp: torch.Tensor | None,
            settings: Settings) -> torch.Tensor:
    """4: ``spatial`` of ``kept.color`` with ``guides`` (emission, albedo, normal, depth, hit), blended towards
    ``fresh`` or ``short`` where the history is short (:func:`_blend_fresh`); returns the filtered radiance."""
    inputs = {"color": kept.color, **guides}
    if spatial_spp is None:
        out = spatial(**inputs)
    else:
        out = spatial(**inputs, spp=(spatial_spp * kept.frames).round().clamp_min(1).to(torch.int64))
    if fresh is not None:
        out = _blend_fresh(out, kept.length, inputs, fresh, fresh_share, short, settings)
    return out


def _update_output_history(out: torch.Tensor, emission: torch.Tensor, albedo: torch.Tensor, surface: torch.Tensor,
                           acc: backends.Accumulated, kept: backends.Changed, settings: Settings,
                           workspace: dict | None) -> tuple[torch.Tensor, torch.Tensor]:
    """5: the reprojected output history ``acc.output`` clamped to within ``sqrt(clamp x`` the accumulated light's
    noise variance) of the filtered ``out``, averaged with it at a weight that follows the history length after the
    change test's drop; returns ``(next output history (demodulated), the frame's image)``."""
    t = settings.temporal
    return backends.run(backends.HistoryOp(out, emission, albedo, surface, box(kept.spread, 1), acc.output,
                                           kept.length, acc.prev_length, t.clamp, t.output_alpha, workspace))


def temporal_step(
    color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, motion: torch.Tensor,
    state: TemporalState | None = None, *, emission: torch.Tensor | None = None, hit: torch.Tensor | None = None,
    spatial: Spatial | None = None, fresh: Spatial | None = None, fresh_share: float = 0.0,
    short: Spatial | None = None, spatial_spp: torch.Tensor | None = None, workspace: dict | None = None,
    settings: Settings = DEFAULTS,
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
        spatial: the filter of the accumulated radiance, called with ``color, emission, albedo,
            normal, depth, hit``; None = ``Denoiser("guided", radius=TEMPORAL.radius, eps=TEMPORAL.eps,
            subsample=1)``.
        fresh: the filter where the history is short (called the same way), or None: none.
        fresh_share: use ``fresh`` only when at least this share of the pixels is new (0: always).
            :class:`TemporalDenoiser` passes the per-frame Denoiser with share 0 below
            ``GUIDED.subsample_from`` px on the short side (where that filters at full resolution)
            and ``TEMPORAL.fresh_share`` above it (a first frame, a cut: above 256 px the
            accumulated light's own filter measured better on new pixels amid old ones,
            docs/temporal.md).
        short: in the frames where ``fresh`` is not used (fewer new pixels than ``fresh_share``),
            the filter short histories are blended towards in the same way (called as
            ``spatial``; only with ``fresh`` given), or None: none. :class:`TemporalDenoiser` passes the guided filter at
            ``TEMPORAL.short_radius`` from 256 px on the short side.
        spatial_spp: ``(B,1,H,W)`` int samples per pixel of one frame; given, ``spatial`` is also
            called with ``spp``: this times the frames the accumulated light averages per pixel
            (what a learned spatial filter reads as its noise level). None: not passed.
        workspace: a dict the CPU kernels keep their buffers in between calls (no fresh pages
            each frame; :class:`TemporalDenoiser` keeps one), or None. The state returned lives
            in it: the next call with the same dict overwrites it, so pass that call this state.
        settings: the :class:`~torchgi.settings.Settings` read (its ``temporal``, ``guided`` and
            ``pipeline`` groups, the names ``TEMPORAL``, ``GUIDED``, ``PIPELINE`` above), also those of
            the default ``spatial``.

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
    check_settings(settings)
    if hit is not None and hit.dtype != torch.bool:
        raise DTypeError(f"hit: expected a bool tensor, got {hit.dtype}")
    t = settings.temporal
    spatial = spatial or Denoiser("guided", radius=t.radius, eps=t.eps, subsample=1, settings=settings)
    surface = light.surface_mask(hit, albedo)
    emission = torch.zeros_like(color) if emission is None else emission
    state = TemporalState.empty(color) if state is None else state
    x, bound = _demodulated(color, emission, albedo, surface, settings)
    acc = _reproject_and_accumulate(x, bound, motion, normal, depth, surface, state, settings, workspace)
    kept = _drop_changed_history(x, bound, acc, albedo, surface, emission, settings, workspace)
    guides = {"emission": emission, "albedo": albedo, "normal": normal, "depth": depth, "hit": hit}
    out = _filter(kept, guides, spatial, fresh, fresh_share, short, spatial_spp, settings)
    history, image = _update_output_history(out, emission, albedo, surface, acc, kept, settings, workspace)
    return image, TemporalState(kept.light, history, kept.moments, torch.round(kept.length), normal, depth,
                                surface.to(x.dtype))


def _check_inputs(gb: GBuffer) -> GBuffer:
    for name in ("color", "albedo", "normal", "depth", "motion"):
        if getattr(gb, name) is None:
            raise ShapeError(f"{name}: required by the TemporalDenoiser")
    return gb


def _checked(den: torch.nn.Module) -> Spatial:
    """``den`` (a :class:`~torchgi.Denoiser`) called on named inputs that are checked already."""
    return lambda **inputs: den._denoise(GBuffer._unchecked(**inputs))


class TemporalDenoiser(torch.nn.Module):
    """Denoise an animated sequence frame by frame, carrying a history (module docstring).

    Call once per frame, in order, with a :class:`~torchgi.GBuffer` (as from
    :func:`torchgi.render_sequence`) or named ``(B, C, H, W)`` tensors: ``color``, ``albedo``,
    ``normal``, ``depth``, ``motion`` and when available ``emission`` and ``hit``; the other
    GBuffer fields are accepted and ignored, as by the Denoiser (:meth:`GBuffer.from_inputs`). Returns that
    frame's ``(B, 3, H, W)`` denoised radiance in the input dtype and device. :meth:`reset`
    forgets the history (call it at a cut; a cut the motion does not explain is also caught by the
    consistency tests, pixel by pixel). A change of shape, dtype or device starts a new history.
    Its :attr:`state` lives in buffers it reuses frame after frame (no fresh pages each frame):
    copy it to keep it past the next call.

    Args:
        spatial: the filter of the accumulated light: ``"guided"`` (radius ``TEMPORAL.radius``, ε
            ``TEMPORAL.eps``) or a learned Denoiser method, ``"pyramid"`` or ``"blend"``, told the
            frames' samples times the frames each pixel's accumulated light averages
            (docs/temporal.md: slower, more accurate on the tuning sequence).
        short_pass: from 256 px on the short side, blend histories shorter than
            ``TEMPORAL.variance_history`` frames towards the guided filter at
            ``TEMPORAL.short_radius`` (True, the default), or skip that second guided pass (False:
            about 1.4x faster per frame, new pixels noisier; docs/temporal.md, "Short histories").
        sanitize: NaN/Inf in ``color`` or ``emission`` raises :class:`~torchgi.core.NonFiniteError`
            naming it (False) or is replaced by 0 with a warning (True); the guides must be finite.
        settings: a :class:`~torchgi.settings.Settings` (default :data:`~torchgi.settings.DEFAULTS`):
            its ``temporal`` group (``TEMPORAL`` here and in the module docstring), and the whole of
            it for the Denoisers this one builds (the spatial filter, the per-frame one, the short pass).

    Example:
        >>> from torchgi.render import render_sequence, scenes
        >>> den = TemporalDenoiser()
        >>> outs = [den(gb) for gb in render_sequence(scenes.cornell(16), 3)]
        >>> outs[-1].shape
        torch.Size([1, 3, 16, 16])
    """

    def __init__(self, *, spatial: str = "guided", short_pass: bool = True, sanitize: bool = False,
                 settings: Settings = DEFAULTS) -> None:

        super().__init__()
        check_option(spatial, "spatial", methods.names(temporal=True))
        if not isinstance(short_pass, bool):
            raise TypeError(f"short_pass: expected True or False, got {short_pass!r}")
        self.settings = check_settings(settings)
        self.sanitize, self.spatial_method = sanitize, spatial
        self.state: TemporalState | None = None
        self._workspace: dict = {}  # the kernels' buffers between frames (the state lives in them)
        # kept between calls (its buffers); called on inputs checked once per frame
        t = settings.temporal
        kind = methods.get(spatial)
        self._learned = kind.learned  # told the frames' samples
        self.spatial = Denoiser(spatial, settings=settings, **kind.temporal_params(t))
        self.fresh = Denoiser("guided", settings=settings)
        self.short = (Denoiser("guided", radius=t.short_radius, eps=t.eps, subsample=1, settings=settings)
                      if short_pass else None)
        if not self._learned and self.short is not None:
            # one pipeline's scratch buffers for both (they run in turn; results are new tensors)
            self.short._workspace = self.spatial._workspace

    def reset(self) -> None:
        """Forget the history: the next frame is filtered as a first frame."""
        self.state = None

    def extra_repr(self) -> str:
        out = f"spatial={self.spatial_method!r}, short_pass={self.short is not None}, sanitize={self.sanitize}"
        return out if self.settings == DEFAULTS else f"{out}, settings={self.settings.changes()!r}"

    def forward(self, gb: GBuffer | None = None, **tensors: torch.Tensor) -> torch.Tensor:
        gb = _check_inputs(GBuffer.from_inputs(gb, tensors, by="TemporalDenoiser"))
        color, emission = finite_or_sanitized_all({"color": gb.color, "emission": gb.emission}, self.sanitize)
        s = self.state
        if s is not None and (s.light.shape != color.shape or s.light.dtype != color.dtype
                              or s.light.device != color.device):
            s = None
        small = min(color.shape[-2:]) < self.settings.guided.subsample_from
        share = 0.0 if small else self.settings.temporal.fresh_share
        short = None if small or self.short is None else _checked(self.short)
        spp = None
        if self._learned:
            spp = gb.spp if gb.spp is not None else torch.ones_like(gb.depth, dtype=torch.int64)
        out, self.state = temporal_step(color, gb.albedo, gb.normal, gb.depth, gb.motion, s, emission=emission,
                                        hit=gb.hit, spatial=_checked(self.spatial), fresh=_checked(self.fresh),
                                        fresh_share=share, short=short, spatial_spp=spp, workspace=self._workspace,
                                        settings=self.settings)
        return out


class DeployedTemporal(torch.nn.Module):
    """:func:`temporal_step` as plain tensor code for ONNX export.

    ``forward(color, emission, albedo, normal, depth, motion, light, history, moments, length,
    prev_normal, prev_depth, prev_surface)`` returns ``(output, light, history, moments, length,
    surface)``: the next frame passes these five as ``light, history, moments, length,
    prev_surface`` and this frame's ``normal`` and ``depth`` inputs as ``prev_normal, prev_depth``
    (``history`` is :attr:`TemporalState.output`). The first frame passes
    :meth:`TemporalState.empty`. ``fresh``: blend new pixels towards the per-frame Denoiser (what
    :class:`TemporalDenoiser` does below 256 px on the short side; fixed here, as the radius is).
    Surfaces are the pixels of non-zero albedo; ``emission`` is required (zeros when no light
    source is in view). ``settings``: as :class:`TemporalDenoiser`'s.

    Example:
        >>> m = DeployedTemporal()
        >>> x = torch.rand(1, 3, 8, 8)
        >>> out = m(x, x * 0, x, x, x[:, :1] + 1, x[:, :2] * 0, *TemporalState.empty(x).tensors())
        >>> [t.shape[1] for t in out]
        [3, 3, 3, 2, 1, 1]
    """

    def __init__(self, fresh: bool = True, *, settings: Settings = DEFAULTS) -> None:

        super().__init__()
        self.settings = check_settings(settings)
        t = settings.temporal
        self.spatial = Denoiser("guided", radius=t.radius, eps=t.eps, settings=settings).deploy(spp=1)
        self.fresh = Denoiser("guided", settings=settings).deploy(spp=1) if fresh else None

    def _spatial(self, **k: torch.Tensor) -> torch.Tensor:
        return self.spatial(k["color"], k["emission"], k["albedo"], k["normal"], k["depth"])

    def _fresh(self, **k: torch.Tensor) -> torch.Tensor:
        return self.fresh(k["color"], k["emission"], k["albedo"], k["normal"], k["depth"])

    input_names = ("color", "emission", "albedo", "normal", "depth", "motion", "light", "history", "moments",
                   "length", "prev_normal", "prev_depth", "prev_surface")
    output_names = ("output", "next_light", "next_history", "next_moments", "next_length", "next_surface")

    def forward(self, color: torch.Tensor, emission: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor,
                depth: torch.Tensor, motion: torch.Tensor, light: torch.Tensor, history: torch.Tensor,
                moments: torch.Tensor, length: torch.Tensor, prev_normal: torch.Tensor, prev_depth: torch.Tensor,
                prev_surface: torch.Tensor) -> tuple[torch.Tensor, ...]:
        state = TemporalState(light, history, moments, length, prev_normal, prev_depth, prev_surface)
        out, nxt = temporal_step(color, albedo, normal, depth, motion, state, emission=emission,
                                 spatial=self._spatial, fresh=None if self.fresh is None else self._fresh,
                                 settings=self.settings)
        return out, nxt.light, nxt.output, nxt.moments, nxt.length, nxt.surface
