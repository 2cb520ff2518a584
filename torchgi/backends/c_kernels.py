"""The C back end: compiled CPU kernels of one À-Trous level, the guided filter (and the box
filter it is built from), the sampling importance map and the sample allocation, float32.

The torch code walks the image once per element-wise op; these kernels (``_native.c``) do a
level, or a guided-filter pass, in one walk over each band of rows, with the channel loops
unrolled and the pixel loop vectorised. Same maths as the torch code (the guided box sums
accumulate in double, so they are closer to a float64 oracle). They take eager float32 CPU
calls without autograd or tracing (:func:`supports` says why not otherwise).

The source is compiled on first use with the system C compiler (``$CC``, else ``cc`` or
``gcc``; ``-O3 -march=native``, a few seconds) into ``$TORCHGI_CACHE`` (default
``~/.cache/torchgi``) and loaded with ctypes; later processes load the cached library. Without
a compiler :func:`library` returns None and :func:`describe` says why. Each call runs one band
of rows per thread (``torch.get_num_threads()`` threads) on OpenMP threads where the compiler
has ``-fopenmp`` — the same libgomp, and so the same worker threads, as torch (a separate pool
competes with torch's spinning workers; docs/calibration.md) — else on the calling thread.

Example:
    >>> from torchgi.backends import c_kernels
    >>> isinstance(c_kernels.describe(), str)
    True
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import torch

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
    float32_eager,
    iterate_levels,
    scaled_guides,
)
from torchgi.core.dtypes import variance_rounding
from torchgi.core.taps import kernel_5x5

__all__ = ["NAME", "describe", "library", "padded", "supports"]

NAME = "c"

_SOURCE = Path(__file__).with_name("_native.c")
_SOURCES = (_SOURCE, Path(__file__).with_name("_pathtracer.c"))  # one library
_FLAGS = ["-O3", "-march=native", "-fno-math-errno", "-fPIC", "-shared"]
# OpenMP first (threads shared with torch's libgomp, see _native.c), else the bands run serially
_THREADING = (["-fopenmp"], [])
_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_status = "not built yet"
_tried = False

# pixels per band below which a call runs on fewer threads (a thread hand-off costs more than
# the band's work; docs/calibration.md)
_MIN_BAND_PIXELS = 1 << 15

_P = ctypes.c_void_p
_I = ctypes.c_int
_F = ctypes.c_float
_L = ctypes.c_longlong
_BANDS = [_I, _P, _L]  # every entry point ends with: threads, scratch, scratch bytes per thread
_SIGNATURES = {
    "torchgi_native_version": ([], _I),
    "torchgi_openmp": ([], _I),
    "torchgi_exp_neg": ([_F], _F),
    "torchgi_atrous_level": ([_P, _I, _P, _I, _P, _P, _P, _P, _I, _I, _I, _I, _L, _I, _P, _P, _P, _P, *_BANDS], None),
    "torchgi_guided_coefficients": ([_P, _P, _I, _P, _P, _I, _I, _I, _I, _P, _F, _P, *_BANDS], None),
    "torchgi_guided_apply": ([_P, _I, _I, _P, _P, _P, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_importance": ([_P, _P, _F, _F, _P, _I, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_allocate": ([_P, _I, _P, _L, _L, _L, _I, _P, _P, _P, _I], _I),
    "torchgi_guide_stats": ([_P, _P, _P, _I, _I, *_BANDS], None),
    "torchgi_guide_edges": ([_I, _P, _P, _P, _P, _P, _I, _I, _F, *_BANDS], None),
    "torchgi_guide_pool": ([_I, _P, _P, _P, _P, _P, _P, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_lights": ([_P, _P, _P, _P, _P, _F, _I, _I, _F, _I, _P, *_BANDS], None),
    "torchgi_prepare": ([_P, _P, _P, _P, _P, _F, _I, _I, _P, _F, _F, _P, _P, *_BANDS], None),
    "torchgi_clamp": ([_P, _P, _F, _I, _I, _I, _P, *_BANDS], None),
    "torchgi_restore_coefficients": ([_I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _I, _I, _I, _I, _P, _F, _P, *_BANDS],
                                     None),
    "torchgi_accumulate": ([_P] * 13 + [_I, _I, _F, _F, _F, _F, _P, *_BANDS], None),
    "torchgi_embree_init": ([_P], None),
    "torchgi_scene_new": ([_P, _L], _P),
    "torchgi_scene_free": ([_P], None),
    "torchgi_render_pixels": ([_P, _P, _L, _P, _L, _P, _P, _I], None),
    "torchgi_render_guides": ([_P, _P, _L, _P, _I], None),
    "torchgi_guided_finish": ([_P, _I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _I, _I, _I, _I, _P, _P, _P, _P, _P, _P, _F,
                               _P, *_BANDS], None),
}
# the library's interface version, written once: in the C source
_VERSION = int(re.search(r"torchgi_native_version\(void\) \{ return (\d+); \}", _SOURCE.read_text()).group(1))


def _cache_dir() -> Path:
    root = os.environ.get("TORCHGI_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "torchgi")
    return Path(root)


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _build() -> ctypes.CDLL:
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler found ($CC, cc, gcc)")
    errors = []
    for threading_flags in _THREADING:
        try:
            return _build_with(cc, [*_FLAGS, *threading_flags])
        except RuntimeError as err:
            errors.append(str(err))
    raise RuntimeError("; ".join(errors))


def _build_with(cc: str, flags: list[str]) -> ctypes.CDLL:
    source = b"\0".join(p.read_bytes() for p in _SOURCES)
    cpu = ""
    if os.path.exists("/proc/cpuinfo"):  # -march=native: one library per CPU model
        cpu = next((ln for ln in Path("/proc/cpuinfo").read_text().splitlines() if ln.startswith("flags")), "")
    key = hashlib.sha256(b"\0".join([source, " ".join(flags).encode(), cc.encode(), cpu.encode(),
                                     platform.machine().encode(), sys.platform.encode()])).hexdigest()[:16]
    out = _cache_dir() / f"native-{key}.so"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
        os.close(fd)
        try:
            proc = subprocess.run([cc, *flags, *map(str, _SOURCES), "-o", tmp, "-lm"], capture_output=True, text=True,
                                  check=False)
            if proc.returncode != 0:
                raise RuntimeError(f"{cc} {' '.join(flags)} failed: {proc.stderr.strip()[-500:]}")
            os.replace(tmp, out)  # atomic: concurrent builders each write their own temporary file
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    try:
        lib = ctypes.CDLL(str(out))
    except OSError as err:  # e.g. an OpenMP runtime that cannot be loaded
        raise RuntimeError(f"{out}: {err}") from err
    for name, (args, res) in _SIGNATURES.items():
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = args, res
    if lib.torchgi_native_version() != _VERSION:
        raise RuntimeError(f"{out}: unexpected version")
    return lib


def library() -> ctypes.CDLL | None:
    """The compiled kernels, built on first use; None when disabled or when no build works.

    Example:
        >>> lib = library()
        >>> lib is None or abs(lib.torchgi_exp_neg(1.0) - 0.36787944) < 1e-7
        True
    """
    global _lib, _status, _tried
    if not _tried:
        with _lock:
            if not _tried:
                try:
                    _lib = _build()
                    threads = "OpenMP threads" if _lib.torchgi_openmp() else "one thread (no OpenMP)"
                    _status = f"compiled kernels in use, {threads} ({_lib._name})"
                except Exception as err:  # noqa: BLE001 - no compiler, a failed build, an unloadable library
                    _lib, _status = None, f"compiled kernels unavailable, torch code in use: {err}"
                _tried = True
    return _lib


def describe() -> str:
    """Whether the compiled kernels are built, and why not (for :func:`torchgi.backends.status`);
    builds them first if no call has yet.

    Example:
        >>> describe().startswith(("compiled kernels in use", "compiled kernels unavailable"))
        True
    """
    library()
    return _status


def supports(op: str, desc: BoxOp | GuidedOp | ATrousOp | ImportanceOp | AllocateOp | GuideStatsOp | EdgeShareOp |
             RestoreOp) -> str | None:
    """None when the kernels take ``desc``: eager float32 CPU tensors (float32/float64
    importance for the allocation, fewer than 2^31 pixels per image), a built library; else why not.

    Example:
        >>> supports("box", BoxOp(torch.ones(1, 1, 2, 2, dtype=torch.float64), 1))
        'the C kernels take float32'
    """
    ts = [t for t in desc.tensors() if t is not None]
    if any(t.device.type != "cpu" for t in ts):
        return "the C kernels take CPU tensors"
    if op == "allocate":
        if desc.q.dtype not in (torch.float32, torch.float64) or desc.q.shape[1] >= 2**31:
            return "the C allocation takes float32/float64 with fewer than 2^31 pixels per image"
    else:
        why = float32_eager(op, desc, "C")
        if why is not None:
            return why
    if op in ("path", "guide_rays"):
        return _path_support(desc)
    if op == "accumulate" and (desc.x.numel() == 0 or desc.x.shape[-2] * desc.x.shape[-1] >= 2**31):
        return "the C accumulation takes non-empty images of fewer than 2^31 pixels"
    if op == "restore" and (desc.color.numel() == 0 or desc.color.shape[-2] * desc.color.shape[-1] >= 2**31):
        return "the C pipeline takes non-empty images of fewer than 2^31 pixels"
    return None if library() is not None else _status


def _threads(parts: int, pixels: int) -> int:
    """Threads for work split ``parts`` ways over ``pixels``: torch's thread count, at most
    one per part and per ``_MIN_BAND_PIXELS`` pixels, at least one."""
    return max(1, min(torch.get_num_threads(), parts, pixels // _MIN_BAND_PIXELS))


def _run(fn, H: int, W: int, *args) -> None:
    """``fn(*args, threads, scratch, scratch_bytes)``: the C side runs rows ``[0, H)`` in one band
    per thread; ``args[-1]`` is the number of float32 scratch values one band needs (0: none)."""
    *args, scratch = args
    threads = _threads(H, H * W)
    bufs = torch.empty(threads * scratch, dtype=torch.float32) if scratch else None  # held until the call returns
    fn(*args, threads, None if bufs is None else bufs.data_ptr(), 4 * scratch)


def _ptr(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


_PAD = 16  # floats (64 bytes) of padding after each row and each plane of a padded tensor


def _layout(H: int, W: int) -> tuple[int, int]:
    """Row and plane strides (floats) of :func:`padded`."""
    return W + _PAD, H * (W + _PAD) + _PAD


def padded(B: int, C: int, H: int, W: int) -> torch.Tensor:
    """An empty float32 ``(B, C, H, W)`` view whose rows are ``W + 16`` and planes ``H (W + 16)
    + 16`` floats apart. With power-of-two widths, plain rows and planes lie a multiple of 4 KB
    apart and the many row streams of an À-Trous tap fall into the same L1 sets
    (docs/calibration.md).

    Example:
        >>> padded(1, 3, 4, 5).stride()   # rows 5 + 16 apart, planes 4 * 21 + 16
        (300, 100, 21, 1)
    """
    rs, ps = _layout(H, W)
    return torch.empty(max(B * C * ps, 1), dtype=torch.float32).as_strided((B, C, H, W), (C * ps, ps, rs, 1))


def _as_padded(t: torch.Tensor) -> torch.Tensor:
    """``t`` if it already has :func:`padded`'s layout, else a padded copy."""
    B, C, H, W = t.shape
    rs, ps = _layout(H, W)
    if t.dtype == torch.float32 and t.stride() == (C * ps, ps, rs, 1):
        return t
    out = padded(B, C, H, W)
    out.copy_(t)
    return out


