"""The seam between the filters and their implementations: one descriptor per op, one
:func:`select`, one switch (:func:`use`).

An op's descriptor holds its tensors and parameters in one convention, already validated by
the public function that built it (shapes, devices, dtypes, ranges): back ends only decide
whether they *support* a call and compute it. Each back end is a module with ``NAME``,
``supports(op, desc) -> str | None`` (None: supported; else the reason it is not) and one
function per op taking the descriptor. :func:`select` walks :data:`ORDER` and takes the first
back end allowed by :func:`use` that supports the call; the torch code supports every call, so
it is the last resort. Modelled on OIDN's device/engine split: the filter is the same object
whatever runs it.
"""

from __future__ import annotations

import contextlib
import contextvars
import importlib
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import torch

from torchgi.backends.kernel_ops import (
    ApplyKernelsGradOp,
    ApplyKernelsOp,
    ATrousLevelGradOp,
    ATrousLevelOp,
    GuidedGradOp,
)
from torchgi.backends.pyramid_ops import AppliedMeansOp, BlockMeanOp, FineBandOp, MixHalfOp, ModelResidualOp
from torchgi.backends.temporal_ops import LUMA, Accumulated, AccumulateOp, Changed, ChangeOp, HistoryOp
from torchgi.backends.tracer_ops import GuideRaysOp, PathOp, TraceSetup, chunks, embree_started, mark_embree_started
from torchgi.core.check import is_tracing
from torchgi.core.errors import OptionError

__all__ = [
    "LUMA",
    "NAMES",
    "ORDER",
    "ATrousLevelGradOp",
    "ATrousLevelOp",
    "ATrousOp",
    "AccumulateOp",
    "Accumulated",
    "AllocateOp",
    "AppliedMeansOp",
    "ApplyKernelsGradOp",
    "ApplyKernelsOp",
    "BackOffOp",
    "BlockMeanOp",
    "BoxOp",
    "ChangeOp",
    "Changed",
    "ChooseOp",
    "EdgeShareOp",
    "FineBandOp",
    "GuideRaysOp",
    "GuideSpec",
    "GuideStats",
    "GuideStatsOp",
    "GuidedGradOp",
    "GuidedOp",
    "HistoryOp",
    "ImportanceOp",
    "LightInOp",
    "LightOutOp",
    "MixHalfOp",
    "ModelResidualOp",
    "PathOp",
    "RestoreOp",
    "TraceSetup",
    "UpsampleApplyOp",
    "chunks",
    "eager",
    "embree_started",
    "enabled",
    "float32_eager",
    "mark_embree_started",
    "plan",
    "run",
    "select",
    "status",
    "use",
]

NAMES = ("torch", "c", "triton")
ORDER = ("c", "triton", "torch")  # tried first to last; CPU and CUDA calls never both fit c and triton
_MODULES = {"torch": "torchgi.backends.torch_code", "c": "torchgi.backends.c_kernels",
            "triton": "torchgi.backends.triton_kernels"}
_COMPILED = frozenset({"c", "triton"})
# TORCHGI_NATIVE=0 switches both compiled back ends off for the whole process
_ENV_OFF = os.environ.get("TORCHGI_NATIVE", "1") == "0"
_allowed: contextvars.ContextVar[frozenset[str]] = contextvars.ContextVar("torchgi_backends", default=frozenset(NAMES))
_last: dict[str, tuple[str, dict[str, str]]] = {}
_loaded: dict[str, ModuleType] = {}


@dataclass(eq=False, slots=True)
class BoxOp:
    """Count-normalised box means over ``(2r+1)²`` windows of ``x (B,C,H,W)`` (float32/64, not empty)."""

    x: torch.Tensor
    radius: int

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.x,)


