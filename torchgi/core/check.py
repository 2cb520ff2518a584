"""Input validation shared by every public function.

Shapes are written symbolically, as in kornia: ``check_shape(x, "B C H W")`` binds the
letters to sizes and returns them, so several tensors can be checked against each other by
passing the same ``sizes`` dict. Digits fix a size (``"B 3 H W"``).
"""

from __future__ import annotations

import importlib
import math
import sys
import warnings
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

import torch

from torchgi.core.errors import (
    DeviceError,
    DTypeError,
    ExtraNotInstalledError,
    NonFiniteError,
    OptionError,
    RangeError,
    ShapeError,
)

__all__ = [
    "check_finite",
    "check_floating",
    "check_int",
    "check_nonnegative",
    "check_option",
    "check_positive",
    "check_range",
    "check_same_device",
    "check_same_floating",
    "check_shape",
    "check_tensor",
    "finite_or_sanitized",
    "finite_or_sanitized_all",
    "finite_or_sanitized_later",
    "is_recording",
    "is_tracing",
    "require",
    "user_stacklevel",
]


def is_tracing() -> bool:
    """True while torch.jit tracing, torch.compile or torch.export / ONNX export records code
    (the compiled back ends of :mod:`torchgi.backends` step aside then: the recorded graph
    needs torch ops).

    Example:
        >>> is_tracing()
        False
    """
    exporting = getattr(torch.compiler, "is_exporting", lambda: False)
    return bool(torch.jit.is_tracing() or torch.compiler.is_compiling() or exporting())


def is_recording() -> bool:
    """True while tracing (:func:`is_tracing`) or while the current CUDA stream is captured
    into a CUDA graph: then nothing may read tensor values on the host.

    Value checks (NaN/Inf, ranges) and data-dependent shortcuts read tensor data, which a
    recorded graph cannot branch on (a captured graph replays on data no host check sees): they
    are skipped while recording; shape, dtype and device checks still run.

    Example:
        >>> is_recording()
        False
    """
    if is_tracing():
        return True
    return torch.cuda.is_available() and torch.cuda.is_current_stream_capturing()


def check_tensor(x: Any, name: str) -> torch.Tensor:
    """Raise ``TypeError`` unless ``x`` is a ``torch.Tensor``; return it.

    Example:
        >>> check_tensor(torch.zeros(1), "x").shape
        torch.Size([1])
    """
    if not isinstance(x, torch.Tensor):
        raise DTypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    return x


def check_shape(
    x: torch.Tensor, spec: str, name: str = "x", sizes: dict[str, int] | None = None
) -> dict[str, int]:
    """Check ``x`` against a symbolic shape such as ``"B C H W"`` or ``"B 3 H W"``.

    Letters bind to sizes on first sight and must agree afterwards (also across calls
    that share ``sizes``); digits are fixed sizes.

    Args:
        x: the tensor.
        spec: space-separated dimension names or integers.
        name: the argument's name, used in the error message.
        sizes: bindings to reuse and extend; a new dict when None.

    Returns:
        The bindings, e.g. ``{"B": 2, "C": 3, "H": 64, "W": 48}``.

    Raises:
        ShapeError: wrong rank or a size that disagrees with the spec.

    Example:
        >>> s = check_shape(torch.zeros(2, 3, 4, 5), "B 3 H W", "color")
        >>> s["H"], s["W"]
        (4, 5)
        >>> _ = check_shape(torch.zeros(2, 1, 4, 5), "B 1 H W", "depth", sizes=s)
    """
    check_tensor(x, name)
    dims = spec.split()
    sizes = {} if sizes is None else sizes
    if x.dim() != len(dims):
        raise ShapeError(
            f"{name}: expected shape ({', '.join(dims)}), got {tuple(x.shape)} "
            f"({x.dim()} dimensions instead of {len(dims)})"
        )
    for dim, size in zip(dims, x.shape):
        if dim.isdigit():
            if size != int(dim):
                raise ShapeError(f"{name}: expected shape ({', '.join(dims)}), got {tuple(x.shape)}")
        elif dim in sizes and sizes[dim] != size:
            raise ShapeError(
                f"{name}: dimension {dim} is {size} but other inputs have {dim}={sizes[dim]} "
                f"(shape {tuple(x.shape)}, expected ({', '.join(dims)}))"
            )
        else:
            sizes[dim] = size
    return sizes


