"""Every setting of :class:`torchgi.Denoiser`, per method, in one place: name, default, range,
unit and the reason for the default (as Falcor's ``SVGFPass.h`` member block or NRD's
``NRDSettings.h`` range comments). The sweeps behind the defaults, with the commands that
reproduce them, are in ``docs/calibration.md``.

Example:
    >>> from torchgi.settings import GUIDED, describe
    >>> GUIDED.radius, describe(GUIDED)[0]["name"]
    (4, 'radius')
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

__all__ = ["ATROUS", "BILATERAL", "DEFAULTS", "GUIDED", "PIPELINE", "TEMPORAL", "ATrousSettings", "BilateralSettings",
           "GuidedSettings", "PipelineSettings", "Settings", "TemporalSettings", "check_settings", "describe"]


def _setting(default: Any, low: float, high: float, unit: str, reason: str) -> Any:
    """A dataclass field with its range ``[low, high]``, unit and one-line reason as metadata."""
    return dataclasses.field(default=default, metadata={"range": (low, high), "unit": unit, "reason": reason})


class _Ranged:
    """Checks on construction that every field holds a number of its default's kind (a bool, an
    int, a float; never NaN) within its ``range`` metadata."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            value, low, high = getattr(self, f.name), *f.metadata["range"]
            name = f"{type(self).__name__}.{f.name}"
            if isinstance(f.default, bool):
                if not isinstance(value, bool):
                    raise TypeError(f"{name}: expected True or False, got {value!r}")
                continue
            kinds = (int,) if isinstance(f.default, int) else (int, float)
            if isinstance(value, bool) or not isinstance(value, kinds):
                kind = "an int" if kinds == (int,) else "a number"
                raise TypeError(f"{name}: expected {kind}, got {value!r}")
            if not low <= value <= high:  # (NaN fails both)
                raise ValueError(f"{name}: expected a value in [{low}, {high}] ({f.metadata['unit']}), got {value!r}")


@dataclasses.dataclass(frozen=True)
class PipelineSettings(_Ranged):
    """The steps around every method's filter (:mod:`torchgi.denoise`)."""

    light: float = _setting(8.0, 1.0, math.inf, "x median demodulated light",
                            "emission this far above the lit scene is a light source, passed untouched")
    light_square: int = _setting(3, 1, 15, "px", "a light source covers a square this wide (an opening): "
                                 "pixels a few samples hit along a silhouette are filtered with the rest")
    firefly_radius: int = _setting(8, 1, 64, "px", "the local level a firefly is compared with: a 17x17 box mean")
    albedo_floor: float = _setting(1e-3, 0.0, 1.0, "albedo", "light is divided by at least this (black surfaces)")
    albedo_ceiling: float = _setting(1.0, 1e-3, 1e3, "albedo", "light is divided by at most this: a reflectance is at "
                                     "most 1, while Mitsuba 3's albedo AOV of a rough conductor reaches 3-10 (tuning "
                                     "scenes rendered by Mitsuba: lower error for every method, docs/calibration.md)")
    hole_radius: int = _setting(2, 1, 16, "px", "an exported Denoiser fills a NaN/Inf pixel from the finite pixels "
                                "of this window (5x5)")
    rel_var_1spp: float = _setting(0.25, 0.0, math.inf, "relative variance",
                                   "the mean relative variance of a 1 spp render: a measured variance maps to spp")
    min_radius: int = _setting(2, 1, 64, "px", "no filter narrower than this, however many samples")
    backoff_radius: int = _setting(3, 0, 64, "px", "the filter's residual is compared with the noise over this "
                                   "window (7x7) before it backs off toward the input (tuning set, 64² and 256²)")
    backoff_margin: float = _setting(2.0, 0.0, math.inf, "x noise / sqrt(spp - 1)",
                                     "the residual must exceed (1 + this / sqrt(spp - 1)) x the measured variance: "
                                     "a variance from few samples is itself noisy (tuning set: at most 3.1 % above "
                                     "the filter alone at 2 spp)")
    auto_tiles_from_mb: float = _setting(2048.0, 0.0, math.inf, "MB", "max_memory_mb='auto' (the default) tiles a "
                                         "call whose untiled pipeline is estimated to add more than this: the pyramid "
                                         "runs 1920x1080 (about 1 GB estimated) and 2560x1440 whole, where tiles cost "
                                         "1.1-1.9x its time, and 3840x2160 (about 4 GB) in tiles, at 0.6-1.5x its untiled time "
                                         "(docs/pyramid.md)")
    auto_budget: float = _setting(2.0, 0.0, math.inf, "x inputs", "those tiles hold at most this multiple of the "
                                  "inputs' memory (issue 28's line at 4K), and at least auto_floor_mb")
    auto_floor_mb: float = _setting(512.0, 0.0, math.inf, "MB", "the least budget of automatic tiles: smaller "
                                    "tiles repeat the pyramid's 208 px overlap too often (400 MB at 4K: 2.4x the time "
                                    "of 800 MB)")
    back_off: bool = _setting(True, 0, 1, "on / off", "with a measured variance, back off toward the input where "
                              "the filter's residual exceeds the noise (and let the guided filter choose among "
                              "radii); off: the filter's output as it is (benchmarks' 'no back-off' rows)")
    fast: float = _setting(0.5, 0.0, math.inf, "x", "quality 'fast' scales radii and footprints by this")
    balanced: float = _setting(1.0, 0.0, math.inf, "x", "quality 'balanced'")
    high: float = _setting(1.5, 0.0, math.inf, "x", "quality 'high'")

    def quality_scale(self, quality: str) -> float:
        """The radius / footprint scale of ``quality`` ("fast", "balanced", "high")."""
        return getattr(self, quality)


