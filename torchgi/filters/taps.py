"""The dilated 5x5 neighbourhood, now :mod:`torchgi.core.taps` (the back ends use it too); kept here
for code that imports it from its old place (deprecated: removed in torchgi 0.3).

Example:
    >>> from torchgi.filters.taps import kernel_5x5
    >>> len(kernel_5x5())
    25
"""

import warnings

from torchgi.core.taps import B3_SPLINE, Padded, kernel_5x5

warnings.warn("torchgi.filters.taps is deprecated and will be removed in torchgi 0.3: import from torchgi.core.taps",
              DeprecationWarning, stacklevel=2)

__all__ = ["B3_SPLINE", "Padded", "kernel_5x5"]
