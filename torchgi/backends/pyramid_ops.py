"""The learned pyramid's ops at the back-end seam (:func:`torchgi.filters.pyramid`): the
candidates' coefficients mixed at half resolution (:class:`MixHalfOp`), the model and residual at
full resolution (:class:`ModelResidualOp`), the finest band (:class:`FineBandOp`), the block means
of its levels (:class:`BlockMeanOp`) and of its finer candidates' views (:class:`AppliedMeansOp`).
Re-exported by :mod:`torchgi.backends.base`."""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["AppliedMeansOp", "BlockMeanOp", "FineBandOp", "MixHalfOp", "ModelResidualOp"]


@dataclass(eq=False, slots=True)
class MixHalfOp:
    """The learned pyramid's coefficients mixed at half resolution
    (:func:`torchgi.filters.pyramid.pyramid_mix`): ``up(coarse) + Σ_j up(weights_j) fines_j`` with
    ``coarse (B,n+1,C,h4,w4)`` the coarser candidates' mix at 1/4, ``weights (B,k,h4,w4)`` the
    ``fines`` (1 to 4 ``(B,n+1,C,h,w)`` coefficients of the scale-2 candidates) at 1/4, ``h =
    2 h4`` or ``2 h4 - 1`` and ``up`` the bilinear x2 step cropped to ``h x w``. One float dtype
    and device. Returns ``(B,n+1,C,h,w)`` (in ``out`` as :class:`GuidedOp`'s)."""

    coarse: torch.Tensor
    weights: torch.Tensor
    fines: tuple[torch.Tensor, ...]
    out: torch.Tensor | None = None

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.coarse, self.weights, *self.fines)


@dataclass(eq=False, slots=True)
class ModelResidualOp:
    """The learned pyramid's model and residual at full resolution
    (:func:`torchgi.filters.pyramid.pyramid_mix`): ``model (B,C,H,W)`` plus ``Σ_j up(weights_j)
    ys_j`` (``ys``: 1 to 4 ``(B,C,H,W)`` outputs of its scale-1 candidates, ``weights (B,n,h,w)``
    theirs at half resolution, ``h = ⌈H/2⌉``, ``up`` the bilinear x2 step), the residual ``x -
    model`` and its 2 x 2 means ``(B,C,h,w)``. One float dtype and device. ``inplace``: the model
    may be written into ``model`` (the caller does not read it again). Returns ``(model,
    residual, means)``, the residual in ``out`` as :class:`GuidedOp`'s result."""

    model: torch.Tensor
    ys: tuple[torch.Tensor, ...]
    weights: torch.Tensor
    x: torch.Tensor
    inplace: bool = False
    out: torch.Tensor | None = None

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.model, *self.ys, self.weights, self.x)


@dataclass(eq=False, slots=True)
class FineBandOp:
    """The learned pyramid's output from its finest band: ``model + (up(band) + up(gain) (residual
    - up(means)))`` with ``model``, ``residual (B,C,H,W)`` and ``means (B,C,h,w)`` from
    :class:`ModelResidualOp`, ``band (B,C,h,w)`` the coarser bands given back so far and ``gain
    (B,1,h,w)`` the finest band's gain, both at half resolution. Returns ``(B,C,H,W)``."""

    model: torch.Tensor
    residual: torch.Tensor
    means: torch.Tensor
    band: torch.Tensor
    gain: torch.Tensor

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.model, self.residual, self.means, self.band, self.gain)


@dataclass(eq=False, slots=True)
class AppliedMeansOp:
    """The ``s x s`` block means (as :class:`BlockMeanOp`'s) of linear models ``coeffs
    (B,n+1,C,H,W)`` (``a_0..a_{n-1}, b``) applied to the centred ``guide (B,n,H,W)``: ``b + Σ_i
    a_i guide_i`` brought to ``(B,C,⌈H/s⌉,⌈W/s⌉)`` (the learned pyramid's views of its finer
    candidates). One float dtype and device."""

    coeffs: torch.Tensor
    guide: torch.Tensor
    s: int

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.coeffs, self.guide)


@dataclass(eq=False, slots=True)
class BlockMeanOp:
    """The means of the ``s x s`` blocks of ``x (B,C,H,W)``: ``(B,C,⌈H/s⌉,⌈W/s⌉)``, a last
    partial block averaged over the pixels it has (the learned pyramid's levels and views)."""

    x: torch.Tensor
    s: int

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        return (self.x,)
