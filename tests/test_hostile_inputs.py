"""Hostile inputs a new user meets: every public rate, size, count, spp, radius, resolution,
frames, iterations or budget refuses NaN, +-Inf, a bool and out-of-range values with an error
naming the argument; the deployed Denoiser's keyword tensors; ``render --frames`` on a still
scene; a ``--temporal`` folder that mixes shots or sizes."""

from __future__ import annotations

import functools
import json
import re

import pytest
import torch

import torchgi
from torchgi import data, export, filters, io, metrics, render, sampling
from torchgi.cli import main
from torchgi.core.errors import ConfigError, RangeError

NAN, INF = float("nan"), float("inf")


@functools.cache
def _scene():
    return render.scenes.cornell(8)


def _t(*shape):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(0))


X, N, P, D = _t(1, 3, 8, 8), torch.nn.functional.normalize(_t(1, 3, 8, 8) - 0.5, dim=1), _t(1, 3, 8, 8), _t(1, 1, 8, 8)
HIT = torch.ones(1, 1, 8, 8, dtype=torch.bool)
GUIDE = torch.cat([N, D], 1)
X16 = _t(1, 3, 16, 16)


def _index(tmp_path):
    """A data folder's index (an input the case reads), in ``tmp_path / "input"``."""
    folder = tmp_path / "input"
    folder.mkdir(exist_ok=True)
    (folder / "index.json").write_text(json.dumps({"shards": [{"reference": False, "spp": 1}]}))
    return folder


def _config(**changed):
    fields = {"scenes": ("cornell",), "resolution": (8, 8), "views": 1, "jitter": 0.0, "spp": (1,),
              "reference_spp": 4, "bounces": 1, "seeds": (0,)}
    return data.DataGenConfig(**(fields | changed))


