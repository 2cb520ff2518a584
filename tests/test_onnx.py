"""ONNX export: dynamic B/H/W, onnxruntime parity with torch at two resolutions."""

import functools
import re

import pytest
import torch

from tests.helpers import rel_error as rel
from torchgi.export import OrtSession, export_onnx
from torchgi.filters import ApplyKernels, Box, Guided

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")



def test_box_parity(tmp_path):
    path = export_onnx(Box(3), [torch.rand(1, 2, 16, 20)], tmp_path / "box.onnx", input_names=["x"])
    session = OrtSession(path)
    for shape in [(1, 2, 16, 16), (3, 2, 45, 29), (1, 2, 5, 3)]:
        x = torch.rand(shape)
        assert rel(session(x=x), Box(3)(x)) < 1e-5, shape


def test_apply_kernels_parity(tmp_path):
    m = ApplyKernels(dilation=2, normalize=True)
    path = export_onnx(m, [torch.rand(1, 3, 16, 20), torch.rand(1, 25, 16, 20)], tmp_path / "k.onnx",
                       input_names=["x", "weights"])
    session = OrtSession(path)
    for B, H, W in [(1, 16, 16), (2, 37, 29), (1, 3, 5)]:
        x, w = torch.rand(B, 3, H, W), torch.rand(B, 25, H, W) + 0.1
        assert rel(session(x=x, weights=w), m(x, w)) < 1e-5, (B, H, W)


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


@pytest.fixture(scope="module")
def guided_export(tmp_path_factory):
    """The guided Denoiser exported once by the CLI (``torchgi export``), for the tests below, and
    what the export said besides: its warnings and torch's log records of level WARNING and up."""
    import logging
    import warnings

    from torchgi.cli import main

    path = tmp_path_factory.mktemp("onnx") / "den.onnx"
    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = records.append
    loggers = [logging.getLogger(name) for name in ("torch", "torch.onnx")]  # (torch.onnx does not propagate)
    for logger in loggers:
        logger.addHandler(handler)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert main(["export", "--method", "guided", "--spp", "1", "--out", str(path)]) == 0
    finally:
        for logger in loggers:
            logger.removeHandler(handler)
    return path, [str(w.message) for w in caught] + [r.getMessage() for r in records]


@pytest.fixture(scope="module")
def guided_onnx(guided_export):
    return guided_export[0]


def test_export_command_says_nothing_but_what_it_wrote(guided_export):
    """``torchgi export`` shows none of the exporter's routine notes (the torchvision operators it
    skips, each input naming the B/H/W axes again, torch's own deprecated calls) and leaves no
    file but the graph."""
    path, said = guided_export
    assert said == []
    assert [p.name for p in path.parent.iterdir()] == [path.name]


def test_exported_denoiser_matches_torch(guided_onnx):
    pytest.importorskip("embreex")
    import torchgi
    from torchgi.denoise import Denoiser
    from torchgi.export import OrtDenoiser

    ort = OrtDenoiser(guided_onnx)
    deployed = Denoiser("guided").deploy(spp=1)
    for size in (40, 24):
        gb = torchgi.render(torchgi.scenes.cornell(size).with_resolution(size, size + 7), spp=1, bounces=1)
        ours = Denoiser("guided")(gb)  # the torch Denoiser itself
        assert rel(deployed(gb.color, gb.emission, gb.albedo, gb.normal, gb.depth), ours) < 1e-4
        assert rel(ort(gb), ours) < 1e-4, size


def _hole_case(run, name: str, value: float, reach: int, W: int = 72, H: int = 64) -> float:
    """Largest relative change of ``run(**inputs)`` more than ``reach`` px (Chebyshev) from one
    pixel set to ``value`` in input ``name``; asserts the output is finite everywhere."""
    import torchgi

    gb = torchgi.render(torchgi.scenes.cornell(W).with_resolution(W, H), spp=1, bounces=1)
    inputs = {k: getattr(gb, k).clone() for k in ("color", "emission", "albedo", "normal", "depth", "position")}
    clean = run(**inputs)
    y, x = H // 2 - 2, W // 2 + 5
    inputs[name][0, 0, y, x] = value
    out = run(**inputs)
    assert bool(torch.isfinite(out).all())
    far = torch.ones(H, W, dtype=torch.bool)
    far[max(0, y - reach) : y + reach + 1, max(0, x - reach) : x + reach + 1] = False
    return float(((out - clean).abs() / (clean.abs() + 1e-2))[..., far].max())


