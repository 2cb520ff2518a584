"""torchgi: fast, accurate denoising of Monte Carlo path-traced images in PyTorch.

The top level stays tiny: ``GBuffer``, ``Denoiser``, ``TemporalDenoiser``, ``render`` (a callable
package: ``torchgi.render(scene, spp, bounces, seed)``), ``render_sequence``, ``render_to``, ``load_scene`` and
``scenes``; everything else lives in subpackages (``torchgi.core``, ``torchgi.io``,
``torchgi.metrics``, ``torchgi.filters``, ``torchgi.sampling``, ``torchgi.temporal``).
"""

from torchgi import render
from torchgi.buffers import GBuffer
from torchgi.denoise import Denoiser
from torchgi.progressive import render_to
from torchgi.render import load_scene, render_sequence, scenes
from torchgi.temporal import TemporalDenoiser

__version__ = "0.1.0"

__all__ = [
    "Denoiser", "GBuffer", "TemporalDenoiser", "__version__", "load_scene", "render", "render_sequence", "render_to", "scenes",
]
