"""The dilated 5x5 neighbourhood, now :mod:`torchgi.core.taps` (the back ends use it too); kept here
for code that imports it from its old place.

Example:
    >>> from torchgi.filters.taps import kernel_5x5
    >>> len(kernel_5x5())
    25
"""

from torchgi.core.taps import B3_SPLINE, Padded, kernel_5x5

__all__ = ["B3_SPLINE", "Padded", "kernel_5x5"]
