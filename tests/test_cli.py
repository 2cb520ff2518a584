import importlib.util
import json
import os
import shutil
import subprocess

import numpy as np
import pytest
import torch

import torchgi
from tests.helpers import SEQUENCES, tile_budgets
from torchgi import methods
from torchgi.cli import main
from torchgi.io import write_exr


def test_console_script_help():
    exe = shutil.which("torchgi")
    assert exe, "the torchgi console script is not installed"
    out = subprocess.run([exe, "--help"], capture_output=True, text=True, check=True).stdout
    for word in ("info", "metrics", "render", "demo"):
        assert word in out


def test_info_json(capsys):
    assert main(["info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["torch"] == torch.__version__
    assert info["extras"]["exr"]["OpenEXR"] is not None


def _metrics_files(tmp_path, size, amounts, ref_layer):
    """A random reference (written as layer ``ref_layer``) and two images of it: with added
    noise of ``amounts[0]`` and scaled by ``amounts[1]``, as EXR files in ``tmp_path``."""
    (noise, scale), g = amounts, torch.Generator().manual_seed(0)
    ref = torch.rand(3, *size, generator=g)
    imgs = [ref + noise * torch.rand(3, *size, generator=g), ref * scale]
    write_exr(tmp_path / "ref.exr", {ref_layer: ref})
    paths = [str(tmp_path / f"img{k}.exr") for k in range(2)]
    for path, img in zip(paths, imgs, strict=True):
        write_exr(path, {"color": img})
    return ref, imgs, paths


def test_metrics_picture_is_each_image_beside_the_reference(tmp_path, capsys):
    """Issue 69: no command wrote a picture of a comparison (only the demo). ``metrics --picture``
    writes a PNG that another decoder (Pillow) reads as each image and then the reference, each
    under its label strip, tonemapped as ``to_srgb8`` does; other names and an existing picture
    are refused before anything is read."""
    pytest.importorskip("OpenEXR")
    from PIL import Image

    from torchgi.io.png import to_srgb8

    ref, imgs, paths = _metrics_files(tmp_path, (20, 24), [0.2, 0.5], "color")
    pic = tmp_path / "cmp.png"
    args = ["metrics", *paths, "--ref", str(tmp_path / "ref.exr"), "--picture", str(pic), "--exposure", "2"]
    assert main(args) == 0
    assert f"wrote {pic} (each image beside the reference" in capsys.readouterr().out
    sheet = np.asarray(Image.open(pic).convert("RGB"))
    strip = sheet.shape[0] - 20
    assert sheet.shape[1] == 3 * 24 and strip > 0
    for k, panel in enumerate([*imgs, ref]):
        np.testing.assert_array_equal(sheet[strip:, 24 * k:24 * (k + 1)], to_srgb8(panel * 2))
    assert main(args) == 2 and "--picture: " in capsys.readouterr().err
    assert main([*args[:-4], "--picture", str(tmp_path / "cmp.exr")]) == 2
    assert "--picture: expected a name ending in .png" in capsys.readouterr().err


def test_info_names_the_back_end_of_each_op_family(capsys):
    """Issue 69: the README says ``torchgi info`` tells which back end runs the kernels; it printed
    versions only. It names each back end's state, the compiler, the kernel cache and, per op
    family and device, the back end a call runs, as :func:`torchgi.backends.status` gives them,
    and follows a back end switched off; and each op family runs by the back end named
    (``status()["last"]`` after a real call)."""
    from torchgi import backends
    from torchgi.filters import box

    assert main(["info", "--json"]) == 0
    status = backends.status()
    info = json.loads(capsys.readouterr().out)["backends"]
    assert info == {k: v for k, v in status.items() if k != "last"}
    assert set(info["ops"]["cpu"]) == set(backends.base._OPS.values())
    assert main(["info"]) == 0
    text = capsys.readouterr().out
    assert f"backend c      {status['c']}\n" in text and f"cache    {status['cache']}" in text
    want = info["ops"]["cpu"]["box"]["runs"]
    assert f"ops on cpu run by {want}: " in text
    box(torch.rand(1, 1, 8, 8), 1)
    assert backends.status()["last"]["box"]["ran"] == want
    with backends.use("torch"):
        assert main(["info"]) == 0
        text = capsys.readouterr().out
    assert "backend c      switched off by torchgi.backends.use(...)" in text
    assert "ops on cpu run by torch: accumulate, " in text and "ops on cpu run by c" not in text


def test_metrics_command(tmp_path, capsys):
    pytest.importorskip("OpenEXR")
    ref, imgs, paths = _metrics_files(tmp_path, (16, 16), [0.1, 1.5], "")
    assert main(["metrics", *paths, "--ref", str(tmp_path / "ref.exr"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["reference"] == str(tmp_path / "ref.exr") and list(out["images"]) == paths
    for path, img in zip(paths, imgs, strict=True):
        table, d = out["images"][path], (img.double() - ref.double()).numpy()
        assert set(table) == {"mse", "relmse", "psnr_db", "ssim", "flip"}
        np.testing.assert_allclose(table["mse"], (d**2).mean(), rtol=1e-5)
        np.testing.assert_allclose(table["relmse"], (d**2 / (ref.double().numpy() ** 2 + 1e-2)).mean(), rtol=1e-5)
    assert main(["metrics", paths[1], "--ref", str(tmp_path / "ref.exr")]) == 0
    assert capsys.readouterr().out.startswith(f"reference (--ref): {tmp_path / 'ref.exr'}")


def test_metrics_command_errors(tmp_path, capsys):
    pytest.importorskip("OpenEXR")
    write_exr(tmp_path / "ref.exr", {"albedo": torch.rand(3, 4, 4)})
    assert main(["metrics", str(tmp_path / "ref.exr"), "--ref", str(tmp_path / "ref.exr")]) == 2
    assert "missing required layer(s) color" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # the old positional order REF IMG: the reference must be named
        main(["metrics", str(tmp_path / "ref.exr"), str(tmp_path / "ref.exr")])
    assert "--ref" in capsys.readouterr().err


def test_render_command_writes_a_multilayer_exr_and_never_overwrites(tmp_path, capsys):
    pytest.importorskip("embreex")
    pytest.importorskip("OpenEXR")
    import torchgi

    out = tmp_path / "cornell.exr"
    args = ["render", "cornell", "--spp", "2", "--bounces", "1", "--seed", "3", "--resolution", "16", "12",
            "--out", str(out), "--no-progress"]
    assert main(args) == 0
    assert ", 1 bounce in " in capsys.readouterr().out  # issue 69: it said "1 bounces"
    gb = torchgi.GBuffer.from_exr(out, required=("color", "direct", "indirect", "emission", "albedo", "normal"))
    ref = torchgi.render(torchgi.scenes.cornell(16).with_resolution(16, 12), spp=2, bounces=1, seed=3)
    assert torch.equal(gb.color, ref.color) and torch.equal(gb.indirect, ref.indirect)
    before = out.read_bytes()
    assert main(args) == 2
    assert "exists" in capsys.readouterr().err and out.read_bytes() == before
    assert main(args + ["--overwrite"]) == 0


def test_render_command_takes_mirror_guides(tmp_path, capsys):
    """--mirror-guides R: the EXR's albedo is render(mirror_guides=R)'s (a polished floor of
    roughness 0.06 followed at 0.1), not the first hit's; refused with --frames."""
    pytest.importorskip("embreex")
    pytest.importorskip("OpenEXR")
    import torchgi

    scene = "configs/scenes/train/mirror_lamps.yaml"
    out = tmp_path / "mirror.exr"
    args = ["render", scene, "--spp", "1", "--resolution", "16", "12", "--out", str(out), "--no-progress"]
    assert main([*args, "--mirror-guides", "0.1"]) == 0
    gb = torchgi.GBuffer.from_exr(out, required=("color", "albedo", "normal"))
    base = torchgi.load_scene(scene).with_resolution(16, 12)
    want = torchgi.render(base, spp=1, mirror_guides=0.1)
    assert torch.equal(gb.albedo, want.albedo) and not torch.equal(gb.albedo, torchgi.render(base, spp=1).albedo)
    assert main([*args, "--overwrite", "--mirror-guides", "0.1", "--frames", "2"]) == 2
    assert "--mirror-guides" in capsys.readouterr().err


@pytest.mark.skipif(importlib.util.find_spec("embreex") is None, reason="the render extra is not installed")
def test_cli_renders_frames_with_a_motion_layer(tmp_path, capsys, meshes_dir):
    pytest.importorskip("OpenEXR")
    from torchgi.cli import main
    from torchgi.io import read_aovs, read_exr, write_exr

    out = tmp_path / "seq.exr"
    args = ["render", os.path.join(SEQUENCES, "cornell_slide.yaml"), "--frames", "2", "--spp", "1",
            "--resolution", "12", "10", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    second = tmp_path / "seq_0001.exr"
    assert (tmp_path / "seq_0000.exr").exists() and second.exists()
    motion = torchgi.GBuffer.from_exr(second).motion
    assert motion.shape == (1, 2, 10, 12) and motion.abs().max() > 0
    before = second.read_bytes()
    assert main(args) == 2 and "seq_0000" in capsys.readouterr().err and second.read_bytes() == before
    # other renderers' names for the layer
    write_exr(tmp_path / "b.exr", {"ViewLayer.Vector": torch.rand(4, 3, 5)})
    assert read_aovs(tmp_path / "b.exr", required=("motion",))["motion"].shape == (2, 3, 5)
    write_exr(tmp_path / "a.exr", {"motionvector": torch.rand(3, 3, 5)})
    assert read_aovs(tmp_path / "a.exr", required=("motion",))["motion"].shape == (2, 3, 5)
    assert list(read_exr(second)["motion"].shape) == [2, 10, 12]


@pytest.mark.parametrize("method", methods.names())
def test_denoise_command_gives_the_python_call_bit_for_bit(tmp_path, method):
    """Every Denoiser method from the shell (issue 30): the file it writes holds exactly what
    ``Denoiser(method)`` gives on the same EXR read back (a torchgi render, 1 spp)."""
    pytest.importorskip("embreex")
    pytest.importorskip("OpenEXR")
    import torchgi
    from torchgi.io import read_aovs

    noisy = tmp_path / "noisy.exr"
    torchgi.render(torchgi.scenes.cornell(24).with_resolution(24, 20), spp=1, bounces=1, seed=1).to_exr(noisy)
    out = tmp_path / f"{method}.exr"
    assert main(["denoise", str(noisy), "--method", method, "--out", str(out)]) == 0
    gb = torchgi.GBuffer.from_exr(noisy, required=("color", "albedo", "normal"))
    want = torchgi.Denoiser(method)(gb)
    got = read_aovs(out)["color"][None]
    assert got.dtype == want.dtype and torch.equal(got, want)


def test_denoise_command_on_a_mitsuba_render(tmp_path, capsys, monkeypatch):
    # A Mitsuba 3 render with AOVs written by Mitsuba's own Bitmap, denoised from the command line.
    # Two nested integrators on the same samples give a colour and an exact emission layer.
    mi = pytest.importorskip("mitsuba")
    pytest.importorskip("OpenEXR")
    from torchgi import metrics
    from torchgi.io import read_aovs
    from torchgi.render.mitsuba import cornell_box, load_mitsuba

    load_mitsuba()
    scene = cornell_box(64)  # box pixel filter: independent pixel noise
    scene["integrator"] = {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal,dd:depth",
                           "color": {"type": "path", "max_depth": 4},
                           "emission": {"type": "path", "max_depth": 1}}
    loaded = mi.load_dict(scene)
    mi.render(loaded, spp=1, seed=1)
    loaded.sensors()[0].film().bitmap(raw=False).write(str(tmp_path / "noisy.exr"))
    scene["integrator"] = {"type": "path", "max_depth": 4}
    ref = np.array(mi.render(mi.load_dict(scene), spp=512, seed=2))[..., :3]
    ref = torch.from_numpy(ref.copy()).permute(2, 0, 1)[None]
    out = tmp_path / "den.exr"
    assert main(["denoise", str(tmp_path / "noisy.exr"), "--method", "guided", "--out", str(out)]) == 0
    den = read_aovs(out)["color"][None]
    noisy = read_aovs(tmp_path / "noisy.exr")["color"][None]
    gain = float(metrics.relmse(noisy, ref)) / float(metrics.relmse(den, ref))
    assert gain > 6  # measured 8.9 here at 64², 1 spp (55.6x at 512²: docs/benchmarks/quality.md)
    tiled = tmp_path / "tiled.exr"
    assert main(["denoise", str(tmp_path / "noisy.exr"), "--max-memory-mb", "1", "--out", str(tiled)]) == 0
    assert float((read_aovs(tiled)["color"][None] - den).abs().max()) <= 1e-5 * float(den.abs().max())
    assert main(["denoise", str(tmp_path / "noisy.exr"), "--max-memory-mb", "none", "--out", str(tiled),
                 "--overwrite"]) == 0  # untiled, as the default ("auto") at this size
    assert torch.equal(read_aovs(tiled)["color"][None], den)
    budgets = tile_budgets(monkeypatch, all_large=True)
    for flag, tiled_by in (([], [512.0]), (["--max-memory-mb", "none"], []), (["--max-memory-mb", "auto"], [512.0])):
        budgets.clear()  # with every call "large": the default and "auto" tile (the floor's budget), "none" does not
        assert main(["denoise", str(tmp_path / "noisy.exr"), *flag, "--out", str(tiled), "--overwrite"]) == 0
        assert budgets == tiled_by, flag
    for bad in ("0", "-3", "inf", "lots"):
        with pytest.raises(SystemExit):
            main(["denoise", str(tmp_path / "noisy.exr"), "--max-memory-mb", bad, "--out", str(tiled)])
    assert "expected MB > 0, 'auto' or 'none', got lots" in capsys.readouterr().err
    capsys.readouterr()
    assert main(["denoise", str(tmp_path / "noisy.exr"), "--out", str(out)]) == 2  # never overwrites
    err = capsys.readouterr().err
    assert f"--out: {out} exists; pass --overwrite" in err and "overwrite=True" not in err  # the flag, not Python
    for flag in (["--no-short-pass"], ["--motion-convention", "cycles"]):  # the TemporalDenoiser's flags
        assert main(["denoise", str(tmp_path / "noisy.exr"), *flag, "--out", str(tmp_path / "x.exr")]) == 2
        assert f"{flag[0]}: only with --temporal" in capsys.readouterr().err


def _sequence_files(folder, frames: int = 4):
    """A rendered camera sequence (tests/helpers.py's sliding Cornell box, 24x20, 1 spp) as torchgi EXR files."""
    import torchgi
    from tests.helpers import sliding_cornell

    folder.mkdir()
    for k, gb in enumerate(torchgi.render_sequence(sliding_cornell(24).with_resolution(24, 20), frames, spp=1)):
        gb.to_exr(folder / f"seq_{k:04d}.exr")
    return folder


def test_temporal_denoise_command_gives_the_python_call_bit_for_bit_and_resumes(tmp_path, capsys):
    """``torchgi denoise --temporal`` (issue 30): each frame's file holds exactly what the
    TemporalDenoiser gives on the frames read back, in order; a re-run keeps the frames already
    written and rebuilds the history from the frames before a missing one (the rewritten frame is
    the uninterrupted run's, bit for bit); other settings or a file it did not write are refused."""
    pytest.importorskip("embreex")
    pytest.importorskip("OpenEXR")
    import torchgi
    from torchgi.io import read_aovs

    frames = _sequence_files(tmp_path / "frames")
    out = tmp_path / "den"
    args = ["denoise", "--temporal", str(frames / "seq_####.exr"), "--out", str(out), "--no-progress"]
    assert main(args) == 0
    den = torchgi.TemporalDenoiser()
    wants = [den(torchgi.GBuffer.from_exr(frames / f"seq_{k:04d}.exr")) for k in range(4)]
    for k, want in enumerate(wants):
        got = read_aovs(out / f"seq_{k:04d}.exr")["color"][None]
        assert got.dtype == want.dtype and torch.equal(got, want), k
    summary = json.loads((out / "summary.json").read_text())
    assert [r["kept"] for r in summary["frames"]] == [False] * 4
    # resumed after frame 2 was lost: frame 3's file is kept, frame 2 rewritten as before
    (out / "seq_0002.exr").unlink()
    before = (out / "seq_0003.exr").stat().st_mtime_ns
    assert main(args[:2] + [str(frames)] + args[3:]) == 0  # the folder form
    assert torch.equal(read_aovs(out / "seq_0002.exr")["color"][None], wants[2])
    assert (out / "seq_0003.exr").stat().st_mtime_ns == before
    assert [r["kept"] for r in json.loads((out / "summary.json").read_text())["frames"]] == [True, True, False, True]
    capsys.readouterr()
    assert main(args + ["--sanitize"]) == 2 and "other settings" in capsys.readouterr().err
    assert main(args + ["--no-short-pass"]) == 2 and "other settings" in capsys.readouterr().err
    assert summary["settings"]["short_pass"] is True
    stranger = tmp_path / "stranger"
    stranger.mkdir()
    (stranger / "seq_0001.exr").write_bytes((frames / "seq_0001.exr").read_bytes())
    assert main(args[:4] + [str(stranger), "--no-progress"]) == 2
    assert "not a frame this command wrote" in capsys.readouterr().err
    assert (stranger / "seq_0001.exr").read_bytes() == (frames / "seq_0001.exr").read_bytes()
    assert main(args + ["--method", "atrous"]) == 2 and "--method" in capsys.readouterr().err
    assert main(args + ["--radius", "2"]) == 2 and "--radius" in capsys.readouterr().err
    learned = tmp_path / "den_pyramid"  # the learned spatial filter, bit for bit too
    assert main(args[:4] + [str(learned), "--no-progress", "--method", "pyramid"]) == 0
    den = torchgi.TemporalDenoiser(spatial="pyramid")
    for k in range(4):
        want = den(torchgi.GBuffer.from_exr(frames / f"seq_{k:04d}.exr"))
        assert torch.equal(read_aovs(learned / f"seq_{k:04d}.exr")["color"][None], want), k
    other = _sequence_files(tmp_path / "other", 2)  # the same file names, other frames
    assert main(["denoise", "--temporal", str(other), "--out", str(out), "--no-progress"]) == 2
    assert "was denoised from" in capsys.readouterr().err
    assert main(["denoise", "--temporal", str(frames), "--out", str(frames)]) == 2
    assert "would replace it" in capsys.readouterr().err


def test_temporal_export_command_matches_the_python_step(tmp_path, capsys):
    """``torchgi export --temporal`` writes DeployedTemporal's graph (the state in and out):
    onnxruntime over three frames of a render agrees with the torch step to 1e-4 relative
    (at two sizes, neither the example's)."""
    pytest.importorskip("embreex")
    pytest.importorskip("onnxruntime")
    import torchgi
    from tests.helpers import rel_error, sliding_cornell
    from torchgi.export import OrtSession
    from torchgi.temporal import DeployedTemporal, TemporalState

    path = tmp_path / "t.onnx"
    assert main(["export", "--temporal", "--out", str(path)]) == 0
    assert "next_history" in capsys.readouterr().out
    m, ort = DeployedTemporal(), OrtSession(path)
    names = list(m.input_names)
    assert ort.input_names == names
    for W, H in ((40, 47), (31, 24)):
        state = TemporalState.empty(torch.zeros(1, 3, H, W)).tensors()
        for gb in torchgi.render_sequence(sliding_cornell(W).with_resolution(W, H), 3, spp=1):
            inputs = [getattr(gb, k) for k in names[:6]]
            a = m(*inputs, *state)
            b = ort.outputs(**dict(zip(names, inputs + list(state))))
            for mine, theirs in zip(a, b, strict=True):
                assert rel_error(theirs, mine) < 1e-4, (W, H)
            state = (*a[1:5], gb.normal, gb.depth, a[5])
    assert np.isfinite(b[0].numpy()).all()
    assert main(["export", "--temporal", "--spp", "4", "--out", str(tmp_path / "u.onnx")]) == 2
    assert "--spp" in capsys.readouterr().err


def _outside_render(path):
    """A torchgi render (24x20, 1 spp) written with Mitsuba 3's AOV names - ``dd.y`` depth, ``nn``
    normals, a nested integrator's ``img`` - and no sample count or position: an outside render."""
    import torchgi

    gb = torchgi.render(torchgi.scenes.cornell(24).with_resolution(24, 20), spp=1, bounces=1, seed=1)
    write_exr(path, {"": gb.color[0], "albedo": gb.albedo[0], "nn": gb.normal[0], "dd.y": gb.depth[0],
                     "img": torch.cat([gb.color[0], torch.ones(1, 20, 24)])})
    return gb


def test_denoise_command_says_which_layers_it_read_and_refuses_a_missing_guide(tmp_path, capsys):
    pytest.importorskip("embreex")
    pytest.importorskip("OpenEXR")
    _outside_render(tmp_path / "mi.exr")
    assert main(["denoise", str(tmp_path / "mi.exr"), "--out", str(tmp_path / "g.exr")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "read color from R,G,B, albedo from 'albedo', normal from 'nn', depth from 'dd.y'"
    assert lines[1] == "ignored 'img' (no name torchgi reads: torchgi.io.AOV_ALIASES)"
    assert "1 spp: the file records none, --spp gives it" in lines[2]
    for method, layer in (("pyramid", "depth"), ("atrous", "position")):
        wrong = tmp_path / "without.exr"
        layers = {"": torch.rand(3, 20, 24), "albedo": torch.rand(3, 20, 24), "nn": torch.rand(3, 20, 24) * 2 - 1}
        write_exr(wrong, layers | ({"pos": torch.rand(3, 20, 24)} if layer == "depth" else {}), overwrite=True)
        assert main(["denoise", str(wrong), "--method", method, "--out", str(tmp_path / "x.exr")]) == 2
        err = capsys.readouterr().err
        assert f"error: method '{method}' needs a {layer} layer (GBuffer.{layer})" in err and "Traceback" not in err
        assert not (tmp_path / "x.exr").exists()


def test_denoise_command_takes_the_sample_count_of_an_outside_render(tmp_path, capsys):
    pytest.importorskip("embreex")
    pytest.importorskip("OpenEXR")
    import torchgi
    from torchgi.io import read_aovs

    _outside_render(tmp_path / "mi.exr")
    gb = torchgi.GBuffer.from_exr(tmp_path / "mi.exr", return_report=True)[0]
    B, H, W = gb.shape
    assert main(["denoise", str(tmp_path / "mi.exr"), "--spp", "4", "--out", str(tmp_path / "4.exr")]) == 0
    assert "(24x20, 4 spp (--spp))" in capsys.readouterr().out
    got = read_aovs(tmp_path / "4.exr")["color"][None]
    assert torch.equal(got, torchgi.Denoiser()(gb, spp=4))
    assert torch.equal(got, torchgi.Denoiser()(gb.replace(spp=torch.full((B, 1, H, W), 4))))
    assert not torch.equal(got, torchgi.Denoiser()(gb))  # 1 spp without the flag
    for bad in ("0", "-2", "0.5", "nan", "inf", "four"):
        with pytest.raises(SystemExit):
            main(["denoise", str(tmp_path / "mi.exr"), "--spp", bad, "--out", str(tmp_path / "x.exr")])
        assert f"--spp: expected the render's samples per pixel, a finite number >= 1, got {bad}" in \
            capsys.readouterr().err
    torchgi.render(torchgi.scenes.cornell(8), spp=2, bounces=1).to_exr(tmp_path / "own.exr")  # records spp 2
    assert main(["denoise", str(tmp_path / "own.exr"), "--spp", "4", "--out", str(tmp_path / "x.exr")]) == 2
    assert "--spp: " in (err := capsys.readouterr().err) and "records its own sample counts (layer 'spp'" in err
    assert main(["denoise", str(tmp_path / "own.exr"), "--spp", "2", "--out", str(tmp_path / "x.exr")]) == 0
    assert main(["denoise", str(tmp_path / "mi.exr"), "--temporal", "--spp", "4", "--out", str(tmp_path / "t")]) == 2
    assert "--spp: not with --temporal" in capsys.readouterr().err


def test_a_missing_output_folder_is_named_as_the_flag(tmp_path, capsys):
    """The library says ``path: folder ... does not exist``; the shell user gave ``--out``."""
    pytest.importorskip("embreex")
    pytest.importorskip("OpenEXR")
    missing = tmp_path / "nope" / "c.exr"
    assert main(["render", "cornell", "--spp", "1", "--resolution", "8", "8", "--out", str(missing),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"--out: folder {missing.parent} does not exist (create it first)" in err
    assert not missing.parent.exists()


def test_render_command_renders_to_a_time_budget_or_a_target(tmp_path, capsys):
    # --seconds / --target: render_to's rounds, per-pixel counts in the EXR's spp layer (the same
    # as the function's for a target and a seed); refused with --spp, together, or over a file.
    pytest.importorskip("embreex")
    pytest.importorskip("OpenEXR")
    import torchgi

    out = tmp_path / "sky.exr"
    base = ["render", "sky", "--resolution", "16", "12", "--seed", "2", "--no-progress"]
    assert main(base + ["--target", "0.05", "--out", str(out)]) == 0
    gb = torchgi.GBuffer.from_exr(out, required=("color", "spp"))
    want = torchgi.render_to(torchgi.scenes.sky(16).with_resolution(16, 12), target=0.05, bounces=1, seed=2, progress=False)
    assert torch.equal(gb.spp, want.spp) and torch.equal(gb.color, want.color)
    assert "spp (mean; per-pixel counts" in capsys.readouterr().out
    assert main(base + ["--seconds", "0.2", "--out", str(tmp_path / "t.exr")]) == 0
    assert int(torchgi.GBuffer.from_exr(tmp_path / "t.exr", required=("spp",)).spp.min()) >= 2
    for extra, words in ((["--seconds", "1", "--spp", "4"], "--seconds: not with --spp"),
                         (["--seconds", "1", "--target", "0.1"], "give one of them"),
                         (["--target", "0.1"], "exists")):
        assert main(base + extra + ["--out", str(out)]) == 2
        assert words in capsys.readouterr().err


def test_png_outputs_are_pictures_and_other_names_are_refused(tmp_path, capsys):
    """``--out x.png`` writes a PNG of the colour (sRGB, exposure said), the EXR's pixels
    tonemapped; a name that is neither .exr nor .png is refused before anything is rendered."""
    pytest.importorskip("embreex")
    pytest.importorskip("imageio")
    import imageio.v3 as iio

    from torchgi.io.png import to_srgb8

    exr, png = tmp_path / "c.exr", tmp_path / "c.png"
    args = ["render", "cornell", "--spp", "2", "--resolution", "16", "16", "--seed", "3"]
    assert main([*args, "--out", str(exr)]) == 0
    assert main([*args, "--out", str(png), "--exposure", "2"]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG" and "exposure 2" in capsys.readouterr().out
    gb = torchgi.GBuffer.from_exr(exr)
    assert (iio.imread(png) == to_srgb8(gb.color[0], exposure=2.0)).all()
    assert main(["denoise", str(exr), "--out", str(tmp_path / "d.png")]) == 0
    assert (tmp_path / "d.png").read_bytes()[:4] == b"\x89PNG"
    assert main([*args, "--out", str(tmp_path / "c.tif")]) == 2
    assert "--out: expected a name ending in .exr" in capsys.readouterr().err
    assert not (tmp_path / "c.tif").exists()


def test_denoise_device_flag_says_where_and_refuses_an_absent_device(tmp_path, capsys):
    """Issue 69: the CLI had no ``--device``, and a CUDA request on a CPU machine surfaced
    torch's own message. ``--device cpu`` denoises there and says so; a device this machine
    lacks, or a name that is none, is refused by the flag's name before anything is read."""
    pytest.importorskip("embreex")
    pytest.importorskip("OpenEXR")
    import torchgi

    noisy = tmp_path / "noisy.exr"
    torchgi.render(torchgi.scenes.cornell(16).with_resolution(16, 12), spp=1, bounces=1, seed=1).to_exr(noisy)
    assert main(["denoise", str(noisy), "--device", "cpu", "--out", str(tmp_path / "a.exr")]) == 0
    assert " on cpu in " in capsys.readouterr().out
    absent = f"cuda:{torch.cuda.device_count()}"
    for device, words in ((absent, f"argument --device: {absent}: "), ("tpu", "expected cpu, cuda or cuda:N, got 'tpu'")):
        with pytest.raises(SystemExit):
            main(["denoise", str(noisy), "--device", device, "--out", str(tmp_path / "b.exr")])
        assert words in capsys.readouterr().err
    assert not (tmp_path / "b.exr").exists()