def test_exported_denoiser_contains_a_non_finite_pixel(guided_onnx):
    """In onnxruntime a NaN/Inf pixel is a hole: finite output everywhere, the clean result
    outside its footprint (8 px of firefly window, the guided filter's radius 4 twice, the
    hole's own 2 px and 2 of light-source opening)."""
    pytest.importorskip("embreex")
    from torchgi.export import OrtDenoiser

    ort = OrtDenoiser(guided_onnx)
    run = lambda **t: ort(**{k: v for k, v in t.items() if k != "position"})
    for name, value in (("color", float("nan")), ("depth", float("inf")), ("albedo", -float("inf"))):
        # measured 7.1e-5 at any reach from 12 px: the rounding of the image-wide sums (the
        # centring means, float32 prefix sums), which the hole's filled value changes
        assert _hole_case(run, name, value, reach=20) < 3e-4, name


@pytest.mark.parametrize(("method", "name"), [("atrous", "normal"), ("blend", "emission")])
def test_deployed_methods_contain_a_non_finite_pixel(method, name):
    """The other exportable methods' graphs, run eagerly: the same hole."""
    pytest.importorskip("embreex")
    from torchgi.denoise import Denoiser

    module = Denoiser(method).deploy(spp=1, sigma_position=1e3)
    geometry = "position" if method == "atrous" else "depth"
    run = lambda **t: module(t["color"], t["emission"], t["albedo"], t["normal"], t[geometry])
    # reach: À-Trous 5 levels (2 + 4 + ... + 32 px, clipped by the image); the blend's widest
    # chain (colour-guided radius 8 on a radius-2 output, features' 8 px context) and the firefly window
    reach = 40 if method == "blend" else 64
    # measured: 0 (À-Trous beyond 40 px), 1.0e-4 (the blend at any reach from 20 px: image-wide sums)
    assert _hole_case(run, name, float("nan"), reach, W=128, H=112) < 3e-4


def test_a_non_finite_variance_pixel_is_a_hole_too():
    """Issue 32: the graph with a variance input (4 spp, deploy(frame=)) fills a NaN variance
    pixel as it fills the other inputs: the output is finite and, beyond 12 px, the clean one
    (measured 7.9e-6 at 72x64: the image-wide sums' rounding)."""
    pytest.importorskip("embreex")
    import torchgi
    from torchgi.denoise import Denoiser

    W, H = 72, 64
    gb = torchgi.render(torchgi.scenes.cornell(W).with_resolution(W, H), spp=4, bounces=1, seed=1)
    module = Denoiser().deploy(frame=gb)
    assert module.input_names[-1] == "variance"
    inputs = {k: getattr(gb, k).clone() for k in module.input_names}
    clean = module(*inputs.values())
    y, x = H // 2 - 2, W // 2 + 5
    inputs["variance"][0, 0, y, x] = float("nan")
    out = module(*inputs.values())
    assert bool(torch.isfinite(out).all())
    far = torch.ones(H, W, dtype=torch.bool)
    far[y - 12 : y + 13, x - 12 : x + 13] = False
    assert float(((out - clean).abs() / (clean.abs() + 1e-2))[..., far].max()) < 3e-4


