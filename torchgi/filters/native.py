"""The old switch of the compiled kernels, kept for scripts that use it (deprecated: removed in
torchgi 0.3; use :func:`torchgi.backends.use` and :func:`torchgi.backends.status`): the kernels
now live in :mod:`torchgi.backends`, which chooses between them.

Example:
    >>> from torchgi.filters import native
    >>> with native.disabled():
    ...     native.enabled()
    False
"""

from __future__ import annotations

import contextlib
import warnings

from torchgi import backends

__all__ = ["available", "disabled", "enabled", "status"]


def disabled() -> contextlib.AbstractContextManager[None]:
    """``torchgi.backends.use("torch")``: the torch code alone inside the block (context-local).

    Example:
        >>> with disabled():
        ...     available()
        False
    """
    _deprecated("disabled", 'backends.use("torch")')
    return backends.use("torch")


def enabled() -> bool:
    """Whether the compiled back ends may run here (not inside :func:`disabled`, nor with
    ``TORCHGI_NATIVE=0``).

    Example:
        >>> enabled() in (True, False)
        True
    """
    _deprecated("enabled", 'backends.enabled(...)')
    return backends.enabled("c") or backends.enabled("triton")


def available() -> bool:
    """True when the C kernels are built and may run here.

    Example:
        >>> available() in (True, False)
        True
    """
    _deprecated("available", 'backends.status()["c"]')
    return backends.status()["c"].startswith("compiled kernels in use")


def status() -> str:
    """The C back end's line of :func:`torchgi.backends.status`.

    Example:
        >>> isinstance(status(), str)
        True
    """
    _deprecated("status", 'backends.status()["c"]')
    return backends.status()["c"]


def _deprecated(name: str, instead: str) -> None:
    warnings.warn(f"torchgi.filters.native.{name} is deprecated and will be removed in torchgi 0.3: use {instead}",
                  DeprecationWarning, stacklevel=3)
