"""GBuffer: the one type every torchgi stage passes on.

All fields are ``(B, C, H, W)`` tensors on one device. Radiance and guides share one
floating dtype; ``spp`` is an integer count and ``hit`` a boolean mask.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from torchgi.core.check import (
    check_finite,
    check_same_device,
    check_same_floating,
    check_shape,
    check_tensor,
    finite_or_sanitized,
    is_recording,
    user_stacklevel,
)
from torchgi.core.errors import DTypeError, LayerError, ShapeError

if TYPE_CHECKING:
    from torchgi.io.exr import LayerReport

__all__ = ["GBuffer"]

# field -> channel count (None: 1 or 3). Order is the order of ``GBuffer.fields``.
_CHANNELS: dict[str, int | None] = {
    "color": 3,
    "direct": 3,
    "indirect": 3,
    "emission": 3,
    "albedo": 3,
    "normal": 3,
    "position": 3,
    "depth": 1,
    "motion": 2,
    "variance": None,
    "spp": 1,
    "hit": 1,
}
_FLOAT_FIELDS = tuple(k for k in _CHANNELS if k not in ("spp", "hit"))


@dataclasses.dataclass(eq=False)
class GBuffer:
    """Radiance, noise-free guides and statistics of a batch of rendered images.

    Fields (all optional, at least one present; every present one is ``(B, C, H, W)``):
        color: ``(B,3,H,W)`` HDR radiance in [0, inf); ``emission + direct + indirect``
            (filled from those three when not given).
        direct, indirect, emission: ``(B,3,H,W)`` radiance split by light path.
        albedo: ``(B,3,H,W)`` first-hit reflectance in [0, 1]; 0 on background.
        normal: ``(B,3,H,W)`` world-space unit normal in [-1, 1]; 0 on background.
        position: ``(B,3,H,W)`` world-space first-hit position, scene units.
        depth: ``(B,1,H,W)`` distance along the camera ray, scene units; finite everywhere.
        motion: ``(B,2,H,W)`` backward screen-space motion in pixels (x right, y down): what
            pixel centre ``(x+0.5, y+0.5)`` sees was seen by the previous frame's camera at
            ``(x+0.5+m_x, y+0.5+m_y)`` (:func:`torchgi.render.render_sequence`).
        variance: ``(B,1|3,H,W)`` per-pixel variance of the colour estimate (of the mean).
        spp: ``(B,1,H,W)`` integer samples per pixel.
        hit: ``(B,1,H,W)`` bool, True where the centre ray hit geometry.

    Construction checks shapes, one device, one floating dtype for the radiance/guide
    fields and finiteness of the guides; nothing is moved or converted.

    Example:
        >>> gb = GBuffer(color=torch.rand(2, 3, 8, 8), normal=torch.zeros(2, 3, 8, 8))
        >>> gb.shape, gb.crop(0, 0, 4, 4).shape
        ((2, 8, 8), (2, 4, 4))
    """

    color: torch.Tensor | None = None
    direct: torch.Tensor | None = None
    indirect: torch.Tensor | None = None
    emission: torch.Tensor | None = None
    albedo: torch.Tensor | None = None
    normal: torch.Tensor | None = None
    position: torch.Tensor | None = None
    depth: torch.Tensor | None = None
    motion: torch.Tensor | None = None
    variance: torch.Tensor | None = None
    spp: torch.Tensor | None = None
    hit: torch.Tensor | None = None

    # -- validation ------------------------------------------------------------------------
    def __post_init__(self) -> None:
        if self.color is None and all(getattr(self, k) is not None for k in ("emission", "direct", "indirect")):
            self.color = self.emission + self.direct + self.indirect
        present = dict(self.items())
        if not present:
            raise ShapeError("GBuffer: expected at least one field, got none")
        sizes: dict[str, int] = {}
        for name, t in present.items():
            check_tensor(t, name)
            channels = _CHANNELS[name]
            if channels is None:
                check_shape(t, "B C H W", name, sizes)
                if t.shape[1] not in (1, 3):
                    raise ShapeError(f"{name}: expected 1 or 3 channels, got shape {tuple(t.shape)}")
            else:
                check_shape(t, f"B {channels} H W", name, sizes)
        check_same_floating({n: t for n, t in present.items() if n in _FLOAT_FIELDS})
        check_same_device(present)
        if self.spp is not None and (self.spp.is_floating_point() or self.spp.dtype == torch.bool):
            raise DTypeError(f"spp: expected an integer tensor, got {self.spp.dtype}")
        if self.hit is not None and self.hit.dtype != torch.bool:
            raise DTypeError(f"hit: expected a bool tensor, got {self.hit.dtype}")
        for name in ("albedo", "normal", "position", "depth", "motion"):
            if (t := getattr(self, name)) is not None:
                check_finite(t, name)

    # -- views -----------------------------------------------------------------------------
    @staticmethod
    def fields() -> tuple[str, ...]:
        """All field names, in a fixed order."""
        return tuple(_CHANNELS)

    @classmethod
    def from_inputs(cls, gb: GBuffer | None, tensors: dict[str, torch.Tensor], *, by: str) -> GBuffer:
        """The one rule for the inputs of every denoiser (``Denoiser``, ``TemporalDenoiser``): a
        GBuffer, or any GBuffer field by its name (``(B, C, H, W)`` tensors, checked as the
        GBuffer checks them); a field the method does not read is accepted and ignored.

        Raises:
            TypeError: a first argument that is not a GBuffer (a bare colour tensor: the message
                shows the call by name).
            ValueError: both a GBuffer and named tensors, or a name that is no GBuffer field
                (the message names it and ``by``).

        Example:
            >>> GBuffer.from_inputs(None, {"color": torch.zeros(1, 3, 2, 2)}, by="a denoiser").shape
            (1, 2, 2)
        """
        if gb is not None and not isinstance(gb, GBuffer):
            what = "a tensor" if isinstance(gb, torch.Tensor) else f"a {type(gb).__name__}"
            raise TypeError(f"{by}: its first argument is a GBuffer, got {what}; pass the layers by name, e.g. "
                            f"{by}()(color=color, albedo=albedo, normal=normal, depth=depth), or a GBuffer")
        if gb is not None and tensors:
            raise ValueError(f"{by}: pass a GBuffer or named tensors, not both")
        if gb is not None:
            return gb
        unknown = sorted(set(tensors) - set(cls.fields()))
        if unknown:
            raise ValueError(f"{by}: unknown input(s) {', '.join(unknown)}; known: {', '.join(cls.fields())}")
        return cls(**tensors)

    def items(self) -> Iterator[tuple[str, torch.Tensor]]:
        """``(name, tensor)`` for every present field."""
        for name in _CHANNELS:
            t = getattr(self, name)
            if t is not None:
                yield name, t

    def _first(self) -> torch.Tensor:
        return next(t for _, t in self.items())

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(B, H, W)``."""
        t = self._first()
        return (t.shape[0], t.shape[2], t.shape[3])

    @property
    def device(self) -> torch.device:
        return self._first().device

    @property
    def dtype(self) -> torch.dtype | None:
        """The floating dtype of the radiance and guide fields (None if only spp/hit)."""
        return next((t.dtype for n, t in self.items() if n in _FLOAT_FIELDS), None)

    @classmethod
    def _unchecked(cls, **fields: torch.Tensor | None) -> GBuffer:
        """A GBuffer of fields a caller has validated already (internal: no second walk over the
        data for the checks of construction)."""
        gb = object.__new__(cls)
        for name in _CHANNELS:
            setattr(gb, name, fields.pop(name, None))
        if fields:
            raise ValueError(f"unknown field(s) {', '.join(sorted(fields))}")
        return gb

    def replace(self, **changes: torch.Tensor | None) -> GBuffer:
        """A new GBuffer with some fields replaced (validated again)."""
        return dataclasses.replace(self, **changes)

    def _map(self, fn: Any) -> GBuffer:
        return GBuffer(**{name: fn(name, t) for name, t in self.items()})

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> GBuffer:
        """Move every field to ``device``; cast the floating fields (not spp/hit) to ``dtype``.

        Example:
            >>> GBuffer(color=torch.rand(1, 3, 2, 2), hit=torch.ones(1, 1, 2, 2, dtype=torch.bool)
            ...         ).to(dtype=torch.float64).hit.dtype
            torch.bool
        """
        if dtype is not None and not dtype.is_floating_point:
            raise DTypeError(f"dtype: expected a floating dtype, got {dtype}")
        return self._map(
            lambda n, t: t.to(device=device, dtype=dtype if n in _FLOAT_FIELDS else None)
        )

    def crop(self, top: int, left: int, height: int, width: int) -> GBuffer:
        """The window ``[top:top+height, left:left+width]`` of every field (a view).

        Example:
            >>> GBuffer(color=torch.rand(1, 3, 8, 8)).crop(2, 2, 3, 4).shape
            (1, 3, 4)
        """
        _, H, W = self.shape
        if not (0 <= top and 0 <= left and height > 0 and width > 0 and top + height <= H and left + width <= W):
            raise ShapeError(
                f"crop: window top={top} left={left} height={height} width={width} "
                f"does not fit in an image of {H}x{W}"
            )
        return self._map(lambda n, t: t[:, :, top : top + height, left : left + width])

    def __getitem__(self, index: int | slice) -> GBuffer:
        """Batch slicing that keeps the batch dimension: ``gb[1]`` has B = 1."""
        if isinstance(index, int):
            B = self.shape[0]
            if not -B <= index < B:
                raise IndexError(f"index {index} out of range for batch of {B}")
            index = slice(index % B, index % B + 1)
        if not isinstance(index, slice):
            raise TypeError(f"index: expected int or slice, got {type(index).__name__}")
        return self._map(lambda n, t: t[index])

    def __len__(self) -> int:
        return self.shape[0]

    @staticmethod
    def cat(buffers: Sequence[GBuffer]) -> GBuffer:
        """Concatenate along the batch; every buffer must hold the same fields.

        Example:
            >>> a = GBuffer(color=torch.rand(1, 3, 2, 2))
            >>> GBuffer.cat([a, a]).shape
            (2, 2, 2)
        """
        if not buffers:
            raise ShapeError("buffers: expected at least one GBuffer")
        names = [n for n, _ in buffers[0].items()]
        for i, b in enumerate(buffers[1:], 1):
            other = [n for n, _ in b.items()]
            if other != names:
                raise LayerError(f"buffers[{i}] has fields {other}, buffers[0] has {names}")
        return GBuffer(**{n: torch.cat([getattr(b, n) for b in buffers]) for n in names})

    # -- numpy -----------------------------------------------------------------------------
    def numpy(self, name: str, index: int = 0) -> np.ndarray:
        """Field ``name`` of image ``index`` as an ``(H, W, C)`` numpy array (a copy on CPU).

        Example:
            >>> GBuffer(color=torch.rand(1, 3, 4, 5)).numpy("color").shape
            (4, 5, 3)
        """
        t = getattr(self, name, None) if name in _CHANNELS else None
        if t is None:
            raise LayerError(f"name: {name!r} is not present; present: {[n for n, _ in self.items()]}")
        return t[index].detach().permute(1, 2, 0).cpu().numpy()

    @classmethod
    def from_numpy(cls, **arrays: np.ndarray) -> GBuffer:
        """Build from ``(H, W, C)`` or ``(B, H, W, C)`` arrays (copied; dtype kept).

        Example:
            >>> GBuffer.from_numpy(color=np.zeros((4, 5, 3), np.float32)).shape
            (1, 4, 5)
        """
        fields = {}
        for name, arr in arrays.items():
            if name not in _CHANNELS:
                raise LayerError(f"{name}: not a GBuffer field; fields: {', '.join(_CHANNELS)}")
            arr = np.asarray(arr)
            if arr.ndim == 3:
                arr = arr[None]
            if arr.ndim != 4:
                raise ShapeError(f"{name}: expected (H, W, C) or (B, H, W, C), got {arr.shape}")
            fields[name] = torch.from_numpy(np.ascontiguousarray(arr.transpose(0, 3, 1, 2)))
        return cls(**fields)

    # -- EXR -------------------------------------------------------------------------------
    def to_exr(self, path: str | os.PathLike, *, index: int | None = None, overwrite: bool = False) -> list[str]:
        """Write every field to a multi-layer EXR named by torchgi's layer names.

        A batch of one goes to ``path``; a larger batch writes one file per image with
        ``_0000``, ``_0001``... before the suffix (or only image ``index`` to ``path``).
        float16/float32 are stored as they are (other float dtypes raise: convert first),
        spp and hit as UINT. Nothing is overwritten unless ``overwrite=True``.

        Returns:
            The paths written.
        """
        from torchgi.io.exr import write_exr

        B = self.shape[0]
        if index is not None:
            return [str(write_exr(path, self._layers(index), overwrite=overwrite))]
        if B == 1:
            return [str(write_exr(path, self._layers(0), overwrite=overwrite))]
        root, ext = os.path.splitext(os.fspath(path))
        return [str(write_exr(f"{root}_{i:04d}{ext}", self._layers(i), overwrite=overwrite)) for i in range(B)]

    def _layers(self, index: int) -> dict[str, torch.Tensor]:
        return {n: t[index] for n, t in self.items()}

    @classmethod
    def from_exr(
        cls, path: str | os.PathLike, *, required: Sequence[str] = ("color",), sanitize: bool = False,
        motion_convention: str | None = None, return_report: bool = False,
    ) -> GBuffer | tuple[GBuffer, LayerReport]:
        """Read a GBuffer (B = 1) from an EXR of torchgi, Blender/Cycles, Mitsuba 3 or Arnold.

        Layer names are mapped with :func:`torchgi.io.match_aovs`. UINT spp comes back as
        int64, hit as bool (a file without an ``spp`` layer gives ``spp=None``: the Denoiser then
        takes 1 sample per pixel unless told, ``Denoiser()(gb, spp=...)``). Half and float layers
        are not mixed: if the file holds both, the error says so (convert the file, or read
        layers with :func:`torchgi.io.read_exr`). A layer of a name torchgi does not know is
        not read: a warning names it (the accepted names: :data:`torchgi.io.AOV_ALIASES`),
        unless ``return_report`` hands the report back.

        Args:
            sanitize: replace NaN/Inf in any float layer by 0 (with a warning giving the
                count) instead of raising.
            motion_convention: the motion layer's convention (``"torchgi"``, ``"cycles"``,
                ``"arnold"``); None = its layer name's (:func:`torchgi.io.find_aovs`).
            return_report: also return the :class:`~torchgi.io.LayerReport`: which layer each
                field was read from, which layers and channels were left.

        Example:
            >>> import tempfile, os
            >>> p = os.path.join(tempfile.mkdtemp(), "g.exr")
            >>> from torchgi.io import write_exr
            >>> _ = write_exr(p, {"": torch.rand(3, 4, 4), "dd.y": torch.rand(1, 4, 4), "uv": torch.rand(2, 4, 4)})
            >>> gb, report = GBuffer.from_exr(p, return_report=True)
            >>> gb.depth.shape, report.used, report.unknown
            (torch.Size([1, 1, 4, 4]), {'color': '', 'depth': 'dd.y'}, ('uv',))
        """
        from torchgi.io.exr import match_aovs, read_exr

        aovs, report = match_aovs(read_exr(path), required=required, source=str(path),
                                  motion_convention=motion_convention)
        if report.unknown and not return_report:
            warnings.warn(f"{path}: layer(s) {', '.join(map(repr, report.unknown))} not read: not a name torchgi "
                          "knows (torchgi.io.AOV_ALIASES lists them; GBuffer.from_exr(..., return_report=True) "
                          "tells what was read from which layer)", stacklevel=user_stacklevel())
        fields: dict[str, torch.Tensor] = {}
        for name, t in aovs.items():
            if name == "hit":
                t = t != 0
            elif name == "spp":
                t = t.to(torch.int64) if not t.is_floating_point() else t.round().to(torch.int64)
            else:
                t = finite_or_sanitized(t, f"{path}: layer {name}", sanitize)
            fields[name] = t[None]
        return (cls(**fields), report) if return_report else cls(**fields)

    def __repr__(self) -> str:
        parts = ", ".join(f"{n}={tuple(t.shape[1:2])}" for n, t in self.items())
        B, H, W = self.shape
        return f"GBuffer(B={B}, H={H}, W={W}, dtype={self.dtype}, device={self.device}, fields: {parts})"


