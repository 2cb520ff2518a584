"""The torchgi error family.

Every error a user can trigger subclasses a builtin (``ValueError``, ``TypeError`` or
``ImportError``) so callers catch them the usual way, and :class:`TorchGIError` so they can
catch all of torchgi's at once.
"""

from __future__ import annotations

__all__ = [
    "ConfigError",
    "DTypeError",
    "DeviceError",
    "ExrError",
    "ExtraNotInstalledError",
    "LayerError",
    "NonFiniteError",
    "OptionError",
    "RangeError",
    "ShapeError",
    "TorchGIError",
]


class TorchGIError(Exception):
    """Base class of every error torchgi raises on purpose."""


class ShapeError(TorchGIError, ValueError):
    """A tensor has the wrong number of dimensions or the wrong size."""


class DeviceError(TorchGIError, ValueError):
    """Tensors that must share a device do not."""


class DTypeError(TorchGIError, TypeError):
    """A tensor has a dtype the function does not accept."""


class NonFiniteError(TorchGIError, ValueError):
    """A tensor holds NaN or +-Inf where only finite values are allowed."""


class RangeError(TorchGIError, ValueError):
    """A value lies outside its documented range."""


class OptionError(TorchGIError, ValueError):
    """A string option is not one of the known choices."""


class LayerError(TorchGIError, ValueError):
    """A required image layer (AOV) is missing from a file or a mapping."""


class ExrError(TorchGIError, ValueError):
    """A file is not a readable OpenEXR image."""


class ConfigError(TorchGIError, ValueError):
    """A configuration (YAML or dict) is malformed."""


class ExtraNotInstalledError(TorchGIError, ImportError):
    """An optional dependency is missing; the message names the extra to install."""
