import numpy as np
import pytest
import torch

from torchgi.core import DTypeError, ExrError, LayerError, ShapeError
from torchgi.io import find_aovs, read_aovs, read_exr, write_exr

OpenEXR = pytest.importorskip("OpenEXR")


def test_round_trip_float_and_half_exact(tmp_path):
    g = torch.Generator().manual_seed(1)
    layers = {
        "color": torch.randn(3, 7, 9, generator=g) * 1e4,
        "normal": torch.randn(3, 7, 9, generator=g).half(),
        "depth": torch.rand(1, 7, 9, generator=g),
        "spp": torch.randint(0, 2**20, (1, 7, 9), generator=g),
        "features": torch.rand(5, 7, 9, generator=g),
    }
    write_exr(tmp_path / "a.exr", layers)
    back = read_exr(tmp_path / "a.exr")
    assert set(back) == set(layers)
    for name, t in layers.items():
        assert back[name].dtype == (torch.int64 if name == "spp" else t.dtype), name
        assert torch.equal(back[name], t), name
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temporary file left behind"


def test_channel_names_written(tmp_path):
    write_exr(tmp_path / "a.exr", {"normal": torch.zeros(3, 2, 2), "depth": torch.zeros(1, 2, 2), "": torch.zeros(3, 2, 2)})
    names = set(OpenEXR.File(str(tmp_path / "a.exr"), separate_channels=True).channels())
    assert names == {"normal.X", "normal.Y", "normal.Z", "depth.Z", "R", "G", "B"}


def test_no_overwrite_unless_asked(tmp_path):
    p = tmp_path / "a.exr"
    write_exr(p, {"color": torch.zeros(3, 2, 2)})
    before = p.read_bytes()
    with pytest.raises(FileExistsError, match="exists"):
        write_exr(p, {"color": torch.ones(3, 2, 2)})
    assert p.read_bytes() == before
    write_exr(p, {"color": torch.ones(3, 2, 2)}, overwrite=True)
    assert torch.equal(read_exr(p)["color"], torch.ones(3, 2, 2))


def test_write_errors(tmp_path):
    with pytest.raises(DTypeError, match=r"layers\['color'\]: EXR stores float16, float32 or uint32; got float64"):
        write_exr(tmp_path / "a.exr", {"color": torch.zeros(3, 2, 2, dtype=torch.float64)})
    with pytest.raises(ShapeError, match=r"layers\['depth'\]: size \(3, 2\) differs"):
        write_exr(tmp_path / "a.exr", {"color": torch.zeros(3, 2, 2), "depth": torch.zeros(1, 3, 2)})
    with pytest.raises(ShapeError, match=r"layers\['x'\]: expected shape \(C, H, W\)"):
        write_exr(tmp_path / "a.exr", {"x": torch.zeros(2, 3, 2, 2)})
    with pytest.raises(DTypeError, match="fit in uint32"):
        write_exr(tmp_path / "a.exr", {"spp": torch.tensor([[[-1]]])})
    with pytest.raises(FileNotFoundError, match="folder"):
        write_exr(tmp_path / "missing" / "a.exr", {"color": torch.zeros(3, 2, 2)})
    assert not list(tmp_path.iterdir())


def test_read_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such file"):
        read_exr(tmp_path / "nope.exr")
    (tmp_path / "text.exr").write_text("hello, not an image")
    with pytest.raises(ExrError, match="not an OpenEXR file"):
        read_exr(tmp_path / "text.exr")
    write_exr(tmp_path / "full.exr", {"color": torch.rand(3, 64, 64)}, compression="none")
    data = (tmp_path / "full.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(ExrError, match="truncated or corrupt"):
        read_exr(tmp_path / "cut.exr")
    (tmp_path / "head.exr").write_bytes(data[:40])
    with pytest.raises(ExrError, match="truncated or corrupt"):
        read_exr(tmp_path / "head.exr")


def _write_raw(path, channels):
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, dict(channels)).write(str(path))


