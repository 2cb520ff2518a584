"""ONNX export with dynamic batch/height/width, and an onnxruntime wrapper (the ``onnx`` extra)."""

from __future__ import annotations

import contextlib
import inspect
import logging
import math
import os
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from torchgi.core.check import check_int, check_positive, check_shape, require
from torchgi.core.files import temp_beside

__all__ = ["OrtDenoiser", "OrtSession", "export_denoiser", "export_onnx", "export_temporal"]


def export_onnx(
    module: nn.Module,
    example_inputs: Sequence[torch.Tensor],
    path: str | os.PathLike,
    *,
    input_names: Sequence[str],
    output_names: Sequence[str] = ("out",),
    opset: int = 18,
    optimize: bool = True,
    overwrite: bool = False,
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Export ``module`` to ONNX with dynamic B, H, W on every ``(B, C, H, W)`` input.

    Args:
        module: a torchgi Module (e.g. :class:`torchgi.filters.Guided`), put in eval mode.
        example_inputs: ``(B, C, H, W)`` tensors of the call signature, in order, with B, H
            and W all different (equal example sizes can be tied together by the exporter).
        path: destination ``.onnx`` file; written atomically, never overwritten unless asked.
        input_names, output_names: graph names; ``input_names`` match ``example_inputs``.
        opset: ONNX opset (>= 17).
        optimize: run the ONNX graph optimizer (cleaner graph; on large unrolled filters like
            5-level À-Trous it is the slow part of the export).
        metadata: string pairs written into the model's ``metadata_props`` (onnxruntime:
            ``session.get_modelmeta().custom_metadata_map``; :class:`OrtSession.metadata`).

    Returns:
        The path written.

    Example:
        >>> import tempfile
        >>> from torchgi.filters import Box
        >>> p = export_onnx(Box(2), [torch.rand(1, 3, 8, 9)],
        ...                 os.path.join(tempfile.mkdtemp(), "box.onnx"), input_names=["x"])
        >>> OrtSession(p)(x=torch.ones(2, 3, 5, 7)).shape
        torch.Size([2, 3, 5, 7])
    """
    require("onnx", "onnx")
    require("onnxscript", "onnx")
    check_int(opset, "opset", 17)
    if len(input_names) != len(example_inputs):
        raise ValueError(f"input_names: {len(input_names)} names for {len(example_inputs)} inputs")
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"path: {path} exists; pass overwrite=True to replace it")
    B, H, W = (torch.export.Dim(d, min=1) for d in "BHW")
    dynamic = []  # by position: graph input names need not be the forward's parameter names
    sizes: dict[str, int] = {}
    for name, x in zip(input_names, example_inputs):
        shape = check_shape(x, "B C H W", name)
        check_shape(x, f"B {shape['C']} H W", name, sizes)
        dynamic.append({0: B, 2: H, 3: W})
    if len({sizes["B"], sizes["H"], sizes["W"]}) < 3:
        # The exporter can tie dimensions whose example sizes coincide into one symbol.
        raise ValueError(
            f"example_inputs: use distinct sizes for B, H and W (got B={sizes['B']}, H={sizes['H']}, "
            f"W={sizes['W']}) so none of them is tied to another in the exported graph"
        )
    shapes = tuple(dynamic)
    if any(p.kind is p.VAR_POSITIONAL for p in inspect.signature(module.forward).parameters.values()):
        shapes = (shapes,)  # forward(*inputs): the exporter sees one argument, a tuple
    tmp = temp_beside(path)
    try:
        with _exporter_notes_hidden():
            torch.onnx.export(
                module.eval(), tuple(example_inputs), tmp, input_names=list(input_names),
                output_names=list(output_names), dynamic_shapes=shapes, opset_version=opset, dynamo=True,
                optimize=optimize, verbose=False,
            )
        if metadata:
            import onnx

            model = onnx.load(tmp)
            for key, value in metadata.items():
                model.metadata_props.add(key=str(key), value=str(value))
            onnx.save(model, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
        data = f"{tmp}.data"  # the exporter's external-weights file, empty: the weights are in the graph
        if os.path.exists(data) and os.path.getsize(data) == 0:
            os.unlink(data)
    return path


# What the exporter says on every export that asks nothing of the user: each input after the
# first names its B, H and W axes again (the same axis: the name is used once), and torch's own
# code calls a deprecated pytree type. A warning that one axis takes *another* axis' name (two
# dimensions tied in the graph) is kept.
_NOTES = (
    (UserWarning, (r"# The axis name: (\w+) will not be used, since it shares the same shape constraints "
                   r"with another axis: \1\.$")),
    (FutureWarning, r"`isinstance\(treespec, LeafSpec\)` is deprecated"),
)


def _skipped_torchvision(record: logging.LogRecord) -> bool:
    """A logging filter: False for the exporter's note that it skips torchvision's operators
    (none of torchgi's graphs uses them)."""
    return not record.getMessage().startswith("torchvision is not installed")


@contextlib.contextmanager
def _exporter_notes_hidden() -> Iterator[None]:
    """Inside: the exporter's routine notes (:data:`_NOTES`, the torchvision log line) are not
    shown; every other warning is."""
    registration = logging.getLogger("torch.onnx._internal.exporter._registration")
    registration.addFilter(_skipped_torchvision)
    try:
        with warnings.catch_warnings():
            for category, message in _NOTES:
                warnings.filterwarnings("ignore", message, category)
            yield
    finally:
        registration.removeFilter(_skipped_torchvision)


class OrtSession:
    """An onnxruntime session called with named torch tensors; returns the first output.

    Inputs are handed to onnxruntime as numpy (CPU); the output comes back as a CPU tensor.
    """

    def __init__(self, path: str | os.PathLike, providers: Sequence[str] | None = None) -> None:
        ort = require("onnxruntime", "onnx")
        self.session = ort.InferenceSession(str(path), providers=list(providers or ["CPUExecutionProvider"]))
        self.input_names = [i.name for i in self.session.get_inputs()]
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)  # export_onnx(metadata=)

    def __call__(self, **inputs: torch.Tensor) -> torch.Tensor:
        return self.outputs(**inputs)[0]

    def outputs(self, **inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Every output of the graph, in its order (e.g. a temporal step's image and next state)."""
        missing = set(self.input_names) - set(inputs)
        if missing:
            raise ValueError(f"missing inputs {sorted(missing)}; the graph takes {self.input_names}")
        feed = {k: np.ascontiguousarray(inputs[k].detach().cpu().numpy()) for k in self.input_names}
        return tuple(torch.from_numpy(y) for y in self.session.run(None, feed))


def export_denoiser(
    method: str,
    path: str | os.PathLike,
    *,
    spp: float | None = None,
    quality: str = "balanced",
    sigma_position: float | None = None,
    emission: bool = True,
    frame: Any = None,
    variance: bool | None = None,
    overwrite: bool = False,
    **filter_params: Any,
) -> Path:
    """Export ``torchgi.Denoiser(method, quality, **filter_params)`` fixed for ``spp`` samples
    per pixel, or for a representative GBuffer ``frame`` (:meth:`torchgi.Denoiser.deploy`), to ONNX.

    The graph takes ``color``, ``emission`` (not with ``emission=False``: the light sources are
    then found from the colour, as the eager Denoiser does without an emission layer),
    ``albedo``, ``normal`` and ``depth`` (or ``position`` for À-Trous, with ``sigma_position``
    in scene units squared) and, with ``variance`` (:meth:`torchgi.Denoiser.deploy`: by default
    where ``frame`` has a variance from 2 samples or more), ``variance`` (3 channels, or the
    frame's count), all ``(B, C, H, W)`` float32 with dynamic B/H/W, and returns the denoised
    ``(B, 3, H, W)`` colour. ``spp`` (default 1) and ``sigma_position``, where given, are finite
    numbers > 0.

    Example:
        >>> import tempfile
        >>> p = export_denoiser("guided", os.path.join(tempfile.mkdtemp(), "d.onnx"))
        >>> OrtDenoiser(p).input_names
        ['color', 'emission', 'albedo', 'normal', 'depth']
    """
    from torchgi import methods
    from torchgi.denoise import Denoiser

    for name, value in (("spp", spp), ("sigma_position", sigma_position)):
        if value is not None:
            check_positive(value, name)
    module = Denoiser(method, quality, **filter_params).deploy(spp=spp, sigma_position=sigma_position,
                                                               emission=emission, frame=frame, variance=variance)
    g = torch.Generator().manual_seed(0)
    B, H, W = 2, 24, 32
    channels = {"depth": 1, "variance": 3 if getattr(frame, "variance", None) is None else frame.variance.shape[1]}
    examples = [torch.rand(B, channels.get(name, 3), H, W, generator=g) for name in module.input_names]
    return export_onnx(module, examples, path, input_names=list(module.input_names), overwrite=overwrite,
                       optimize=methods.get(method).onnx_optimize, metadata=module.metadata())


def export_temporal(path: str | os.PathLike, *, fresh: bool = True, overwrite: bool = False) -> Path:
    """Export one frame of temporal denoising, :class:`torchgi.temporal.DeployedTemporal` (its
    ``input_names`` and ``output_names``: the frame's layers and the state in, the image and the
    next state out), to ONNX with dynamic B/H/W.

    Args:
        path: destination ``.onnx`` file; never overwritten unless ``overwrite``.
        fresh: new pixels blended towards the per-frame Denoiser (``DeployedTemporal(fresh)``).

    Example (an export takes about 30 s on 2 cores; tests/test_cli.py runs it):
        >>> import tempfile
        >>> p = export_temporal(os.path.join(tempfile.mkdtemp(), "t.onnx"))  # doctest: +SKIP
        >>> OrtSession(p).input_names[:6]  # doctest: +SKIP
        ['color', 'emission', 'albedo', 'normal', 'depth', 'motion']
    """
    from torchgi.temporal import DeployedTemporal

    module = DeployedTemporal(fresh)
    g = torch.Generator().manual_seed(0)
    B, H, W = 2, 24, 32
    channels = {"color": 3, "emission": 3, "albedo": 3, "normal": 3, "depth": 1, "motion": 2, "light": 3,
                "history": 3, "moments": 2, "length": 1, "prev_normal": 3, "prev_depth": 1, "prev_surface": 1}
    examples = [torch.rand(B, channels[name], H, W, generator=g) for name in module.input_names]
    return export_onnx(module, examples, path, input_names=list(module.input_names),
                       output_names=list(module.output_names), optimize=False, overwrite=overwrite)


class OrtDenoiser:
    """An exported Denoiser in onnxruntime, called like :class:`torchgi.Denoiser`: with a
    GBuffer or with named tensors: those of :attr:`input_names`. Nothing is dropped or made up:
    an emission layer the graph was exported with must be given, one it was exported without is
    refused; a ``variance`` is refused by a graph exported without one (but for 2 samples per
    pixel or more, where the eager Denoiser would use it), and a sample count
    (``gb.spp``, or ``spp=`` a number or a ``(B, 1, H, W)`` plane) other than the one the graph
    was fixed for (:attr:`spp`, from its metadata: :meth:`torchgi.deployed.DeployedDenoiser.metadata`)
    is refused by name, unless ``ignore`` names it: ``ignore=("spp", "variance")`` runs the graph
    as fixed whatever the input says.

    Args:
        path: the ``.onnx`` file (:func:`export_denoiser`, ``torchgi export``).
        providers: onnxruntime execution providers (default CPU).
        ignore: inputs the graph cannot use that a call may carry without being refused
            (``"spp"``, ``"variance"``).

    Example:
        >>> import tempfile
        >>> p = export_denoiser("guided", os.path.join(tempfile.mkdtemp(), "d.onnx"), spp=4)  # doctest: +SKIP
        >>> OrtDenoiser(p).spp  # doctest: +SKIP
        4.0
    """

    IGNORABLE = ("spp", "variance")

    def __init__(self, path: str | os.PathLike, providers: Sequence[str] | None = None, *,
                 ignore: Sequence[str] = ()) -> None:
        if isinstance(ignore, str) or any(k not in self.IGNORABLE for k in ignore):
            raise ValueError(f"ignore: expected a sequence of {', '.join(map(repr, self.IGNORABLE))}, got {ignore!r}")
        self.session = OrtSession(path, providers)
        self.input_names = self.session.input_names
        self.ignore = tuple(ignore)
        recorded = self.session.metadata.get("torchgi.spp")
        #: the render's sample count the graph is fixed for; None where it records none
        self.spp = float(recorded) if recorded else None

    def __call__(self, gb=None, *, spp: float | torch.Tensor | None = None, **tensors: torch.Tensor) -> torch.Tensor:
        if gb is not None:
            if tensors:
                raise TypeError(f"{', '.join(tensors)}: give a GBuffer or named tensors, not both")
            tensors = {k: getattr(gb, k) for k in set(self.input_names) | {"emission", "variance"}
                       if getattr(gb, k, None) is not None}
            if spp is None:
                spp = gb.spp
        unknown = [k for k in tensors if k not in self.input_names and k not in ("emission", "variance")]
        if unknown:
            raise TypeError(f"{', '.join(unknown)}: not an input of this graph (inputs {', '.join(self.input_names)})")
        missing = [k for k in self.input_names if k not in tensors]
        if "emission" in missing:
            raise ValueError("emission: this graph was exported with an emission input; pass it (zeros when no "
                             "light source is in view) or export with emission=False for renders without one")
        if "emission" in tensors and "emission" not in self.input_names:
            raise ValueError("emission: this graph was exported without an emission input (emission=False); "
                             "export with emission=True to use one")
        if missing:
            raise ValueError(f"{', '.join(missing)}: required by this graph (inputs {', '.join(self.input_names)})")
        if spp is not None and "spp" not in self.ignore:
            self._check_spp(spp)
        # at 1 sample the variance is unknown (stored as 0) and the eager Denoiser does not use it either
        used = self.spp is None or self.spp >= 2
        if "variance" in tensors and "variance" not in self.input_names and used and "variance" not in self.ignore:
            raise ValueError("variance: this graph was exported without a variance input and would not use it; "
                             "export with variance=True (torchgi export --variance) or pass ignore=('variance',)")
        return self.session(**{k: v.float() for k, v in tensors.items() if k in self.input_names})

    def _check_spp(self, spp: float | torch.Tensor) -> None:
        """Refuse a sample count (a number, or a plane: its mean) other than :attr:`spp`."""
        from torchgi.buffers import mean_spp

        given = mean_spp(spp) if isinstance(spp, torch.Tensor) else spp
        if isinstance(given, bool) or not isinstance(given, (int, float)) or not 1 <= given < math.inf:
            raise ValueError(f"spp: expected the render's samples per pixel, a finite number >= 1, got {spp!r}")
        if self.spp is None:
            raise ValueError(f"spp: this graph records no sample count it was fixed for (exported from a frame "
                             f"without one, or without torchgi's metadata), so it cannot check {given:g}; "
                             "pass ignore=('spp',) to run it as fixed")
        if abs(given - self.spp) > 1e-3 * self.spp:
            raise ValueError(f"spp: this graph is fixed for {self.spp:g} samples per pixel, the input has {given:g}; "
                             f"export one for {given:g} (torchgi export --spp {given:g}) or pass ignore=('spp',)")
