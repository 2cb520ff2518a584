"""Method "kpn" (torchgi/methods/kpn.py): the Denoiser gives the filter's function on the render's
own layers, its deployed graph gives the eager call, onnxruntime gives the graph at two sizes,
float16 stays float16 and a non-finite pixel stays a hole."""

import pytest
import torch

import torchgi
from tests.helpers import rel_error as rel
from torchgi import Denoiser
from torchgi.filters.kpn import kpn


@pytest.fixture(scope="module")
def gb():
    return torchgi.render(torchgi.scenes.cornell(48).with_resolution(48, 40), spp=4, bounces=1, seed=3)


def test_the_denoiser_is_the_filter_on_the_renders_layers(gb):
    """The shared checks, then the network told the mean count on surfaces and given the variance."""
    want = kpn(gb.color, gb.albedo, gb.normal, gb.depth, emission=gb.emission, variance=gb.variance, spp=4.0)
    assert torch.equal(Denoiser("kpn")(gb), want)
    # a direct/indirect split kept as sampled (filter_direct=False): the direct light passes as emission does
    kept = kpn(gb.color, gb.albedo, gb.normal, gb.depth, emission=gb.emission + gb.direct, variance=gb.variance,
               spp=4.0)
    assert torch.equal(Denoiser("kpn", filter_direct=False)(gb), kept)
    assert Denoiser("kpn").weights(gb).shape == (1, 3, 40, 48)


def test_float16_in_and_out(gb):
    half = gb.replace(**{k: getattr(gb, k).half() for k in ("color", "albedo", "normal", "depth", "emission",
                                                            "variance", "position", "direct", "indirect")})
    out = Denoiser("kpn")(half)
    assert out.dtype == torch.float16 and bool(torch.isfinite(out).all())
    assert rel(out.float(), Denoiser("kpn")(gb)) < 1e-2


def test_the_deployed_graph_is_the_eager_call_and_contains_a_hole(gb):
    d = Denoiser("kpn")
    m = d.deploy(frame=gb)
    assert m.input_names == ("color", "emission", "albedo", "normal", "depth", "variance")
    inputs = [getattr(gb, k) for k in m.input_names]
    assert torch.equal(m(*inputs), d(gb))
    holed = [t.clone() for t in inputs]
    holed[0][0, :, 20, 24] = float("nan")
    out = m(*holed)
    assert bool(torch.isfinite(out).all())


@pytest.mark.slow
def test_onnx_parity_at_two_sizes(tmp_path, gb):
    pytest.importorskip("onnxruntime")
    from torchgi.export import OrtDenoiser, export_denoiser

    path = tmp_path / "kpn.onnx"
    export_denoiser("kpn", path, frame=gb)
    session = OrtDenoiser(path)
    for size in ((48, 40), (37, 29)):  # one size the network pads
        g = torchgi.render(torchgi.scenes.cornell(48).with_resolution(*size), spp=4, bounces=1, seed=5)
        assert rel(session(g), Denoiser("kpn")(g)) < 1e-4, size


def test_tiles_give_the_untiled_output():
    """Under a budget the tiles (overlapping by REACH, the depth centred by the whole image's
    mean) give the one pass to float rounding."""
    g = torchgi.render(torchgi.scenes.cornell(64).with_resolution(360, 296), spp=2, bounces=1, seed=1)
    whole = Denoiser("kpn", max_memory_mb=None)(g)
    assert rel(Denoiser("kpn", max_memory_mb=24)(g), whole) < 1e-5