@dataclasses.dataclass(frozen=True)
class GuidedSettings(_Ranged):
    """``Denoiser("guided")``: the guided filter on normal + depth guides (Bauszat et al. 2011)."""

    radius: int = _setting(4, 1, 64, "px at 1 spp", "the best compromise over the tuning scenes; shrinks as "
                           "1/sqrt(spp)")
    eps: float = _setting(1e-4, 0.0, math.inf, "guide units squared", "same sweep as radius")
    firefly: float = _setting(4.0, 1.0, math.inf, "x local level",
                              "light above this is scaled down to it before filtering")
    subsample_from: int = _setting(256, 1, math.inf, "px (short side)",
                                   "half resolution only from this size: below it the error grows")
    full_from_spp: float = _setting(2.0, 1.0, math.inf, "samples per pixel",
                                    "full resolution from this many samples: there the half-resolution bias outweighs "
                                    "the noise (tuning set, 256², docs/calibration.md; 1.14-1.45x the time)")
    choose_from_spp: float = _setting(3.0, 2.0, math.inf, "samples per pixel",
                                      "with a variance from this many samples and at full resolution, the filter runs "
                                      "at half and twice its radius and each pixel takes a blend by estimated error "
                                      "(light.choose; tuning set, 256², docs/calibration.md: worse at 2 spp)")
    choose_noise: float = _setting(1.5, 0.0, math.inf, "x noise variance / (2r+1)²",
                                   "the noise a radius-r filter leaves, in light.choose's error estimate (tuning set; "
                                   "0.44 for a box mean applied twice on a flat guide, edges leave more)")
    choose_temperature: float = _setting(0.6, 0.01, math.inf, "x the sharpest filter's noise",
                                         "the softmax temperature of light.choose (tuning set: 0.15-1.5 swept)")
    edge: float = _setting(0.1, 0.0, math.inf, "guide units", "a neighbour this different in the guide is an edge")
    edge_share: float = _setting(0.1, 0.0, 1.0, "share of pixels",
                                 "half resolution only where fewer pixels than this lie on edges")


@dataclasses.dataclass(frozen=True)
class ATrousSettings(_Ranged):
    """``Denoiser("atrous")``: edge-avoiding À-Trous (Dammertz et al. 2010)."""

    footprint: float = _setting(16.0, 1.0, math.inf, "px at 1 spp",
                                "levels enough for this footprint, shrinking as 1/sqrt(spp)")
    min_iterations: int = _setting(2, 1, 16, "levels", "at least this many levels")
    max_iterations: int = _setting(8, 1, 16, "levels", "at most this many (a 1025 px footprint)")
    sigma_normal: float = _setting(0.1, 0.0, math.inf, "normal distance squared", "the paper's value")
    sigma_position_footprints: float = _setting(4.0, 0.0, math.inf, "pixel footprints",
                                                "σ_x = (this x the median pixel footprint)²: scene units unknown")
    deployed_sigma_color: float = _setting(1.0, 0.0, math.inf, "colour units squared",
                                           "an exported model has no image maximum to tie σ_rt to")
    firefly: float = _setting(2.0, 1.0, math.inf, "x local level",
                              "colour-weighted filters keep an outlier as a speck, so a lower bound pays")


