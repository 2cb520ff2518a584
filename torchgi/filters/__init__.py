"""Filters: pure torch, function + Module pairs, differentiable, ONNX-exportable."""

from torchgi.filters.atrous import ATrous, atrous
from torchgi.filters.bilateral import CrossBilateral, cross_bilateral
from torchgi.filters.blend import Blend, blend
from torchgi.filters.box import Box, box
from torchgi.filters.guided import Guided, guide_from, guide_from_gbuffer, guided
from torchgi.filters.kernels import ApplyKernels, apply_kernels
from torchgi.filters.pyramid import Pyramid, pyramid

__all__ = ["ATrous", "ApplyKernels", "Blend", "Box", "CrossBilateral", "Guided", "Pyramid", "apply_kernels", "atrous", "blend", "box", "cross_bilateral",
           "guide_from", "guide_from_gbuffer", "guided", "pyramid"]