def test_blender_cycles_layout(tmp_path):
    rng = np.random.default_rng(0)
    planes = {}
    for layer, comps in [("Combined", "RGBA"), ("Noisy Image", "RGBA"), ("Denoising Normal", "XYZ"),
                         ("Denoising Albedo", "RGB"), ("Denoising Depth", "Z"), ("Normal", "XYZ")]:
        for c in comps:
            planes[f"ViewLayer.{layer}.{c}"] = rng.random((5, 6), dtype=np.float32)
    _write_raw(tmp_path / "b.exr", planes)
    aovs = read_aovs(tmp_path / "b.exr", required=("color", "albedo", "normal", "depth"))
    # Cycles' Combined is the denoised result when denoising data is written: take the noisy one.
    np.testing.assert_array_equal(aovs["color"][0].numpy(), planes["ViewLayer.Noisy Image.R"])
    np.testing.assert_array_equal(aovs["color"][2].numpy(), planes["ViewLayer.Noisy Image.B"])
    np.testing.assert_array_equal(aovs["normal"][1].numpy(), planes["ViewLayer.Denoising Normal.Y"])
    np.testing.assert_array_equal(aovs["albedo"][0].numpy(), planes["ViewLayer.Denoising Albedo.R"])
    np.testing.assert_array_equal(aovs["depth"][0].numpy(), planes["ViewLayer.Denoising Depth.Z"])
    assert aovs["color"].shape == (3, 5, 6) and aovs["depth"].shape == (1, 5, 6)

    # Without the view-layer prefix, and with only the Combined pass.
    plain = {k.split(".", 1)[1]: v for k, v in planes.items() if "Noisy" not in k}
    _write_raw(tmp_path / "c.exr", plain)
    aovs = read_aovs(tmp_path / "c.exr", required=("color", "normal"))
    np.testing.assert_array_equal(aovs["color"][1].numpy(), plain["Combined.G"])


def test_arnold_layout(tmp_path):
    rng = np.random.default_rng(1)
    planes = {c: rng.random((4, 4), dtype=np.float32) for c in ["R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z",
                                                                 "P.X", "P.Y", "P.Z", "albedo.R", "albedo.G", "albedo.B"]}
    _write_raw(tmp_path / "a.exr", planes)
    aovs = read_aovs(tmp_path / "a.exr", required=("color", "normal", "position", "depth", "albedo"))
    np.testing.assert_array_equal(aovs["color"][2].numpy(), planes["B"])
    np.testing.assert_array_equal(aovs["depth"][0].numpy(), planes["Z"])
    np.testing.assert_array_equal(aovs["position"][0].numpy(), planes["P.X"])


def test_mitsuba_exr(tmp_path):
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    scene = mi.cornell_box()
    scene["sensor"]["film"].update(width=12, height=10)
    scene["integrator"] = {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal,dd.y:depth,pp:position",
                           "img": {"type": "path", "max_depth": 3}}
    loaded = mi.load_dict(scene)
    mi.render(loaded, spp=4)
    bitmap = loaded.sensors()[0].film().bitmap(raw=False)
    bitmap.write(str(tmp_path / "mitsuba.exr"))
    parts = {name: np.array(b, dtype=np.float32).reshape(10, 12, -1) for name, b in bitmap.split()}
    aovs = read_aovs(tmp_path / "mitsuba.exr", required=("color", "albedo", "normal", "position", "depth"))
    np.testing.assert_array_equal(aovs["color"].permute(1, 2, 0).numpy(), parts["<root>"])
    np.testing.assert_array_equal(aovs["albedo"].permute(1, 2, 0).numpy(), parts["albedo"])
    np.testing.assert_array_equal(aovs["normal"].permute(1, 2, 0).numpy(), parts["nn"])
    np.testing.assert_array_equal(aovs["position"].permute(1, 2, 0).numpy(), parts["pp"])
    np.testing.assert_array_equal(aovs["depth"].permute(1, 2, 0).numpy(), parts["dd.y"])  # Mitsuba's docs' name
    assert (aovs["depth"] > 0).all()  # the Cornell box is closed towards the camera's view


def test_missing_layer_names_what_was_found():
    layers = {"color": torch.zeros(3, 2, 2), "junk": torch.zeros(1, 2, 2)}
    with pytest.raises(LayerError, match=r"missing required layer\(s\) albedo; found layers: 'color', 'junk'"):
        find_aovs(layers, required=("color", "albedo"))
    with pytest.raises(LayerError, match="layer 'normal' .*has 2 channels, expected 3"):
        find_aovs({"normal": torch.zeros(2, 2, 2)}, required=())


