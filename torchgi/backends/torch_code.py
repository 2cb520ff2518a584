"""The torch code of every op: the reference (autograd, tracing, ONNX export, float64, any
device) and the CPU in-place paths used where no compiled kernel applies.

* box: separable ``torch.cumsum`` + ``index_select`` (:func:`box_cumsum`; exported to ONNX as
  ``CumSum``/``Gather``); eagerly on the CPU, :class:`PlaneBoxer` (blocked prefix sums — a 16x16
  triangular matmul per block plus a carry — into reused buffers, a cache-sized stack of planes
  at a time).
* guided: products of the centred guide and source box-filtered, the per-pixel ``C x C`` solve
  as a closed-form LDLᵀ in element-wise ops (:func:`solve`: exportable, half-safe, no
  ``torch.linalg``), coefficients box-filtered and applied; eagerly on the CPU the same through
  a :class:`PlaneBoxer` one image at a time with the solve in row strips.
* atrous: each level over the 25 taps as shifted views of padded tensors (never a
  ``(B, 25·C, H, W)`` unfold), optionally through ``torch.compile`` (``fused``).
* importance: the same taps at step 1; allocation: float64 shares, floors and the largest
  remainders (Hamilton's method) by ``kthvalue``.
"""

from __future__ import annotations

import functools
import itertools
import math

import torch
import torch.nn.functional as F

from torchgi.backends.base import (
    AccumulateOp,
    AllocateOp,
    ATrousOp,
    BoxOp,
    EdgeShareOp,
    GuidedOp,
    GuideRaysOp,
    GuideStatsOp,
    ImportanceOp,
    PathOp,
    RestoreOp,
    colour_scale,
    eager,
    iterate_levels,
    scaled_guides,
)
from torchgi.core.dtypes import compute_dtype, variance_rounding
from torchgi.core.taps import Padded, kernel_5x5

__all__ = [
    "NAME", "PlaneBoxer", "apply_coefficients", "box_cumsum", "channel_planes", "describe", "solve", "squared_distance",
    "supports",
]

NAME = "torch"
_TAPS = kernel_5x5()
# block widths of PlaneBoxer's blocked prefix sums (docs/calibration.md)
_BLOCK_W, _BLOCK_H = 16, 16


def supports(op: str, desc: object) -> str | None:
    """The torch code takes every call.

    Example:
        >>> supports("box", BoxOp(torch.ones(1, 1, 2, 2, dtype=torch.float64), 1)) is None
        True
    """
    return None


def describe() -> str:
    """One line for :func:`torchgi.backends.status`.

    Example:
        >>> describe().startswith("always available")
        True
    """
    return "always available: the reference, autograd, tracing and export"


def in_place(desc: BoxOp | GuidedOp) -> bool:
    """The in-place CPU paths (:class:`PlaneBoxer`, the guided workspace) take eager CPU calls
    (no autograd, no tracing: :func:`~torchgi.backends.base.eager`).

    Example:
        >>> in_place(BoxOp(torch.ones(1, 1, 2, 2), 1)), in_place(BoxOp(torch.ones(1, 1, 2, 2, requires_grad=True), 1))
        (True, False)
    """
    return all(t.device.type == "cpu" for t in desc.tensors() if t is not None) and eager(desc) is None


