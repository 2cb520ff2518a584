"""Rendering. For now: Mitsuba 3 reference renders as GBuffers (``torchgi.render.mitsuba``)."""

__all__: list[str] = []