def _with_samples(gb: GBuffer, spp: Any, by: str) -> GBuffer:
    """``gb`` with ``spp`` samples per pixel in every pixel: the sample count of a render that did
    not record one (an int or float >= 1: a whole count is the int64 plane ``gb.replace(spp=...)``
    gives, bit for bit; another, the mean of an adaptive render, a float32 plane the Denoiser
    reads as that count). Refused by name: bool, NaN, Inf, below 1, and a count other than
    the one ``gb.spp`` records."""
    if isinstance(spp, bool) or not isinstance(spp, (int, float)) or not 1 <= spp < math.inf:
        raise ValueError(f"spp: expected the render's samples per pixel, a finite int or float >= 1, got {spp!r}")
    if gb.spp is not None:
        if gb.spp.numel() and bool((gb.spp == spp).all()):
            return gb
        raise ValueError(f"spp: {by} was given spp={spp!r} and the input's own sample counts (gb.spp, mean "
                         f"{float(gb.spp.float().mean()):.4g}); give one of them")
    B, H, W = gb.shape
    if float(spp).is_integer():
        return gb.replace(spp=torch.full((B, 1, H, W), int(spp), dtype=torch.int64, device=gb.device))
    return GBuffer._unchecked(**dict(gb.items()), spp=torch.full((B, 1, H, W), float(spp), device=gb.device))