def check_same_device(tensors: Mapping[str, torch.Tensor | None]) -> torch.device | None:
    """Raise :class:`DeviceError` unless every non-None tensor is on one device.

    Nothing is ever moved: the caller decides where data lives.

    Example:
        >>> check_same_device({"a": torch.zeros(1), "b": torch.ones(1), "c": None})
        device(type='cpu')
    """
    device = None
    first = None
    for key, t in tensors.items():
        if t is None:
            continue
        if device is None:
            device, first = t.device, key
        elif t.device != device:
            raise DeviceError(
                f"{key} is on {t.device} but {first} is on {device}: "
                "move them to one device first (torchgi never moves data on its own)"
            )
    return device


def check_floating(x: torch.Tensor, name: str) -> None:
    """Raise :class:`DTypeError` unless ``x`` has a floating dtype.

    Example:
        >>> check_floating(torch.zeros(1, dtype=torch.float16), "color")
    """
    if not x.is_floating_point():
        raise DTypeError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")


def check_same_floating(tensors: Mapping[str, torch.Tensor | None]) -> None:
    """Every non-None tensor is floating and shares the first one's dtype (nothing is cast).

    Example:
        >>> check_same_floating({"color": torch.zeros(1), "normal": torch.zeros(1), "x": None})
    """
    first = None
    for name, t in tensors.items():
        if t is None:
            continue
        check_floating(t, name)
        if first is None:
            first = (name, t.dtype)
        elif t.dtype != first[1]:
            raise DTypeError(f"{name} is {t.dtype} but {first[0]} is {first[1]}: pass one dtype")