@dataclasses.dataclass(frozen=True)
class BilateralSettings(_Ranged):
    """``Denoiser("bilateral")``: brute-force cross-bilateral on normal + depth."""

    radius: int = _setting(6, 1, 64, "px at 1 spp", "shrinks as 1/sqrt(spp); σ_space is half of it")
    sigma_color: float = _setting(2.0, 0.0, math.inf, "colour units (scaled input)", "on light scaled to mean 1")
    sigma_guide: float = _setting(0.2, 0.0, math.inf, "guide units", "normal and depth / extent alike")
    firefly: float = _setting(2.0, 1.0, math.inf, "x local level",
                              "colour-weighted filters keep an outlier as a speck, so a lower bound pays")


@dataclasses.dataclass(frozen=True)
class TemporalSettings(_Ranged):
    """:class:`torchgi.TemporalDenoiser` (SVGF-class accumulation before the guided filter)."""

    alpha: float = _setting(0.2, 0.0, 1.0, "weight of the new frame",
                            "exponential average of light and moments once the history is long (SVGF's value)")
    max_history: int = _setting(32, 1, 1024, "frames", "the history length is capped here (weights >= 1/this)")
    normal_tolerance: float = _setting(0.9, -1.0, 1.0, "cosine",
                                       "a history tap whose normal is further than this from the pixel's is rejected")
    depth_tolerance: float = _setting(0.05, 0.0, math.inf, "relative depth",
                                      "a history tap whose depth differs by more than this share is rejected")
    variance_history: int = _setting(4, 1, 1024, "frames",
                                     "below this history length the variance is a spatial estimate (SVGF)")
    variance_radius: int = _setting(3, 0, 64, "px", "the spatial estimate's window (7x7)")
    radius: int = _setting(2, 1, 64, "px", "the guided filter's radius on the accumulated light (tuning sequence)")
    eps: float = _setting(1e-5, 0.0, math.inf, "guide units squared", "its ε (tuning sequence: 1e-5 below 1e-4)")
    fresh_share: float = _setting(0.5, 0.0, 1.0, "share of pixels",
                                  "from 256 px, the per-frame Denoiser fills new pixels only when at least this share "
                                  "of the frame is new (a first frame, a cut): as good as a single frame")
    short_radius: int = _setting(4, 1, 64, "px",
                                 "from 256 px, in other frames short histories are blended towards the guided filter "
                                 "at this radius (and eps) on the accumulated light (tuning sequences: new pixels' "
                                 "relMSE 0.0188 against 0.0279 at radius 2)")
    output_alpha: float = _setting(0.2, 0.0, 1.0, "weight of the new frame",
                                   "exponential average of the filtered output (temporal anti-flicker)")
    clamp: float = _setting(0.1, 0.0, math.inf, "x noise variance",
                            "the output history is clamped to this share of the accumulated light's noise variance")
    change_radius: int = _setting(4, 0, 64, "px", "the light's change is measured in windows of this radius (9x9)")
    change_scale: int = _setting(4, 1, 64, "x change_radius",
                                 "and of this many times the radius (33x33: slow changes; tuning sequences)")
    change_threshold: float = _setting(4.0, 0.0, math.inf, "noise sigmas",
                                       "the history is dropped where this frame's window mean leaves the history's by "
                                       "more than this (fully one sigma further; tuning sequences); 0 = off")
    follow: float = _setting(3.0, 0.0, math.inf, "noise sigmas",
                             "below the drop, the history's window means move toward this frame's by the gain "
                             "d² / (d² + (this x sigma)²) of their change d (tuning sequences); 0 = off")


PIPELINE = PipelineSettings()
GUIDED = GuidedSettings()
ATROUS = ATrousSettings()
BILATERAL = BilateralSettings()
TEMPORAL = TemporalSettings()