# (argument, call with the value, whether 0 is refused, the error type); the calls take tmp_path
CASES = {
    "adaptive_render": ("rate", lambda v, _: sampling.adaptive_render(_scene(), rate=v), True, RangeError),
    "adaptive_render.variance_share": (
        "variance_share", lambda v, _: sampling.adaptive_render(_scene(), variance_share=v), False, RangeError),
    "render_to.seconds": ("seconds", lambda v, _: torchgi.render_to(_scene(), seconds=v), True, RangeError),
    "render_to.target": ("target", lambda v, _: torchgi.render_to(_scene(), target=v), True, RangeError),
    "adaptive_counts": ("rate", lambda v, _: sampling.adaptive_counts(
        torchgi.GBuffer(normal=N, position=P, hit=HIT), v), True, RangeError),
    "allocate": ("budget", lambda v, _: sampling.allocate(D, v, min_samples=0), False, RangeError),
    "allocate.min_samples": ("min_samples", lambda v, _: sampling.allocate(D, 64, min_samples=v), False, RangeError),
    "sample_batches": ("batch_size", lambda v, _: list(sampling.sample_batches(HIT.long(), v)), True, RangeError),
    "accumulate": ("num_pixels", lambda v, _: sampling.accumulate(torch.ones(1, 1), torch.tensor([0]), v),
                   True, ValueError),
    "importance_map": ("window", lambda v, _: sampling.importance_map(N, P, window=v), True, RangeError),
    "sigma_position_rule": ("footprints", lambda v, _: sampling.sigma_position_rule(P, HIT, v), True, RangeError),
    "render": ("spp", lambda v, _: render.render(_scene(), v), True, RangeError),
    "render.workers": ("workers", lambda v, _: render.render(_scene(), workers=v), True, RangeError),
    "render.bounces": ("bounces", lambda v, _: render.render(_scene(), bounces=v), False, RangeError),
    "render_guides": ("chunk_size", lambda v, _: render.render_guides(_scene(), chunk_size=v), True, RangeError),
    "render_guide_rays": ("spp", lambda v, _: render.render_guide_rays(_scene(), v), True, RangeError),
    "render_sequence": ("frames", lambda v, _: next(torchgi.render_sequence(_scene(), v)), True, RangeError),
    "Camera": ("resolution", lambda v, _: render.Camera((0, 0, 1), (0, 0, 0), resolution=(v, 8)), True, ValueError),
    "atrous": ("iterations", lambda v, _: filters.atrous(X, N, P, iterations=v), True, RangeError),
    "atrous.subsample": ("subsample", lambda v, _: filters.atrous(X, N, P, subsample=v), True, ValueError),
    "ATrous": ("iterations", lambda v, _: filters.ATrous(iterations=v)(X, N, P), True, RangeError),
    "box": ("radius", lambda v, _: filters.box(X, v), False, RangeError),
    "Box": ("radius", lambda v, _: filters.Box(v)(X), False, RangeError),
    "Box.__init__": ("radius", lambda v, _: filters.Box(v), False, RangeError),
    "ATrous.__init__": ("sigma_color", lambda v, _: filters.ATrous(sigma_color=v), True, RangeError),
    "CrossBilateral.__init__": ("radius", lambda v, _: filters.CrossBilateral(v, 1.0, 1.0), False, RangeError),
    "CrossBilateral.sigma_guides": ("sigma_guides", lambda v, _: filters.CrossBilateral(1, 1.0, 1.0, (v,)), True,
                                    RangeError),
    "Material": ("roughness", lambda v, _: render.Material("glossy", roughness=v), True, ConfigError),
    "Material.albedo": ("albedo", lambda v, _: render.Material("diffuse", albedo=(v, 0.5, 0.5)), False, ConfigError),
    "PointLight": ("intensity", lambda v, _: render.PointLight((0, 1, 0), (1, v, 1)), False, ConfigError),
    "Sky": ("radiance", lambda v, _: render.Sky((v, 1, 1)), False, ConfigError),
    "cross_bilateral": ("radius", lambda v, _: filters.cross_bilateral(
        X, radius=v, sigma_space=1.0, sigma_color=1.0), False, RangeError),
    "cross_bilateral.sigma_space": ("sigma_space", lambda v, _: filters.cross_bilateral(
        X, radius=1, sigma_space=v, sigma_color=1.0), True, RangeError),
    "guided": ("radius", lambda v, _: filters.guided(X, GUIDE, radius=v), False, RangeError),
    "guided.eps": ("eps", lambda v, _: filters.guided(X, GUIDE, eps=v), False, RangeError),
    "Guided": ("eps", lambda v, _: filters.Guided(eps=v), False, RangeError),
    "Guided.subsample": ("subsample", lambda v, _: filters.Guided(subsample=v), True, RangeError),
    "guide_from": ("depth_scale", lambda v, _: filters.guide_from(N, D, depth_scale=v), True, RangeError),
    "blend": ("spp", lambda v, _: filters.blend(X, GUIDE, spp=v), True, RangeError),
    "pyramid": ("spp", lambda v, _: filters.pyramid(X16, torch.cat([_t(1, 3, 16, 16), _t(1, 1, 16, 16)], 1),
                                                    spp=v), True, RangeError),
    "to_srgb8": ("exposure", lambda v, _: io.to_srgb8(X[0], exposure=v), True, RangeError),
    "relmse": ("eps", lambda v, _: metrics.relmse(X, X, eps=v), False, RangeError),
    "psnr": ("data_range", lambda v, _: metrics.psnr(X, X * 0.5, data_range=v), True, RangeError),
    "ssim": ("data_range", lambda v, _: metrics.ssim(X16, X16, data_range=v), True, RangeError),
    "ssim.window": ("window", lambda v, _: metrics.ssim(X16, X16, data_range=1.0, window=v), True, ValueError),
    "temporal": ("warmup", lambda v, _: metrics.temporal(_t(3, 1, 3, 8, 8), _t(3, 1, 3, 8, 8), warmup=v),
                 False, ValueError),
    "FilterFeatures": ("radius", lambda v, _: data.FilterFeatures(radius=v), False, RangeError),
    "FilterFeatures.iterations": ("iterations", lambda v, _: data.FilterFeatures(iterations=v), True, RangeError),
    "FilterFeatures.eps": ("eps", lambda v, _: data.FilterFeatures(eps=v), False, RangeError),
    "DataGenConfig": ("views", lambda v, _: _config(views=v), True, ConfigError),
    "DataGenConfig.spp": ("spp", lambda v, _: _config(spp=(v,)), True, ConfigError),
    "DataGenConfig.resolution": ("resolution", lambda v, _: _config(resolution=(8, v)), True, ConfigError),
    "DataGenConfig.jitter": ("jitter", lambda v, _: _config(jitter=v), False, ConfigError),
    "ShardDataset": ("crop", lambda v, tmp: data.ShardDataset(_index(tmp), crop=v), True, RangeError),
    "ShardDataset.seed": ("seed", lambda v, tmp: data.ShardDataset(_index(tmp), seed=v), False, RangeError),
    "run_job": ("workers", lambda v, tmp: data.run_job(_config(), tmp, workers=v), True, RangeError),
    "export_denoiser": ("spp", lambda v, tmp: export.export_denoiser("guided", tmp / "d.onnx", spp=v), True,
                        RangeError),
    "export_denoiser.sigma_position": ("sigma_position", lambda v, tmp: export.export_denoiser(
        "atrous", tmp / "d.onnx", sigma_position=v), True, RangeError),
    "export_onnx": ("opset", lambda v, tmp: export.export_onnx(
        filters.Box(1), [_t(2, 1, 3, 4)], tmp / "b.onnx", input_names=["x"], opset=v), True, RangeError),
    "Denoiser": ("max_memory_mb", lambda v, _: torchgi.Denoiser(max_memory_mb=v), True, ValueError),
    "Denoiser.input_scale": ("input_scale", lambda v, _: torchgi.Denoiser(input_scale=v), True, RangeError),
    "Denoiser.deploy": ("spp", lambda v, _: torchgi.Denoiser().deploy(spp=v), True, RangeError),
    "Denoiser.__call__": ("spp", lambda v, _: torchgi.Denoiser()(color=X, albedo=X, normal=N, spp=v), True,
                          ValueError),
}
VALUES = {"nan": NAN, "inf": INF, "-inf": -INF, "-1": -1, "0": 0, "True": True}