@dataclass(eq=False, slots=True)
class GuidedOp:
    """The guided filter of ``src (B,Cs,H,W)`` by ``guide (B,n,H,W)`` (n <= 4, same float dtype),
    both centred inside by ``mean_src`` / ``mean_guide`` ``(B,C,1,1)``; ``eps (B,n,1,1)`` or a
    per-pixel ``(B,n,H,W)`` map, >= 0.
    Returns ``(B,Cs,H,W)`` (``mean_src`` added back) or, with ``coefficients_only``, the
    box-filtered coefficients ``(B,n+1,Cs,H,W)`` (``a_0..a_{n-1}, b``). ``workspace`` keeps a
    back end's buffers between calls of one size (the :class:`~torchgi.filters.Guided` module's);
    ``out``, a buffer of the result's shape the compiled back ends may write the result into (and
    return) instead of new memory (the torch code returns a new tensor)."""

    guide: torch.Tensor
    src: torch.Tensor
    mean_guide: torch.Tensor
    mean_src: torch.Tensor
    radius: int
    eps: torch.Tensor
    coefficients_only: bool = False
    workspace: dict | None = None
    out: torch.Tensor | None = None

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.guide, self.src, self.eps)


@dataclass(eq=False, slots=True)
class UpsampleApplyOp:
    """Linear-model coefficients ``coeffs (B,n+1,Cs,h,w)`` (``a_0..a_{n-1}, b``) at half
    resolution, ``h, w = ⌈H/2⌉, ⌈W/2⌉``, upsampled bilinearly x2 (torch's ``interpolate``,
    ``align_corners=False``, cropped to ``H x W``) and applied to the centred ``guide (B,n,H,W)``
    (n <= 4): returns ``b + Σ_i a_i guide_i``, ``(B,Cs,H,W)`` (in ``out`` as :class:`GuidedOp`'s)."""

    coeffs: torch.Tensor
    guide: torch.Tensor
    out: torch.Tensor | None = None

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.coeffs, self.guide)


@dataclass(eq=False, slots=True)
class ATrousOp:
    """``iterations`` À-Trous levels of ``color (B,C,H,W)`` (holes of sub-sampling already 0).

    ``normal`` / ``position`` ``(B,3,H,W)`` raw guides (None: no such weight, as when their
    inverse σ is None); ``variance (B,C,H,W)`` propagated along (SVGF) or None; ``valid
    (B,1,H,W)`` bool sources of sub-sampling or None; ``inv_color (B,1,1,1)`` (or a per-pixel
    ``(B,1,H,W)`` map) is ``1/σ_rt``, or ``1/σ²`` with a variance; ``inv_normal`` / ``inv_position`` ``(B,1,1,1)`` or None. The
    colour weight is on from level ``fill`` when ``color_weight``. Returns the filtered colour
    and, with ``return_details``, the detail coefficients of each level."""

    color: torch.Tensor
    normal: torch.Tensor | None
    position: torch.Tensor | None
    variance: torch.Tensor | None
    valid: torch.Tensor | None
    inv_color: torch.Tensor
    inv_normal: torch.Tensor | None
    inv_position: torch.Tensor | None
    iterations: int
    fill: int = 0
    color_weight: bool = True
    return_details: bool = False
    fused: bool = False

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.color, self.normal, self.position, self.variance, self.inv_color, self.inv_normal,
                self.inv_position)


@dataclass(eq=False, slots=True)
class ImportanceOp:
    """Sampling importance ``(B,1,H,W)`` from ``normal`` / ``position`` ``(B,3,H,W)`` (same float
    dtype), σ's as floats > 0, ``hit (B,1,H,W)`` bool or None, a ``window x window``
    neighbourhood (offsets ``-(w//2) .. (w-1)//2``)."""

    normal: torch.Tensor
    position: torch.Tensor
    sigma_normal: float
    sigma_position: float
    hit: torch.Tensor | None
    window: int
    fused: bool = False

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.normal, self.position)


@dataclass(eq=False, slots=True)
class AllocateOp:
    """Integer samples per pixel ``(B,N)`` int64 from the importance ``q (B,N)`` (finite, >= 0),
    ``eligible (B,N)`` bool or None (every pixel), ``n_eligible (B,)`` int64, ``budget`` samples
    per image (at least ``min_samples`` times the eligible pixels)."""

    q: torch.Tensor
    eligible: torch.Tensor | None
    n_eligible: torch.Tensor
    budget: int
    min_samples: int

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.q,)


