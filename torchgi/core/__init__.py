"""Validation, errors and registries shared by every torchgi module."""

from torchgi.core.check import (
    check_finite,
    check_floating,
    check_option,
    check_range,
    check_same_device,
    check_shape,
    check_tensor,
    finite_or_sanitized,
    is_tracing,
    require,
)
from torchgi.core.errors import (
    ConfigError,
    DeviceError,
    DTypeError,
    ExrError,
    ExtraNotInstalledError,
    LayerError,
    NonFiniteError,
    OptionError,
    RangeError,
    ShapeError,
    TorchGIError,
)
from torchgi.core.registry import Registry

__all__ = [
    "check_finite",
    "check_floating",
    "check_option",
    "check_range",
    "check_same_device",
    "check_shape",
    "check_tensor",
    "finite_or_sanitized",
    "is_tracing",
    "require",
    "Registry",
    "TorchGIError",
    "ShapeError",
    "DeviceError",
    "DTypeError",
    "NonFiniteError",
    "RangeError",
    "OptionError",
    "LayerError",
    "ExrError",
    "ConfigError",
    "ExtraNotInstalledError",
]
