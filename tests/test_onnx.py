"""ONNX export: dynamic B/H/W, onnxruntime parity with torch at two resolutions."""

import pytest
import torch

from tests.helpers import rel_error as rel
from torchgi.export import OrtSession, export_onnx
from torchgi.filters import Box, Guided

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")



def test_box_parity(tmp_path):
    path = export_onnx(Box(3), [torch.rand(1, 2, 16, 20)], tmp_path / "box.onnx", input_names=["x"])
    session = OrtSession(path)
    for shape in [(1, 2, 16, 16), (3, 2, 45, 29), (1, 2, 5, 3)]:
        x = torch.rand(shape)
        assert rel(session(x=x), Box(3)(x)) < 1e-5, shape


@pytest.mark.parametrize("subsample", [1, 2])
def test_guided_parity(tmp_path, subsample):
    m = Guided(radius=6, eps=torch.tensor([0.01, 0.01, 0.01, 0.03]), subsample=subsample)
    path = export_onnx(m, [torch.rand(2, 3, 24, 32), torch.rand(2, 4, 24, 32)], tmp_path / "g.onnx",
                       input_names=["src", "guide"])
    session = OrtSession(path)
    g = torch.Generator().manual_seed(0)
    for B, H, W in [(1, 64, 48), (2, 37, 91)]:
        src = torch.rand(B, 3, H, W, generator=g) * 10
        guide = torch.rand(B, 4, H, W, generator=g) + 1e3  # offset guides: centring is in the graph too
        assert rel(session(src=src, guide=guide), m(src, guide)) < 1e-4, (B, H, W)


def test_export_never_overwrites(tmp_path):
    (tmp_path / "x.onnx").write_bytes(b"keep")
    with pytest.raises(FileExistsError, match="exists"):
        export_onnx(Box(1), [torch.rand(1, 1, 4, 5)], tmp_path / "x.onnx", input_names=["x"])
    assert (tmp_path / "x.onnx").read_bytes() == b"keep"
    with pytest.raises(ValueError, match="distinct sizes for B, H and W"):
        export_onnx(Box(1), [torch.rand(1, 1, 4, 4)], tmp_path / "y.onnx", input_names=["x"])


def test_atrous_parity(tmp_path):
    from torchgi.filters import ATrous

    m = ATrous(iterations=2, sigma_color=0.5, sigma_normal=0.2, sigma_position=0.3)
    ex = [torch.rand(2, 3, 20, 28), torch.rand(2, 3, 20, 28), torch.rand(2, 3, 20, 28)]
    # unoptimised graph: the optimiser takes most of the export time of the unrolled levels
    path = export_onnx(m, ex, tmp_path / "a.onnx", input_names=["color", "normal", "position"], optimize=False)
    session = OrtSession(path)
    g = torch.Generator().manual_seed(1)
    for B, H, W in [(1, 33, 47), (3, 16, 9)]:
        c = torch.rand(B, 3, H, W, generator=g) * 4
        n = torch.nn.functional.normalize(torch.randn(B, 3, H, W, generator=g), dim=1)
        x = torch.rand(B, 3, H, W, generator=g) + 100.0
        assert rel(session(color=c, normal=n, position=x), m(c, n, x)) < 1e-4, (B, H, W)


def test_exported_denoiser_matches_torch(tmp_path):
    pytest.importorskip("embreex")
    import torchgi
    from torchgi.cli import main
    from torchgi.denoise import Denoiser
    from torchgi.export import OrtDenoiser

    path = tmp_path / "den.onnx"
    assert main(["export", "--method", "guided", "--spp", "1", "--out", str(path)]) == 0
    ort = OrtDenoiser(path)
    deployed = Denoiser("guided").deploy(spp=1)
    for size in (40, 24):
        gb = torchgi.render(torchgi.scenes.cornell(size).with_resolution(size, size + 7), spp=1, bounces=1)
        ours = Denoiser("guided")(gb)  # the torch Denoiser itself
        assert rel(deployed(gb.color, gb.emission, gb.albedo, gb.normal, gb.depth), ours) < 1e-4
        assert rel(ort(gb), ours) < 1e-4, size


@pytest.mark.parametrize(("method", "name", "value"), [("guided", "color", float("nan")),
                                                       ("guided", "depth", float("inf")),
                                                       ("atrous", "normal", float("nan")),
                                                       ("blend", "albedo", -float("inf"))])
def test_exported_denoiser_contains_a_non_finite_pixel(tmp_path, method, name, value):
    """A NaN/Inf pixel is a hole: finite output everywhere, the clean result outside its footprint
    (the firefly window, the filter's support twice over and the hole's own window)."""
    pytest.importorskip("embreex")
    import torchgi
    from torchgi.export import OrtDenoiser, export_denoiser

    path = export_denoiser(method, tmp_path / "d.onnx", sigma_position=1e3)
    ort = OrtDenoiser(path)
    gb = torchgi.render(torchgi.scenes.cornell(72).with_resolution(72, 64), spp=1, bounces=1)
    inputs = {k: getattr(gb, k).clone() for k in ("color", "emission", "albedo", "normal", "depth", "position")}
    clean = ort(**inputs)
    y, x = 30, 41
    inputs[name][0, 0, y, x] = value
    out = ort(**inputs)
    assert bool(torch.isfinite(out).all())
    far = torch.ones(64, 72, dtype=torch.bool)
    reach = 28  # px: 8 (fireflies) + 2 x 8 (guided r = 4 twice; blend's widest candidate) + 2 (hole) + 2
    far[max(0, y - reach) : y + reach + 1, max(0, x - reach) : x + reach + 1] = False
    diff = ((out - clean).abs() / (clean.abs() + 1e-2))[..., far]
    assert float(diff.max()) < 1e-3, float(diff.max())
