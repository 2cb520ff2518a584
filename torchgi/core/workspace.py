"""Buffers kept between calls: a result written into a tensor a caller keeps in a dict
(``workspace``) instead of a new one, so that its pages are not faulted in again on every call
(docs/pyramid.md, "Results kept between calls"). Only where no gradient flows and no graph is
recorded."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from torchgi.core.check import is_recording


def reusable(fresh: torch.Tensor, *others: torch.Tensor) -> bool:
    """Whether ``fresh`` (a temporary the caller just made and nothing else holds) may take a
    result in place of a new tensor: no gradient flows through it or ``others`` (the call runs
    for inference, not training) and no graph is being recorded.

    Example:
        >>> reusable(torch.zeros(2)), reusable(torch.zeros(2, requires_grad=True))
        (True, False)
    """
    return not is_recording() and not (fresh.requires_grad or any(t.requires_grad for t in others))


def kept_buffer(workspace: dict | None, key: str, shape: Sequence[int], like: torch.Tensor) -> torch.Tensor | None:
    """A float32 CPU buffer of ``shape`` kept in ``workspace`` under ``key`` for a result between
    calls (remade when the size changes), or None without a workspace, where ``like`` is not a
    float32 CPU tensor or where gradients flow (:func:`reusable`). Every key is written once per
    call and read in that call; pass the result as an ``out=`` (None: a new tensor).

    Example:
        >>> ws = {}
        >>> a = kept_buffer(ws, "x", (1, 3, 4, 4), torch.zeros(1))
        >>> a is kept_buffer(ws, "x", (1, 3, 4, 4), torch.zeros(1)), kept_buffer(None, "x", (1,), torch.zeros(1))
        (True, None)
    """
    if workspace is None or like.dtype != torch.float32 or like.device.type != "cpu" or not reusable(like):
        return None
    if workspace.get(key) is None or tuple(workspace[key].shape) != tuple(shape):
        workspace[key] = torch.empty(tuple(shape), dtype=torch.float32)
    return workspace[key]
