"""The Triton back end, for CUDA tensors (float32, without autograd or tracing): an À-Trous level,
the guided filter (with the box filter it is built from) and its gradients, the Denoiser's guided pipeline, the
temporal accumulation, and per-pixel kernels with their gradients.

One file per op family: :mod:`.filter_atrous`, :mod:`.filter_guided` (and the box filter), :mod:`.filter_guided_grad`, :mod:`.filter_kernels`,
:mod:`.pipeline`, :mod:`.accumulation` (one launch per frame);
:mod:`.common` holds Triton itself and what the kernels share. This module is the back end's
registry: :func:`supports`, :func:`describe` and one function per op.

The torch code of an À-Trous level launches about ten kernels per tap; the level kernel does a
level in one launch: each program filters a tile of pixels, walks the 25 taps with the weighted
sums in registers and writes the level's colour, variance and weight sum. Same maths as the
torch code and the C back end.

The guided filter is six launches: products of the centred guide and source summed down the
columns (sliding windows, double accumulators), those sums summed along the rows (a running
difference and a prefix sum, double), the per-pixel LDLᵀ solve (written once for four guide
channels; absent channels enter as exact zeros), the two box passes again over the
coefficients, and the apply. Cost does not depend on the radius beyond one window per tile.

Triton comes with CUDA builds of torch; without it (or on the CPU) the torch code runs. With
``TRITON_INTERPRET=1`` set before torchgi is imported, the same kernels run on CPU tensors
through Triton's interpreter (the tests check them there against float64 oracles). Tile sizes
and warps come from ``scripts/sweep_gpu_tiles.py`` (docs/calibration.md).

Example:
    >>> import torch
    >>> from torchgi.backends import BoxOp, triton_kernels
    >>> triton_kernels.supports("box", BoxOp(torch.zeros(1, 1, 2, 2), 1)) is not None   # a CPU tensor
    True
"""

from __future__ import annotations

import torch

from torchgi.backends.base import AccumulateOp, ATrousOp, BoxOp, GuidedOp, RestoreOp, float32_eager
from torchgi.backends.triton_kernels.accumulation import accumulate
from torchgi.backends.triton_kernels.common import _INTERPRET, triton
from torchgi.backends.triton_kernels.filter_atrous import MAX_CHANNELS, atrous, atrous_level, atrous_level_grad
from torchgi.backends.triton_kernels.filter_guided import box, guided
from torchgi.backends.triton_kernels.filter_guided_grad import guided_grad
from torchgi.backends.triton_kernels.filter_kernels import apply_kernels, apply_kernels_grad
from torchgi.backends.triton_kernels.pipeline import restore

__all__ = ["MAX_CHANNELS", "NAME", "OPS", "accumulate", "apply_kernels", "apply_kernels_grad", "atrous", "atrous_level",
           "atrous_level_grad", "box", "describe", "guided", "guided_grad", "ready", "restore", "supports"]

NAME = "triton"
OPS = ("box", "guided", "guided_grad", "atrous", "restore", "accumulate", "apply_kernels", "apply_kernels_grad",
       "atrous_level", "atrous_level_grad")  # the ops with a Triton kernel


def describe() -> str:
    """One line for :func:`torchgi.backends.status`.

    Example:
        >>> isinstance(describe(), str)
        True
    """
    if triton is None:
        return "Triton not installed (it ships with CUDA builds of torch)"
    where = "CPU tensors through Triton's interpreter" if _INTERPRET else "CUDA tensors"
    return f"Triton {triton.__version__} kernels for {where}"


def ready(op: str, device: str) -> str | None:
    """None when the kernels can take eager float32 calls of ``op`` on ``device`` tensors ("cpu",
    "cuda") here, whatever their sizes; else why not (:func:`torchgi.backends.plan`).

    Example:
        >>> ready("importance", "cuda")
        'no Triton kernel for importance'
    """
    if op not in OPS:
        return f"no Triton kernel for {op}"
    if triton is None:
        return "Triton not installed"
    if device != "cuda" and not _INTERPRET:
        return "the Triton kernels take CUDA tensors"
    if device == "cuda" and not torch.cuda.is_available():
        return "no CUDA device here"
    return None


def supports(op: str, desc: BoxOp | GuidedOp | ATrousOp | RestoreOp | AccumulateOp) -> str | None:
    """None when the kernels take ``desc``: an À-Trous level, the guided or box filter, the
    guided pipeline, the temporal accumulation or per-pixel kernels and their gradients of eager float32 CUDA tensors (CPU ones under the
    interpreter), at most 4 À-Trous colour channels; else why not.

    Example:
        >>> supports("importance", None)   # no Triton kernel of the importance map
        'no Triton kernel for importance'
    """
    ts = [t for t in desc.tensors() if t is not None] if op in OPS else []
    why = ready(op, "cuda" if ts and all(t.device.type == "cuda" for t in ts) else "cpu")
    if why is not None:
        return why
    why = float32_eager(op, desc, "Triton")
    if why is not None:
        return why
    if op == "accumulate" and desc.x.shape[-2] * desc.x.shape[-1] >= 2**31:
        return "the Triton accumulation takes images of fewer than 2^31 pixels"
    if op == "atrous" and desc.color.shape[1] > MAX_CHANNELS:
        return f"the À-Trous kernel takes at most {MAX_CHANNELS} colour channels"
    if op in ("atrous_level", "atrous_level_grad") and (desc.color.shape[1] > MAX_CHANNELS or (
            len(desc.guides) > 2 or any(g.shape[1] != 3 for g in desc.guides))):
        return f"the Triton {op} takes at most {MAX_CHANNELS} colour channels and at most 2 guides of 3 planes"
    if op == "atrous" and desc.inv_color.shape[-2:] != (1, 1):
        return "a per-pixel sigma_color map: the torch code"
    return None