def test_frame_paths_orders_folders_globs_and_patterns_by_frame_number(tmp_path):
    """``torchgi.io.sequence.frame_paths`` (the frames of ``denoise --temporal``): digits compare
    as numbers (f_9 before f_10), a ``#`` run matches at least that many digits and nothing else,
    an explicit list keeps its order; empty matches, missing files and one name twice are refused."""
    from torchgi.io.sequence import frame_paths

    for name in ("f_10.exr", "f_9.exr", "f_100.exr", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    def names(spec):
        return [p.name for p in frame_paths(spec)]

    assert names([tmp_path]) == ["f_9.exr", "f_10.exr", "f_100.exr"]
    assert names([str(tmp_path / "f_*.exr")]) == ["f_9.exr", "f_10.exr", "f_100.exr"]
    (tmp_path / "f_x.exr").write_bytes(b"")  # no frame number: no pattern takes it
    assert names([str(tmp_path / "f_##.exr")]) == ["f_10.exr", "f_100.exr"]
    assert names([str(tmp_path / "f_#.exr")]) == ["f_9.exr", "f_10.exr", "f_100.exr"]
    assert names([tmp_path / "f_10.exr", tmp_path / "f_9.exr"]) == ["f_10.exr", "f_9.exr"]
    with pytest.raises(FileNotFoundError, match="pattern"):
        frame_paths([str(tmp_path / "h_####.exr")])
    with pytest.raises(FileNotFoundError, match="no such file"):
        frame_paths([tmp_path / "f_9.exr", tmp_path / "f_8.exr"])
    other = tmp_path / "other"
    other.mkdir()
    (other / "f_9.exr").write_bytes(b"")
    with pytest.raises(ValueError, match="f_9.exr"):
        frame_paths([tmp_path / "f_9.exr", other / "f_9.exr"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="holds no .exr"):
        frame_paths([tmp_path / "empty"])


def test_a_mitsuba_dd_y_depth_is_read_and_unknown_layers_are_named(tmp_path):
    """Mitsuba 3's aov integrator with its documentation's ``dd.y:depth`` writes the layer ``dd.y``
    (channel ``dd.y.T``): read as depth. A layer of no known name is never dropped without a word:
    GBuffer.from_exr warns naming it, and its report says which layer each field came from."""
    from torchgi import GBuffer
    from torchgi.io import match_aovs

    g = torch.Generator().manual_seed(0)
    layers = {"": torch.rand(3, 4, 5, generator=g), "albedo": torch.rand(3, 4, 5, generator=g),
              "nn": torch.rand(3, 4, 5, generator=g) * 2 - 1, "dd.y": torch.rand(1, 4, 5, generator=g) + 1,
              "img": torch.rand(4, 4, 5, generator=g), "uv": torch.rand(2, 4, 5, generator=g)}
    write_exr(tmp_path / "m.exr", layers)
    with pytest.warns(UserWarning, match="not read: not a name torchgi knows") as caught:
        gb = GBuffer.from_exr(tmp_path / "m.exr", required=("color", "albedo", "normal", "depth"))
    assert "'img'" in str(caught[0].message) and "'uv'" in str(caught[0].message)
    assert torch.equal(gb.depth[0], layers["dd.y"]) and torch.equal(gb.normal[0], layers["nn"])
    gb, report = GBuffer.from_exr(tmp_path / "m.exr", return_report=True)
    assert report.used == {"color": "", "albedo": "albedo", "normal": "nn", "depth": "dd.y"}
    assert sorted(report.unknown) == ["img", "uv"] and report.alternatives == {} and report.channels_left == {}

    # Blender's layout: another name of an AOV read, and channels left (alpha; Vector's last two)
    blender = {f"ViewLayer.{k}": torch.zeros(c, 2, 2) for k, c in
               (("Noisy Image", 4), ("Denoising Normal", 3), ("Normal", 3), ("Vector", 4), ("Shadow", 3))}
    _, report = match_aovs(blender)
    assert report.used == {"color": "ViewLayer.Noisy Image", "normal": "ViewLayer.Denoising Normal",
                           "motion": "ViewLayer.Vector"}
    assert report.channels_left == {"color": 1, "motion": 2}
    assert report.alternatives == {"ViewLayer.Normal": "normal"} and report.unknown == ("ViewLayer.Shadow",)
    assert str(report) == (
        "read color from 'ViewLayer.Noisy Image' (not its 4th channel), normal from 'ViewLayer.Denoising Normal', "
        "motion from 'ViewLayer.Vector' (not its 3rd-4th channels)\n"
        "ignored 'ViewLayer.Shadow' (no name torchgi reads: torchgi.io.AOV_ALIASES); 'ViewLayer.Normal' (another "
        "name of normal, read from 'ViewLayer.Denoising Normal')")
