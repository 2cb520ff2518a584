"""How the C back end calls its kernels: threads per call (one band of rows each), scratch
blocks, per-band partial results, padded plane layouts and reused buffers."""

from __future__ import annotations

import functools

import torch

from torchgi.core.taps import kernel_5x5

# pixels per band below which a call runs on fewer threads (a thread hand-off costs more than
# the band's work; docs/calibration.md)
_MIN_BAND_PIXELS = 1 << 15


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


def result(out: torch.Tensor | None, shape: tuple[int, ...]) -> torch.Tensor:
    """``out`` when it is a contiguous float32 CPU tensor of ``shape`` (an op's result buffer the
    caller keeps between calls: no fresh pages to fault in), else a new tensor of that shape.

    Example:
        >>> buf = torch.empty(2, 3)
        >>> result(buf, (2, 3)) is buf, result(buf, (3, 2)).shape
        (True, torch.Size([3, 2]))
    """
    if out is not None and tuple(out.shape) == tuple(shape) and out.dtype == torch.float32 and out.device.type == "cpu" \
            and out.is_contiguous():
        return out
    return torch.empty(shape, dtype=torch.float32)


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


def _box_scratch(K: int, W: int) -> int:
    """Floats of one band's scratch of the box passes in ``native.c`` over ``K`` planes of width
    ``W``: doubles for the column sums (rows ``W + 8``), 1 / window columns (``W``) and a row's
    prefix sums (``W + 8``), then floats for the box means (rows ``W + 16``)."""
    return 2 * (K * (W + 8) + 2 * W + 8) + K * (W + 16)



_PART_BYTES = 64  # the partial results at the start of each band's scratch block (PART_BYTES in native.c)


def _parts(fn, bands: int, pixels: int, *args, doubles: int, extra_bytes: int = 0) -> torch.Tensor:
    """``fn(*args, threads, scratch, stride)`` over ``bands`` rows (:func:`_run`'s threads) where
    each band's scratch block starts with ``doubles`` (<= 8) partial results, ``extra_bytes`` of
    scratch after them; returns those results summed over the bands, float64 ``(doubles,)``."""
    threads = _threads(bands, pixels)
    stride = _PART_BYTES + -(-extra_bytes // 64) * 64
    buf = torch.zeros(threads * stride // 8, dtype=torch.float64)
    fn(*args, threads, buf.data_ptr(), stride)
    return buf.view(threads, -1)[:, :doubles].sum(0)


def _buffer(holder: dict | None, name: str, shape: tuple[int, ...], dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """An empty buffer kept in ``holder`` between calls of one shape (no page faults)."""
    if holder is None:
        return torch.empty(shape, dtype=dtype)
    key = f"buffer_{name}"
    buf = holder.get(key)
    if buf is None or buf.shape != shape or buf.dtype != dtype:
        buf = holder[key] = torch.empty(shape, dtype=dtype)
    return buf


