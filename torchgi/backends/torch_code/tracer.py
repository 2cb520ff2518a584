"""The torch code of the tracer ops: the renderer's own torch wavefronts, handed in by the
renderer in each op's :class:`~torchgi.backends.base.TraceSetup` (the back ends sit below the
renderer and never import it)."""

from __future__ import annotations

import torch

from torchgi.backends.base import (
    GuideRaysOp,
    PathOp,
)


def path(desc: PathOp) -> tuple:
    """A tile of the renderer's "path" integrator by its torch wavefronts
    (``desc.setup.wavefronts``: :func:`torchgi.render.integrators.path.radiance`, chunk by chunk
    into a film): the reference the compiled tracer must match in expectation.

    Example:
        >>> from torchgi.render import scenes
        >>> from torchgi.render.tiles import path_op
        >>> import numpy as np
        >>> s = scenes.cornell(4)
        >>> mean, var = path(path_op(s.arrays(), s.camera, np.full(16, 2), bounces=1, seed=0))
        >>> mean.shape, var.shape
        ((9, 16), (3, 16))
    """
    return desc.setup.wavefronts(desc)


def guide_rays(desc: GuideRaysOp) -> dict[str, torch.Tensor]:
    """The guides of the pixel centres by the renderer's torch code (``desc.setup.wavefronts``:
    embreex and :func:`torchgi.render.integrators.common.guides`, ``chunk_size`` rays at a time).

    Example:
        >>> from torchgi.render import scenes
        >>> from torchgi.render.tiles import guide_rays_op
        >>> s = scenes.cornell(4)
        >>> guide_rays(guide_rays_op(s.arrays(), s.camera))["normal"].shape
        torch.Size([3, 16])
    """
    return desc.setup.wavefronts(desc)
