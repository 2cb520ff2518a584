"""What every test file shares: the relative error against an oracle, and which back end ran."""

from __future__ import annotations

import numpy as np
import torch

from torchgi import backends


def rel_error(out: torch.Tensor, ref: torch.Tensor | np.ndarray, scale: str = "max") -> float:
    """``max |out - ref|`` over ``max |ref|`` (``scale="max"``) or over ``max ref - min ref``
    (``"range"``: for outputs whose offset is arbitrary, like a guided filter of offset guides)."""
    ref = torch.as_tensor(np.asarray(ref) if not torch.is_tensor(ref) else ref).double().cpu()
    diff = float((out.detach().double().cpu() - ref).abs().max())
    return diff / float(ref.abs().max() if scale == "max" else ref.max() - ref.min())


def last_backend(op: str) -> str:
    """The back end that computed the last ``op`` ("box", "guided", "atrous", "importance", "allocate")."""
    return backends.status()["last"][op]["ran"]


def rel_range(out: torch.Tensor, ref: torch.Tensor | np.ndarray) -> float:
    """:func:`rel_error` over the range of ``ref``."""
    return rel_error(out, ref, "range")