@pytest.mark.parametrize(("case", "value"), [(c, v) for c in CASES for v in VALUES if v != "0" or CASES[c][2]])
def test_numbers_are_refused_by_name(case, value, tmp_path):
    """NaN, +-Inf, -1, a bool and 0 (where 0 is out of range) are refused with an error of the
    stated type whose message names the argument; nothing is written."""
    arg, call, _, error = CASES[case]
    with pytest.raises(error) as caught:
        call(VALUES[value], tmp_path)
    assert re.search(rf"\b{re.escape(arg)}\b", str(caught.value)), str(caught.value)
    written = [p for p in tmp_path.rglob("*") if p.parent != tmp_path / "input" and p != tmp_path / "input"]
    assert written == []  # nothing at all beside a case's input: no output, no temporary, no stray file


def test_atrous_levels_have_an_upper_bound():
    """À-Trous levels step 2^(i-1) px: a count no image can use (it once ran without end) is
    refused by name, in the function and the module alike; 30 levels still run."""
    for call in (lambda: filters.atrous(X, N, P, iterations=10**30), lambda: filters.ATrous(iterations=31)):
        with pytest.raises(RangeError, match=r"^iterations: expected an int in \[1, 30\]"):
            call()
    assert filters.atrous(X, N, P, iterations=30).shape == X.shape


def test_adaptive_rate_too_large_for_an_exact_budget():
    """A rate whose budget passes 2^52 samples an image (where float64 shares stop being exact
    integers) is refused by name, as is such a budget."""
    g = torchgi.GBuffer(normal=N, position=P, hit=HIT)
    with pytest.raises(RangeError, match=r"^rate: .* more than 2\*\*52"):
        sampling.adaptive_counts(g, 2.0**52 / 64 * 2)
    with pytest.raises(RangeError, match=r"^budget: expected at most 2\*\*52"):
        sampling.allocate(D, 2**52 + 1)
    assert int(sampling.allocate(D, 2**40).sum()) == 2**40


