"""What every test file shares: the relative error against an oracle, and which back end ran."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import numpy as np
import pytest
import torch

from torchgi import backends


def rel_error(out: torch.Tensor, ref: torch.Tensor | np.ndarray, scale: str = "max") -> float:
    """``max |out - ref|`` over ``max |ref|`` (``scale="max"``) or over ``max ref - min ref``
    (``"range"``: for outputs whose offset is arbitrary, like a guided filter of offset guides)."""
    ref = torch.as_tensor(np.asarray(ref) if not torch.is_tensor(ref) else ref.detach()).double().cpu()
    diff = float((out.detach().double().cpu() - ref).abs().max())
    return diff / float(ref.abs().max() if scale == "max" else ref.max() - ref.min())


def check_parameter_gradient(loss, raw: torch.Tensor, h: float = 1e-6) -> None:
    """The autograd gradient of ``loss()`` with respect to the scalar parameter ``raw`` (float64)
    against the central difference ``(loss(raw + h) - loss(raw - h)) / 2h``, to 1e-5 relative."""
    loss().backward()
    fd = []
    with torch.no_grad():
        for sign in (1, -1):
            raw += sign * h
            fd.append(float(loss()))
            raw -= sign * h
    assert abs(float(raw.grad) - (fd[0] - fd[1]) / (2 * h)) <= 1e-5 * abs(float(raw.grad)) + 1e-9


def last_backend(op: str) -> str:
    """The back end that computed the last ``op`` ("box", "guided", "atrous", "importance", "allocate")."""
    return backends.status()["last"][op]["ran"]


@contextlib.contextmanager
def c_walks(monkeypatch, threads: int) -> Iterator[None]:
    """Inside: the C back end alone, on ``threads`` threads, every image split into bands of rows
    however small (one and two bands); skips the test where the compiled kernels are not in use."""
    from torchgi.backends import c_kernels

    if not backends.status()["c"].startswith("compiled kernels in use"):
        pytest.skip(f"c: {backends.status()['c']}")
    monkeypatch.setattr(c_kernels.runtime, "_MIN_BAND_PIXELS", 16)
    count = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        with backends.use("c"):
            yield
    finally:
        torch.set_num_threads(count)


def rel_range(out: torch.Tensor, ref: torch.Tensor | np.ndarray) -> float:
    """:func:`rel_error` over the range of ``ref``."""
    return rel_error(out, ref, "range")


def tile_budgets(monkeypatch, all_large: bool = False) -> list[float]:
    """The memory budget (MB) of every tiled Denoiser call from now on, appended to the list
    returned (``tile_side`` spied on where the pyramid and ``tiled`` call it); ``all_large``: every
    call's untiled estimate taken as above ``settings.pipeline.auto_tiles_from_mb`` (for calls a
    test cannot give settings, the CLI's; others pass ``settings=``)."""
    from torchgi.core import tiles
    from torchgi.methods import base, pyramid

    budgets: list[float] = []
    real = tiles.tile_side
    for module in (pyramid, tiles):
        monkeypatch.setattr(module, "tile_side", lambda color, mb, *a: budgets.append(mb) or real(color, mb, *a))
    if all_large:
        auto = tiles.auto_budget
        monkeypatch.setattr(base, "auto_budget", lambda color, inputs, per_pixel, _, *a: auto(color, inputs, per_pixel,
                                                                                             0.0, *a))
    return budgets


def scene_fingerprint(scene) -> tuple[tuple, frozenset]:
    """A scene's camera (position, target, up, field of view, to 1e-6) and its geometry (one
    SHA-256 per mesh of its world-space vertices to 1e-5 and its faces), independent of file
    names, materials and resolution: two scenes are the same shot when either part matches."""
    import hashlib

    cam = scene.camera
    camera = tuple(round(float(v), 6) for v in (*cam.position, *cam.look_at, *cam.up, cam.fov)) + (cam.fov_axis,)
    geometry = frozenset(
        hashlib.sha256(np.round(np.asarray(m.vertices, np.float64), 5).tobytes()
                       + np.asarray(m.faces, np.int64).tobytes()).hexdigest()
        for m in scene.meshes)
    return camera, geometry


def check_weights_provenance(weights, script: str, load) -> None:
    """A shipped weights file (:meth:`save` JSON of a learned filter) is small, loads to its own
    config with ``load``, comes from a clean commit by ``script``, names its data by a SHA-256,
    and was trained on scenes that are none of the tuning or judged scenes, compared by geometry
    and camera (tests/render/test_scene_sets.py), not by name."""
    import json
    import re

    from tests.render.test_scene_sets import SCENES, clashes, read_sets

    assert weights.stat().st_size < 2_000_000
    data = json.loads(weights.read_text())
    prov = data["provenance"]
    assert re.fullmatch(r"[0-9a-f]{40}", prov["commit"]) and prov["dirty"] is False
    assert re.fullmatch(r"[0-9a-f]{64}", prov["data_sha256"])
    assert prov["script"] == script
    assert load(weights).config() == data["config"]
    data_gen = SCENES.parent / "data_gen"
    trained_on = [str((data_gen / s).resolve()) for s in prov["data_config"]["scenes"]]
    found = clashes({**read_sets(), "training": trained_on})
    assert not found, found