def test_exported_selects_and_channel_maxima_are_exact_without_their_slow_operators(tmp_path):
    """Exported, ``core.exported.where`` is arithmetic on the mask and ``channel_max`` a Max of the
    channel slices (onnxruntime runs Where and ReduceMax over channels several times slower:
    docs/benchmarks/onnx.md): the graph holds neither, and onnxruntime gives what ``torch.where``
    and ``amax`` give, bit for bit - a tiny value picked beside a large one included (``b + m (a -
    b)`` would round it away)."""
    from torchgi.core import exported

    class Picks(torch.nn.Module):
        def forward(self, x, y):
            c = x[:, :1] > 0.5
            return (exported.where(c, x * 1e-6, y * 1e3), exported.where(c, x, 0.0), exported.where(c, 0.0, y),
                    exported.where(c, y, 1.0), exported.channel_max(y))

    g = torch.Generator().manual_seed(0)
    x, y = torch.rand(2, 3, 9, 11, generator=g), torch.rand(2, 3, 9, 11, generator=g)
    path = export_onnx(Picks(), [x[:1, :, :8], y[:1, :, :8]], tmp_path / "p.onnx", input_names=["x", "y"],
                       output_names=["a", "b", "c", "d", "e"])
    import onnx

    ops = {n.op_type for n in onnx.load(path).graph.node}
    assert not ops & {"Where", "ReduceMax"}, ops
    c = x[:, :1] > 0.5
    want = (torch.where(c, x * 1e-6, y * 1e3), torch.where(c, x, 0.0), torch.where(c, 0.0, y), torch.where(c, y, 1.0),
            y.amax(1, keepdim=True))
    for got, w in zip(OrtSession(path).outputs(x=x, y=y), want, strict=True):
        assert torch.equal(got, w)


def test_finite_inputs_whose_sum_overflows_pass_unchanged():
    """The hole filling runs only where the inputs' sum is not finite (an If in the graph); finite
    values whose sum overflows float32 take that branch and must still pass bit for bit, and a
    NaN beside them is filled from its finite neighbours (a hand case)."""
    from torchgi.deployed import _fill_holes

    x = torch.rand(1, 3, 9, 11)
    x[0, 0, 2, 2] = x[0, 1, 5, 7] = 3e38  # finite; their sum is inf
    y = torch.rand(1, 1, 9, 11)
    assert not torch.isfinite(x.sum())
    got = _fill_holes([x, y])
    assert torch.equal(got[0], x) and torch.equal(got[1], y)
    y[0, 0, 4, 4] = float("nan")
    z = torch.ones(1, 1, 9, 11)
    z[0, 0, 4, 4] = float("nan")
    assert torch.equal(_fill_holes([z])[0], torch.ones(1, 1, 9, 11))  # the mean of its finite 5x5 neighbours
    got = _fill_holes([x, y])
    assert bool(torch.isfinite(got[1]).all()) and got[0][0, 0, 4, 4] != x[0, 0, 4, 4]  # the whole pixel is a hole


@functools.cache
def _cornell(W: int, spp: int, seed: int):
    """A Cornell box render of ``W x (W + 7)`` (1 bounce), rendered once per test process (the
    tests below share their references)."""
    import torchgi

    return torchgi.render(torchgi.scenes.cornell(W).with_resolution(W, W + 7), spp=spp, bounces=1, seed=seed)


@pytest.mark.slow
@pytest.mark.parametrize("emission", [True, False])
def test_exported_default_matches_the_eager_default_on_large_renders(tmp_path, emission):
    """Issue 32: the default Denoiser exported with the choices it makes on a representative
    frame (``frame=``: half or full resolution, the sample count), and with or without an
    emission input, against the eager default on the same inputs at 256x263 and 512x519 (a
    Cornell box, 1 spp, 128 spp reference). Measured at 256x263: 2.1e-7 with emission, 1.9e-7
    without; exported without the frame (full resolution) 4.6e-3; zeros fed as the emission
    of a render without one (what OrtDenoiser used to do) 0.97 and 3.1x the eager relMSE."""
    pytest.importorskip("embreex")
    from torchgi import metrics
    from torchgi.denoise import Denoiser
    from torchgi.export import OrtDenoiser, export_denoiser

    frames = []
    for W in (256, 512):
        gb = _cornell(W, 1, 3)
        frames.append((gb if emission else gb.replace(emission=None), _cornell(W, 128, 4).color))
    ort = OrtDenoiser(export_denoiser("guided", tmp_path / "d.onnx", emission=emission, frame=frames[0][0]))
    assert ("emission" in ort.input_names) == emission
    for gb, ref in frames:
        eager, exported = Denoiser()(gb), ort(gb)
        assert rel(exported, eager) < 1e-4, gb.color.shape
        assert abs(float(metrics.relmse(exported, ref)) / float(metrics.relmse(eager, ref)) - 1) < 0.05


