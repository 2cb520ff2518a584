"""Adaptive sampling (Bauszat et al. 2011): importance from the filters' geometry weights and an
exact apportionment of a fixed sample budget, wired into the renderer (``adaptive_render``), and rounds merged into one render (``merge_rounds``)."""

from torchgi.geometry import pixel_footprint, sigma_position_rule
from torchgi.sampling.adaptive import adaptive_counts, adaptive_render, geometry_importance, merge_rounds
from torchgi.sampling.allocate import allocate, exclusive_scan
from torchgi.sampling.batches import SampleBatch, accumulate, sample_batches
from torchgi.sampling.importance import importance_map

__all__ = [
    "SampleBatch",
    "accumulate",
    "adaptive_counts",
    "adaptive_render",
    "allocate",
    "exclusive_scan",
    "geometry_importance",
    "importance_map",
    "merge_rounds",
    "pixel_footprint",
    "sample_batches",
    "sigma_position_rule",
]
