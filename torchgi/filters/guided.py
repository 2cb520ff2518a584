"""Guided image filter (He et al. 2010) with multi-channel guides, as used for indirect light
by Bauszat et al. 2011: per window ``w_k`` of radius ``r``

    a_k = (Σ_k + diag(ε))^-1 cov_k(I, p),   b_k = mean_k(p) - a_kᵀ mean_k(I)
    q_i = mean_{k∋i}(a_k)ᵀ I_i + mean_{k∋i}(b_k)

with every mean a count-normalised box filter (:mod:`torchgi.filters.box`), so cost does not
depend on ``r``. The per-pixel ``C x C`` solve is a closed-form LDLᵀ written with
elementwise ops (ONNX-exportable, half-safe), not ``torch.linalg.solve``.

Where it applies the whole filter runs in compiled kernels — C on the CPU
(:mod:`torchgi.filters.native`), Triton on CUDA (:mod:`torchgi.filters.gpu`): box sums
sliding down the rows in double, the same solve — else in the torch code below.

Numerics: guide and source are centred by their per-image means before any sum (the filter
is invariant to constant offsets), variances are clamped at 0, and ε is raised per pixel to
the rounding level of the variance so flat guides and ``eps=0`` stay finite and exact.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from torchgi.buffers import GBuffer
from torchgi.core.check import (
    check_floating,
    check_int,
    check_same_device,
    check_same_floating,
    check_shape,
    finite_or_sanitized_later,
    is_recording,
)
from torchgi.core.errors import RangeError, ShapeError
from torchgi.filters import gpu, native
from torchgi.filters.box import PlaneBoxer, _box_cumsum, compute_dtype, use_fast_path

__all__ = ["Guided", "guide_from_gbuffer", "guided"]


def _pairs(n: int) -> list[tuple[int, int]]:
    """Lower-triangle index pairs ``(i, j), j <= i`` of an ``n x n`` symmetric matrix."""
    return [(i, j) for i in range(n) for j in range(i + 1)]


def _check_eps(
    eps: float | torch.Tensor, B: int, n: int, guide: torch.Tensor, dtype: torch.dtype
) -> tuple[torch.Tensor, Callable[[], None]]:
    """ε as a ``(B, n, 1, 1)`` tensor of ``dtype`` on ``guide``'s device, and the check of a tensor ε's
    values (finite, >= 0) to call just before the filter returns: its read back then waits for
    nothing the GPU has not done anyway. A float is checked here."""
    if isinstance(eps, torch.Tensor):
        check_same_device({"eps": eps, "guide": guide})
        check_floating(eps, "eps")
        if eps.shape not in ((), (n,), (B, n)):
            raise ShapeError(f"eps: expected a float, shape ({n},) or ({B}, {n}); got {tuple(eps.shape)}")
        e = eps.to(dtype)
        if is_recording():
            return e.expand(B, n).reshape(B, n, 1, 1), lambda: None
        bad = (~torch.isfinite(eps) | (eps < 0)).any()  # one read back, later

        def check() -> None:
            if bool(bad):
                raise RangeError(f"eps: expected finite values >= 0, got {eps.flatten().tolist()[:8]}")

        return e.expand(B, n).reshape(B, n, 1, 1), check
    if not isinstance(eps, (int, float)) or isinstance(eps, bool) or not eps >= 0 or eps == float("inf"):
        raise RangeError(f"eps: expected a finite float >= 0, got {eps!r}")
    return torch.full((), float(eps), dtype=dtype, device=guide.device).expand(B, n).reshape(B, n, 1, 1), lambda: None


def _solve(
    mI: list[torch.Tensor], mp: torch.Tensor, mII: dict[tuple[int, int], torch.Tensor],
    mIp: list[torch.Tensor], eps: torch.Tensor, out: list[torch.Tensor] | None = None,
) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Per-pixel ``a = (Σ + diag(ε))^-1 cov`` and ``b = mean(p) - aᵀ mean(I)``.

    ``mI[i]`` is ``(B,1,H,W)``, ``mp`` ``(B,Cs,H,W)``, ``mII[(i,j)]`` ``(B,1,H,W)`` for j <= i,
    ``mIp[i]`` ``(B,Cs,H,W)``; ``eps`` is ``(B,n,1,1)``. Returns ``a`` as a list over guide
    channels of ``(B,Cs,H,W)`` and ``b (B,Cs,H,W)``, written into ``out`` (``n + 1`` tensors)
    when given. LDLᵀ (``E = L·D``), no square roots, no branches, elementwise ops only.

    ``Σ_ii = E[I_i²] - E[I_i]²`` carries a rounding error of a few ``finfo.eps · E[I_i²]``;
    each ε_i is raised to ``16 · finfo.eps · E[I_i²]`` per pixel (plus the smallest normal
    number) and pivots are clamped there, so flat guides and ``eps = 0`` give finite, exact
    box means instead of amplified rounding noise.
    """
    n = len(mI)
    unit = 16 * torch.finfo(mp.dtype).eps
    eps = eps.clamp_min(torch.finfo(mp.dtype).tiny)
    outs: list[dict] = [{} if out is None else {"out": o} for o in (out or [None] * (n + 1))]
    A: dict[tuple[int, int], torch.Tensor] = {}
    eps_eff: list[torch.Tensor] = []
    for i, j in _pairs(n):
        s = torch.addcmul(mII[(i, j)], mI[i], mI[j], value=-1)
        if i == j:
            eps_eff.append(torch.maximum(mII[(i, i)] * unit, eps[:, i : i + 1]))
            s = s.clamp_min(0) + eps_eff[i]
        A[(i, j)] = s
    L: dict[tuple[int, int], torch.Tensor] = {}
    E: dict[tuple[int, int], torch.Tensor] = {}
    D: list[torch.Tensor] = []
    for j in range(n):
        d = A[(j, j)]
        for k in range(j):
            d = torch.addcmul(d, L[(j, k)], E[(j, k)], value=-1)
        D.append(torch.maximum(d, eps_eff[j]))
        for i in range(j + 1, n):
            v = A[(i, j)]
            for k in range(j):
                v = torch.addcmul(v, L[(i, k)], E[(j, k)], value=-1)
            E[(i, j)] = v
            L[(i, j)] = v / D[j]
    y: list[torch.Tensor] = []
    for i in range(n):
        v = torch.addcmul(mIp[i], mI[i], mp, value=-1)  # cov(I_i, p)
        for k in range(i):
            v = torch.addcmul(v, L[(i, k)], y[k], value=-1)
        y.append(v)
    a: list[torch.Tensor] = [mp] * n
    for i in reversed(range(n)):
        last = i + 1 == n
        v = torch.div(y[i], D[i], **(outs[i] if last else {}))
        for k in range(i + 1, n):
            v = torch.addcmul(v, L[(k, i)], a[k], value=-1, **(outs[i] if k + 1 == n else {}))
        a[i] = v
    b = mp
    for i in range(n):
        b = torch.addcmul(b, a[i], mI[i], value=-1, **(outs[n] if i + 1 == n else {}))
    return a, b