def test_exported_default_backs_off_with_the_variance_as_the_eager_one(tmp_path):
    """Issue 32: at 4 spp the eager default backs off toward the input with the render's
    variance (issue 33); exported with ``frame=`` a render with one, the graph takes ``variance``
    and does the same: onnxruntime within 1e-4 of the eager call, relMSE within 5 %, at a size
    other than the frame's (a Cornell box, 256x263 and 128x135). Measured at 256x263: 1.0e-7;
    exported without the variance input 0.45 (relMSE +0.8 % there; +14 % on a 64² box). The graph
    refuses a render without its emission layer (nothing made up)."""
    pytest.importorskip("embreex")
    from torchgi import metrics
    from torchgi.denoise import Denoiser
    from torchgi.export import OrtDenoiser, export_denoiser

    gb, ref = _cornell(256, 4, 3), _cornell(256, 128, 4).color
    ort = OrtDenoiser(export_denoiser("guided", tmp_path / "v.onnx", frame=gb))
    assert ort.input_names[-1] == "variance"
    import onnx

    # the operators onnxruntime runs slowly, kept out of the pipeline (docs/benchmarks/onnx.md):
    # two selects on the median's 1/16 of the pixels, no Softmax over the two radii
    ops = [n.op_type for n in onnx.load(tmp_path / "v.onnx").graph.node]
    assert ops.count("Where") == 2 and "Softmax" not in ops, ops
    small = gb.crop(0, 0, 135, 128)
    for frame, want in ((gb, ref), (small, ref[..., :135, :128])):
        eager, exported = Denoiser()(frame), ort(frame)
        assert rel(exported, eager) < 1e-4, frame.color.shape
        assert abs(float(metrics.relmse(exported, want)) / float(metrics.relmse(eager, want)) - 1) < 0.05
    with pytest.raises(ValueError, match="variance"):
        ort(gb.replace(variance=None))
    with pytest.raises(ValueError, match="variance: the back-off needs 2 samples"):
        Denoiser().deploy(spp=1, variance=True)
    # nothing made up: a graph with an emission input refuses a render without one (zeros would
    # filter its lights into the scene)
    with pytest.raises(ValueError, match="emission: this graph was exported with an emission input"):
        ort(gb.replace(emission=None))
    with pytest.raises(ValueError, match="spp, frame"):
        Denoiser().deploy(spp=1.0, frame=gb)


def test_cli_export_without_emission_with_variance(tmp_path, capsys):
    """``torchgi export --no-emission --spp 4 --variance``: the graph takes no emission input and
    a variance, and gives what the Python deploy(spp=4, emission=False, variance=True) module
    gives in torch on a 4 spp render without an emission layer (to float32 rounding); it refuses
    a render with one; ``--variance`` below 2 spp is refused, naming the flag."""
    pytest.importorskip("embreex")
    import torchgi
    from torchgi.cli import main
    from torchgi.denoise import Denoiser
    from torchgi.export import OrtDenoiser

    path = tmp_path / "n.onnx"
    assert main(["export", "--method", "guided", "--no-emission", "--spp", "4", "--variance", "--out", str(path)]) == 0
    said = capsys.readouterr()
    assert "inputs color, albedo, normal, depth, variance " in said.out
    # issue 69: it says what it builds before (an export takes a while) and what it built, with its time
    assert said.err.startswith("exporting guided, fixed for 4 spp (other sample counts refused), balanced, with a "
                               "variance input to ONNX ...")
    assert re.search(r"\(guided, fixed for 4 spp .*\) in \d+\.\d s; inputs", said.out)
    assert OrtDenoiser(path).spp == 4.0
    ort = OrtDenoiser(path)
    assert ort.input_names == ["color", "albedo", "normal", "depth", "variance"]
    gb = torchgi.render(torchgi.scenes.cornell(32).with_resolution(32, 39), spp=4, bounces=1)
    deployed = Denoiser().deploy(spp=4.0, emission=False, variance=True)
    torch.testing.assert_close(ort(gb.replace(emission=None)),
                               deployed(gb.color, gb.albedo, gb.normal, gb.depth, gb.variance), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="emission: this graph was exported without an emission input"):
        ort(gb)  # a graph without one refuses one (it would be ignored)
    assert main(["export", "--variance", "--out", str(tmp_path / "w.onnx")]) == 2
    assert "--variance" in capsys.readouterr().err