@dataclass(eq=False, slots=True)
class GuideStatsOp:
    """Per image of ``normal (B,3,H,W)`` and ``depth (B,1,H,W)`` or None (same float dtype), with
    ``hit (B,1,H,W)`` bool or None: a float64 CPU ``(B, 11)`` tensor of the channel minima (normal
    x, y, z, depth; +inf without depth), maxima (-inf without depth), the largest depth on hit
    pixels (every pixel without ``hit``; -inf where none), and the counts of non-finite values
    in normal and in depth, then (B, 15) the channel sums (normal x, y, z, depth; 0 without)."""

    normal: torch.Tensor
    depth: torch.Tensor | None
    hit: torch.Tensor | None

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.normal, self.depth)


@dataclass(frozen=True, eq=False)
class GuideStats:
    """Named views of :class:`GuideStatsOp`'s ``(B, 15)`` result (``packed``; the layout is
    defined here only)."""

    packed: torch.Tensor

    @property
    def minima(self) -> torch.Tensor:
        """``(B, 4)`` the minima of normal x, y, z and depth (+inf without depth)."""
        return self.packed[:, 0:4]

    @property
    def maxima(self) -> torch.Tensor:
        """``(B, 4)`` their maxima (-inf without depth)."""
        return self.packed[:, 4:8]

    @property
    def depth_max(self) -> torch.Tensor:
        """``(B,)`` the largest depth on hit pixels (-inf where none)."""
        return self.packed[:, 8]

    @property
    def nonfinite_normal(self) -> torch.Tensor:
        """``(B,)`` how many values of the normal are NaN/Inf."""
        return self.packed[:, 9]

    @property
    def nonfinite_depth(self) -> torch.Tensor:
        """``(B,)`` how many of the depth are."""
        return self.packed[:, 10]

    @property
    def sums(self) -> torch.Tensor:
        """``(B, 4)`` the channel sums of normal x, y, z and depth (0 without)."""
        return self.packed[:, 11:]


@dataclass(eq=False, slots=True)
class GuideSpec:
    """The Denoiser's guide as planes of ``normal (B,3,H,W)`` and ``depth (B,1,H,W)`` (or None):
    channel ``k`` is plane ``channels[k]`` of [normal x, y, z, depth] times ``scale[k]`` plus
    ``offset[k]`` (1 to 4 channels)."""

    normal: torch.Tensor
    depth: torch.Tensor | None
    channels: tuple[int, ...]
    scale: tuple[float, ...]
    offset: tuple[float, ...]

    def planes(self) -> list[torch.Tensor]:
        """The ``(B,1,H,W)`` source plane of each channel (views)."""
        return [self.normal[:, c : c + 1] if c < 3 else self.depth for c in self.channels]

    def build(self) -> torch.Tensor:
        """The ``(B,n,H,W)`` guide by torch ops (``(normal + 1) / 2`` rounds as ``normal / 2 + 1 / 2``).

        Example:
            >>> n = torch.zeros(1, 3, 2, 2); d = torch.full((1, 1, 2, 2), 4.0)
            >>> GuideSpec(n, d, (0, 3), (0.5, 0.25), (0.5, 0.0)).build()[0, :, 0, 0].tolist()
            [0.5, 1.0]
        """
        return torch.cat([p * s + o for p, s, o in zip(self.planes(), self.scale, self.offset, strict=True)], 1)


@dataclass(eq=False, slots=True)
class EdgeShareOp:
    """The share of horizontal neighbours on even rows whose guide (``spec``) differs by more
    than ``edge`` (Euclidean, guide units), over the batch: a float."""

    spec: GuideSpec
    edge: float

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.spec.normal, self.spec.depth)