# read by the compiled kernels for the whole process: one value for every instance (Settings refuses others)
PROCESS_WIDE = {"pipeline": ("light", "light_square", "firefly_radius", "albedo_floor", "albedo_ceiling",
                             "hole_radius", "backoff_radius", "backoff_margin"),
                "guided": ("choose_noise", "choose_temperature")}


@dataclasses.dataclass(frozen=True)
class Settings:
    """Every setting of one :class:`torchgi.Denoiser` or :class:`torchgi.TemporalDenoiser`, by
    group (as NRD's per-denoiser settings structs): ``pipeline`` (the steps around every filter),
    ``guided``, ``atrous``, ``bilateral`` (each method's) and ``temporal``. Frozen; each group
    checks its ranges on construction; :meth:`replace` changes some fields of some groups. The
    fields in ``PROCESS_WIDE`` are read by the compiled kernels for the whole process: a value
    other than the default is refused.

    Example:
        >>> s = DEFAULTS.replace(guided={"firefly": 3.0}, temporal={"follow": 0.0})
        >>> s.guided.firefly, s.temporal.follow, s.guided.radius
        (3.0, 0.0, 4)
    """

    pipeline: PipelineSettings = PIPELINE
    guided: GuidedSettings = GUIDED
    atrous: ATrousSettings = ATROUS
    bilateral: BilateralSettings = BILATERAL
    temporal: TemporalSettings = TEMPORAL

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            group = getattr(self, f.name)
            if type(group) is not type(f.default):
                raise TypeError(f"settings.{f.name}: expected a {type(f.default).__name__}, got {group!r}")
            for name in PROCESS_WIDE.get(f.name, ()):
                if getattr(group, name) != getattr(f.default, name):
                    raise ValueError(f"settings.{f.name}.{name}: read by the compiled kernels for the whole process, "
                                     f"so it stays {getattr(f.default, name)!r}; got {getattr(group, name)!r}")

    def replace(self, **groups: dict[str, Any]) -> Settings:
        """These settings with some fields changed, ``group={field: value, ...}`` per group (checked
        as on construction: an unknown group or field raises naming it)."""
        changed = {}
        for group, fields in groups.items():
            if group not in {f.name for f in dataclasses.fields(self)}:
                raise TypeError(f"{group}: not a settings group (pipeline, guided, atrous, bilateral, temporal)")
            current = getattr(self, group)
            known = {f.name for f in dataclasses.fields(current)}
            for name in fields:
                if name not in known:
                    raise TypeError(f"{group}.{name}: not a setting of {type(current).__name__}")
            changed[group] = dataclasses.replace(current, **fields)
        return dataclasses.replace(self, **changed)

    def changes(self) -> dict[str, Any]:
        """``{"group.field": value}`` of the fields that differ from the defaults (what ``repr``
        of a Denoiser shows).

        Example:
            >>> DEFAULTS.replace(temporal={"follow": 0.0}).changes()
            {'temporal.follow': 0.0}
        """
        return {f"{g.name}.{f.name}": getattr(getattr(self, g.name), f.name) for g in dataclasses.fields(self)
                for f in dataclasses.fields(getattr(self, g.name))
                if getattr(getattr(self, g.name), f.name) != getattr(g.default, f.name)}


DEFAULTS = Settings()


def check_settings(settings: Any) -> Settings:
    """``settings`` if it is a :class:`Settings`, else a TypeError naming the argument.

    Example:
        >>> check_settings(DEFAULTS) is DEFAULTS
        True
    """
    if not isinstance(settings, Settings):
        raise TypeError(f"settings: expected a torchgi.settings.Settings, got {type(settings).__name__}")
    return settings


def describe(settings: Any) -> list[dict[str, Any]]:
    """One row per setting of a settings instance: name, value, range, unit, reason (for docs
    and benchmark metadata).

    Example:
        >>> describe(BILATERAL)[0]
        {'name': 'radius', 'value': 6, 'range': (1, 64), 'unit': 'px at 1 spp', 'reason': 'shrinks as 1/sqrt(spp); σ_space is half of it'}
    """
    return [{"name": f.name, "value": getattr(settings, f.name), **f.metadata} for f in dataclasses.fields(settings)]