class _Layers(torch.nn.Module):
    """A stand-in exported Denoiser: the colour scaled by the mean of the other layers times 0
    (every input stays in the graph), so a call's refusals are tested without a minute's export."""

    def forward(self, color, emission, albedo, normal, depth):
        return color + 0 * (emission + albedo + normal + depth).mean(1, keepdim=True)


def _layers_graph(path, spp):
    names = ["color", "emission", "albedo", "normal", "depth"]
    g = torch.Generator().manual_seed(0)
    examples = [torch.rand(2, 1 if n == "depth" else 3, 24, 32, generator=g) for n in names]
    metadata = None if spp is None else {"torchgi.spp": spp}
    return export_onnx(_Layers(), examples, path, input_names=names, optimize=False, metadata=metadata)


def _frame(spp, H=9, W=11):
    from torchgi import GBuffer

    g = torch.Generator().manual_seed(spp)
    rand = lambda c: torch.rand(1, c, H, W, generator=g)
    return GBuffer(color=rand(3), emission=rand(3) * 0, albedo=rand(3), normal=rand(3), depth=rand(1),
                   variance=rand(3) if spp > 1 else torch.zeros(1, 3, H, W),
                   spp=torch.full((1, 1, H, W), spp, dtype=torch.int64))


def test_exported_graph_refuses_the_spp_and_variance_it_cannot_use(tmp_path):
    """Issue 69: an exported Denoiser fixed for a sample count and without a variance input ran
    a 4 spp render with its variance, or ``spp=4``, without a word (the variance and the count
    dropped). It records the count it was built for and refuses, by name, a different one and a
    variance it would not use, unless told to ignore them; a graph that records no count refuses
    to check one; a 1 spp render's (unknown, zero) variance is not refused by a 1 spp graph, as
    the eager Denoiser does not use it either."""
    from torchgi.export import OrtDenoiser

    four = OrtDenoiser(_layers_graph(tmp_path / "four.onnx", "4.0"))
    assert four.spp == 4.0
    gb = _frame(4)
    with pytest.raises(ValueError, match=r"^variance: this graph was exported without a variance input"):
        four(gb)
    torch.testing.assert_close(OrtDenoiser(tmp_path / "four.onnx", ignore=("variance",))(gb), gb.color)
    bare = {k: getattr(gb, k) for k in ("color", "emission", "albedo", "normal", "depth")}
    torch.testing.assert_close(four(**bare, spp=4), gb.color)
    with pytest.raises(ValueError, match=r"^spp: this graph is fixed for 4 samples per pixel, the input has 2"):
        four(**bare, spp=2)
    with pytest.raises(ValueError, match=r"^spp: this graph is fixed for 4 samples per pixel, the input has 1"):
        four(_frame(1))
    with pytest.raises(TypeError, match=r"^posiiton: not an input of this graph"):
        four(**bare, posiiton=gb.depth)
    one = OrtDenoiser(_layers_graph(tmp_path / "one.onnx", "1.0"))
    torch.testing.assert_close(one(_frame(1)), _frame(1).color)
    unknown = OrtDenoiser(_layers_graph(tmp_path / "none.onnx", None))
    assert unknown.spp is None
    with pytest.raises(ValueError, match=r"^spp: this graph records no sample count"):
        unknown(gb.replace(variance=None))
    torch.testing.assert_close(OrtDenoiser(tmp_path / "none.onnx", ignore=("spp", "variance"))(gb), gb.color)
    with pytest.raises(ValueError, match=r"^ignore: expected a sequence of 'spp', 'variance'"):
        OrtDenoiser(tmp_path / "one.onnx", ignore="spp")