@dataclass(eq=False, slots=True)
class RestoreOp:
    """The Denoiser's pipeline around the guided filter (:mod:`torchgi.denoise`'s docstring) for
    ``color (B,3,H,W)``: ``emission`` and ``kept`` (light added back unfiltered: the direct
    light of the papers' split) ``(B,3,H,W)`` or None, ``albedo (B,3,H,W)``, ``hit (B,1,H,W)``
    bool or None (surfaces: non-zero albedo), the guide ``spec``, the per-image ``level
    (B,1,1,1)`` thresholds are multiples of, the guided filter's ``radius``, ``eps`` (float),
    ``subsample`` and the firefly factor; the other constants are ``settings.PIPELINE``'s. All
    tensors of one float dtype and device. ``centre_src (B,3)`` and ``centre_guide (B,n)``
    (float64 CPU) are the constants the C kernels centre light and guide by before any sum (the
    filter does not depend on them; tiles of one image given the same ones compute the same
    sums), None: this call's means. Returns the ``(B,3,H,W)`` radiance."""

    color: torch.Tensor
    emission: torch.Tensor | None
    kept: torch.Tensor | None
    albedo: torch.Tensor
    hit: torch.Tensor | None
    spec: GuideSpec
    level: torch.Tensor
    radius: int
    eps: float
    subsample: int
    firefly: float
    workspace: dict | None = None
    centre_src: torch.Tensor | None = None
    centre_guide: torch.Tensor | None = None

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.color, self.emission, self.kept, self.albedo, self.spec.normal, self.spec.depth, self.level)

    def light_inputs(self) -> list[tuple[str, torch.Tensor]]:
        """The light inputs present, by the names a NaN/Inf error gives them (kept light is the
        user's ``direct``), in the order they are checked."""
        named = (("direct", self.kept), ("color", self.color), ("emission", self.emission), ("albedo", self.albedo))
        return [(name, t) for name, t in named if t is not None]


@dataclass(eq=False, slots=True)
class LightInOp:
    """The Denoiser's steps before a filter other than its fused guided one
    (:func:`torchgi.light.prepare`): light sources found, the light demodulated and its
    fireflies clamped at ``firefly`` x their local level. ``color``, ``emission`` / ``kept`` (or
    None), ``albedo`` ``(B,3,H,W)``, ``hit (B,1,H,W)`` bool or None, ``level (B,1,1,1)``; one
    float dtype and device. Returns ``(clamped, x, lights)``: the filter's input and the light
    before the clamp ``(B,3,H,W)``, the light-source mask ``(B,1,H,W)`` bool. ``workspace``: a dict
    in which the compiled back ends keep these results' buffers between calls (the caller is done
    with them before its next call with it: no fresh pages each call)."""

    color: torch.Tensor
    emission: torch.Tensor | None
    kept: torch.Tensor | None
    albedo: torch.Tensor
    hit: torch.Tensor | None
    level: torch.Tensor
    firefly: float
    workspace: dict | None = None

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.color, self.emission, self.kept, self.albedo, self.level)

    def light_inputs(self) -> list[tuple[str, torch.Tensor]]:
        """As :meth:`RestoreOp.light_inputs`."""
        named = (("direct", self.kept), ("color", self.color), ("emission", self.emission), ("albedo", self.albedo))
        return [(name, t) for name, t in named if t is not None]


@dataclass(eq=False, slots=True)
class LightOutOp:
    """The Denoiser's steps after such a filter (:func:`torchgi.light.finish`): its output
    ``filtered (B,3,H,W)`` clamped at 0 and remodulated, the light sources and ``kept`` light
    added back (without an emission input a light source's pixels are its colour). The other
    tensors as :class:`LightInOp`'s, ``lights`` its mask. ``inplace``: the result may be written
    into ``filtered`` (the caller does not read it again). Returns ``(B,3,H,W)``."""

    filtered: torch.Tensor
    color: torch.Tensor
    emission: torch.Tensor | None
    kept: torch.Tensor | None
    albedo: torch.Tensor
    hit: torch.Tensor | None
    lights: torch.Tensor
    inplace: bool = False

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.filtered, self.color, self.emission, self.kept, self.albedo)


@dataclass(eq=False, slots=True)
class BackOffOp:
    """:func:`torchgi.light.back_off`: ``out (B,3,H,W)`` (a filter's output) moved toward ``color
    (B,3,H,W)`` where the residual exceeds the noise ``variance (B,1|3,H,W)`` (of the mean, not
    None), ``spp`` the sample count (a float when every pixel has the same, else a ``(B,1,H,W)``
    float plane; None: 2), ``emitting (B,1,H,W)`` bool; constants ``settings.PIPELINE``'s. All
    float tensors of one dtype and device. Returns the ``(B,3,H,W)`` result."""

    out: torch.Tensor
    color: torch.Tensor
    variance: torch.Tensor
    spp: float | torch.Tensor | None
    emitting: torch.Tensor

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.out, self.color, self.variance)


