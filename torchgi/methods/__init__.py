"""The Denoiser's methods, each a :class:`Method` of its own, and the one registry that maps their
names to them: :class:`torchgi.Denoiser`, its deployed form, the TemporalDenoiser, the CLI's
``--method`` choices and the README's method table read it. A new method is a module in this
package and one :func:`register` call (docs/architecture.md).

Example:
    >>> from torchgi import methods
    >>> methods.names()
    ('pyramid', 'blend', 'kpn', 'guided', 'atrous', 'bilateral', 'none')
    >>> methods.names(exportable=True)
    ('pyramid', 'blend', 'kpn', 'guided', 'atrous')
"""

from __future__ import annotations

from torchgi.core.check import check_option
from torchgi.methods.base import Method
from torchgi.methods.blend import Blend
from torchgi.methods.classical import ATrous, Bilateral, NoFilter
from torchgi.methods.guided import Guided
from torchgi.methods.kpn import KPNMethod
from torchgi.methods.pyramid import Pyramid

__all__ = ["Method", "get", "names", "register"]

_REGISTRY: dict[str, type[Method]] = {}


def register(method: type[Method]) -> type[Method]:
    """Add ``method`` under its ``name`` (names are unique); returns it (usable as a decorator).

    Example:
        >>> class Halve(Method):
        ...     name = "halve-example"
        ...     def filter(self, x, gb, surface, raw=None, *, workspace=None):
        ...         return x / 2, None
        >>> register(Halve) is Halve and "halve-example" in names()
        True
        >>> _ = _REGISTRY.pop("halve-example")
    """
    if not (isinstance(method, type) and issubclass(method, Method)) or not method.name:
        raise TypeError(f"method: expected a named subclass of torchgi.methods.Method, got {method!r}")
    if method.name in _REGISTRY:
        raise ValueError(f"method {method.name!r} is already registered")
    _REGISTRY[method.name] = method
    return method


def get(name: str) -> type[Method]:
    """The method registered as ``name``; a :class:`~torchgi.core.OptionError` naming ``method``
    and the known names otherwise.

    Example:
        >>> get("guided").exportable
        True
    """
    check_option(name, "method", names())
    return _REGISTRY[name]


def names(**flags: bool) -> tuple[str, ...]:
    """The registered names in registration order, those whose class attributes equal ``flags``
    (e.g. ``exportable=True``, ``learned=True``, ``temporal=True``).

    Example:
        >>> names(learned=True)
        ('pyramid', 'blend', 'kpn')
    """
    return tuple(n for n, m in _REGISTRY.items() if all(getattr(m, k) == v for k, v in flags.items()))


for _method in (Pyramid, Blend, KPNMethod, Guided, ATrous, Bilateral, NoFilter):
    register(_method)
