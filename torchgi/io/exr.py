"""Multi-layer OpenEXR read/write of AOVs, on the ``OpenEXR`` package (the ``exr`` extra).

A *layer* is a group of channels that share a prefix: ``albedo.R, albedo.G, albedo.B`` form
the layer ``albedo``; un-prefixed ``R, G, B, A`` form the layer ``""``. Layers are tensors of
shape ``(C, H, W)``; half-float channels come back as ``torch.float16``, float channels as
``torch.float32`` (round trips are exact) and UINT channels as ``torch.int64``.

:func:`read_aovs` maps the layer names that renderers write (torchgi, Blender/Cycles with or
without a view-layer prefix, Mitsuba 3, Arnold, Intel Open Image Denoise's short names) onto
torchgi's canonical AOV names.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import torch

from torchgi.core.check import check_option, require
from torchgi.core.errors import DTypeError, ExrError, LayerError, ShapeError
from torchgi.core.files import temp_beside
from torchgi.io.motion import motion_convention_of, to_torchgi_motion

__all__ = ["AOV_ALIASES", "AOV_CHANNELS", "LayerReport", "find_aovs", "match_aovs", "read_aovs", "read_exr",
           "write_exr"]

_MAGIC = b"\x76\x2f\x31\x01"

# Canonical AOV name -> accepted layer names, most preferred first (compared case-insensitively,
# also after dropping a Blender view-layer prefix such as "ViewLayer."). "" is the un-prefixed
# R,G,B(,A) of Mitsuba 3, Arnold and most renderers' beauty. Blender's "Combined" is the
# denoised result when Cycles writes denoising data, so its "Noisy Image" comes first, and
# Cycles' "Denoising *" guides (made for denoisers) win over its plain Normal/Depth passes.
# Mitsuba 3's aov integrator names a layer as its user does (its documentation's "dd.y:depth" writes
# the channel dd.y.T, the layer "dd.y").
# Motion: Blender's "Vector" (X, Y of its 4 components) and Arnold's "motionvector" (R, G) are
# converted to torchgi's convention (GBuffer.motion) from their renderer's (torchgi.io.motion).
AOV_ALIASES: dict[str, tuple[str, ...]] = {
    "color": ("color", "noisy image", "combined", "", "rgba", "rgb", "beauty", "hdr", "ldr", "image"),
    "albedo": ("denoising albedo", "albedo", "alb", "diffcol", "diffuse_albedo"),
    "normal": ("denoising normal", "normal", "nrm", "normals", "n", "nn", "sh_normal", "shading_normal"),
    "position": ("position", "pos", "p", "pp", "world_position"),
    "depth": ("denoising depth", "depth", "z", "dd", "dd.y", "distance"),
    "emission": ("emission", "emit", "emissive", "ee"),
    "motion": ("motion", "vector", "motionvector", "motion_vector", "mv"),
    "direct": ("direct",),
    "indirect": ("indirect",),
    "variance": ("variance", "var"),
    "spp": ("spp",),
    "hit": ("hit",),
}

# Number of channels each canonical AOV has once found (an alpha channel is dropped).
AOV_CHANNELS: dict[str, int] = {
    "color": 3, "albedo": 3, "normal": 3, "position": 3, "emission": 3, "direct": 3,
    "indirect": 3, "depth": 1, "spp": 1, "hit": 1, "motion": 2,
}

# Component order inside a layer: RGBA, then XYZW, UV, Mitsuba's depth "T"; digits numerically.
_ORDER = {c: i for i, c in enumerate(["R", "G", "B", "A", "X", "Y", "Z", "W", "U", "V", "T"])}
_TOP_LEVEL_RGBA = {"R", "G", "B", "A"}


def _component_key(component: str) -> tuple[int, int, str]:
    if component.isdigit():
        return (1, int(component), "")
    return (0, _ORDER.get(component.upper(), len(_ORDER)), component)


def _suffixes(name: str, channels: int) -> list[str]:
    """Channel suffixes used when writing a layer of ``channels`` channels."""
    base = name.rsplit(".", 1)[-1].lower()
    if channels == 1:
        return ["Z"] if base in ("depth", "z") else ["Y"]
    if channels == 2:
        return ["X", "Y"]
    if channels == 3 and base in ("normal", "position", "n", "p"):
        return ["X", "Y", "Z"]
    if channels == 3:
        return ["R", "G", "B"]
    if channels == 4:
        return ["R", "G", "B", "A"]
    return [str(i) for i in range(channels)]


def _to_numpy_planes(name: str, value: torch.Tensor | np.ndarray) -> list[np.ndarray]:
    arr = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
    if arr.ndim == 4 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise ShapeError(f"layers[{name!r}]: expected shape (C, H, W), (H, W) or (1, C, H, W), got {arr.shape}")
    if arr.dtype == np.bool_ or np.issubdtype(arr.dtype, np.integer):
        if arr.size and (arr.min() < 0 or arr.max() > np.iinfo(np.uint32).max):
            raise DTypeError(f"layers[{name!r}]: integer values must fit in uint32 to be stored as EXR UINT")
        arr = arr.astype(np.uint32)
    elif arr.dtype not in (np.float16, np.float32):
        raise DTypeError(
            f"layers[{name!r}]: EXR stores float16, float32 or uint32; got {arr.dtype} "
            "(convert explicitly, e.g. .float(), so no precision is lost without your say)"
        )
    return [np.ascontiguousarray(plane) for plane in arr]


def write_exr(
    path: str | os.PathLike,
    layers: Mapping[str, torch.Tensor | np.ndarray],
    *,
    overwrite: bool = False,
    compression: str = "zip",
) -> Path:
    """Write named layers to one multi-layer EXR file, atomically.

    Args:
        path: destination file.
        layers: layer name -> tensor or array of shape ``(C, H, W)``, ``(H, W)`` or
            ``(1, C, H, W)``; float16 is stored as HALF, float32 as FLOAT, bool and
            non-negative integers as UINT. All layers share H and W. The name ``""`` writes
            plain ``R, G, B``. Channel suffixes: ``X, Y, Z`` for normal/position, ``Z`` for
            depth, ``Y`` for other single channels, ``R, G, B(, A)`` otherwise.
        overwrite: replace an existing file; otherwise :class:`FileExistsError`.
        compression: ``"zip"``, ``"piz"``, ``"none"``.

    Returns:
        The path written.

    The file is written to a temporary name in the same folder and then moved into place,
    so readers never see a partial file and a crash leaves no file at ``path``.

    Example:
        >>> import tempfile, os
        >>> p = os.path.join(tempfile.mkdtemp(), "a.exr")
        >>> _ = write_exr(p, {"color": torch.rand(3, 4, 5)})
        >>> read_exr(p)["color"].shape
        torch.Size([3, 4, 5])
    """
    OpenEXR = require("OpenEXR", "exr")
    check_option(compression, "compression", ("zip", "piz", "none"))
    path = Path(path)
    if not layers:
        raise LayerError("layers: expected at least one layer to write")
    channels: dict[str, np.ndarray] = {}
    size = None
    for name, value in layers.items():
        planes = _to_numpy_planes(name, value)
        if size is None:
            size = planes[0].shape
        elif planes[0].shape != size:
            raise ShapeError(f"layers[{name!r}]: size {planes[0].shape} differs from the other layers' {size}")
        for suffix, plane in zip(_suffixes(name, len(planes)), planes):
            channels[f"{name}.{suffix}" if name else suffix] = plane
    if path.exists() and not overwrite:
        raise FileExistsError(f"path: {path} exists; pass overwrite=True to replace it")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"path: folder {path.parent} does not exist")
    comp = {"zip": OpenEXR.ZIP_COMPRESSION, "piz": OpenEXR.PIZ_COMPRESSION, "none": OpenEXR.NO_COMPRESSION}
    header = {"compression": comp[compression], "type": OpenEXR.scanlineimage}
    tmp = temp_beside(path)
    try:
        OpenEXR.File(header, channels).write(tmp)
        if overwrite:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)  # fails if another writer got there first; never overwrites
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def read_exr(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """Read every layer of an EXR file.

    Args:
        path: an OpenEXR file (single- or multi-part; parts are merged).

    Returns:
        Layer name -> tensor ``(C, H, W)`` on the CPU, channels in R,G,B,A / X,Y,Z order.
        Un-prefixed ``R, G, B, A`` form the layer ``""``; any other un-prefixed channel
        (``Z``, ``Y``) is a layer of its own.

    Raises:
        FileNotFoundError: no such file.
        ExrError: not an OpenEXR file, or truncated / corrupt.

    Example:
        >>> import tempfile, os
        >>> p = os.path.join(tempfile.mkdtemp(), "a.exr")
        >>> _ = write_exr(p, {"depth": torch.ones(1, 2, 2, dtype=torch.float16)})
        >>> read_exr(p)["depth"].dtype
        torch.float16
    """
    OpenEXR = require("OpenEXR", "exr")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no such file: {path}")
    with open(path, "rb") as fh:
        if fh.read(4) != _MAGIC:
            raise ExrError(f"path: {path} is not an OpenEXR file (wrong magic number)")
    try:
        # The File API fills missing scanlines with garbage and only prints a warning:
        # ask the file whether every chunk is present before reading pixels.
        probe = OpenEXR.InputFile(str(path))
        complete = probe.isComplete()
        probe.close()
    except Exception as exc:
        raise ExrError(f"path: cannot read {path} as OpenEXR (truncated or corrupt?): {exc}") from exc
    if not complete:
        raise ExrError(f"path: {path} is incomplete (truncated or corrupt): some pixel chunks are missing")
    try:
        exr = OpenEXR.File(str(path), separate_channels=True)
        groups: dict[str, dict[str, np.ndarray]] = {}
        for index in range(len(exr.parts)):
            for full, channel in exr.channels(index).items():
                layer, _, component = full.rpartition(".")
                if not layer and component not in _TOP_LEVEL_RGBA:
                    layer = component
                if component in groups.setdefault(layer, {}):
                    raise ExrError(f"path: channel {full!r} appears in more than one part of {path}")
                groups[layer][component] = channel.pixels
    except ExrError:
        raise
    except Exception as exc:  # OpenEXR raises RuntimeError/OSError variants for broken files
        raise ExrError(f"path: cannot read {path} as OpenEXR (truncated or corrupt?): {exc}") from exc
    out = {}
    for layer, comps in groups.items():
        planes = [comps[c] for c in sorted(comps, key=_component_key)]
        arr = np.stack(planes).astype(np.int64) if planes[0].dtype == np.uint32 else np.stack(planes)
        out[layer] = torch.from_numpy(arr)
    return out


def _normalise(name: str) -> list[str]:
    """Candidate spellings of a layer name: itself, then without a view-layer prefix."""
    low = name.lower()
    forms = [low]
    if "." in low:
        forms.append(low.split(".", 1)[1])
    return forms


@dataclasses.dataclass(frozen=True)
class LayerReport:
    """What :func:`match_aovs` took from a file's layers, and what it left.

    Attributes:
        source: what the layers came from (a path, say).
        used: canonical AOV name -> the layer name it was read from (``""``: the un-prefixed
            ``R, G, B``), in :data:`AOV_ALIASES` order.
        channels_left: canonical AOV name -> how many channels of its layer were not read (an
            alpha channel, the last two of Blender's 4-channel ``Vector``); only AOVs that left some.
        alternatives: layer name -> the AOV it is another name for, left because a more preferred
            name of that AOV was read (Blender's ``Normal`` beside ``Denoising Normal``).
        unknown: layer names that are no accepted name of any AOV (:data:`AOV_ALIASES`): not read.

    ``str(report)`` is two lines: what was read from which name, and what was left.

    Example:
        >>> _, r = match_aovs({"": torch.zeros(4, 2, 2), "nn": torch.zeros(3, 2, 2), "uv": torch.zeros(2, 2, 2)})
        >>> print(r)
        read color from R,G,B (not its 4th channel), normal from 'nn'
        ignored 'uv' (no name torchgi reads: torchgi.io.AOV_ALIASES)
    """

    source: str
    used: dict[str, str]
    channels_left: dict[str, int]
    alternatives: dict[str, str]
    unknown: tuple[str, ...]

    def __str__(self) -> str:
        def shown(layer: str) -> str:
            return repr(layer) if layer else "R,G,B"

        read = ", ".join(f"{aov} from {shown(layer)}" + (
            f" (not its {_ordinals(AOV_CHANNELS[aov], self.channels_left[aov])})" if aov in self.channels_left else "")
            for aov, layer in self.used.items())
        left = [f"{', '.join(map(shown, self.unknown))} (no name torchgi reads: torchgi.io.AOV_ALIASES)"] \
            if self.unknown else []
        left += [f"{shown(n)} (another name of {aov}, read from {shown(self.used[aov])})"
                 for n, aov in self.alternatives.items()]
        return f"read {read or 'nothing'}\nignored {'; '.join(left) or 'nothing'}"


def _ordinals(first: int, count: int) -> str:
    """``"4th channel"`` / ``"4th-5th channels"``: channels ``first + 1 .. first + count`` (1-based)."""
    def nth(k: int) -> str:
        return f"{k}{'th' if 10 <= k % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(k % 10, 'th')}"

    return f"{nth(first + 1)} channel" if count == 1 else f"{nth(first + 1)}-{nth(first + count)} channels"


def match_aovs(
    layers: Mapping[str, torch.Tensor], *, required: Iterable[str] = ("color",), source: str = "layers",
    motion_convention: str | None = None,
) -> tuple[dict[str, torch.Tensor], LayerReport]:
    """:func:`find_aovs`, and a :class:`LayerReport` of which layer each AOV was read from and
    which layers and channels were left (nothing is dropped without a word).

    Example:
        >>> aovs, report = match_aovs({"": torch.zeros(3, 2, 2), "dd.y": torch.ones(1, 2, 2),
        ...                            "img": torch.zeros(4, 2, 2)})
        >>> report.used, report.unknown
        ({'color': '', 'depth': 'dd.y'}, ('img',))
    """
    index: dict[str, str] = {}
    for name in layers:
        for form in _normalise(name):
            index.setdefault(form, name)
    found: dict[str, torch.Tensor] = {}
    used: dict[str, str] = {}
    left: dict[str, int] = {}
    for aov, aliases in AOV_ALIASES.items():
        match = next((index[a] for a in aliases if a in index), None)
        if match is None:
            continue
        value = layers[match]
        want = AOV_CHANNELS.get(aov)
        if want is not None:
            if value.shape[0] < want:
                raise LayerError(
                    f"{source}: layer {match!r} (used as {aov}) has {value.shape[0]} channels, expected {want}"
                )
            if value.shape[0] > want:
                left[aov] = value.shape[0] - want
            value = value[:want]
        if aov == "motion":
            value = to_torchgi_motion(value, motion_convention or motion_convention_of(match))
        found[aov] = value
        used[aov] = match
    missing = [r for r in required if r not in found]
    if missing:
        raise LayerError(
            f"{source}: missing required layer(s) {', '.join(missing)}; found layers: "
            f"{', '.join(repr(n) for n in layers) or '(none)'}; accepted names for "
            + "; ".join(f"{m}: {', '.join(repr(a) for a in AOV_ALIASES.get(m, (m,)))}" for m in missing)
        )
    aov_of = {a: aov for aov, aliases in AOV_ALIASES.items() for a in aliases}
    alternatives = {}  # a layer left with an accepted name: another name (or view layer) of an AOV read
    for n in layers:
        aov = next((aov_of[f] for f in _normalise(n) if f in aov_of), None)
        if n not in used.values() and aov in used:
            alternatives[n] = aov
    unknown = tuple(n for n in layers if n not in used.values() and n not in alternatives)
    return found, LayerReport(source, used, left, alternatives, unknown)


def find_aovs(
    layers: Mapping[str, torch.Tensor], *, required: Iterable[str] = ("color",), source: str = "layers",
    motion_convention: str | None = None,
) -> dict[str, torch.Tensor]:
    """Map renderer-specific layer names to torchgi's canonical AOV names.

    Layers of no accepted name are left out without a word here: :func:`match_aovs` reports
    them (and :meth:`torchgi.GBuffer.from_exr` warns).

    Args:
        layers: layer name -> ``(C, H, W)`` tensor, as from :func:`read_exr`.
        required: canonical names that must be found.
        source: what ``layers`` came from, for error messages (a path, say).
        motion_convention: the convention the motion layer is written in (``"torchgi"``,
            ``"cycles"``, ``"arnold"``: :mod:`torchgi.io.motion`); None = its layer name's
            (``motion``: torchgi, ``Vector``: Cycles, ``motionvector``: Arnold).

    Returns:
        Canonical name (``color``, ``albedo``, ``normal``, ``position``, ``depth``,
        ``emission``, ``direct``, ``indirect``, ``variance``, ``spp``, ``hit``, ``motion``) ->
        tensor ``(C, H, W)``; 3-channel AOVs drop an alpha channel, depth keeps one channel;
        ``motion`` (2 channels) in torchgi's convention (``GBuffer.motion``).

    Raises:
        LayerError: a required AOV is missing (the message lists the layers found) or a
            layer has too few channels.

    Example:
        >>> lay = {"ViewLayer.Noisy Image": torch.zeros(4, 2, 2),
        ...        "ViewLayer.Denoising Normal": torch.zeros(3, 2, 2)}
        >>> sorted(find_aovs(lay))
        ['color', 'normal']
    """
    return match_aovs(layers, required=required, source=source, motion_convention=motion_convention)[0]


def read_aovs(path: str | os.PathLike, *, required: Iterable[str] = ("color",),
              motion_convention: str | None = None) -> dict[str, torch.Tensor]:
    """Read an EXR written by torchgi, Blender/Cycles, Mitsuba 3 or Arnold into canonical AOVs.

    Shorthand for ``find_aovs(read_exr(path), required=required, motion_convention=...)``.

    Example:
        >>> import tempfile, os
        >>> p = os.path.join(tempfile.mkdtemp(), "m.exr")
        >>> _ = write_exr(p, {"": torch.rand(3, 2, 2), "nn": torch.rand(3, 2, 2)})
        >>> sorted(read_aovs(p, required=("color", "normal")))
        ['color', 'normal']
    """
    return find_aovs(read_exr(path), required=required, source=str(path), motion_convention=motion_convention)