@dataclass(eq=False, slots=True)
class ChooseOp:
    """:func:`torchgi.light.choose`: a per-pixel blend of ``outs`` (2 to 4 ``(B,3,H,W)`` outputs of
    one filter at ``radii``, sharpest first) by their estimated error against the noise
    ``variance (B,1|3,H,W)`` (of the mean), pooled over pixels that are not ``emitting (B,1,H,W)``
    bool; constants ``settings.PIPELINE``'s and ``settings.GUIDED``'s. All float tensors of one
    dtype and device. Returns the ``(B,3,H,W)`` blend."""

    outs: tuple[torch.Tensor, ...]
    radii: tuple[int, ...]
    variance: torch.Tensor
    emitting: torch.Tensor

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (*self.outs, self.variance)


Op = BoxOp | GuidedOp | ATrousOp | ImportanceOp | AllocateOp | GuideStatsOp | EdgeShareOp | RestoreOp | LightInOp | \
    LightOutOp | MixHalfOp | ModelResidualOp | FineBandOp | BlockMeanOp | AppliedMeansOp | BackOffOp | ChooseOp | AccumulateOp | ChangeOp | HistoryOp | PathOp | \
    GuideRaysOp | ApplyKernelsOp | ApplyKernelsGradOp | ATrousLevelOp | ATrousLevelGradOp | GuidedGradOp
_OPS = {BoxOp: "box", GuidedOp: "guided", UpsampleApplyOp: "upsample_apply", ATrousOp: "atrous", ImportanceOp: "importance", AllocateOp: "allocate",
        GuideStatsOp: "guide_stats", EdgeShareOp: "edge_share", RestoreOp: "restore", LightInOp: "light_in",
        LightOutOp: "light_out", MixHalfOp: "mix_half", ModelResidualOp: "model_residual", FineBandOp: "fine_band", BlockMeanOp: "block_means", AppliedMeansOp: "applied_means", BackOffOp: "back_off",
        ChooseOp: "choose",
        AccumulateOp: "accumulate", ChangeOp: "change", HistoryOp: "history", PathOp: "path", GuideRaysOp: "guide_rays",
        ApplyKernelsOp: "apply_kernels", ApplyKernelsGradOp: "apply_kernels_grad", ATrousLevelOp: "atrous_level",
        ATrousLevelGradOp: "atrous_level_grad", GuidedGradOp: "guided_grad"}


def eager(desc: Op) -> str | None:
    """Why a compiled kernel cannot take ``desc`` (traced, or autograd through one of its
    tensors), or None: kernels compute values, not graphs.

    Example:
        >>> eager(BoxOp(torch.ones(1, 1, 2, 2, requires_grad=True), 1))
        'autograd: an input requires grad'
    """
    if is_tracing():
        return "tracing or exporting: the torch code is the traced graph"
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in desc.tensors()):
        return "autograd: an input requires grad"
    return None


def float32_eager(op: str, desc: Op, who: str) -> str | None:
    """Why the compiled kernels of ``who`` ("C", "Triton") cannot take ``desc`` beyond its
    device: a tensor that is not float32, a call that is traced or needs autograd (:func:`eager`),
    an empty box input, a per-pixel ``eps`` map of the guided filter; None when none of these holds.

    Example:
        >>> float32_eager("box", BoxOp(torch.ones(1, 1, 2, 2, dtype=torch.float64), 1), "C")
        'the C kernels take float32'
    """
    if any(t is not None and t.dtype != torch.float32 for t in desc.tensors()):
        return f"the {who} kernels take float32"
    why = eager(desc)
    if why is not None:
        return why
    if op == "box" and desc.x.numel() == 0:
        return "an empty tensor: nothing to compute"
    if op in ("guided", "guided_grad") and desc.eps.shape[-2:] != (1, 1):
        return f"the {who} guided kernels take one eps per image and guide channel, not a per-pixel map"
    return None


def _module(name: str) -> ModuleType:
    mod = _loaded.get(name)
    if mod is None:
        mod = _loaded[name] = importlib.import_module(_MODULES[name])
    return mod


def select(desc: Op) -> tuple[str, Callable[[Any], Any]]:
    """The first back end of :data:`ORDER` allowed here that supports ``desc``: its name and the
    function computing the op; :func:`status` records why the ones before it did not.

    Example:
        >>> x = torch.rand(1, 1, 4, 4, dtype=torch.float64)
        >>> select(BoxOp(x, 1))[0]   # float64: only the torch code takes it
        'torch'
    """
    op = _OPS[type(desc)]
    name, _ = _last[op] = _first(lambda name: _module(name).supports(op, desc))
    return name, getattr(_module(name), op)


