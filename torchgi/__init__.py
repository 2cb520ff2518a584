"""torchgi: fast, accurate denoising of Monte Carlo path-traced images in PyTorch.

The top level stays tiny; everything else lives in subpackages (``torchgi.core``,
``torchgi.io``, ``torchgi.metrics``, ``torchgi.render``).
"""

from torchgi.buffers import GBuffer

__version__ = "0.1.0"

__all__ = ["GBuffer", "__version__"]