# --- DeployedDenoiser by keyword ---------------------------------------------------------------------------


@pytest.mark.parametrize(("method", "emission"), [("guided", True), ("guided", False), ("atrous", True)])
def test_deployed_denoiser_takes_keyword_tensors(method, emission):
    """Keywords (any order), positions, or the first by position and the rest by name give the
    same bits; an unknown name, a name also given by position, emission to a module deployed
    without one, and a missing input are refused by name."""
    m = torchgi.Denoiser(method).deploy(spp=2, sigma_position=0.5, emission=emission)
    g = torch.Generator().manual_seed(3)
    tensors = {k: torch.rand(1, 1 if k == "depth" else 3, 12, 10, generator=g) for k in m.input_names}
    positional = m(*tensors.values())
    assert torch.equal(m(**dict(reversed(tensors.items()))), positional)
    first, *rest = m.input_names
    assert torch.equal(m(tensors[first], **{k: tensors[k] for k in rest}), positional)
    with pytest.raises(TypeError, match="^colour: not an input of this module"):
        m(colour=tensors["color"], **{k: tensors[k] for k in rest})
    with pytest.raises(TypeError, match="^color: given by position and by name"):
        m(tensors["color"], **tensors)
    with pytest.raises(ValueError, match=f"^{rest[-1]}: required"):
        m(**{k: tensors[k] for k in m.input_names[:-1]})
    if not emission:
        with pytest.raises(TypeError, match="^emission: this module was deployed without an emission input"):
            m(emission=tensors["color"], **tensors)


# --- render --frames on a still scene ----------------------------------------------------------------------


def test_render_frames_of_a_still_scene_are_refused(tmp_path, capsys):
    """``torchgi render cornell --frames 4``: the Cornell box has no camera, mesh or light path,
    so the four frames would be one still view: refused naming --frames, nothing written. A still
    camera over moving meshes and a moving light renders."""
    out = tmp_path / "c.exr"
    assert main(["render", "cornell", "--resolution", "8", "8", "--frames", "4", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--frames" in err and "no camera, mesh or light path" in err
    assert not list(tmp_path.iterdir())
    blocks = "configs/scenes/sequences/train_blocks_moving.yaml"  # still camera, moving meshes and light
    assert render.load_scene(blocks).path is None
    assert main(["render", blocks, "--resolution", "8", "6", "--frames", "2", "--out", str(out)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c_0000.exr", "c_0001.exr"]


# --- sequence folders ----------------------------------------------------------------------------------------


def test_a_sequence_folder_of_two_shots_or_two_sizes_is_refused(tmp_path):
    """A folder or glob whose files differ in more than the frame number (``shot_0001.exr``
    beside ``other_0001.exr``), or frames of another size than the first, are refused naming the
    file that differs and how; a pattern picks one shot out of such a folder."""
    from torchgi.io.sequence import frame_paths

    for k in range(3):
        io.write_exr(tmp_path / f"shot_{k:04d}.exr", {"color": torch.zeros(3, 4, 6)})
    assert [p.name for p in frame_paths([tmp_path])] == ["shot_0000.exr", "shot_0001.exr", "shot_0002.exr"]
    io.write_exr(tmp_path / "other_0001.exr", {"color": torch.zeros(3, 4, 6)})
    for spec in (tmp_path, str(tmp_path / "*.exr")):
        with pytest.raises(ValueError, match="mixes frames named other_0001.exr and shot_0000.exr"):
            frame_paths([spec])
    assert len(frame_paths([str(tmp_path / "shot_####.exr")])) == 3
    (tmp_path / "other_0001.exr").unlink()
    io.write_exr(tmp_path / "shot_0003.exr", {"color": torch.zeros(3, 5, 6)})
    for spec in ([tmp_path], [str(tmp_path / "shot_####.exr")], sorted(tmp_path.iterdir())):
        with pytest.raises(ValueError, match="shot_0003.exr is 6x5 but shot_0000.exr is 6x4"):
            frame_paths(spec)
    assert frame_paths([tmp_path / "shot_0003.exr"]) == [tmp_path / "shot_0003.exr"]