def _product_specs(n: int, Cs: int) -> list[tuple[str, int, str, int]]:
    """The planes whose box means the solve needs, in a fixed order:
    ``I_i``, ``p_c``, ``I_i I_j (j <= i)``, ``I_i p_c`` as (tensor, index, tensor, index);
    an empty second name means the plane itself."""
    return (
        [("I", i, "", 0) for i in range(n)]
        + [("p", c, "", 0) for c in range(Cs)]
        + [("I", i, "I", j) for i, j in _pairs(n)]
        + [("I", i, "p", c) for i in range(n) for c in range(Cs)]
    )


def _unpack(planes: list[torch.Tensor], n: int, Cs: int):
    """Split box means ordered as :func:`_product_specs` (``(B,1,H,W)`` each) into the
    ``mI, mp, mII, mIp`` arguments of :func:`_solve`."""
    pairs = _pairs(n)
    mI = planes[:n]
    mp = torch.cat(planes[n : n + Cs], 1)
    off = n + Cs
    mII = dict(zip(pairs, planes[off : off + len(pairs)]))
    off += len(pairs)
    mIp = [torch.cat(planes[off + i * Cs : off + (i + 1) * Cs], 1) for i in range(n)]
    return mI, mp, mII, mIp


def _guided_reference(
    I: torch.Tensor, p: torch.Tensor, r: int, eps: torch.Tensor, coefficients_only: bool = False
) -> torch.Tensor:
    """Differentiable, traceable path: cumsum box filters over stacked planes. Returns the output
    without ``mean(p)`` (centred inputs), or the box-filtered coefficients ``(B, n + 1, Cs, H, W)``
    (``a_0 .. a_{n-1}, b``)."""
    n, Cs = I.shape[1], p.shape[1]
    tensors = {"I": I, "p": p}
    planes = [
        tensors[a][:, i : i + 1] * (tensors[b][:, j : j + 1] if b else 1) if b else tensors[a][:, i : i + 1]
        for a, i, b, j in _product_specs(n, Cs)
    ]
    m = _box_cumsum(torch.cat(planes, 1), r)
    a, b = _solve(*_unpack(list(m.split(1, 1)), n, Cs), eps)
    coeffs = _box_cumsum(torch.cat(a + [b], 1), r)
    if coefficients_only:
        return coeffs.unflatten(1, (n + 1, Cs))
    return _apply(coeffs.unflatten(1, (n + 1, Cs)), I)


