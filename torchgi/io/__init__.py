"""File input/output: multi-layer OpenEXR, preview PNGs, triangle meshes (OBJ, PLY)."""

from torchgi.io.exr import AOV_ALIASES, find_aovs, read_aovs, read_exr, write_exr
from torchgi.io.mesh import read_mesh
from torchgi.io.png import to_srgb8, write_png

__all__ = ["AOV_ALIASES", "find_aovs", "read_aovs", "read_exr", "read_mesh", "to_srgb8", "write_exr", "write_png"]