def check_positive(value: Any, name: str) -> None:
    """Raise :class:`RangeError` unless ``value`` is a finite real number ``> 0``.

    Example:
        >>> check_positive(0.1, "sigma_space")
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < float("inf"):
        raise RangeError(f"{name}: expected a finite float > 0, got {value!r}")


def check_nonnegative(value: Any, name: str) -> None:
    """Raise :class:`RangeError` unless ``value`` is a finite real number ``>= 0``.

    Example:
        >>> check_nonnegative(0.0, "eps")
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < float("inf"):
        raise RangeError(f"{name}: expected a finite float >= 0, got {value!r}")


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise :class:`NonFiniteError` if ``x`` holds NaN or +-Inf, with counts.

    Example:
        >>> check_finite(torch.tensor([0.0, 1e6]), "color")
    """
    finite_or_sanitized_all({name: x}, False)


def _count_non_finite(x: torch.Tensor, name: str) -> None:
    """The exact check behind a non-finite sum: raise with the counts, or return when the sum
    merely overflowed."""
    finite = torch.isfinite(x)
    if bool(finite.all()):
        return
    n_nan = int(torch.isnan(x).sum())
    n_inf = int((~finite).sum()) - n_nan
    raise NonFiniteError(
        f"{name}: expected finite values, found {n_nan} NaN and {n_inf} +-Inf "
        f"of {x.numel()} elements (pass sanitize=True where offered to replace them)"
    )


def finite_or_sanitized(x: torch.Tensor, name: str, sanitize: bool) -> torch.Tensor:
    """``x`` if it is finite; otherwise raise, or with ``sanitize=True`` replace NaN/Inf by 0
    and warn with the count (the caller asked for it: nothing is replaced silently).

    Example:
        >>> finite_or_sanitized(torch.tensor([1.0, 2.0]), "color", False)
        tensor([1., 2.])
    """
    return finite_or_sanitized_all({name: x}, sanitize)[0]


def finite_or_sanitized_all(named: Mapping[str, torch.Tensor | None], sanitize: bool) -> list[torch.Tensor | None]:
    """:func:`finite_or_sanitized` of several tensors (None entries pass through), returned in
    order. Without ``sanitize`` the common all-finite case costs one reduction per tensor and a
    single read back to the host for all of them (one GPU synchronisation, not one each).

    Example:
        >>> c, n = finite_or_sanitized_all({"color": torch.ones(2), "normal": None}, False)
        >>> n is None
        True
    """
    values, check = finite_or_sanitized_later(named, sanitize)
    check()
    return values


def finite_or_sanitized_later(
    named: Mapping[str, torch.Tensor | None], sanitize: bool
) -> tuple[list[torch.Tensor | None], Callable[[], None]]:
    """:func:`finite_or_sanitized_all` with the NaN/Inf test split in two: the reductions are
    launched now, the returned ``check()`` reads them back and raises :class:`NonFiniteError`.
    A filter calls ``check()`` just before it returns, so on a GPU its kernels are queued
    behind the reductions instead of waiting for the read back (the GPU idles while the host
    waits). With ``sanitize`` the tensors come back sanitized and ``check`` does nothing.

    Example:
        >>> (c,), check = finite_or_sanitized_later({"color": torch.tensor([1.0, float("nan")])}, False)
        >>> out = c * 2           # the filter's work
        >>> check()
        Traceback (most recent call last):
        ...
        torchgi.core.errors.NonFiniteError: color: expected finite values, found 1 NaN and 0 +-Inf of 2 elements (pass sanitize=True where offered to replace them)
    """
    if sanitize:
        return _sanitized(named), _nothing
    present = [(k, v) for k, v in named.items() if v is not None and v.is_floating_point() and v.numel()]
    if not present or is_recording():
        return list(named.values()), _nothing
    # One reduction per tensor decides the common case: a sum is finite iff every term is,
    # unless it overflows (|sum| > 3e38 in float32); only a non-finite sum leads to the exact
    # count. The sums are read back together where they share a device, and tested on the host
    # (one launch fewer).
    totals = [v.sum(dtype=torch.float32) if v.dtype in (torch.float16, torch.bfloat16) else v.sum()
              for _, v in present]
    if len({t.device for t in totals}) == 1:
        common = totals[0].dtype if len({t.dtype for t in totals}) == 1 else torch.float64
        stacked = torch.stack([t.to(common) for t in totals])

        def check() -> None:
            for (k, v), ok in zip(present, (math.isfinite(t) for t in stacked.tolist())):
                if not ok:
                    _count_non_finite(v, k)
    else:

        def check() -> None:
            for (k, v), t in zip(present, totals):
                if not bool(torch.isfinite(t)):
                    _count_non_finite(v, k)

    return list(named.values()), check


def _nothing() -> None:
    """The ``check`` with nothing left to check."""


_OWN_CODE = (str(Path(__file__).resolve().parents[1]), str(Path(torch.__file__).resolve().parent))


def user_stacklevel() -> int:
    """The ``stacklevel`` for :func:`warnings.warn` called by this function's caller that points
    at the first frame outside torchgi and torch: the user's line that called the filter (or
    the module), however deep the call went inside.

    Example:
        >>> user_stacklevel() >= 1
        True
    """
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(_OWN_CODE):
        frame, level = frame.f_back, level + 1
    return level


def _sanitized(named: Mapping[str, torch.Tensor | None]) -> list[torch.Tensor | None]:
    """The named tensors with NaN/Inf replaced by 0 (a warning naming each tensor that had any,
    at the user's line that called the filter)."""
    out = []
    for name, x in named.items():
        if x is not None and x.is_floating_point():
            bad = ~torch.isfinite(x)
            if is_recording():
                x = torch.where(bad, torch.zeros((), dtype=x.dtype, device=x.device), x)
            elif bool(bad.any()):
                warnings.warn(f"{name}: replaced {int(bad.sum())} non-finite values by 0 (sanitize=True)",
                              stacklevel=user_stacklevel())
                x = torch.where(bad, torch.zeros((), dtype=x.dtype, device=x.device), x)
        out.append(x)
    return out


def check_range(
    x: torch.Tensor, name: str, low: float | None = None, high: float | None = None
) -> None:
    """Raise :class:`RangeError` if any element of ``x`` lies outside ``[low, high]``.

    Example:
        >>> check_range(torch.tensor([0.0, 0.5]), "albedo", 0.0, 1.0)
    """
    if x.numel() == 0 or is_recording():
        return
    if low is not None and bool((x < low).any()):
        raise RangeError(f"{name}: expected values >= {low}, found min {float(x.min()):g}")
    if high is not None and bool((x > high).any()):
        raise RangeError(f"{name}: expected values <= {high}, found max {float(x.max()):g}")


def check_option(value: Any, name: str, options: Iterable[Any]) -> None:
    """Raise :class:`OptionError` unless ``value`` is one of ``options`` (listed).

    Example:
        >>> check_option("mean", "reduction", ("mean", "none"))
    """
    options = tuple(options)
    if value not in options:
        raise OptionError(f"{name}: expected one of {', '.join(map(repr, options))}; got {value!r}")


def check_int(value: Any, name: str, low: int = 0) -> None:
    """Raise :class:`RangeError` (a ``ValueError``) unless ``value`` is an int ``>= low``.

    Example:
        >>> check_int(3, "radius")
    """
    if not isinstance(value, int) or isinstance(value, bool) or value < low:
        raise RangeError(f"{name}: expected an int >= {low}, got {value!r}")


def require(module: str, extra: str) -> ModuleType:
    """Import an optional dependency or raise an error naming the extra to install.

    Example:
        >>> require("numpy", "core").__name__
        'numpy'
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ExtraNotInstalledError(
            f"{module} is needed here but is not installed: pip install 'torchgi[{extra}]' ({exc})"
        ) from exc
