"""Registries that let configs say ``{type: name, ...}``.

A registry maps a name to a constructor (a class or a function); ``build`` resolves a config
dict through it to the same constructors the Python API uses.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Generic, TypeVar

from torchgi.core.errors import ConfigError

__all__ = ["Registry"]

T = TypeVar("T")


class Registry(Generic[T]):
    """A named table of constructors.

    Example:
        >>> filters = Registry("filter")
        >>> @filters.register("scale")
        ... def make_scale(factor: float = 1.0):
        ...     return lambda x: x * factor
        >>> filters.build({"type": "scale", "factor": 2.0})(3.0)
        6.0
        >>> filters.names()
        ['scale']
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._table: dict[str, Callable[..., T]] = {}

    def register(self, name: str) -> Callable[[Callable[..., T]], Callable[..., T]]:
        """Decorator that adds a constructor under ``name`` (names are unique)."""

        def add(fn: Callable[..., T]) -> Callable[..., T]:
            if name in self._table:
                raise ValueError(f"{self.kind} {name!r} is already registered")
            self._table[name] = fn
            return fn

        return add

    def names(self) -> list[str]:
        """The registered names, sorted."""
        return sorted(self._table)

    def get(self, name: str) -> Callable[..., T]:
        """The constructor for ``name``; :class:`ConfigError` listing the known names otherwise."""
        try:
            return self._table[name]
        except KeyError:
            raise ConfigError(
                f"unknown {self.kind} type {name!r}; known: {', '.join(self.names()) or '(none)'}"
            ) from None

    def build(self, config: Mapping[str, Any], **overrides: Any) -> T:
        """Construct from ``{type: name, **kwargs}``; ``overrides`` win over the config."""
        if not isinstance(config, Mapping) or "type" not in config:
            raise ConfigError(f"{self.kind} config: expected a mapping with a 'type' key, got {config!r}")
        kwargs = {k: v for k, v in config.items() if k != "type"}
        kwargs.update(overrides)
        fn = self.get(config["type"])
        try:
            return fn(**kwargs)
        except TypeError as exc:
            raise ConfigError(f"{self.kind} {config['type']!r}: {exc}") from exc
