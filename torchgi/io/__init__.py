"""File input/output: multi-layer OpenEXR, motion-layer conventions, frame sequences, preview PNGs,
triangle meshes (OBJ, PLY)."""

from torchgi.io.exr import AOV_ALIASES, LayerReport, find_aovs, match_aovs, read_aovs, read_exr, write_exr
from torchgi.io.mesh import read_mesh
from torchgi.io.motion import MOTION_CONVENTIONS, from_torchgi_motion, to_torchgi_motion
from torchgi.io.png import to_srgb8, write_png
from torchgi.io.sequence import frame_paths

__all__ = ["AOV_ALIASES", "MOTION_CONVENTIONS", "LayerReport", "find_aovs", "frame_paths", "from_torchgi_motion",
           "match_aovs", "read_aovs", "read_exr", "read_mesh", "to_srgb8", "to_torchgi_motion", "write_exr",
           "write_png"]