def _counts(n: int | torch.Tensor, r: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    j = torch.arange(n, device=device)
    hi = torch.clamp(j + (r + 1), max=n)
    lo = torch.clamp(j - r, min=0)
    return hi, lo


def box_cumsum(x: torch.Tensor, r: int) -> torch.Tensor:
    """Separable count-normalised box mean of ``(..., H, W)`` by cumsum and gathers.

    Example:
        >>> box_cumsum(torch.arange(3.0).view(1, 1, 1, 3), 1)
        tensor([[[[0.5000, 1.0000, 1.5000]]]])
    """
    H, W = x.shape[-2], x.shape[-1]
    s = F.pad(torch.cumsum(x, -1), (1, 0))
    hi, lo = _counts(W, r, x.device)
    x = (s.index_select(-1, hi) - s.index_select(-1, lo)) / (hi - lo).to(x.dtype)
    s = F.pad(torch.cumsum(x, -2), (0, 0, 1, 0))
    hi, lo = _counts(H, r, x.device)
    return (s.index_select(-2, hi) - s.index_select(-2, lo)) / (hi - lo).to(x.dtype)[:, None]


def _segments(n: int, r: int) -> list[tuple[int, int]]:
    """Split ``[0, n)`` where ``min(j+r, n-1)`` or ``j-r-1 >= 0`` change form."""
    cuts = sorted({0, n, min(max(n - r, 0), n), min(r + 1, n)})
    return [(a, b) for a, b in itertools.pairwise(cuts) if b > a]


# Planes box-filtered together (PlaneBoxer._stack): about 1 MB of float32 per
# operand, so small images pay the per-op overhead once per stack, not once per plane, and
# large ones still go one cache-resident plane at a time.
_STACK_ELEMENTS = 1 << 18


class PlaneBoxer:
    """Box-filters ``(H, W)`` planes (or ``(P, H, W)`` stacks of them) on the CPU into
    caller-given outputs, reusing buffers.

    Writes box *means* (count-normalised). Not differentiable; the planes being read and
    the output may be the same tensor.

    Example:
        >>> boxer = PlaneBoxer(4, 5, radius=1, dtype=torch.float64)
        >>> x = torch.rand(4, 5, dtype=torch.float64)
        >>> torch.allclose(boxer(x, torch.empty_like(x)), box_cumsum(x[None, None], 1)[0, 0])
        True
    """

    def __init__(self, H: int, W: int, radius: int, dtype: torch.dtype = torch.float32) -> None:
        self.H, self.W, self.r = H, W, radius
        self.stack = max(1, _STACK_ELEMENTS // max(H * W, 1))  # planes boxed together
        self._prefix_buf = torch.empty(self.stack, H, W, dtype=dtype)  # prefix sums along W, then H
        self._rows_buf = torch.empty(self.stack, H, W, dtype=dtype)  # box sums along W
        self._upper = torch.triu(torch.ones(_BLOCK_W, _BLOCK_W, dtype=dtype))
        self._lower = torch.tril(torch.ones(_BLOCK_H, _BLOCK_H, dtype=dtype))
        # running totals of the block sums: along H a triangular matmul, along W a cumsum of the
        # strided totals (whichever was faster, docs/calibration.md)
        nh = max(H // _BLOCK_H - 1, 1)
        self._carry_h = torch.tril(torch.ones(nh, nh, dtype=dtype))
        hh, lh = _counts(H, radius, torch.device("cpu"))
        hw, lw = _counts(W, radius, torch.device("cpu"))
        inv_h = 1.0 / (hh - lh).to(torch.float64)
        inv_w = 1.0 / (hw - lw).to(torch.float64)
        self.inv_count = torch.outer(inv_h, inv_w).to(dtype)
        self._seg_w, self._seg_h = _segments(W, radius), _segments(H, radius)

    def _prefix(self, x: torch.Tensor, s: torch.Tensor, dim: int) -> None:
        """Inclusive prefix sums of ``x (P, H, W)`` along ``dim`` (-1: W, -2: H) into ``s``:
        blocks by one triangular matmul, then each block adds the running total of the blocks
        before it."""
        P, H, W = x.shape
        b = _BLOCK_W if dim == -1 else _BLOCK_H
        n = x.shape[dim]
        nb = n // b
        m = nb * b
        if nb:
            if dim == -1:
                blocks = x[..., :m].reshape(P, H, nb, b)
                if m == W:
                    torch.matmul(blocks, self._upper, out=s.view(P, H, nb, b))
                else:
                    s[..., :m].copy_(torch.matmul(blocks, self._upper).view(P, H, m))
                if nb > 1:
                    carry = s[..., b - 1 : m - b : b].cumsum(-1)
                    s[..., b:m].unflatten(-1, (nb - 1, b)).add_(carry[..., None])
            else:
                if m == H:
                    torch.matmul(self._lower, x.view(P, nb, b, W), out=s.view(P, nb, b, W))
                else:
                    s[:, :m].copy_(torch.matmul(self._lower, x[:, :m].unflatten(1, (nb, b))).view(P, m, W))
                if nb > 1:
                    carry = torch.matmul(self._carry_h, s[:, b - 1 : m - b : b])
                    s[:, b:m].unflatten(1, (nb - 1, b)).add_(carry[:, :, None, :])
        for j in range(m, n):  # fewer than b leftovers
            if j == 0:
                s.select(dim, 0).copy_(x.select(dim, 0))
            else:
                torch.add(s.select(dim, j - 1), x.select(dim, j), out=s.select(dim, j))

    def _difference(self, s: torch.Tensor, out: torch.Tensor, dim: int, segments: list[tuple[int, int]]) -> None:
        """``out[j] = s[min(j+r, n-1)] - (s[j-r-1] if j > r else 0)`` along ``dim``, by views."""
        n, r = out.shape[dim], self.r
        for a, e in segments:
            hi = s.narrow(dim, n - 1, 1) if a >= n - r else s.narrow(dim, a + r, e - a)
            dst = out.narrow(dim, a, e - a)
            if e <= r + 1:
                dst.copy_(hi.expand_as(dst))
            else:
                torch.sub(hi, s.narrow(dim, a - r - 1, e - a), out=dst)

    def _stack(self, x: torch.Tensor, out: torch.Tensor) -> None:
        """Box means of at most ``self.stack`` planes ``x (P, H, W)`` into ``out``."""
        P = x.shape[0]
        prefix, rows = self._prefix_buf[:P], self._rows_buf[:P]
        self._prefix(x, prefix, -1)
        self._difference(prefix, rows, -1, self._seg_w)
        self._prefix(rows, prefix, -2)
        self._difference(prefix, out, -2, self._seg_h)
        out.mul_(self.inv_count)

    def __call__(self, x: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """Box means of ``x`` - one plane ``(H, W)`` or planes ``(P, H, W)`` - into ``out`` of
        the same shape (may be ``x`` itself); stacks of ``self.stack`` planes at a time."""
        if x.dim() == 2:
            self._stack(x[None], out[None])
            return out
        for a in range(0, x.shape[0], self.stack):
            self._stack(x[a : a + self.stack], out[a : a + self.stack])
        return out


def _pairs(n: int) -> list[tuple[int, int]]:
    """Lower-triangle index pairs ``(i, j), j <= i`` of an ``n x n`` symmetric matrix."""
    return [(i, j) for i in range(n) for j in range(i + 1)]


def solve(
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

    Example:
        >>> one = torch.ones(1, 1, 1, 1)   # E[I] = 0, E[I²] = 1, E[p] = 0, E[Ip] = 0.5: a = 0.5 / (1 + ε)
        >>> a, b = solve([0 * one], 0 * one, {(0, 0): one}, [0.5 * one], torch.zeros(1, 1, 1, 1))
        >>> round(float(a[0]), 5), float(b)   # ε raised to the rounding level, 16 · eps(float32)
        (0.5, 0.0)
    """
    n = len(mI)
    unit = variance_rounding(mp.dtype)
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
    ``mI, mp, mII, mIp`` arguments of :func:`solve`."""
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
    m = box_cumsum(torch.cat(planes, 1), r)
    a, b = solve(*_unpack(list(m.split(1, 1)), n, Cs), eps)
    coeffs = box_cumsum(torch.cat(a + [b], 1), r)
    if coefficients_only:
        return coeffs.unflatten(1, (n + 1, Cs))
    return apply_coefficients(coeffs.unflatten(1, (n + 1, Cs)), I)


def apply_coefficients(coeffs: torch.Tensor, I: torch.Tensor) -> torch.Tensor:
    """``b + Σ_i a_i I_i`` for coefficients ``(B, n + 1, Cs, H, W)`` and a centred guide ``(B, n, H, W)``.

    Example:
        >>> coeffs = torch.tensor([2.0, 1.0]).view(1, 2, 1, 1, 1)   # a = 2, b = 1
        >>> apply_coefficients(coeffs, torch.full((1, 1, 1, 1), 3.0)).item()
        7.0
    """
    n = I.shape[1]
    out = coeffs[:, n]
    for i in range(n):
        out = out + coeffs[:, i] * I[:, i : i + 1]
    return out


_STRIP_ELEMENTS = 1 << 16  # pixels per strip of the per-pixel solve: temporaries stay in L2


class _Workspace:
    """Buffers of the CPU path for one (guide channels, source channels, H, W, r, dtype).

    glibc returns large freed blocks to the OS, so fresh buffers are page-faulted in on every
    call (a large share of the run time, docs/calibration.md). :class:`Guided` keeps one workspace
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
            solve(
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


def squared_distance(a: list[torch.Tensor], b: list[torch.Tensor]) -> torch.Tensor:
    """Σ (a - b)² over channels ``(B,1,H,W)``: either one ``(B,C,H,W)`` tensor each (a channel
    reduction: few ops, compact ONNX graphs) or lists of ``(B,1,H,W)`` planes (pointwise only:
    what ``torch.compile`` fuses into one loop).

    Example:
        >>> squared_distance([torch.ones(1, 2, 1, 1)], [torch.zeros(1, 2, 1, 1)]).item()
        2.0
    """
    out = (a[0] - b[0]).square().sum(1, keepdim=True)
    for u, v in zip(a[1:], b[1:]):
        out = out + (u - v).square()
    return out


def channel_planes(t: torch.Tensor, split: bool) -> list[torch.Tensor]:
    """``t (B,C,H,W)`` as a list of channel planes (``split``) or as ``[t]``.

    Example:
        >>> [p.shape[1] for p in channel_planes(torch.ones(1, 3, 2, 2), True)]
        [1, 1, 1]
    """
    return [t[:, k : k + 1] for k in range(t.shape[1])] if split else [t]


def _iteration(
    c: torch.Tensor, feat: torch.Tensor | None, var: torch.Tensor | None, valid: torch.Tensor | None,
    step: int, colour_scale: torch.Tensor | None, split: bool = False,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """One À-Trous level.

    ``feat`` ``(B,F,H,W)`` holds the geometry guides already divided by the square roots of
    their σ's (normal also by the step), so ``w_n · w_x = exp(-|f(p) - f(q)|²``); None: no
    geometry weight. ``colour_scale`` is ``1/σ_rt,i`` ``(B,1,1,1)`` or, variance-guided,
    ``1/(σ² · blur(Var))`` ``(B,1,H,W)``; None: no colour weight. ``valid`` ``(B,1,H,W)``
    marks pixels that may act as sources (None: all). Returns the filtered colour, the
    propagated variance and the weight sum.

    With ``split`` every channel is its own plane and the level is pure pointwise arithmetic
    over shifted views, which ``torch.compile`` fuses into one loop (the ``fused=True`` path);
    without it channels are reduced with ``sum`` (fewer ops for eager code and ONNX).
    """
    pad = 2 * step
    pc = Padded(c, pad)
    pf = Padded(feat, pad) if feat is not None else None
    pv = Padded(torch.ones_like(c[:, :1]) if valid is None else valid.to(c.dtype), pad)  # 0 outside / on holes
    pvar = Padded(var, pad) if var is not None else None
    cc = channel_planes(c, split)
    ff = channel_planes(feat, split) if feat is not None else []
    num: list[torch.Tensor] = []
    var_num: list[torch.Tensor] = []
    den = torch.zeros_like(c[:, :1])
    for dy, dx, h in _TAPS:
        oy, ox = dy * step, dx * step
        cq = channel_planes(pc.at(oy, ox), split)
        d = None
        if colour_scale is not None:
            d = squared_distance(cc, cq) * colour_scale
        if pf is not None:
            dg = squared_distance(ff, channel_planes(pf.at(oy, ox), split))
            d = dg if d is None else d + dg
        w = pv.at(oy, ox) * h
        if d is not None:
            w = w * torch.exp(-d)
        num = [w * q for q in cq] if not num else [a + w * q for a, q in zip(num, cq)]
        den = den + w
        if pvar is not None:
            w2 = w.square()
            vq = channel_planes(pvar.at(oy, ox), split)
            var_num = [w2 * q for q in vq] if not var_num else [a + w2 * q for a, q in zip(var_num, vq)]
    ok = den > 0
    safe = torch.where(ok, den, torch.ones_like(den))
    out = torch.where(ok, torch.cat(num, 1) / safe, c)  # no weight at all: keep the centre pixel
    var_out = torch.where(ok, torch.cat(var_num, 1) / safe.square(), var) if var is not None else None
    return out, var_out, den


@functools.cache
def _compiled_iteration():
    """``torch.compile(_iteration, dynamic=True)``, built on first use (one compile serves
    every size and step)."""
    return torch.compile(_iteration, dynamic=True)


def _core(f: torch.Tensor, valid: torch.Tensor, window: int) -> torch.Tensor:
    """``1 - mean over the window of exp(-|f_p - f_q|²)`` over valid taps, 0 off ``valid``."""
    lo, hi = -(window // 2), (window - 1) // 2
    pad = max(-lo, hi)
    pf, pv = Padded(f, pad), Padded(valid, pad)
    total = torch.zeros_like(valid)
    count = torch.zeros_like(valid)
    for oy in range(lo, hi + 1):
        for ox in range(lo, hi + 1):
            v = pv.at(oy, ox)
            total = total + v * torch.exp(-(f - pf.at(oy, ox)).square().sum(1, keepdim=True))
            count = count + v
    return (1 - total / count.clamp_min(1)).clamp(0, 1) * valid


@functools.cache
def _compiled_core():
    """``torch.compile(_core, dynamic=False)`` built on first use: one specialised loop over pixels per
    (size, window); static shapes ran faster than ``dynamic=True`` (docs/calibration.md)."""
    return torch.compile(_core, dynamic=False)


# ---------------------------------------------------------------------------------------- ops
def box(desc: BoxOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.BoxOp` in torch: :class:`PlaneBoxer` eagerly on the CPU,
    else :func:`box_cumsum`.

    Example:
        >>> box(BoxOp(torch.arange(3.0).view(1, 1, 1, 3), 1))
        tensor([[[[0.5000, 1.0000, 1.5000]]]])
    """
    x = desc.x
    if not in_place(desc) or x.numel() == 0:
        return box_cumsum(x, desc.radius)
    B, C, H, W = x.shape
    out = torch.empty(B, C, H, W, dtype=x.dtype)
    PlaneBoxer(H, W, desc.radius, x.dtype)(x.reshape(B * C, H, W), out.view(B * C, H, W))
    return out


def guided(desc: GuidedOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.GuidedOp` in torch: the in-place CPU path eagerly on the
    CPU, else the differentiable reference.

    Example:
        >>> p = torch.rand(1, 1, 6, 6); m = p.mean((2, 3), keepdim=True)
        >>> flat = torch.ones(1, 1, 6, 6)   # a constant guide: the box mean of the box mean
        >>> out = guided(GuidedOp(flat, p, torch.ones(1, 1, 1, 1), m, 1, torch.zeros(1, 1, 1, 1)))
        >>> torch.allclose(out, box_cumsum(box_cumsum(p, 1), 1), atol=1e-6)
        True
    """
    g, p, e = desc.guide, desc.src, desc.eps
    if in_place(desc):
        return _guided_fast(g, p, desc.mean_guide, desc.mean_src, desc.radius, e, desc.workspace,
                            desc.coefficients_only)
    out = _guided_reference(g - desc.mean_guide, p - desc.mean_src, desc.radius, e, desc.coefficients_only)
    return out if desc.coefficients_only else out + desc.mean_src


def atrous(desc: ATrousOp) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """:class:`~torchgi.backends.base.ATrousOp` in torch: per level, the guides divided by the
    square roots of their σ's (normals also by the step) so ``w_n · w_x = exp(-|f(p) - f(q)|²)``.

    Example:
        >>> c = torch.full((1, 3, 8, 8), 0.5)   # a constant image stays constant
        >>> out, _ = atrous(ATrousOp(c, None, None, None, None, torch.ones(1, 1, 1, 1), None, None, iterations=2))
        >>> torch.equal(out, c)
        True
    """
    guides = scaled_guides(desc)
    level_fn = _compiled_iteration() if desc.fused else _iteration

    def level(c, var, valid, i):
        step = 2**i
        scale = colour_scale(desc, i, var)
        feat = torch.cat([g * (s / step if per_step else s) for g, s, per_step in guides], 1) if guides else None
        return level_fn(c, feat, var, valid, step, scale, desc.fused)

    return iterate_levels(desc, level)


def importance(desc: ImportanceOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.ImportanceOp` in torch: one feature vector per pixel,
    ``G_n · G_x = exp(-|f_p - f_q|²)``.

    Example:
        >>> n = torch.zeros(1, 3, 4, 4); n[:, 2] = 1   # flat: nothing to sample
        >>> float(importance(ImportanceOp(n, torch.zeros(1, 3, 4, 4), 0.1, 0.1, None, 3)).max())
        0.0
    """
    n, x = desc.normal, desc.position
    x = x - x.mean(dim=(2, 3), keepdim=True)
    f = torch.cat([n / desc.sigma_normal**0.5, x / desc.sigma_position**0.5], 1)
    valid = torch.ones_like(n[:, :1]) if desc.hit is None else desc.hit.to(n.dtype)
    core = _compiled_core() if desc.fused else _core
    return core(f, valid, desc.window)


def allocate(desc: AllocateOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AllocateOp` in torch (float64 shares, ``kthvalue``).

    Example:
        >>> q = torch.tensor([[0.0, 1.0, 3.0]])
        >>> allocate(AllocateOp(q, None, torch.tensor([3]), 7, 1)).tolist()
        [[1, 2, 4]]
    """
    q, eligible, n_eligible, min_samples = desc.q, desc.eligible, desc.n_eligible, desc.min_samples
    if eligible is None:
        eligible = torch.ones_like(q, dtype=torch.bool)
    q = q.to(torch.float64)
    q = torch.where(eligible, q, torch.zeros_like(q))
    spare = (desc.budget - min_samples * n_eligible).to(torch.float64)  # (B,)
    Q = q.sum(1)
    uniform = eligible.to(torch.float64) / n_eligible.clamp_min(1)[:, None]
    share = torch.where((Q > 0)[:, None], q / torch.where(Q > 0, Q, 1.0)[:, None], uniform)
    exact = share * spare[:, None]
    counts = exact.floor()
    left = (spare - counts.sum(1)).round().to(torch.int64)  # < number of eligible pixels
    frac = torch.where(eligible, exact - counts, torch.full_like(exact, -1.0))
    counts = counts.to(torch.int64)
    for b in range(q.shape[0]):  # the `left` largest remainders, ties to the lowest pixel index
        k = int(left[b])
        if k <= 0:
            continue
        threshold = -torch.kthvalue(-frac[b], k).values  # k-th largest remainder (O(N) selection)
        above = frac[b] > threshold
        tied = frac[b] == threshold
        take = above | (tied & (tied.cumsum(0) <= k - int(above.sum())))
        counts[b] += take.to(torch.int64)
    return torch.where(eligible, counts + min_samples, torch.zeros_like(counts))


def guide_stats(desc: GuideStatsOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.GuideStatsOp` by reductions.

    Example:
        >>> n = torch.zeros(1, 3, 2, 2); d = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])
        >>> guide_stats(GuideStatsOp(n, d, d > 2.5))[0, [3, 8]].tolist()   # depth min, depth max on hit
        [1.0, 4.0]
    """
    n, d = desc.normal, desc.depth
    B = n.shape[0]
    planes = n if d is None else torch.cat([n, d], 1)
    lo, hi = planes.amin(dim=(2, 3)).double(), planes.amax(dim=(2, 3)).double()
    if d is None:
        lo, hi = torch.cat([lo, lo.new_full((B, 1), math.inf)], 1), torch.cat([hi, hi.new_full((B, 1), -math.inf)], 1)
        dmax = lo.new_full((B, 1), -math.inf)
    else:
        valid = d if desc.hit is None else torch.where(desc.hit, d, -torch.inf)
        dmax = valid.amax(dim=(1, 2, 3)).double().view(B, 1)
    bad_n = (~torch.isfinite(n)).flatten(1).sum(1, keepdim=True).double()
    bad_d = torch.zeros_like(bad_n) if d is None else (~torch.isfinite(d)).flatten(1).sum(1, keepdim=True).double()
    sums = planes.double().sum(dim=(2, 3))
    sums = sums if d is not None else torch.cat([sums, sums.new_zeros(B, 1)], 1)
    return torch.cat([lo, hi, dmax, bad_n, bad_d, sums], 1).cpu()


def edge_share(desc: EdgeShareOp) -> float:
    """:class:`~torchgi.backends.base.EdgeShareOp` on the guide built by torch ops.

    Example:
        >>> from torchgi.backends.base import GuideSpec
        >>> n = torch.zeros(1, 3, 2, 3); n[..., 2] = 1.0
        >>> edge_share(EdgeShareOp(GuideSpec(n, None, (0,), (0.5,), (0.5,)), 0.1))   # 1 of 2 neighbours
        0.5
    """
    guide = desc.spec.build()
    edges = (guide[:, :, ::2, 1:] - guide[:, :, ::2, :-1]).square().sum(1) > desc.edge**2
    return float(edges.float().mean())


def restore(desc: RestoreOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.RestoreOp` as the Denoiser's torch code: the steps of
    :func:`torchgi.denoise._restore` in eager ops around the guided filter (whose own back end is
    chosen as for :func:`torchgi.filters.guided`).

    Example:
        >>> from torchgi.backends.base import GuideSpec
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5)
        >>> spec = GuideSpec(torch.zeros_like(c), None, (0,), (0.5,), (0.5,))
        >>> restore(RestoreOp(c, None, None, a, None, spec, torch.ones(1, 1, 1, 1), 1, 1e-4, 1, 4.0)).shape
        torch.Size([1, 3, 8, 8])
    """
    from torchgi.core.check import check_finite
    from torchgi.denoise import _restore, _surface
    from torchgi.filters.guided import _filtered

    for name, t in desc.light_inputs():
        check_finite(t, name)
    guide = desc.spec.build()
    B, n = guide.shape[:2]
    eps = torch.full((B, n, 1, 1), float(desc.eps), dtype=compute_dtype(guide.dtype), device=guide.device)
    return _restore(desc.color, desc.emission, desc.kept, desc.albedo, _surface(desc.hit, desc.albedo),
                    lambda x: _filtered(x, guide, desc.radius, eps, desc.workspace, desc.subsample), desc.firefly,
                    desc.level)


_LUMA = (0.2126, 0.7152, 0.0722)


def accumulate(desc: AccumulateOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AccumulateOp` by tensor ops: four bilinear taps of the
    history gathered at ``pixel + motion``, each kept where it passes the consistency tests.

    Example:
        >>> z = lambda c: torch.zeros(1, c, 2, 2)
        >>> out = accumulate(AccumulateOp(torch.ones(1, 3, 2, 2), z(1) + 9, z(2), z(3), z(1) + 1, z(1) > 0, z(3),
        ...                               z(3), z(2), z(1), z(3), z(1), z(1), 0.2, 32, 0.9, 0.05))
        >>> [round(v, 4) for v in out[0, :, 0, 0].tolist()]   # no history: the frame itself, length 1
        [1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0]
    """
    d = desc
    normal, depth, surface = d.normal, d.depth, d.surface
    B, _, H, W = normal.shape
    dt, dev = normal.dtype, normal.device
    ys = torch.arange(H, dtype=dt, device=dev).view(1, H, 1)
    xs = torch.arange(W, dtype=dt, device=dev).view(1, 1, W)
    px, py = xs + d.motion[:, 0], ys + d.motion[:, 1]  # (B, H, W): pixel-centre coordinates in the previous frame
    x0, y0 = torch.floor(px), torch.floor(py)
    fx, fy = px - x0, py - y0
    values = torch.cat([d.light, d.output, d.moments, d.length], 1).flatten(2)  # (B, 9, HW)
    tests = torch.cat([d.prev_normal, d.prev_depth, d.prev_surface], 1).flatten(2)  # (B, 5, HW)
    acc = torch.zeros(B, 9, H, W, dtype=dt, device=dev)
    total = torch.zeros(B, 1, H, W, dtype=dt, device=dev)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        tx, ty = x0 + dx, y0 + dy
        w = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
        inside = (tx >= 0) & (tx <= W - 1) & (ty >= 0) & (ty <= H - 1)
        index = (ty.clamp(0, H - 1) * W + tx.clamp(0, W - 1)).to(torch.int64).flatten(1)  # (B, HW)
        t = tests.gather(2, index[:, None].expand(-1, 5, -1)).view(B, 5, H, W)
        same_kind = (t[:, 4:5] > 0.5) == surface
        close = ((t[:, :3] * normal).sum(1, keepdim=True) >= d.normal_tolerance) & (
            (t[:, 3:4] - depth).abs() <= d.depth_tolerance * depth.abs())
        w = torch.where(inside[:, None] & same_kind & (close | ~surface), w[:, None], 0.0)
        acc = acc + w * values.gather(2, index[:, None].expand(-1, 9, -1)).view(B, 9, H, W)
        total = total + w
    found = total > 1e-3
    hist = torch.where(found, acc / torch.where(found, total, 1.0), 0.0)
    hist_length = torch.where(found, torch.round(hist[:, 8:9]), 0.0)
    length = torch.where(hist_length > 0, (hist_length + 1).clamp_max(d.max_history), 1.0)
    a = torch.maximum(1.0 / length, torch.full((), d.alpha, dtype=dt, device=dev))
    peak = d.x.amax(1, keepdim=True)
    over = peak > d.bound
    x = torch.where(over, d.x * (d.bound / torch.where(over, peak, 1.0)), d.x)
    light = hist[:, :3] + a * (x - hist[:, :3])
    lum = (x * torch.tensor(_LUMA, dtype=dt, device=dev).view(1, 3, 1, 1)).sum(1, keepdim=True)
    moments = hist[:, 6:8] + a * (torch.cat([lum, lum * lum], 1) - hist[:, 6:8])
    var = (moments[:, 1:2] - moments[:, :1].square()).clamp_min(0)
    # frames averaged: 1/length while the weights are equal, (2 - α)/α once the average is exponential
    frames = torch.minimum(length, (2 - a) / a)
    return torch.cat([light, hist[:, 3:6], moments, length, hist_length, var, frames, lum], 1)


def path(desc: PathOp) -> tuple:
    """A tile of the renderer's "path" integrator by the torch wavefronts
    (:func:`torchgi.render.integrators.path.radiance`, chunk by chunk into a film): the
    reference the compiled tracer must match in expectation.

    Example:
        >>> from torchgi.render import scenes
        >>> from torchgi.render.lights import Tables
        >>> from torchgi.render.integrators.common import SKIPS
        >>> import numpy as np
        >>> s = scenes.cornell(4); a = s.arrays()
        >>> mean, var = path(PathOp(a, Tables.from_arrays(a), s.camera, 1, 0, 0, "all", frozenset(SKIPS), 0,
        ...                         np.full(16, 2), 1 << 15))
        >>> mean.shape, var.shape
        ((9, 16), (3, 16))
    """
    from torchgi.render.engine import film_tile  # the renderer sits above the back ends

    return film_tile(desc, "path")


def guide_rays(desc: GuideRaysOp) -> dict[str, torch.Tensor]:
    """The guides of the pixel centres by embreex and :func:`torchgi.render.integrators.common.guides`,
    ``chunk_size`` rays at a time.

    Example:
        >>> from torchgi.render import scenes
        >>> from torchgi.render.lights import Tables
        >>> s = scenes.cornell(4); a = s.arrays()
        >>> guide_rays(GuideRaysOp(a, Tables.from_arrays(a), s.camera))["normal"].shape
        torch.Size([3, 16])
    """
    from torchgi.render.engine import _context
    from torchgi.render.integrators.common import guides

    width, height = desc.camera.resolution
    ctx = _context(desc.arrays, desc.camera, 0, 0)
    channels = {"albedo": 3, "normal": 3, "position": 3, "depth": 1, "hit": 1}
    g = {k: torch.zeros(c, width * height, dtype=torch.bool if k == "hit" else torch.float32)
         for k, c in channels.items()}
    for start in range(0, width * height, desc.chunk_size):
        pixel = torch.arange(start, min(start + desc.chunk_size, width * height))
        for k, v in guides(ctx, pixel).items():
            g[k][:, start : start + pixel.numel()] = v
    return g