def require_guides(gb: GBuffer, method: str, needs: Sequence[str]) -> None:
    """Refuse by name an input without albedo or normal (every method filtering needs both) or
    without a guide layer that ``method`` needs (never a crash or a silently worse result)."""
    missing = [name for name in ("albedo", "normal") if getattr(gb, name) is None]
    if missing:
        raise ShapeError(f"{' and '.join(missing)}: required by every method but 'none' (this input has no "
                         f"{' and no '.join(missing)} layer)")
    why = {"depth": "the guide its network was trained with (distance along the camera ray)",
           "position": "its edge-stopping weight between world-space positions"}
    how = {"depth": "Mitsuba 'dd.y:depth', Blender's Denoising Depth or Z pass",
           "position": "Mitsuba 'pos:position', Blender's Position pass"}
    for name in needs:
        if getattr(gb, name) is None:
            raise LayerError(f"method {method!r} needs a {name} layer (GBuffer.{name}): {why[name]}; this input has "
                             f"none: render it with torchgi, write a {name} AOV ({how[name]}), or use the method "
                             "'guided' (it uses depth when given)")


INDEPENDENT = -2 / 3  # the lag-1 correlation of second differences of independent pixel noise
CORRELATED = -0.55  # above this, neighbouring pixels' noise is taken as correlated (a wide pixel filter)