def _apply(coeffs: torch.Tensor, I: torch.Tensor) -> torch.Tensor:
    """``b + Σ_i a_i I_i`` for coefficients ``(B, n + 1, Cs, H, W)`` and a centred guide ``(B, n, H, W)``."""
    n = I.shape[1]
    out = coeffs[:, n]
    for i in range(n):
        out = out + coeffs[:, i] * I[:, i : i + 1]
    return out


_STRIP_ELEMENTS = 1 << 16  # pixels per strip of the per-pixel solve: temporaries stay in L2


class _Workspace:
    """Buffers of the CPU path for one (guide channels, source channels, H, W, r, dtype).

    glibc returns large freed blocks to the OS, so fresh buffers are page-faulted in on every
    call (measured: ~40 % of the run time at 1024x768). :class:`Guided` keeps one workspace
    between calls; the functional form builds a new one each time.
    """

    def __init__(self, n: int, Cs: int, H: int, W: int, r: int, dtype: torch.dtype) -> None:
        self.key = (n, Cs, H, W, r, dtype)
        self.boxer = PlaneBoxer(H, W, r, dtype)
        self.I = torch.empty(n, H, W, dtype=dtype)  # centred guide of one image
        self.p = torch.empty(Cs, H, W, dtype=dtype)  # centred source of one image
        self.mI = torch.empty(n, H, W, dtype=dtype)
        self.mp = torch.empty(Cs, H, W, dtype=dtype)
        self.mII = torch.empty(len(_pairs(n)), H, W, dtype=dtype)
        self.mIp = torch.empty(n, Cs, H, W, dtype=dtype)
        self.coeffs = torch.empty(n + 1, Cs, H, W, dtype=dtype)  # a_0 .. a_{n-1}, b

    @classmethod
    def get(cls, holder: dict | None, n: int, Cs: int, H: int, W: int, r: int, dtype: torch.dtype) -> _Workspace:
        key = (n, Cs, H, W, r, dtype)
        if holder is not None and holder.get("ws") is not None and holder["ws"].key == key:
            return holder["ws"]
        ws = cls(*key)
        if holder is not None:
            holder["ws"] = ws
        return ws


