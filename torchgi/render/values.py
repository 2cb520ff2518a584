"""The checks of scene-file values that the scene's data classes share: three finite numbers,
one number in an open range, no unknown keys; each error names the key."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from torchgi.core.errors import ConfigError

__all__: list[str] = []


def _vec3(value: Any, key: str, *, low: float | None = None) -> tuple[float, float, float]:
    """Three finite floats (a scalar is broadcast), else :class:`ConfigError` naming ``key``."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value] * 3
    try:
        out = tuple(float(v) for v in value if not isinstance(v, bool))
    except (TypeError, ValueError):
        raise ConfigError(f"{key}: expected three numbers, got {value!r}") from None
    if len(out) != 3 or not all(math.isfinite(v) for v in out):
        raise ConfigError(f"{key}: expected three finite numbers, got {value!r}")
    if low is not None and min(out) < low:
        raise ConfigError(f"{key}: expected values >= {low}, got {value!r}")
    return out  # type: ignore[return-value]


def _number(value: Any, key: str, low: float | None = None, high: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{key}: expected a finite number, got {value!r}")
    if (low is not None and value <= low) or (high is not None and value >= high):
        raise ConfigError(f"{key}: expected a number in ({low}, {high}), got {value!r}")
    return float(value)


def _no_unknown_keys(cfg: Mapping[str, Any], key: str, known: Sequence[str]) -> None:
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"{key}: expected a mapping, got {type(cfg).__name__}")
    extra = sorted(set(cfg) - set(known))
    if extra:
        raise ConfigError(f"{key}: unknown key(s) {', '.join(map(repr, extra))}; known: {', '.join(known)}")