def _first(why_not: Callable[[str], str | None]) -> tuple[str, dict[str, str]]:
    """The first back end of :data:`ORDER` allowed here for which ``why_not`` is None, and why
    each one before it declined."""
    skipped: dict[str, str] = {}
    for name in ORDER:
        why = _switched_off(name) or why_not(name)
        if why is None:
            return name, skipped
        skipped[name] = why
    raise AssertionError(f"no back end: {skipped}")  # the torch code takes every call


def _switched_off(name: str) -> str | None:
    """Why back end ``name`` may not run here (:func:`use`, ``TORCHGI_NATIVE=0``), or None."""
    if name not in _allowed.get():
        return "switched off by torchgi.backends.use(...)"
    if name in _COMPILED and _ENV_OFF:
        return "switched off by TORCHGI_NATIVE=0"
    return None


def plan(device: str = "cpu") -> dict[str, tuple[str, dict[str, str]]]:
    """Per op family, the back end that runs an eager float32 call on ``device`` ("cpu", "cuda")
    tensors here and why each before it in :data:`ORDER` declines (a call's sizes, dtypes or
    autograd can still send it further down: :func:`status`'s ``last`` says what ran).

    Example:
        >>> plan("cuda")["importance"][1]["triton"]
        'no Triton kernel for importance'
    """
    return {op: _first(lambda name, op=op: _module(name).ready(op, device)) for op in sorted(set(_OPS.values()))}


def run(desc: Op) -> Any:
    """Compute ``desc`` with the back end :func:`select` picks.

    Example:
        >>> run(BoxOp(torch.arange(3.0).view(1, 1, 1, 3), 1))
        tensor([[[[0.5000, 1.0000, 1.5000]]]])
    """
    return select(desc)[1](desc)


@contextlib.contextmanager
def use(*names: str) -> Iterator[None]:
    """Restrict the back ends to ``names`` inside this block (this thread / task only: a
    context variable); the torch code stays allowed, as it takes every call.
    ``use("torch")`` runs the torch code alone (benchmarks and tests compare the two).

    Example:
        >>> with use("torch"):
        ...     select(BoxOp(torch.rand(1, 1, 4, 4), 1))[0]
        'torch'
    """
    for name in names:
        if name not in NAMES:
            raise OptionError(f"backends.use: unknown back end {name!r}; known: {', '.join(NAMES)}")
    token = _allowed.set(frozenset(names) | {"torch"})
    try:
        yield
    finally:
        _allowed.reset(token)


def enabled(name: str) -> bool:
    """Whether back end ``name`` may run here (not switched off by :func:`use` or the environment).

    Example:
        >>> with use("torch"):
        ...     enabled("c")
        False
    """
    return name in _allowed.get() and not (name in _COMPILED and _ENV_OFF)


def status() -> dict[str, Any]:
    """What each back end can do here, the C compiler and the kernel cache, per op family and
    device the back end an eager float32 call runs (:func:`plan`) and, per op, which one ran last
    and why the others did not (``torchgi info``, logs, benchmarks); builds the C kernels first.

    Returns:
        ``{"c": str, "triton": str, "torch": str, "compiler": path | None, "cache": path,
        "ops": {device: {op: {"runs": name, "declined": {name: reason}}}},
        "last": {op: {"ran": name, "skipped": {name: reason}}}}``.

    Example:
        >>> s = status()
        >>> sorted(s) == ["c", "cache", "compiler", "last", "ops", "torch", "triton"]
        True
    """
    from torchgi.backends.c_kernels import build

    out: dict[str, Any] = {name: _switched_off(name) or _module(name).describe() for name in NAMES}
    out["compiler"] = build._compiler()
    out["cache"] = str(build._cache_dir())
    out["ops"] = {device: {op: {"runs": ran, "declined": skipped} for op, (ran, skipped) in plan(device).items()}
                  for device in ("cpu", "cuda")}
    out["last"] = {op: {"ran": ran, "skipped": dict(skipped)} for op, (ran, skipped) in sorted(_last.items())}
    return out
