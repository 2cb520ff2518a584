"""What the learned filters share: their networks' weights as JSON (no pickle) with the
provenance of their training, the shipped network read once per process, and the learnable
parameters of the filter Modules that stay in range (:func:`register_positive`)."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any, TypeVar

import torch
import torch.nn.utils.parametrize
from torch import nn
from typing_extensions import Self

__all__ = ["Positive", "SavedNet", "register_positive", "shipped"]

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
        """Write config, weights (as lists) and ``provenance`` to a JSON file (no pickle)."""
        state = {k: v.detach().double().tolist() for k, v in self.state_dict().items()}
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
