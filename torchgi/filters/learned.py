"""What the learned filters share: their networks' weights as JSON (no pickle) with the
provenance of their training, the shipped network read once per process, the learnable
parameters of the filter Modules that stay in range (:func:`register_positive`) and the σ-like
parameters as floats, per-image tensors or per-pixel maps (:func:`inverse_power`)."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch
import torch.nn.utils.parametrize
from torch import nn
from typing_extensions import Self

from torchgi.core.check import check_floating, check_same_device, is_recording
from torchgi.core.errors import RangeError, ShapeError

__all__ = ["Positive", "SavedNet", "inverse_power", "register_positive", "shipped"]

N = TypeVar("N", bound="SavedNet")


class SavedNet(nn.Module):
    """A network saved with its constructor arguments (:meth:`config`, defined by each learned
    filter) and the provenance of its training.

    Example:
        >>> from torchgi.filters.pyramid import PyramidNet
        >>> import os, tempfile
        >>> path = os.path.join(tempfile.mkdtemp(), "net.json")
        >>> PyramidNet().save(path, {"script": "example"})
        >>> PyramidNet.load(path).provenance
        {'script': 'example'}
    """

    def config(self) -> dict[str, Any]:
        """The constructor arguments (what the weights file records)."""
        raise NotImplementedError

    def save(self, path: str | Path, provenance: dict[str, Any]) -> None:
        """Write config, weights and ``provenance`` to a JSON file (no pickle): each weight as the
        shortest decimal that reads back to the same float32 (:meth:`load` is bit-exact)."""
        state = {k: _shortest(v) for k, v in self.state_dict().items()}
        Path(path).write_text(json.dumps({"config": self.config(), "provenance": provenance, "state": state}))

    @classmethod
    def load(cls, path: str | Path) -> Self:
        """Read a file written by :meth:`save`: the network in eval mode, without gradients,
        with its ``provenance``."""
        data = json.loads(Path(path).read_text())
        net = cls(**data["config"])
        net.load_state_dict({k: torch.tensor(v, dtype=torch.float32) for k, v in data["state"].items()})
        net.provenance = data.get("provenance", {})
        return net.eval().requires_grad_(False)


def _shortest(t: torch.Tensor) -> Any:
    """``t`` as nested lists of the shortest decimals that read back to its float32 values."""
    a = t.detach().cpu().float().numpy()
    return np.array([float(str(x)) for x in a.ravel()], dtype=np.float64).reshape(a.shape).tolist()


def shipped(cls: type[N], path: Path, device: torch.device | str, cache: dict[torch.device, N], what: str,
            script: str) -> N:
    """The network of ``cls`` shipped at ``path`` on ``device``: read once per process into
    ``cache``, one copy per device; a missing file names ``what`` and the ``script`` that makes it.

    Example:
        >>> from torchgi.filters.pyramid import WEIGHTS, PyramidNet
        >>> len(shipped(PyramidNet, WEIGHTS, "cpu", {}, "the pyramid's weights", "scripts/train_pyramid.py").candidates)
        9
    """
    device = torch.device(device)
    if device not in cache:
        if device.type != "cpu":
            cache[device] = copy.deepcopy(shipped(cls, path, "cpu", cache, what, script)).to(device)
        elif not path.is_file():
            raise FileNotFoundError(f"{path}: {what} are missing (python {script})")
        else:
            cache[device] = cls.load(path)
    return cache[device]


class Positive(nn.Module):
    """The parametrization of a learnable parameter that must stay above 0 (a filter's ε or σ):
    the stored, unconstrained value ``u`` is read as ``softplus(u) + FLOOR``, so no optimiser step
    can leave the range (softplus alone underflows to 0 in float32 below ``u`` ≈ -104).

    Example:
        >>> p = Positive()
        >>> round(float(p(p.right_inverse(torch.tensor(0.01)))), 6)   # a value survives the round trip
        0.01
        >>> float(p(torch.tensor(-1e4))) > 0
        True
    """

    FLOOR = 1e-12

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        return nn.functional.softplus(u) + self.FLOOR

    def right_inverse(self, value: torch.Tensor) -> torch.Tensor:
        v = value - self.FLOOR
        return v + torch.log(-torch.expm1(-v))  # softplus⁻¹


def register_positive(module: nn.Module, name: str, value: torch.Tensor) -> None:
    """Make ``module.<name>`` a learnable parameter > 0 holding ``value``: ``module.<name>`` reads
    the value in the filter's units (with its gradient path), the optimiser sees the unconstrained
    ``module.parametrizations.<name>.original``. ``value`` must be above :attr:`Positive.FLOOR` (a ValueError naming it
    otherwise).

    Example:
        >>> m = nn.Module()
        >>> register_positive(m, "eps", torch.tensor(0.05))
        >>> round(float(m.eps.detach()), 6), [n for n, _ in m.named_parameters()]
        (0.05, ['parametrizations.eps.original'])
    """
    if not bool((value > Positive.FLOOR).all()) or not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name}: a learnable {name} must be finite and > {Positive.FLOOR:g} (stored as softplus⁻¹), "
                         f"got {value.tolist()}")
    module.register_parameter(name, nn.Parameter(value.clone()))
    torch.nn.utils.parametrize.register_parametrization(module, name, Positive())


def inverse_power(value: float | torch.Tensor | None, name: str, B: int, like: torch.Tensor, power: int = 1,
             per_pixel: bool = False) -> torch.Tensor | None:
    """``value^-power`` of a filter's σ-like parameter (a float or a ``(B,)`` tensor, > 0) as
    ``(B, 1, 1, 1)`` in ``like``'s dtype/device; with ``per_pixel`` also a ``(B, 1, H, W)`` map of
    ``like``'s size, returned as such; None stays None. A float is checked and inverted on the
    host and filled in on the device (one launch, no synchronisation); a tensor is differentiable.

    Example:
        >>> inverse_power(2.0, "sigma", 1, torch.zeros(1, 3, 4, 4), power=2).flatten().tolist()
        [0.25]
        >>> inverse_power(torch.full((1, 1, 4, 4), 0.5), "sigma", 1, torch.zeros(1, 3, 4, 4), per_pixel=True).shape
        torch.Size([1, 1, 4, 4])
    """
    if value is None:
        return None
    if isinstance(value, torch.Tensor):
        check_same_device({name: value, "color": like})
        check_floating(value, name)
        plane = (B, 1, *like.shape[-2:])
        if value.shape not in ((), (1,), (B,)) and not (per_pixel and tuple(value.shape) == plane):
            raise ShapeError(f"{name}: expected a float or shape ({B},)"
                             + (f" or a {plane} map" if per_pixel else "") + f", got {tuple(value.shape)}")
        t = value.to(like.dtype)
        if not is_recording() and bool((~torch.isfinite(t) | (t <= 0)).any()):
            raise RangeError(f"{name}: expected finite values > 0 (a float or a ({B},) tensor), got "
                             f"{t.flatten().tolist()[:4]}")
        if t.dim() == 4:
            return t.pow(-power)
        return t.pow(-power).reshape(-1, 1, 1, 1).expand(B, 1, 1, 1)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise RangeError(f"{name}: expected finite values > 0 (a float or a ({B},) tensor), got {value!r}")
    return torch.full((B, 1, 1, 1), float(value) ** -power, dtype=like.dtype, device=like.device)