def pixel_noise_correlation(gb: GBuffer, *, pixels: int = 32768, min_pairs: int = 1000) -> float | None:
    """How correlated the noise of neighbouring pixels is: the lag-1 correlation of the second
    differences ``y[i-1] - 2 y[i] + y[i+1]`` of the demodulated colour's mean ``y`` (colour over
    albedo) along rows and along columns spread evenly over the image (about ``pixels`` pixels
    each way, at least 16 lines), over runs of 4 surface pixels whose guides (albedo, normal, log depth) differ by less than 0.02, from the sign of
    each product (robust to edges and fireflies: ``-sin(π (P(<0) - 1/2))``, zero products left
    out). Independent pixels give -2/3 (:data:`INDEPENDENT`) whatever the noise level; a pixel
    filter wider than a pixel (Mitsuba 3's default "gaussian") raises it towards 0. None where
    fewer than ``min_pairs`` pairs count. Unitless; reads ``(B, C, H, W)`` colour, albedo,
    normal and, where present, depth and emission (emitters are left out).

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> gb = GBuffer(color=torch.rand(1, 3, 64, 64, generator=g), albedo=torch.ones(1, 3, 64, 64),
        ...              normal=torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(1, 3, 64, 64))
        >>> round(pixel_noise_correlation(gb), 1)
        -0.7
    """
    negative = counted = 0
    for dim in (3, 2):  # runs along rows (a sample of rows), then along columns
        across = 2 if dim == 3 else 3
        size, length = gb.color.shape[across], gb.color.shape[dim]
        lines = min(size, max(16, pixels // max(length, 1)))
        pick = torch.linspace(0, size - 1, lines, device=gb.color.device).round().long().unique()
        a = gb.albedo.index_select(across, pick).float()
        y = (gb.color.index_select(across, pick).float() / a.clamp_min(0.02)).mean(1, keepdim=True)
        surface = a.amax(1, keepdim=True) > 0.02
        if gb.emission is not None:
            surface &= gb.emission.index_select(across, pick).amax(1, keepdim=True) <= 0
        guides = [a, gb.normal.index_select(across, pick).float()]
        if gb.depth is not None:
            guides.append(gb.depth.index_select(across, pick).float().clamp_min(1e-30).log())
        g = torch.cat(guides, 1)
        n = y.shape[dim]
        if n < 4:
            continue

        def run(t: torch.Tensor, i: int, dim: int = dim, n: int = n) -> torch.Tensor:
            return t.narrow(dim, i, n - 3)

        keep = run(surface, 0) & run(surface, 1) & run(surface, 2) & run(surface, 3)
        for i in range(3):
            keep &= (run(g, i) - run(g, i + 1)).abs().amax(1, keepdim=True) < 0.02
        h0 = run(y, 0) - 2 * run(y, 1) + run(y, 2)
        h1 = run(y, 1) - 2 * run(y, 2) + run(y, 3)
        product = (h0 * h1)[keep]
        product = product[product.isfinite()]  # (a NaN / Inf pixel: refused or sanitized by the Denoiser)
        negative += int((product < 0).sum())
        counted += int((product != 0).sum())
    if counted < min_pairs:
        return None
    return -math.sin(math.pi * (negative / counted - 0.5))


def _warn_if_correlated(gb: GBuffer) -> None:
    """Warn where :func:`pixel_noise_correlation` says the render's pixel filter spread each
    sample over several pixels: the Denoiser reads such noise as detail and keeps it."""
    if is_recording() or gb.color.shape[-1] < 8 or gb.color.shape[-2] < 8:
        return
    rho = pixel_noise_correlation(gb)
    if rho is not None and rho > CORRELATED:
        warnings.warn(f"color: neighbouring pixels' noise is correlated (second-difference correlation {rho:.2f}; "
                      f"independent pixels give {INDEPENDENT:.2f}): the renderer's pixel filter spreads each sample "
                      "over several pixels, and the Denoiser keeps such noise as detail. Render with a box pixel "
                      "filter: Mitsuba 3 'rfilter': {'type': 'box'} (its default is 'gaussian'); Blender Cycles "
                      "Film > Pixel Filter: Box (width 1 px); Arnold: box_filter, width 1",
                      stacklevel=user_stacklevel())


def _warn_of_the_colour(gb: GBuffer) -> None:
    """The Denoiser's warnings about a colour it filtered as given: negative values, correlated
    noise (with the albedo and normal it needs)."""
    if gb.color is None:
        return
    _warn_if_negative(gb.color)
    if gb.albedo is not None and gb.normal is not None:
        _warn_if_correlated(gb)


def _warn_if_negative(color: torch.Tensor) -> None:
    """Warn, with their count and the least, where ``color (B, 3, H, W)`` has values below 0:
    radiance is not negative, so they come from a renderer's negative-lobe pixel filter or an
    earlier subtraction, and are filtered as given (never clamped here)."""
    if is_recording() or color.numel() == 0:
        return
    negative = color < 0
    if bool(negative.any()):
        warnings.warn(f"color: {int(negative.sum())} of {color.numel()} values are negative (least "
                      f"{float(color.min()):.4g}); radiance is >= 0: a renderer's negative-lobe pixel filter (use "
                      "a box filter) or an earlier subtraction makes them; they are filtered as given",
                      stacklevel=user_stacklevel())


def _warn_if_colour_normals(normal: torch.Tensor) -> None:
    """Warn where ``normal (B, 3, H, W)`` looks like a normal map stored as a colour (``(n + 1) / 2``,
    in [0, 1]): no component below 0 and most non-zero normals off unit length. Signed unit
    normals have components below 0 in all but the rarest views, so the common call reads only
    every 4th row and column."""
    if is_recording() or normal.numel() == 0 or bool((normal[..., ::4, ::4] < 0).any()) or bool((normal < 0).any()):
        return
    sq = normal.float().square().sum(1)
    covered = sq > 0
    off = ((sq - 1).abs() > 0.2) & covered
    if bool(covered.any()) and 2 * int(off.sum()) > int(covered.sum()):
        warnings.warn("normal: no component is below 0 and most normals are not of unit length: this looks like a "
                      "normal map stored as a colour, in [0, 1]; GBuffer.normal is world-space unit normals, each "
                      "component in [-1, 1] (for a map stored as (n + 1) / 2, pass 2 * normal - 1)", stacklevel=user_stacklevel())


def _noise_free(gb: GBuffer) -> bool:
    """The colour carries no noise to filter (docs/design.md, Skips): a measured variance of 0 everywhere,
    from at least 2 samples in every pixel (with 1 sample the variance is unknown, stored as 0)."""
    if gb.variance is None or gb.spp is None:
        return False
    return int(gb.spp.min()) >= 2 and not bool(gb.variance.any())


def mean_spp(spp: torch.Tensor, where: torch.Tensor | None = None) -> float:
    """The mean of a ``(B,1,H,W)`` sample-count plane (0 for an empty one); with ``where`` ``(B,1,H,W)``
    bool, over those pixels (the surfaces a Denoiser filters: an adaptive render's background has
    few samples and no noise), or over all where none is True."""
    if where is not None and bool(where.any()):
        return float(torch.where(where, spp, 0).sum()) / int(where.sum())
    return float(spp.sum()) / max(spp.numel(), 1)
