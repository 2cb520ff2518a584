"""The C back end: compiled CPU kernels of the filters (one À-Trous level, the guided filter and
the box filter it is built from, its gradients, per-pixel kernels and their gradients), the Denoiser's guided pipeline, the sampling importance map and
the sample allocation, the temporal ops and the path tracer, float32.

One file per op family, in Python and in C: :mod:`.filters` (``atrous.c``, ``guided.c``), :mod:`.kernels` (``kernels.c``),
:mod:`.pipeline` (``pipeline.c``), :mod:`.pyramid` (``pyramid.c``), :mod:`.sampling` (``importance.c``, ``allocate.c``),
:mod:`.accumulation` (``accumulate.c``), :mod:`.tracer` (``tracer.c``, embree 4 through
:mod:`.embree`); :mod:`.build` compiles and loads the library (``native.c`` includes the family
files and ``common.h``), :mod:`.runtime` holds how a call is cut into bands. This module is
the back end's registry: :func:`supports`, :func:`describe` and one function per op.

The torch code walks the image once per element-wise op; these kernels do a
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

import math

import torch

from torchgi.backends.base import (
    AllocateOp,
    AppliedMeansOp,
    ATrousOp,
    BackOffOp,
    BlockMeanOp,
    BoxOp,
    ChooseOp,
    EdgeShareOp,
    FineBandOp,
    GuidedOp,
    GuideStatsOp,
    ImportanceOp,
    LightInOp,
    LightOutOp,
    MixHalfOp,
    ModelResidualOp,
    RestoreOp,
    UpsampleApplyOp,
    float32_eager,
)
from torchgi.backends.c_kernels import build
from torchgi.backends.c_kernels.accumulation import accumulate, change, history
from torchgi.backends.c_kernels.build import describe, library
from torchgi.backends.c_kernels.filters import (
    atrous,
    atrous_level,
    atrous_level_grad,
    box,
    guided,
    guided_grad,
    upsample_apply,
)
from torchgi.backends.c_kernels.kernels import apply_kernels, apply_kernels_grad
from torchgi.backends.c_kernels.pipeline import back_off, choose, edge_share, guide_stats, light_in, light_out, restore
from torchgi.backends.c_kernels.pyramid import applied_means, block_means, fine_band, mix_half, model_residual
from torchgi.backends.c_kernels.runtime import empty_planes, padded
from torchgi.backends.c_kernels.sampling import allocate, importance
from torchgi.backends.c_kernels.tracer import _path_support, guide_rays, path

__all__ = [
    "NAME", "accumulate", "allocate", "applied_means", "apply_kernels", "apply_kernels_grad", "atrous", "atrous_level", "atrous_level_grad", "back_off", "block_means", "box", "change", "choose", "describe", "edge_share",
    "empty_planes", "fine_band", "guide_rays", "guide_stats", "guided", "guided_grad", "history", "importance", "library", "light_in", "light_out",
    "mix_half", "model_residual", "padded", "path", "ready", "restore", "supports",
    "upsample_apply",
]

NAME = "c"
# the image tensor of the ops whose kernels walk one image of fewer than 2^31 pixels per call
_IMAGE = {"accumulate": "x", "change": "x", "history": "out", "restore": "color", "light_in": "color", "light_out": "color", "model_residual": "x",
          "fine_band": "model", "block_means": "x", "applied_means": "guide", "apply_kernels": "x", "apply_kernels_grad": "x",
          "atrous_level": "color", "atrous_level_grad": "color", "guided_grad": "src"}


def ready(op: str, device: str) -> str | None:
    """None when the kernels can take eager float32 calls of ``op`` on ``device`` tensors ("cpu",
    "cuda") here, whatever their sizes (a built library, CPU tensors); else why not
    (:func:`torchgi.backends.plan`).

    Example:
        >>> ready("box", "cuda")
        'the C kernels take CPU tensors'
    """
    if device != "cpu":
        return "the C kernels take CPU tensors"
    return None if library() is not None else build._status


def supports(op: str, desc: BoxOp | GuidedOp | ATrousOp | ImportanceOp | AllocateOp | GuideStatsOp | EdgeShareOp |
             RestoreOp | LightInOp | LightOutOp | MixHalfOp | ModelResidualOp | FineBandOp | BlockMeanOp | AppliedMeansOp |
             BackOffOp | ChooseOp | UpsampleApplyOp) -> str | None:
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
    image, surface = _IMAGE.get(op), getattr(desc, "surface", None)  # (the temporal ops' mask, read as bytes)
    if image is not None and (getattr(desc, image).numel() == 0 or math.prod(getattr(desc, image).shape[-2:]) >= 2**31
                              or (surface is not None and surface.dtype != torch.bool)):
        return f"the C {op} takes non-empty images of fewer than 2^31 pixels (and a bool surface mask)"
    why = _shape_limits(op, desc)
    if why is not None:
        return why
    return None if build.library() is not None else build._status


def _shape_limits(op: str, desc: object) -> str | None:
    """Why the C kernel of ``op`` cannot take the shapes (or per-pixel inputs) of ``desc``, or None."""
    if op in ("model_residual", "mix_half") and not 1 <= len(desc.ys if op == "model_residual" else desc.fines) <= 4:
        return f"the C {op} takes 1 to 4 candidates"
    if op in ("atrous_level", "atrous_level_grad") and (desc.color.shape[1] not in (1, 3) or (
            len(desc.guides) > 2 or any(g.shape[1] != 3 for g in desc.guides))):
        return f"the C {op} takes 1 or 3 colour channels and at most 2 guides of 3 planes"
    if op == "guided_grad" and desc.src.shape[1] > 3:
        return "the C guided filter's gradients take at most 3 source channels"
    if op == "upsample_apply":
        C, (n, H, W) = desc.coeffs.shape[2], desc.guide.shape[1:]
        if n > 4 or C > 64 or H * W == 0 or H * W >= 2**31:
            return "the C upsampling takes at most 4 guide planes, 64 channels, 1 to 2^31 pixels"
    if op == "back_off":
        if torch.is_tensor(desc.spp):
            return "per-pixel sample counts: the torch code"
        if desc.out.numel() == 0 or desc.out.shape[1] != 3 or desc.variance.shape[1] not in (1, 3):
            return "the C back-off takes non-empty 3-channel images with 1 or 3 variance planes"
    if op == "choose":
        o = desc.outs[0]
        if not 2 <= len(desc.outs) <= 4 or o.numel() == 0 or o.shape[1] != 3 or desc.variance.shape[1] not in (1, 3):
            return "the C choice takes 2 to 4 non-empty 3-channel images with 1 or 3 variance planes"
    return None
