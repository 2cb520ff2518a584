"""Guided image filter (He et al. 2010) with multi-channel guides, as used for indirect light
by Bauszat et al. 2011: per window ``w_k`` of radius ``r``

    a_k = (Σ_k + diag(ε))^-1 cov_k(I, p),   b_k = mean_k(p) - a_kᵀ mean_k(I)
    q_i = mean_{k∋i}(a_k)ᵀ I_i + mean_{k∋i}(b_k)

with every mean a count-normalised box filter (:mod:`torchgi.filters.box`), so cost does not
depend on ``r``. The per-pixel ``C x C`` solve is a closed-form LDLᵀ written with
elementwise ops (ONNX-exportable, half-safe), not ``torch.linalg.solve``.

The filter runs in the back end :mod:`torchgi.backends` picks: compiled kernels (C on the
CPU, Triton on CUDA: box sums sliding down the rows in double, the same solve) for eager
float32 calls, else the torch code (:mod:`torchgi.backends.torch_code`).

Numerics: guide and source are centred by their per-image means before any sum (the filter
is invariant to constant offsets), variances are clamped at 0, and ε is raised per pixel to
the rounding level of the variance so flat guides and ``eps=0`` stay finite and exact.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import nn

from torchgi.backends.torch_code import guided_filter
from torchgi.buffers import GBuffer
from torchgi.core.check import (
    check_floating,
    check_int,
    check_nonnegative,
    check_same_device,
    check_same_floating,
    check_shape,
    finite_or_sanitized_later,
    is_recording,
)
from torchgi.core.dtypes import compute_dtype
from torchgi.core.errors import RangeError, ShapeError
from torchgi.core.workspace import kept_buffer
from torchgi.filters.learned import register_positive

__all__ = ["Guided", "depth_scales", "guide_from", "guide_from_gbuffer", "guided"]


def _check_eps(
    eps: float | torch.Tensor, B: int, n: int, guide: torch.Tensor, dtype: torch.dtype
) -> tuple[torch.Tensor, Callable[[], None]]:
    """ε as a ``(B, n, 1, 1)`` tensor (or a ``(B, n, H, W)`` map) of ``dtype`` on ``guide``'s device,
    and the check of a tensor ε's values (finite, >= 0) to call just before the filter returns:
    its read back then waits for nothing the GPU has not done anyway. A float is checked here."""
    if isinstance(eps, torch.Tensor):
        check_same_device({"eps": eps, "guide": guide})
        check_floating(eps, "eps")
        H, W = guide.shape[-2:]
        if eps.shape in ((B, 1, H, W), (B, n, H, W)):
            e = eps.to(dtype).expand(B, n, H, W)
        elif eps.shape in ((), (n,), (B, n)):
            e = eps.to(dtype).expand(B, n).reshape(B, n, 1, 1)
        else:
            raise ShapeError(f"eps: expected a float, shape ({n},), ({B}, {n}) or a map ({B}, 1 or {n}, {H}, {W}); "
                             f"got {tuple(eps.shape)}")
        if is_recording():
            return e, lambda: None
        bad = (~torch.isfinite(eps) | (eps < 0)).any()  # one read back, later

        def check() -> None:
            if bool(bad):
                raise RangeError(f"eps: expected finite values >= 0, got {eps.flatten().tolist()[:8]}")

        return e, check
    if not isinstance(eps, (int, float)) or isinstance(eps, bool) or not eps >= 0 or eps == float("inf"):
        raise RangeError(f"eps: expected a finite float >= 0, got {eps!r}")
    return torch.full((), float(eps), dtype=dtype, device=guide.device).expand(B, n).reshape(B, n, 1, 1), lambda: None


def _guided(
    src: torch.Tensor, guide: torch.Tensor, radius: int, eps: float | torch.Tensor, sanitize: bool,
    _holder: dict | None, subsample: int = 1,
) -> torch.Tensor:
    """:func:`guided`; ``_holder`` keeps the CPU workspace between calls (see :class:`Guided`)."""
    sizes = check_shape(src, "B C H W", "src")
    check_shape(guide, "B G H W", "guide", {"B": sizes["B"], "H": sizes["H"], "W": sizes["W"]})
    check_same_device({"src": src, "guide": guide})
    check_same_floating({"src": src, "guide": guide})
    n = guide.shape[1]
    if not 1 <= n <= 4:
        raise ShapeError(f"guide: expected 1 to 4 channels, got {n} (shape {tuple(guide.shape)})")
    check_int(radius, "radius")
    check_int(subsample, "subsample", 1)
    (src, guide), check_finite_inputs = finite_or_sanitized_later({"src": src, "guide": guide}, sanitize)
    e, check_eps = _check_eps(eps, src.shape[0], n, guide, compute_dtype(src.dtype))
    out = guided_filter(src, guide, radius, e, _holder, subsample)
    check_finite_inputs()  # the values read back here: on a GPU the kernels are queued by now
    check_eps()
    return out


def guided(
    src: torch.Tensor,
    guide: torch.Tensor,
    *,
    radius: int = 24,
    eps: float | torch.Tensor = 0.01,
    subsample: int = 1,
    sanitize: bool = False,
    workspace: dict | None = None,
) -> torch.Tensor:
    """Guided image filter of ``src`` with a 1-4 channel ``guide``; cost independent of ``radius``.

    Args:
        src: ``(B, C, H, W)`` image to filter (e.g. demodulated indirect light, HDR, any range).
        guide: ``(B, G, H, W)``, ``1 <= G <= 4``, same dtype and device as ``src`` — e.g. the
            normal (xyz mapped to [0, 1]) and depth (divided by the scene extent), see
            :func:`guide_from_gbuffer`. Values in guide units; any offset is fine.
        radius: window radius ``r >= 0`` in pixels (window ``(2r+1)²``, shrinking at borders).
        eps: regulariser in guide units squared: a float, ``(G,)`` per guide channel,
            ``(B, G)``, or a per-pixel map ``(B, 1, H, W)`` (all channels) or ``(B, G, H, W)``
            (a pixel's ε enters the solve of the window centred on it; with ``subsample`` s > 1
            the map is averaged over the s x s blocks); ``>= 0``. Per pixel it is raised to at
            least ``16 · finfo.eps · E[I²]`` (the rounding level of the variance), so ``eps=0``
            and flat guides stay finite. A map runs the torch code (no compiled kernel takes one).
        subsample: ``s >= 1``; above 1, the fast guided filter (He & Sun 2015): the
            coefficients are solved on ``s x s`` means of ``src`` and ``guide`` with radius
            ``round(r / s)``, upsampled bilinearly by the factor ``s`` and applied to the
            full-resolution guide
            (about ``s²`` times less work; edges stay those of the full guide).
        sanitize: replace NaN/Inf in the inputs by 0 (with a warning) instead of raising.
        workspace: None, or a dict in which the CPU path keeps its scratch buffers between calls
            of the same size (what :class:`Guided` does); it is not read otherwise.

    Returns:
        ``(B, C, H, W)`` filtered image, dtype and device of ``src``. float16/bfloat16 inputs
        are computed in float32 and cast back. Differentiable (with respect to ``src``,
        ``guide`` and a tensor ``eps``).

    Example:
        >>> src = torch.rand(1, 3, 32, 32)
        >>> guide = torch.rand(1, 4, 32, 32)
        >>> guided(src, guide, radius=4, eps=0.01).shape
        torch.Size([1, 3, 32, 32])
        >>> from torchgi.filters import box
        >>> flat = torch.full((1, 1, 8, 8), 0.5)   # constant guide: a = 0, q = box(box(src))
        >>> torch.allclose(guided(src[..., :8, :8], flat, radius=1, eps=0.0),
        ...                box(box(src[..., :8, :8], 1), 1), atol=1e-6)
        True
    """
    return _guided(src, guide, radius, eps, sanitize, workspace, subsample)


def guide_from_gbuffer(
    gb: GBuffer, *, depth_scale: float | None = None, drop_constant: bool = True
) -> torch.Tensor:
    """The paper's guide from a GBuffer: normal xyz mapped to [0, 1] and depth / extent
    (:func:`guide_from` of ``gb.normal``, ``gb.depth`` and ``gb.hit``).

    Args:
        gb: needs ``normal``; ``depth`` is appended when present.
        depth_scale: the fixed scene-extent constant depth is divided by (scene units); by
            default the largest depth among hit pixels of the batch (all pixels without ``hit``).
        drop_constant: drop channels that are constant over the whole batch (docs/design.md, Skips): they
            carry no edges and only cost work in the solve.

    Returns:
        ``(B, G, H, W)`` guide, ``1 <= G <= 4``, dtype/device of the GBuffer. If every channel
        is constant one channel is kept (the filter then is a box mean).

    Example:
        >>> gb = GBuffer(normal=torch.zeros(1, 3, 4, 4), depth=torch.rand(1, 1, 4, 4) + 1)
        >>> guide_from_gbuffer(gb).shape   # constant normal channels are dropped
        torch.Size([1, 1, 4, 4])
    """
    if gb.normal is None:
        raise ShapeError("gb: the guide needs gb.normal (and uses gb.depth when present)")
    return guide_from(gb.normal, gb.depth, hit=gb.hit, depth_scale=depth_scale, drop_constant=drop_constant)


def guide_from(
    normal: torch.Tensor, depth: torch.Tensor | None = None, *, hit: torch.Tensor | None = None,
    depth_scale: float | str | torch.Tensor | None = None, drop_constant: bool = False,
    workspace: dict | None = None,
) -> torch.Tensor:
    """The guided filter's guide, built one way for the Denoiser, its exported form and
    :class:`~torchgi.data.FilterFeatures`: ``(normal + 1) / 2`` and ``depth / scale``.

    Args:
        normal: ``(B, 3, H, W)`` in [-1, 1].
        depth: ``(B, 1, H, W)`` or None (the guide is the normal alone).
        hit: ``(B, 1, H, W)`` bool, the pixels whose depth sets the default scale.
        depth_scale: a float (scene units); None = the largest depth on ``hit`` pixels of the
            batch (a host read); ``"image"`` = each image's own largest depth (no host read:
            traceable, and a sample's guide does not depend on its batch); a ``(B, 1, 1, 1)``
            tensor = each image's scale given (e.g. ``"image"``'s of a whole image, for its tiles:
            :func:`depth_scales`).
        drop_constant: drop channels constant over the whole batch (a host read).
        workspace: a dict in which a float32 CPU guide is kept between calls
            (:func:`~torchgi.core.workspace.kept_buffer`: no fresh pages each call; overwritten by
            the next call with it), or None: a new tensor.

    Returns:
        ``(B, G, H, W)``, ``G <= 4``, dtype/device of ``normal``.

    Example:
        >>> n = torch.zeros(2, 3, 2, 2); d = torch.tensor([1.0, 4.0]).view(2, 1, 1, 1).expand(2, 1, 2, 2)
        >>> guide_from(n, d, depth_scale="image")[:, 3, 0, 0].tolist()   # each image by its own maximum
        [1.0, 1.0]
        >>> ws = {}
        >>> guide_from(n, d, workspace=ws) is guide_from(n, d, workspace=ws)   # one buffer, written each call
        True
    """
    scale = None if depth is None else _depth_scale(depth, hit, depth_scale)
    if depth is not None and not is_recording() and normal.dtype == depth.dtype == getattr(scale, "dtype", depth.dtype) \
            and not (normal.requires_grad or depth.requires_grad or getattr(scale, "requires_grad", False)):
        # the same arithmetic written into one tensor (no copies to concatenate: fewer pages to fault in)
        B, _, H, W = normal.shape
        guide = kept_buffer(workspace, "guide_from", (B, 4, H, W), normal)
        guide = torch.empty(B, 4, H, W, dtype=normal.dtype, device=normal.device) if guide is None else guide
        torch.add(normal, 1, out=guide[:, :3]).mul_(0.5)
        torch.div(depth, scale, out=guide[:, 3:])
    else:
        guide = torch.cat([(normal + 1) * 0.5] + ([] if depth is None else [depth / scale]), 1)
    if drop_constant:
        flat = guide.flatten(2)
        varying = (flat.amax(dim=(0, 2)) > flat.amin(dim=(0, 2))).nonzero().flatten()
        keep = varying if varying.numel() else torch.zeros(1, dtype=torch.long, device=guide.device)
        guide = guide.index_select(1, keep)
    return guide


def _depth_scale(depth: torch.Tensor, hit: torch.Tensor | None,
                 depth_scale: float | str | torch.Tensor | None) -> float | torch.Tensor:
    """What :func:`guide_from` divides ``depth`` by, from its ``depth_scale`` argument."""
    if isinstance(depth_scale, torch.Tensor):
        check_shape(depth_scale, "B 1 1 1", "depth_scale", {"B": depth.shape[0]})
        return depth_scale
    if depth_scale == "image":
        return depth_scales(depth)
    if depth_scale is None:
        valid = depth if hit is None else torch.where(hit, depth, -torch.inf)
        depth_scale = float(valid.max()) if valid.numel() else 1.0
        return depth_scale if depth_scale > 0 else 1.0  # (-inf: no hit pixel)
    if isinstance(depth_scale, (str, bool)) or not 0 < depth_scale < math.inf:
        raise RangeError(f"depth_scale: expected a finite number > 0, None or 'image', got {depth_scale!r}")
    return depth_scale


def depth_scales(depth: torch.Tensor) -> torch.Tensor:
    """Each image's largest depth ``(B, 1, 1, 1)`` (at least 1e-12): :func:`guide_from`'s
    ``depth_scale="image"`` of ``depth (B, 1, H, W)``.

    Example:
        >>> depth_scales(torch.tensor([1.0, 4.0]).view(2, 1, 1, 1).expand(2, 1, 2, 2)).flatten().tolist()
        [1.0, 4.0]
    """
    return depth.amax(dim=(1, 2, 3), keepdim=True).clamp_min(1e-12)


class Guided(nn.Module):
    """Module form of :func:`guided`; ``eps`` is a buffer (or a learnable Parameter).

    On the CPU the module keeps its scratch buffers between calls of the same size, which
    saves the page faults of fresh buffers: the coefficient planes of the compiled kernel
    (``(G + 1) C`` planes of ``H x W``; 45 MB at 1024x768 with G = 4, C = 3) or, where the
    torch code runs, its workspace (about ``(G² / 2 + 2 G C + 2 C + 2 G)`` planes; 140 MB);
    ``release()`` frees them.

    Args:
        radius: window radius in pixels.
        eps: float or ``(G,)`` tensor, guide units squared.
        learnable: make ``eps`` learnable (> 0): ``self.eps`` reads it in guide units squared,
            the optimiser updates ``parametrizations.eps.original`` (``eps = softplus(original)``),
            so no step leaves the range.
        subsample: see :func:`guided`.

    Example:
        >>> f = Guided(radius=8, eps=torch.tensor([0.01, 0.01, 0.01, 0.03]))
        >>> f(torch.rand(1, 3, 16, 16), torch.rand(1, 4, 16, 16)).shape
        torch.Size([1, 3, 16, 16])
    """

    def __init__(
        self, radius: int = 24, eps: float | torch.Tensor = 0.01, learnable: bool = False, subsample: int = 1
    ) -> None:
        super().__init__()
        check_int(radius, "radius")
        check_int(subsample, "subsample", 1)
        self.radius, self.subsample = radius, subsample
        self._workspace: dict = {}
        if not isinstance(eps, torch.Tensor):  # a tensor is checked where the call reads it
            check_nonnegative(eps, "eps")
        value = torch.as_tensor(eps, dtype=torch.float32).clone()
        if learnable:
            register_positive(self, "eps", value)
        else:
            self.register_buffer("eps", value)

    def forward(self, src: torch.Tensor, guide: torch.Tensor) -> torch.Tensor:
        eps = self.eps if self.eps.dim() else self.eps.expand(guide.shape[1])
        return _guided(src, guide, self.radius, eps.to(dtype=compute_dtype(src.dtype)), False, self._workspace,
                       self.subsample)

    def release(self) -> None:
        """Free the CPU scratch buffers kept between calls."""
        self._workspace.clear()

    def extra_repr(self) -> str:
        sub = f", subsample={self.subsample}" if self.subsample > 1 else ""
        return f"radius={self.radius}, eps={self.eps.detach().tolist()}{sub}"
