"""Integrators: ``basic`` (readable, the specification) and ``path`` (fast, MIS)."""

__all__ = ["basic", "path"]