def check_data_hash(weights, folder, config: str) -> None:
    """The data hash of a weights file recomputed from the shards' bytes (the training scripts'
    definition, ``train_blend.data_sha256``: the index's config, then each file's name and
    SHA-256, sorted by name) when the data are in ``folder``; skips naming the datagen command
    (``torchgi datagen <config>``) otherwise."""
    import hashlib
    import json

    import pytest

    if not (folder / "index.json").is_file():
        pytest.skip(f"no training data at {folder}: render it with torchgi datagen {config} --out {folder} "
                    f"to check the hash")
    index = json.loads((folder / "index.json").read_text())
    h = hashlib.sha256(json.dumps(index["config"], sort_keys=True).encode())
    for name in sorted({s["file"] for s in index["shards"]} | {s["reference_file"] for s in index["shards"]}):
        h.update(f"{name}:{hashlib.sha256((folder / name).read_bytes()).hexdigest()}\n".encode())
    prov = json.loads(weights.read_text())["provenance"]
    assert h.hexdigest() == prov["data_sha256"]
    assert prov["data_config"] == index["config"]


def shipped_untrained_guided(monkeypatch, method: str, name: str, size: int) -> tuple[float, float, float, float]:
    """relMSE on a judged render (``name``, ``size``², 1 spp against 256 spp, 1 bounce) of
    ``Denoiser(method)`` with its shipped network, with that network's weights all zero, with
    them freshly initialised (seed 0), and of ``Denoiser("guided")``: what a learned method's
    test asks of its trained weights."""
    import copy
    import importlib

    import pytest

    import torchgi
    from tests.render.test_scene_sets import load
    from torchgi import metrics

    pytest.importorskip("embreex", reason="the render extra is not installed")
    module = importlib.import_module(f"torchgi.filters.{method}")
    scene = load(f"judged/{name}").with_resolution(size, size)
    noisy, ref = torchgi.render(scene, spp=1, bounces=1, seed=1), torchgi.render(scene, spp=256, bounces=1, seed=2)

    def error(net=None) -> float:
        if net is not None:
            monkeypatch.setattr(module, "default_net", lambda device=None: net)
        return float(metrics.relmse(torchgi.Denoiser(method)(noisy), ref.color))

    shipped = error()
    guided = float(metrics.relmse(torchgi.Denoiser("guided")(noisy), ref.color))
    uniform, fresh = copy.deepcopy(module.default_net()), copy.deepcopy(module.default_net())
    torch.manual_seed(0)
    with torch.no_grad():
        for p in uniform.parameters():
            p.zero_()
        for m in fresh.modules():
            if hasattr(m, "reset_parameters"):
                m.reset_parameters()
    return shipped, error(uniform), error(fresh), guided


def onnx_parity(tmp_path, method: str, sizes: tuple[int, ...]) -> tuple[list[str], list[tuple[float, float]]]:
    """``Denoiser(method).deploy(spp=1)`` exported (without the ONNX optimizer: half the export
    time) and run on Cornell box renders of ``size x (size + 7)``, 1 spp: the graph's input names
    and, per size, the eager deployed module's and onnxruntime's :func:`rel_error` against the
    eager ``Denoiser(method)``."""
    import pytest

    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    pytest.importorskip("embreex")
    import torchgi
    from torchgi.denoise import Denoiser
    from torchgi.export import OrtDenoiser, export_onnx

    deployed = Denoiser(method).deploy(spp=1)
    g = torch.Generator().manual_seed(0)
    examples = [torch.rand(2, 3, 24, 32, generator=g) for _ in range(4)] + [torch.rand(2, 1, 24, 32, generator=g)]
    path = export_onnx(deployed, examples, tmp_path / f"{method}.onnx", input_names=list(deployed.input_names),
                       optimize=False, metadata=deployed.metadata())
    ort = OrtDenoiser(path)
    errors = []
    for size in sizes:
        gb = torchgi.render(torchgi.scenes.cornell(size).with_resolution(size, size + 7), spp=1, bounces=1)
        ours = Denoiser(method)(gb)
        errors.append((rel_error(deployed(gb.color, gb.emission, gb.albedo, gb.normal, gb.depth), ours),
                       rel_error(ort(gb), ours)))
    return ort.input_names, errors


# The camera-path scene files (configs/scenes/sequences): tests/render/test_sequences.py, tests/test_cli.py.
SEQUENCES = os.path.join(os.path.dirname(__file__), "..", "configs", "scenes", "sequences")


def sliding_cornell(size: int, shift: float = 80.0):
    """The Cornell box with a camera sliding right and forwards (reveals the wall behind the tall block)."""
    from torchgi.render import CameraPath, scenes

    scene = scenes.cornell(size)
    p = scene.camera.position
    scene.path = CameraPath((0.0, 1.0), (p, (p[0] + shift, p[1] + 20, p[2] + 60)), ((278, 273, 0), (300, 260, 0)),
                            (39.3, 38.0))
    return scene


def sliding_sequence(size: int, frames: int, spp: int = 1, seed: int = 1):
    """``frames`` G-buffers of :func:`sliding_cornell` rendered along its camera path (skips the test
    without the render extra)."""
    pytest.importorskip("embreex")
    import torchgi

    return list(torchgi.render_sequence(sliding_cornell(size), frames, spp=spp, seed=seed))
