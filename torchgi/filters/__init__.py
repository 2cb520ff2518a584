"""Filters: pure torch, function + Module pairs, differentiable, ONNX-exportable."""

from torchgi.filters.box import Box, box
from torchgi.filters.guided import Guided, guide_from_gbuffer, guided

__all__ = ["box", "Box", "guided", "Guided", "guide_from_gbuffer"]
