"""Counter-based random numbers: every value is a pure function of (seed, pixel, sample, dimension).

No state is carried between calls, so how samples are batched, which worker traces them and
how many samples a pixel gets never change what any one sample sees (pbrt-v4's habit).

The hash is a 32-bit integer mixer (two multiply-xorshift rounds with the odd constant
0x45D9F3B, "hash32" by T. Mueller) on int32 tensors: multiplication wraps modulo 2^32 and
right shifts are masked to act as logical shifts, so the same bits come out on every device.
"""

from __future__ import annotations

import torch

__all__ = ["key_head", "mix32", "sample_keys", "uniform"]

_MUL = 0x45D9F3B


def _signed(x: int) -> int:
    """An unsigned 32-bit Python int as the int32 with the same bits."""
    x &= 0xFFFFFFFF
    return x - (1 << 32) if x >= 1 << 31 else x


def mix32(x: torch.Tensor | int) -> torch.Tensor | int:
    """Hash 32-bit values: int32 tensors (bits as unsigned) or Python ints in [0, 2^32).

    Example:
        >>> bits = mix32(torch.tensor([0, 1, 2, -1], dtype=torch.int32)).tolist()
        >>> [b & 0xFFFFFFFF for b in bits] == [mix32(0), mix32(1), mix32(2), mix32(0xFFFFFFFF)]
        True
    """
    if isinstance(x, int):
        x &= 0xFFFFFFFF
        x = (((x >> 16) ^ x) * _MUL) & 0xFFFFFFFF
        x = (((x >> 16) ^ x) * _MUL) & 0xFFFFFFFF
        return (x >> 16) ^ x
    x = (((x >> 16) & 0xFFFF) ^ x) * _MUL
    x = (((x >> 16) & 0xFFFF) ^ x) * _MUL
    return ((x >> 16) & 0xFFFF) ^ x


def key_head(seed: int, stream: int = 0) -> int:
    """The part of every sample's key that comes from ``(seed, stream)``, an unsigned 32-bit int:
    the key of ``(pixel, sample)`` is ``mix32(mix32(pixel ^ head) ^ sample)``.

    Example:
        >>> key_head(0) == mix32(mix32(0))
        True
    """
    return mix32(mix32(seed) ^ ((stream * 0x9E3779B9) & 0xFFFFFFFF))


def sample_keys(seed: int, pixel: torch.Tensor, sample: torch.Tensor, stream: int = 0) -> torch.Tensor:
    """One 32-bit key per sample from ``(seed, stream, pixel, sample)``.

    Args:
        seed: the render's seed, an int in [0, 2^32).
        pixel: ``(N,)`` integer global pixel index ``b*H*W + y*W + x`` (< 2^31).
        sample: ``(N,)`` integer sample index within the pixel (< 2^31).
        stream: separates independent passes over the same pixels.

    Returns:
        ``(N,)`` int32 keys (32 random bits each).

    Example:
        >>> k = sample_keys(0, torch.tensor([5, 5]), torch.tensor([0, 1]))
        >>> k.dtype, bool(k[0] != k[1])
        (torch.int32, True)
    """
    head = _signed(key_head(seed, stream))
    return mix32(mix32(pixel.to(torch.int32) ^ head) ^ sample.to(torch.int32))


def uniform(keys: torch.Tensor, dims: range | list[int], dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Uniform numbers in [0, 1) for dimensions ``dims`` of each key.

    Args:
        keys: ``(N,)`` int32 from :func:`sample_keys`.
        dims: the dimension indices, one row each.

    Returns:
        ``(len(dims), N)`` values in [0, 1 - 2^-24].

    Example:
        >>> u = uniform(torch.arange(4, dtype=torch.int32), [0, 1])
        >>> u.shape, bool(((u >= 0) & (u < 1)).all())
        (torch.Size([2, 4]), True)
    """
    salt = torch.tensor([_signed(mix32(d * 0x27D4EB2F + 0x165667B1)) for d in dims], dtype=torch.int32)
    h = mix32(keys.unsqueeze(0) ^ salt.to(keys.device).unsqueeze(1))
    return ((h >> 8) & 0xFFFFFF).to(dtype) * (1.0 / (1 << 24))
