"""Motion-vector conventions of the renderers whose EXR files torchgi reads.

torchgi's convention (``GBuffer.motion``): backward, in pixels, x right, y down (the image's
rows as stored, top first): what pixel centre ``(x+0.5, y+0.5)`` sees was seen by the previous
frame's camera at ``(x+0.5+m_x, y+0.5+m_y)``. The other conventions differ from it by the sign
of each axis; docs/temporal.md cites where each one is defined:

- ``"cycles"`` (Blender/Cycles' ``Vector`` pass, its X, Y): ``previous - current`` raster position
  (Cycles' ``primitive_motion_vector``: ``motion_pre - motion_center``), in Cycles' raster space,
  whose y axis points up (``screentondc`` starts at the view plane's bottom), while the file's
  rows run top down: ``m = (X, -Y)``.
- ``"arnold"`` (Arnold's ``motionvector`` AOV, its R, G: "screen space motion vector"): read as the
  displacement in pixels from the shutter's open to its close, forward in time, y up (the
  reading, not a quoted formula: docs/temporal.md): ``m = (-R, G)``. Forward and
  backward displacements are each other's negatives for motion at a constant speed over the
  frame (the shutter spanning one frame); for other shutters or accelerating motion this is a
  first-order reading.
- ``"torchgi"``: as stored.
"""

from __future__ import annotations

import torch

from torchgi.core.check import check_option

__all__ = ["MOTION_CONVENTIONS", "MOTION_LAYER_CONVENTIONS", "from_torchgi_motion", "motion_convention_of",
           "to_torchgi_motion"]

# convention -> the signs that turn its (first, second) components into torchgi's (m_x, m_y)
MOTION_CONVENTIONS: dict[str, tuple[float, float]] = {
    "torchgi": (1.0, 1.0),
    "cycles": (1.0, -1.0),
    "arnold": (-1.0, 1.0),
}

# motion layer name (lower case, without a view-layer prefix; find_aovs' aliases) -> its convention
MOTION_LAYER_CONVENTIONS: dict[str, str] = {
    "motion": "torchgi", "mv": "torchgi", "vector": "cycles", "motionvector": "arnold", "motion_vector": "arnold",
}


def motion_convention_of(layer: str) -> str:
    """The convention a motion layer of this name is written in (its renderer's).

    Args:
        layer: the EXR layer name, with or without a view-layer prefix (``"ViewLayer.Vector"``).

    Raises:
        ValueError: a name that is not one of :data:`MOTION_LAYER_CONVENTIONS` (name the
            convention explicitly).

    Example:
        >>> motion_convention_of("ViewLayer.Vector"), motion_convention_of("motionvector")
        ('cycles', 'arnold')
    """
    low = layer.lower()
    for form in (low, low.split(".", 1)[-1]):
        if form in MOTION_LAYER_CONVENTIONS:
            return MOTION_LAYER_CONVENTIONS[form]
    raise ValueError(f"layer {layer!r}: no known motion convention; name one of {', '.join(MOTION_CONVENTIONS)}")


def _signs(motion: torch.Tensor, convention: str) -> torch.Tensor:
    check_option(convention, "convention", tuple(MOTION_CONVENTIONS))
    if motion.ndim < 3 or motion.shape[-3] != 2:
        raise ValueError(f"motion: expected shape (2, H, W) or (B, 2, H, W), got {tuple(motion.shape)}")
    if not motion.is_floating_point():
        raise TypeError(f"motion: expected a floating dtype, got {motion.dtype}")
    return torch.tensor(MOTION_CONVENTIONS[convention], dtype=motion.dtype, device=motion.device).view(2, 1, 1)


def to_torchgi_motion(motion: torch.Tensor, convention: str) -> torch.Tensor:
    """A motion layer in ``convention`` as torchgi's backward, y-down motion (exact sign flips).

    Args:
        motion: ``(2, H, W)`` or ``(B, 2, H, W)`` float, pixels, the layer's first two components.
        convention: one of :data:`MOTION_CONVENTIONS`.

    Returns:
        The same shape, dtype and device, in torchgi's convention (module docstring).

    Example:
        >>> to_torchgi_motion(torch.tensor([[[1.0]], [[2.0]]]), "cycles").flatten().tolist()
        [1.0, -2.0]
    """
    return motion * _signs(motion, convention)


def from_torchgi_motion(motion: torch.Tensor, convention: str) -> torch.Tensor:
    """torchgi's motion ``(2, H, W)`` or ``(B, 2, H, W)`` written in ``convention`` (the inverse of
    :func:`to_torchgi_motion`; each convention's signs are their own inverse).

    Example:
        >>> from_torchgi_motion(torch.tensor([[[1.0]], [[2.0]]]), "arnold").flatten().tolist()
        [-1.0, 2.0]
    """
    return to_torchgi_motion(motion, convention)