@functools.cache
def _taps() -> torch.Tensor:
    """The 25 tap weights, float32."""
    return torch.tensor([h for _, _, h in kernel_5x5()], dtype=torch.float32)


def empty_planes(like: torch.Tensor, C: int) -> torch.Tensor:
    """A :func:`padded` ``(B, C, H, W)`` buffer for the planes of ``like`` (the feature planes
    :func:`atrous_level` reads).

    Example:
        >>> empty_planes(torch.zeros(2, 3, 4, 5), 6).shape
        torch.Size([2, 6, 4, 5])
    """
    B, _, H, W = like.shape
    return padded(B, C, H, W)


def _atrous_level(
    c: torch.Tensor, feat: torch.Tensor | None, feat_scale: list[float], var: torch.Tensor | None,
    valid: torch.Tensor | None, step: int, colour_scale: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """One À-Trous level with the arguments of ``torch_code._iteration``, except that ``feat`` holds
    groups of 3 planes whose squared distances are multiplied by ``feat_scale`` (one per group;
    the level's ``1 / step²`` for normals). Returns the filtered colour ``(B,C,H,W)`` and the
    propagated variance, both in :func:`padded` layout (pass them on as they are), and the
    weight sum ``(B,1,H,W)``."""
    taps = _taps()
    lib = library()
    B, C, H, W = c.shape
    F = 0 if feat is None else feat.shape[1]
    if F % 3 or len(feat_scale) != F // 3:
        raise ValueError(f"feat: expected groups of 3 planes with one scale each, got {F} planes, {feat_scale}")
    fs = torch.tensor(list(feat_scale) or [1.0], dtype=torch.float32)
    rs, ps = _layout(H, W)
    c = _as_padded(c)
    feat = None if feat is None else _as_padded(feat)
    var = None if var is None else _as_padded(var)
    valid = None if valid is None else _as_padded(valid.to(torch.float32).expand(B, 1, H, W))
    plane = colour_scale is not None and colour_scale.shape[-2:] == (H, W)
    cs = None if colour_scale is None else _as_padded(colour_scale.expand(B, 1, H, W)) if plane else \
        colour_scale.reshape(B).contiguous()
    out = padded(B, C, H, W)
    var_out = None if var is None else padded(B, C, H, W)
    den = torch.empty(B, 1, H, W, dtype=torch.float32)
    for b in range(B):
        cs_b = None if cs is None else (cs[b] if plane else cs[b : b + 1])
        _run(lib.torchgi_atrous_level, H, W, c[b].data_ptr(), C, _ptr(None if feat is None else feat[b]), F,
             fs.data_ptr(), _ptr(None if var is None else var[b]), _ptr(None if valid is None else valid[b]), _ptr(cs_b),
             int(plane), H, W, rs, ps, step, taps.data_ptr(), out[b].data_ptr(),
             _ptr(None if var_out is None else var_out[b]), den[b].data_ptr(),
             (2 * C + 1) * (W + _PAD))
    return out, var_out, den


def _importance(normal: torch.Tensor, position: torch.Tensor, sigma_normal: float, sigma_position: float,
               hit: torch.Tensor | None, window: int) -> torch.Tensor:
    """Sampling importance ``(B,1,H,W)`` (``torch_code._core``) from float32 ``normal``
    and ``position`` ``(B,3,H,W)`` with the weights ``exp(-|Δn|² / σ_n - |Δx|² / σ_x)``, the
    bool ``hit (B,1,H,W)`` or None, over a ``window x window`` neighbourhood (offsets
    ``-(w//2) .. (w-1)//2``). Reads the inputs as they are: nothing image-sized is allocated
    but the output."""
    lib = library()
    B, _, H, W = normal.shape
    normal, position = normal.contiguous(), position.contiguous()
    hit = None if hit is None else hit.to(torch.float32).contiguous()
    out = torch.empty(B, 1, H, W, dtype=torch.float32)
    for b in range(B):
        _run(lib.torchgi_importance, H, W, normal[b].data_ptr(), position[b].data_ptr(), 1.0 / sigma_normal,
             1.0 / sigma_position, _ptr(None if hit is None else hit[b]), H, W, -(window // 2), (window - 1) // 2,
             out[b].data_ptr(), 0)
    return out


def _allocate(q: torch.Tensor, eligible: torch.Tensor | None, n_eligible: list[int], spare: list[int],
             min_samples: int) -> torch.Tensor:
    """Integer samples per pixel ``(B, N)`` int64 (``torch_code.allocate``) from the importance
    ``q (B, N)`` (float32 or float64, >= 0), the bool ``eligible (B, N)`` or None, each image's
    number of eligible pixels and spare samples (budget minus the minimum), and ``min_samples``."""
    lib = library()
    B, N = q.shape
    if N >= 2**31 or q.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"q: expected float32/float64 with at most 2^31 - 1 pixels per image, got {q.dtype}, {N}")
    q = q.contiguous()
    eligible = None if eligible is None else eligible.to(torch.bool).contiguous()
    threads = _threads(N, N)
    counts = torch.empty(B, N, dtype=torch.int64)
    bucket, hist = torch.empty(N, dtype=torch.int16), torch.empty(threads * 65536, dtype=torch.int32)
    for b in range(B):
        if lib.torchgi_allocate(q[b].data_ptr(), int(q.dtype == torch.float64),
                                _ptr(None if eligible is None else eligible[b]), N, n_eligible[b], spare[b], min_samples,
                                counts[b].data_ptr(), bucket.data_ptr(), hist.data_ptr(), threads):
            raise MemoryError("the C allocation kernel: out of memory")
    return counts


def _box_scratch(K: int, W: int) -> int:
    """Floats of one band's scratch of the box passes in ``_native.c`` over ``K`` planes of width
    ``W``: doubles for the column sums (rows ``W + 8``), 1 / window columns (``W``) and a row's
    prefix sums (``W + 8``), then floats for the box means (rows ``W + 16``)."""
    return 2 * (K * (W + 8) + 2 * W + 8) + K * (W + 16)


def _box(x: torch.Tensor, r: int) -> torch.Tensor:
    """Count-normalised box means over ``(2r+1)²`` windows of float32 ``x (B,C,H,W)`` (the
    coefficient pass of the guided filter without the apply)."""
    lib = library()
    B, C, H, W = x.shape
    x = x.contiguous()
    out = torch.empty_like(x)
    for b in range(B):
        _run(lib.torchgi_guided_apply, H, W, x[b].data_ptr(), 0, C, None, None, None, H, W, r, out[b].data_ptr(),
             _box_scratch(C, W))
    return out


def _guided(
    I: torch.Tensor, p: torch.Tensor, mean_I: torch.Tensor, mean_p: torch.Tensor, offset: torch.Tensor, r: int,
    eps: torch.Tensor, coefficients_only: bool = False, holder: dict | None = None,
) -> torch.Tensor:
    """Guided filter of ``p (B,Cs,H,W)`` by ``I (B,n,H,W)`` (n <= 4), both centred inside by
    ``mean_p``, ``mean_I`` (``(B,C,1,1)``), ``eps (B,n,1,1)`` (>= 0), radius ``r``;
    ``offset (B,Cs,1,1)`` is added to the output. Returns ``(B,Cs,H,W)``, or the box-filtered
    coefficients ``(B,n+1,Cs,H,W)`` (``a_0..a_{n-1}, b``). ``holder`` keeps the coefficient
    planes between calls of one size (no page faults)."""
    lib = library()
    B, n, H, W = I.shape
    Cs = p.shape[1]
    I, p = I.contiguous(), p.contiguous()
    K = n + Cs + n * (n + 1) // 2 + n * Cs
    Q = (n + 1) * Cs
    key = (n, Cs, H, W)
    if holder is not None and holder.get("native_key") == key:
        coef = holder["native_coef"]
    else:
        coef = torch.empty(Q, H, W, dtype=torch.float32)
        if holder is not None:
            holder["native_key"], holder["native_coef"] = key, coef
    out = torch.empty((B, n + 1, Cs, H, W) if coefficients_only else (B, Cs, H, W), dtype=torch.float32)
    eps = eps.reshape(B, n).to(torch.float32).clamp_min(torch.finfo(torch.float32).tiny).contiguous()
    offset = offset.reshape(B, Cs).to(torch.float32).contiguous()
    mean_I = mean_I.reshape(B, n).to(torch.float32).contiguous()
    mean_p = mean_p.reshape(B, Cs).to(torch.float32).contiguous()
    unit = variance_rounding(torch.float32)
    for b in range(B):
        _run(lib.torchgi_guided_coefficients, H, W, I[b].data_ptr(), mean_I[b].data_ptr(), n, p[b].data_ptr(),
             mean_p[b].data_ptr(), Cs, H, W, r,
             eps[b].data_ptr(), unit, coef.data_ptr(),
             _box_scratch(K, W))
        _run(lib.torchgi_guided_apply, H, W, coef.data_ptr(), n, Cs, None if coefficients_only else I[b].data_ptr(),
             mean_I[b].data_ptr(), offset[b].data_ptr(), H, W, r, out[b].data_ptr(),
             _box_scratch(Q, W))
    return out


# ---------------------------------------------------------------------------------------- ops
def box(desc: BoxOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.BoxOp` by the guided kernel's box passes.

    Example:
        >>> library() is None or box(BoxOp(torch.arange(3.0).view(1, 1, 1, 3), 1)).tolist() == [[[[0.5, 1.0, 1.5]]]]
        True
    """
    return _box(desc.x, desc.radius)


def guided(desc: GuidedOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.GuidedOp` in two kernels (coefficients, apply).

    Example:
        >>> p = torch.rand(1, 1, 6, 6); m = p.mean((2, 3), keepdim=True)
        >>> out = library() is None or guided(GuidedOp(torch.ones(1, 1, 6, 6), p, torch.ones(1, 1, 1, 1), m, 0,
        ...                                           torch.zeros(1, 1, 1, 1)))
        >>> out is True or torch.allclose(out, p, atol=1e-6)   # r = 0 and a constant guide: the source
        True
    """
    return _guided(desc.guide, desc.src, desc.mean_guide, desc.mean_src, desc.mean_src, desc.radius, desc.eps,
                   coefficients_only=desc.coefficients_only, holder=desc.workspace)


def atrous(desc: ATrousOp) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """:class:`~torchgi.backends.base.ATrousOp`, a level per kernel call: the guides divided by
    the square roots of their σ's once, into :func:`padded` planes; the kernel scales the normals'
    distances by ``1 / step²``.

    Example:
        >>> c = torch.full((1, 3, 8, 8), 0.5)
        >>> desc = ATrousOp(c, None, None, None, None, torch.ones(1, 1, 1, 1), None, None, iterations=2)
        >>> library() is None or torch.allclose(atrous(desc)[0], c)   # a constant image stays constant
        True
    """
    guides = scaled_guides(desc)
    feat = None
    if guides:
        feat = empty_planes(desc.color, 3 * len(guides))
        for k, (g, s, _) in enumerate(guides):
            torch.mul(g, s, out=feat[:, 3 * k : 3 * k + 3])

    def level(c, var, valid, i):
        step = 2**i
        scale = colour_scale(desc, i, var)
        return _atrous_level(c, feat, [1.0 / step**2 if per_step else 1.0 for _, _, per_step in guides], var, valid,
                             step, scale)

    return iterate_levels(desc, level)


def importance(desc: ImportanceOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.ImportanceOp` straight from the normal / position planes.

    Example:
        >>> n = torch.zeros(1, 3, 4, 4); n[:, 2] = 1   # flat: nothing to sample
        >>> library() is None or float(importance(ImportanceOp(n, torch.zeros(1, 3, 4, 4), 0.1, 0.1, None, 3)).max()) == 0
        True
    """
    return _importance(desc.normal, desc.position, desc.sigma_normal, desc.sigma_position, desc.hit, desc.window)


def allocate(desc: AllocateOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AllocateOp`: the same double arithmetic, the remainders
    ranked by 2^16 buckets, then a sort of the bucket holding the cut.

    Example:
        >>> q = torch.tensor([[0.0, 1.0, 3.0]])
        >>> library() is None or allocate(AllocateOp(q, None, torch.tensor([3]), 7, 1)).tolist() == [[1, 2, 4]]
        True
    """
    n = desc.n_eligible
    return _allocate(desc.q, desc.eligible, n.tolist(), (desc.budget - desc.min_samples * n).tolist(),
                     desc.min_samples)


_PART_BYTES = 64  # the partial results at the start of each band's scratch block (PART_BYTES in _native.c)


def _parts(fn, bands: int, pixels: int, *args, doubles: int, extra_bytes: int = 0) -> torch.Tensor:
    """``fn(*args, threads, scratch, stride)`` over ``bands`` rows (:func:`_run`'s threads) where
    each band's scratch block starts with ``doubles`` (<= 8) partial results, ``extra_bytes`` of
    scratch after them; returns those results summed over the bands, float64 ``(doubles,)``."""
    threads = _threads(bands, pixels)
    stride = _PART_BYTES + -(-extra_bytes // 64) * 64
    buf = torch.zeros(threads * stride // 8, dtype=torch.float64)
    fn(*args, threads, buf.data_ptr(), stride)
    return buf.view(threads, -1)[:, :doubles].sum(0)


def guide_stats(desc: GuideStatsOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.GuideStatsOp` in one walk per image.

    Example:
        >>> n = torch.zeros(1, 3, 2, 2); d = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])
        >>> library() is None or guide_stats(GuideStatsOp(n, d, d > 2.5))[0, [3, 8]].tolist() == [1.0, 4.0]
        True
    """
    lib = library()
    n = desc.normal.contiguous()
    d = None if desc.depth is None else desc.depth.contiguous()
    hit = None if desc.hit is None else desc.hit.contiguous()
    B, _, H, W = n.shape
    rows = []
    for b in range(B):
        threads = _threads(H, H * W)
        buf = torch.zeros(threads, 15, dtype=torch.float64)
        lib.torchgi_guide_stats(n[b].data_ptr(), _ptr(None if d is None else d[b]),
                                _ptr(None if hit is None else hit[b]), H, W, threads, buf.data_ptr(), 120)
        rows.append(torch.cat([buf[:, :4].amin(0), buf[:, 4:9].amax(0), buf[:, 9:].sum(0)]))
    return torch.stack(rows)


def _plane_ptrs(planes: list[torch.Tensor], b: int) -> list[int | None]:
    """Image ``b``'s pointer of each guide plane, None past the guide's channels (4 in all)."""
    return [p[b, 0].data_ptr() for p in planes] + [None] * (4 - len(planes))


def _spec_planes(spec) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
    """A :class:`~torchgi.backends.base.GuideSpec`'s ``(B,1,H,W)`` source planes (contiguous),
    scales and offsets (float32)."""
    normal = spec.normal.contiguous()
    depth = None if spec.depth is None else spec.depth.contiguous()
    planes = [normal[:, c : c + 1] if c < 3 else depth for c in spec.channels]
    return planes, torch.tensor(spec.scale, dtype=torch.float32), torch.tensor(spec.offset, dtype=torch.float32)


def edge_share(desc: EdgeShareOp) -> float:
    """:class:`~torchgi.backends.base.EdgeShareOp` on the guide's source planes (no guide built).

    Example:
        >>> from torchgi.backends.base import GuideSpec
        >>> n = torch.zeros(1, 3, 2, 3); n[..., 2] = 1.0
        >>> library() is None or edge_share(EdgeShareOp(GuideSpec(n, None, (0,), (0.5,), (0.5,)), 0.1)) == 0.5
        True
    """
    lib = library()
    planes, scale, _ = _spec_planes(desc.spec)
    B, _, H, W = planes[0].shape
    count = 0.0
    for b in range(B):
        count += float(_parts(lib.torchgi_guide_edges, H, H * W, len(planes), *_plane_ptrs(planes, b),
                              scale.data_ptr(), H, W, float(desc.edge), doubles=1, extra_bytes=4 * W)[0])
    total = B * ((H + 1) // 2) * max(W - 1, 0)
    return count / total if total else float("nan")


def _buffer(holder: dict | None, name: str, shape: tuple[int, ...], dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """An empty buffer kept in ``holder`` between calls of one shape (no page faults)."""
    if holder is None:
        return torch.empty(shape, dtype=dtype)
    key = f"restore_{name}"
    buf = holder.get(key)
    if buf is None or buf.shape != shape or buf.dtype != dtype:
        buf = holder[key] = torch.empty(shape, dtype=dtype)
    return buf


def restore(desc: RestoreOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.RestoreOp` fused: per image a walk for the light-source mask,
    one for the demodulated light and its capped peak, the firefly bound's box, one for the clamp
    (with the s x s means of light and guide at half resolution), the guided filter's coefficient
    pass, and its last pass with the remodulation (the coefficients upsampled first at half
    resolution). The guide is read from its normal and depth planes, never built. Raises
    :class:`~torchgi.core.errors.NonFiniteError` naming an input with NaN/Inf.

    Example:
        >>> from torchgi.backends.base import GuideSpec
        >>> c = torch.rand(1, 3, 8, 8); a = torch.full_like(c, 0.5)
        >>> spec = GuideSpec(torch.zeros_like(c), None, (0,), (0.5,), (0.5,))
        >>> library() is None or restore(RestoreOp(c, None, None, a, None, spec, torch.ones(1, 1, 1, 1), 1, 1e-4, 1,
        ...                                        4.0)).shape == (1, 3, 8, 8)
        True
    """
    from torchgi.core.check import check_finite
    from torchgi.settings import PIPELINE

    lib = library()
    color, albedo = desc.color.contiguous(), desc.albedo.contiguous()
    emission = None if desc.emission is None else desc.emission.contiguous()
    kept = None if desc.kept is None else desc.kept.contiguous()
    hit = None if desc.hit is None else desc.hit.contiguous()
    planes, scale, offset = _spec_planes(desc.spec)
    B, _, H, W = color.shape
    n, s = len(planes), desc.subsample
    h, w = -(-H // s), -(-W // s)
    r_low = desc.radius if s == 1 else round(desc.radius / s)
    K, Q = n + 3 + n * (n + 1) // 2 + 3 * n, (n + 1) * 3
    ws = desc.workspace
    x, peak = _buffer(ws, "x", (3, H, W)), _buffer(ws, "peak", (1, 1, H, W))
    mask = _buffer(ws, "mask", (H, W), torch.uint8)
    low_x = _buffer(ws, "low_x", (3, h, w)) if s > 1 else None
    low_g = _buffer(ws, "low_g", (n, h, w)) if s > 1 else None
    coef = _buffer(ws, "coef", (Q, h, w))
    coef_box = _buffer(ws, "coef_box", (Q, h, w)) if s > 1 else None
    out = torch.empty(B, 3, H, W, dtype=torch.float32)
    eps = torch.full((n,), max(float(desc.eps), torch.finfo(torch.float32).tiny), dtype=torch.float32)
    unit, floor, k = variance_rounding(torch.float32), float(PIPELINE.albedo_floor), float(desc.firefly)
    r_light = PIPELINE.light_square // 2
    ones, zeros = torch.ones(n, dtype=torch.float32), torch.zeros(n, dtype=torch.float32)
    rows = -(-H // _threads(H, H * W)) + 1  # the most rows of one band
    for b in range(B):
        level = float(desc.level[b].reshape(()))
        light_in = [color[b].data_ptr(), _ptr(None if emission is None else emission[b]),
                    _ptr(None if kept is None else kept[b]), albedo[b].data_ptr(), _ptr(None if hit is None else hit[b]),
                    floor]
        seen = _parts(lib.torchgi_lights, H, H * W, *light_in, H, W, PIPELINE.light * level, r_light,
                      mask.data_ptr(), doubles=1, extra_bytes=12 * W + 3 * (rows + 4 * r_light) * W + W)[0]
        lights = mask.data_ptr() if seen > 0 else None
        bad = _parts(lib.torchgi_prepare, H, H * W, *light_in, H, W, lights, level, k * level, x.data_ptr(),
                     peak.data_ptr(), doubles=4, extra_bytes=21 * W)
        if bool(bad.any()):  # counted in the walk: the named error (with its counts) from the torch check
            for name, t in desc.light_inputs():
                check_finite(t, name)
        mean = _box(peak, PIPELINE.firefly_radius)
        mean_p = (_parts(lib.torchgi_clamp, h, H * W, x.data_ptr(), mean.data_ptr(), k, H, W, s, _ptr(low_x),
                         doubles=3, extra_bytes=8 * W) / (H * W)).float()
        g = _plane_ptrs(planes, b)
        mean_g = (_parts(lib.torchgi_guide_pool, h, H * W, n, *g, scale.data_ptr(), offset.data_ptr(), H, W, s,
                         _ptr(low_g), doubles=n) / (H * W)).float()
        if desc.centre_src is not None:  # given (tiles of one image share them), not this call's means
            mean_p = desc.centre_src[b].reshape(-1).to(torch.float32).expand(3).contiguous()
            mean_g = desc.centre_guide[b].to(torch.float32).contiguous()
        # the coefficients from the guide's planes, or at half resolution from its block means
        g_low, sc_low, of_low = (g, scale, offset) if s == 1 else \
            ([p.data_ptr() for p in low_g] + [None] * (4 - n), ones, zeros)
        _run(lib.torchgi_restore_coefficients, h, w, n, *g_low, sc_low.data_ptr(), of_low.data_ptr(), mean_g.data_ptr(),
             (x if s == 1 else low_x).data_ptr(), mean_p.data_ptr(), 3, h, w, r_low, eps.data_ptr(), unit,
             coef.data_ptr(), _box_scratch(K, w))
        if s > 1:  # the coefficients' box means at low resolution, upsampled in the last pass
            _run(lib.torchgi_guided_apply, h, w, coef.data_ptr(), n, 3, None, None, None, h, w, r_low,
                 coef_box.data_ptr(), _box_scratch(Q, w))
        _run(lib.torchgi_guided_finish, H, W, (coef if s == 1 else coef_box).data_ptr(), n, 3, *g, scale.data_ptr(),
             offset.data_ptr(), mean_g.data_ptr(), mean_p.data_ptr(), H, W, r_low, s, out[b].data_ptr(), *light_in,
             lights, _box_scratch(Q, W) + 3 * W if s == 1 else 7 * W + w)
    return out


def accumulate(desc: AccumulateOp) -> torch.Tensor:
    """:class:`~torchgi.backends.base.AccumulateOp` in one walk per image.

    Example:
        >>> z = lambda c: torch.zeros(1, c, 2, 2)
        >>> op = AccumulateOp(torch.ones(1, 3, 2, 2), z(1) + 9, z(2), z(3), z(1) + 1, z(1) > 0, z(3), z(3), z(2),
        ...                   z(1), z(3), z(1), z(1), 0.2, 32, 0.9, 0.05)
        >>> library() is None or accumulate(op)[0, :, 0, 0].tolist()[6:9] == [1.0, 1.0, 1.0]
        True
    """
    lib = library()
    d = desc
    ts = [t.contiguous() for t in (d.x, d.bound, d.motion, d.normal, d.depth, d.surface, d.light, d.output, d.moments,
                                   d.length, d.prev_normal, d.prev_depth, d.prev_surface)]
    B, _, H, W = d.x.shape
    out = torch.empty(B, 13, H, W, dtype=torch.float32)
    for b in range(B):
        _run(lib.torchgi_accumulate, H, W, *(t[b].data_ptr() for t in ts), H, W, d.alpha, float(d.max_history),
             d.normal_tolerance, d.depth_tolerance, out[b].data_ptr(), 0)
    return out


class _Render(ctypes.Structure):
    """``pt_render`` of _pathtracer.c."""

    _fields_ = [("tri", _P), ("light", _P), ("cdf", _P), ("points", _P), ("intensities", _P), ("sky", _P),
                ("T", _L), ("L", _I), ("P", _I), ("any_glossy", _I), ("eps", _F), ("origin", _F * 3),
                ("basis", _F * 9), ("tan_x", _F), ("tan_y", _F), ("width", _I), ("height", _I), ("bounces", _I),
                ("roulette_from", _I), ("record", _I), ("head", ctypes.c_uint32), ("profile", _P)]


_RECORD = {"all": 0, "direct": 1, "indirect": 2}
_embree_status: str | None = None  # None: not tried yet; "": loaded
_SCENES_KEPT = 2  # BVHs a process keeps between calls
_scenes: dict[str, list] = {}  # scene key -> [BVH handle, its tables, calls tracing it]; least recently used first


def _path_support(desc: PathOp | GuideRaysOp) -> str | None:
    """Why the compiled tracer cannot take ``desc``, or None."""
    from torchgi.render.integrators.common import SKIPS

    if isinstance(desc, PathOp) and desc.skip != frozenset(SKIPS):
        return "the compiled tracer applies every skip of DESIGN §4; with one off the torch code runs"
    width, height = desc.camera.resolution
    if desc.arrays.triangles.shape[0] >= 2**31 or width * height >= 2**31:
        return "the compiled tracer takes fewer than 2^31 triangles and pixels"
    if library() is None:
        return _status
    global _embree_status
    if _embree_status is None:
        with _lock:
            if _embree_status is None:
                try:
                    from torchgi.render.accel import embree_functions

                    library().torchgi_embree_init((ctypes.c_void_p * 13)(*embree_functions()))
                    _embree_status = ""
                except Exception as err:  # noqa: BLE001 - no embree 4 library: the torch code runs
                    _embree_status = f"compiled tracer unavailable: {err}"
    return _embree_status or None


@contextlib.contextmanager
def _bvh(arrays, tables) -> Iterator[tuple[int, tuple[torch.Tensor | None, ...]]]:
    """This scene's embree BVH (built once per process) and its tables laid out one row per
    triangle / light, held for the ``with`` block: beyond :data:`_SCENES_KEPT` scenes the least
    recently used one is freed, but never while a call (another thread's) still traces it."""
    lib = library()
    with _lock:
        entry = _scenes.pop(arrays.key, None)
        if entry is None:
            tri = torch.from_numpy(arrays.triangles).to(torch.float32).contiguous()
            handle = lib.torchgi_scene_new(tri.data_ptr(), tri.shape[0])
            if not handle:
                raise RuntimeError("embree could not build the BVH")
            keep = (tables.tri.T.contiguous(), tables.light.T.contiguous(), tables.light_cdf.contiguous(),
                    tables.points.to(torch.float32).contiguous(), tables.intensities.to(torch.float32).contiguous(),
                    None if tables.sky is None else tables.sky.reshape(3).to(torch.float32).contiguous())
            entry = [handle, keep, 0]
        _scenes[arrays.key] = entry  # the most recently used last
        entry[2] += 1
        _evict(lib)
    try:
        yield entry[0], entry[1]
    finally:
        with _lock:
            entry[2] -= 1
            _evict(lib)


def _evict(lib: ctypes.CDLL) -> None:
    """Free the least recently used idle BVHs beyond :data:`_SCENES_KEPT` (under ``_lock``)."""
    while len(_scenes) > _SCENES_KEPT:
        idle = next((key for key, entry in _scenes.items() if entry[2] == 0), None)
        if idle is None:
            return
        lib.torchgi_scene_free(_scenes.pop(idle)[0])


def _render_struct(desc: PathOp | GuideRaysOp, tables: tuple[torch.Tensor | None, ...]) -> _Render:
    """The ``pt_render`` of a call: the tables, the camera, the pass."""
    from torchgi.render.camera import camera_frame
    from torchgi.render.integrators.common import RR_START
    from torchgi.render.sampler import key_head

    tri, light, cdf, points, intensities, sky = tables
    forward, right, up, tan_x, tan_y = camera_frame(desc.camera)
    width, height = desc.camera.resolution
    path_op = isinstance(desc, PathOp)
    record = desc.record if path_op else "direct"
    return _Render(tri.data_ptr(), light.data_ptr(), cdf.data_ptr(), points.data_ptr(), intensities.data_ptr(),
                   None if sky is None else sky.data_ptr(), tri.shape[0], light.shape[0], points.shape[0],
                   int(desc.tables.any_glossy), max(desc.tables.scale * 2.0**-15, 1e-7),
                   (_F * 3)(*desc.camera.position), (_F * 9)(*right, *up, *forward), tan_x, tan_y, width, height,
                   desc.bounces if path_op and record != "direct" else 0, RR_START, _RECORD[record],
                   key_head(desc.seed, desc.stream) if path_op else 0,
                   desc.profile.data_ptr() if path_op and desc.profile is not None else None)


def path(desc: PathOp) -> tuple:
    """:class:`~torchgi.backends.base.PathOp` by the compiled tracer (``_pathtracer.c``): each
    pixel's samples in order on one of ``desc.threads`` OpenMP threads, the film merged there.

    Example:
        >>> from torchgi.render import scenes
        >>> from torchgi.render.lights import Tables
        >>> from torchgi.render.integrators.common import SKIPS
        >>> import numpy as np
        >>> s = scenes.cornell(4); a = s.arrays()
        >>> op = PathOp(a, Tables.from_arrays(a), s.camera, 1, 0, 0, "all", frozenset(SKIPS), 0, np.full(16, 2), 1 << 15)
        >>> supports("path", op) is not None or path(op)[0].shape == (9, 16)
        True
    """
    why = _path_support(desc)
    if why is not None:
        raise RuntimeError(why)
    with _bvh(desc.arrays, desc.tables) as (handle, tables):
        return _trace_pixels(desc, handle, _render_struct(desc, tables))


def _trace_pixels(desc: PathOp, handle: int, r: _Render) -> tuple:
    from torchgi.render.engine import _chunks  # the torch wavefronts' cut into chunks

    counts = torch.from_numpy(desc.counts).to(torch.int64).contiguous()
    n = counts.numel()
    mean = torch.zeros(9, n, dtype=torch.float64)
    var = torch.zeros(3, n, dtype=torch.float64)
    # pieces of at most chunk_size samples per thread (>= 1 pixel), so that progress is reported as it goes
    for a, b in _chunks(counts, desc.chunk_size * desc.threads):
        m, v = torch.zeros(9, b - a, dtype=torch.float64), torch.zeros(3, b - a, dtype=torch.float64)
        library().torchgi_render_pixels(handle, ctypes.byref(r), desc.first_pixel + a, counts[a:].data_ptr(), b - a,
                                        m.data_ptr(), v.data_ptr(), desc.threads)
        mean[:, a:b], var[:, a:b] = m, v
        if desc.on_chunk is not None:
            desc.on_chunk(int(counts[a:b].sum()))
    return mean.numpy(), var.numpy()


def guide_rays(desc: GuideRaysOp) -> dict[str, torch.Tensor]:
    """:class:`~torchgi.backends.base.GuideRaysOp` by the compiled tracer, on ``desc.threads`` threads.

    Example:
        >>> from torchgi.render import scenes
        >>> from torchgi.render.lights import Tables
        >>> s = scenes.cornell(4); a = s.arrays()
        >>> op = GuideRaysOp(a, Tables.from_arrays(a), s.camera)
        >>> supports("guide_rays", op) is not None or guide_rays(op)["hit"].dtype == torch.bool
        True
    """
    why = _path_support(desc)
    if why is not None:
        raise RuntimeError(why)
    width, height = desc.camera.resolution
    out = torch.empty(11, width * height, dtype=torch.float32)
    with _bvh(desc.arrays, desc.tables) as (handle, tables):
        library().torchgi_render_guides(handle, ctypes.byref(_render_struct(desc, tables)), width * height,
                                        out.data_ptr(), desc.threads)
    return {"albedo": out[0:3], "normal": out[3:6], "position": out[6:9], "depth": out[9:10], "hit": out[10:11] > 0}