def _guided_fast(
    g: torch.Tensor, p: torch.Tensor, mean_g: torch.Tensor, mean_p: torch.Tensor, r: int,
    eps: torch.Tensor, holder: dict | None = None, coefficients_only: bool = False,
) -> torch.Tensor:
    """CPU eager path: box means one plane at a time (cache-resident, reused buffers), the
    solve in row strips so its temporaries stay small; strips of the grouped buffers are views.
    Centring (by ``mean_g``, ``mean_p``) happens here, into the workspace. Returns the output,
    or the box-filtered coefficients ``(B, n + 1, Cs, H, W)``."""
    B, n, H, W = g.shape
    Cs = p.shape[1]
    ws = _Workspace.get(holder, n, Cs, H, W, r, g.dtype)
    boxer, pairs = ws.boxer, _pairs(n)
    out = torch.empty((B, n + 1, Cs, H, W) if coefficients_only else (B, Cs, H, W), dtype=g.dtype)
    for bi in range(B):
        Ib = torch.sub(g[bi], mean_g[bi], out=ws.I)
        pb = torch.sub(p[bi], mean_p[bi], out=ws.p)
        boxer(Ib, ws.mI)
        boxer(pb, ws.mp)
        # products and their box means a stack at a time: while a stack is in cache
        for group, factors in (
            (ws.mII, [(Ib[i], Ib[j]) for i, j in pairs]),
            (ws.mIp.view(n * Cs, H, W), [(Ib[i], pb[c]) for i in range(n) for c in range(Cs)]),
        ):
            for a in range(0, len(factors), boxer.stack):
                stack = group[a : a + boxer.stack]
                for dst, (u, v) in zip(stack, factors[a : a + boxer.stack]):
                    torch.mul(u, v, out=dst)
                boxer(stack, stack)
        e = eps[bi : bi + 1]
        strip = max(1, _STRIP_ELEMENTS // W)
        for y in range(0, H, strip):
            rows = slice(y, y + strip)
            _solve(
                [ws.mI[i : i + 1, rows][None] for i in range(n)], ws.mp[:, rows][None],
                {pr: ws.mII[k : k + 1, rows][None] for k, pr in enumerate(pairs)},
                [ws.mIp[i, :, rows][None] for i in range(n)], e,
                out=[ws.coeffs[k, :, rows][None] for k in range(n + 1)],
            )
        planes = ws.coeffs.view(-1, H, W)
        boxer(planes, planes)
        if coefficients_only:
            out[bi].copy_(ws.coeffs)
            continue
        acc = torch.add(ws.coeffs[n], mean_p[bi], out=out[bi])
        for i in range(n):
            acc.addcmul_(ws.coeffs[i], Ib[i : i + 1])
    return out


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
    out = _filtered(src, guide, radius, e, _holder, subsample)
    check_finite_inputs()  # the values read back here: on a GPU the kernels are queued by now
    check_eps()
    return out


def _filtered(
    src: torch.Tensor, guide: torch.Tensor, radius: int, e: torch.Tensor, _holder: dict | None, subsample: int,
) -> torch.Tensor:
    """:func:`_guided` after the argument checks (``e``: ε ``(B, n, 1, 1)`` in the compute dtype)."""
    n = guide.shape[1]
    ct = compute_dtype(src.dtype)
    Cs, H, W = src.shape[1:]
    if src.numel() == 0:
        return src.clone()
    g, p = guide.to(ct), src.to(ct)
    mean_g, mean_p = g.mean(dim=(2, 3), keepdim=True), p.mean(dim=(2, 3), keepdim=True)
    fast = use_fast_path(src, guide, e)
    if subsample == 1 and native.applies(g, p, e):
        return native.guided(g, p, mean_g, mean_p, mean_p, radius, e, holder=_holder).to(src.dtype)
    if subsample == 1 and gpu.applies(g, p, e):
        return gpu.guided(g, p, mean_g, mean_p, mean_p, radius, e).to(src.dtype)
    if subsample == 1:
        if fast:
            return _guided_fast(g, p, mean_g, mean_p, radius, e, _holder).to(src.dtype)
        return (_guided_reference(g - mean_g, p - mean_p, radius, e) + mean_p).to(src.dtype)
    # He & Sun 2015: coefficients from s x s means at radius r / s, upsampled bilinearly, applied
    # to the full-resolution guide
    gc = g - mean_g
    low_g = F.avg_pool2d(gc, subsample, ceil_mode=True)
    low_p = F.avg_pool2d(p - mean_p, subsample, ceil_mode=True)
    r_low = round(radius / subsample)
    zero_g, zero_p = torch.zeros_like(mean_g), torch.zeros_like(mean_p)  # low_g, low_p are centred
    if native.applies(low_g, low_p, e):
        coeffs = native.guided(low_g, low_p, zero_g, zero_p, zero_p, r_low, e, coefficients_only=True,
                               holder=_holder)
    elif gpu.applies(low_g, low_p, e):
        coeffs = gpu.guided(low_g, low_p, zero_g, zero_p, zero_p, r_low, e, coefficients_only=True)
    elif fast:
        coeffs = _guided_fast(low_g, low_p, zero_g, zero_p, r_low, e, _holder, coefficients_only=True)
    else:
        coeffs = _guided_reference(low_g, low_p, r_low, e, coefficients_only=True)
    coeffs = F.interpolate(coeffs.flatten(1, 2), size=(H, W), mode="bilinear", align_corners=False)
    return (_apply(coeffs.unflatten(1, (n + 1, Cs)), gc) + mean_p).to(src.dtype)


def guided(
    src: torch.Tensor,
    guide: torch.Tensor,
    *,
    radius: int = 24,
    eps: float | torch.Tensor = 0.01,
    subsample: int = 1,
    sanitize: bool = False,
) -> torch.Tensor:
    """Guided image filter of ``src`` with a 1-4 channel ``guide``; cost independent of ``radius``.

    Args:
        src: ``(B, C, H, W)`` image to filter (e.g. demodulated indirect light, HDR, any range).
        guide: ``(B, G, H, W)``, ``1 <= G <= 4``, same dtype and device as ``src`` — e.g. the
            normal (xyz mapped to [0, 1]) and depth (divided by the scene extent), see
            :func:`guide_from_gbuffer`. Values in guide units; any offset is fine.
        radius: window radius ``r >= 0`` in pixels (window ``(2r+1)²``, shrinking at borders).
        eps: regulariser in guide units squared: a float, ``(G,)`` per guide channel or
            ``(B, G)``; ``>= 0``. Per pixel it is raised to at least ``16 · finfo.eps ·
            E[I²]`` (the rounding level of the variance), so ``eps=0`` and flat guides stay
            finite.
        subsample: ``s >= 1``; above 1, the fast guided filter (He & Sun 2015): the
            coefficients are solved on ``s x s`` means of ``src`` and ``guide`` with radius
            ``round(r / s)``, upsampled bilinearly and applied to the full-resolution guide
            (about ``s²`` times less work; edges stay those of the full guide).
        sanitize: replace NaN/Inf in the inputs by 0 (with a warning) instead of raising.

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
    return _guided(src, guide, radius, eps, sanitize, None, subsample)


def guide_from_gbuffer(
    gb: GBuffer, *, depth_scale: float | None = None, drop_constant: bool = True
) -> torch.Tensor:
    """The paper's guide from a GBuffer: normal xyz mapped to [0, 1] and depth / extent.

    Args:
        gb: needs ``normal``; ``depth`` is appended when present.
        depth_scale: the fixed scene-extent constant depth is divided by (scene units); by
            default the largest depth among hit pixels of the batch (all pixels without ``hit``).
        drop_constant: drop channels that are constant over the whole batch (DESIGN §4): they
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
    channels = [(gb.normal + 1) * 0.5]
    if gb.depth is not None:
        if depth_scale is None:
            valid = gb.depth if gb.hit is None else torch.where(gb.hit, gb.depth, -torch.inf)
            depth_scale = float(valid.max()) if valid.numel() else 1.0
            depth_scale = depth_scale if depth_scale > 0 else 1.0  # (-inf: no hit pixel)
        elif not depth_scale > 0:
            raise RangeError(f"depth_scale: expected > 0, got {depth_scale}")
        channels.append(gb.depth / depth_scale)
    guide = torch.cat(channels, 1)
    if drop_constant:
        flat = guide.flatten(2)
        varying = (flat.amax(dim=(0, 2)) > flat.amin(dim=(0, 2))).nonzero().flatten()
        keep = varying if varying.numel() else torch.zeros(1, dtype=torch.long, device=guide.device)
        guide = guide.index_select(1, keep)
    return guide


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
        learnable: make ``eps`` an ``nn.Parameter``.
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
        value = torch.as_tensor(eps, dtype=torch.float32).clone()
        if learnable:
            self.eps = nn.Parameter(value)
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
        return f"radius={self.radius}, eps={self.eps.tolist()}{sub}"
