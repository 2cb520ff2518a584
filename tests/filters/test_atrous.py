import contextlib

import numpy as np
import pytest
import torch

from tests.helpers import check_parameter_gradient
from tests.helpers import rel_error as rel
from torchgi import backends
from torchgi.core import DTypeError, NonFiniteError, RangeError, ShapeError
from torchgi.filters import ATrous, atrous

from ..oracles import atrous_oracle


def buffers(B=1, H=13, W=17, seed=0):
    g = torch.Generator().manual_seed(seed)
    color = torch.rand(B, 3, H, W, generator=g, dtype=torch.float64) * 2
    normal = torch.nn.functional.normalize(torch.randn(B, 3, H, W, generator=g, dtype=torch.float64), dim=1)
    normal[:, :, : H // 2] = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)[:, None, None]  # a flat floor
    position = torch.rand(B, 3, H, W, generator=g, dtype=torch.float64)
    return color.float(), normal.float(), position.float()



@pytest.mark.parametrize("kernels", ["compiled", "torch"])
@pytest.mark.parametrize("iterations", [1, 2, 3])
@pytest.mark.parametrize("weights", ["cnx", "c", "nx", "", "cx"])
def test_matches_per_pixel_oracle(iterations, weights, kernels):
    """The default call (the compiled CPU kernel where it builds) and the float32 torch code."""
    c, n, x = buffers(seed=iterations)
    kw = {"iterations": iterations, "sigma_color": 0.5, "sigma_normal": 0.2 if "n" in weights else None,
              "sigma_position": 0.3 if "x" in weights else None}
    with backends.use("torch") if kernels == "torch" else contextlib.nullcontext():
        out = atrous(c, n, x, color_weight="c" in weights, **kw)
    want = atrous_oracle(c[0], n[0], x[0], color_weight="c" in weights, **kw)
    assert rel(out[0], want) < 1e-5


def test_default_sigma_color_is_image_maximum():
    c, n, x = buffers(B=2, seed=4)
    c[1] *= 7
    out = atrous(c, n, x, iterations=2)
    for b in range(2):
        assert rel(out[b], atrous_oracle(c[b], n[b], x[b], iterations=2)) < 1e-5


def test_real_rendered_buffers_five_iterations():
    render = pytest.importorskip("torchgi.render.mitsuba")
    pytest.importorskip("mitsuba")
    gb = render.render_gbuffer(render.cornell_box(40), spp=1, seed=3)
    gb = gb.crop(4, 6, 28, 30)
    out = atrous(gb.color, gb.normal, gb.position, iterations=5, sigma_normal=0.1, sigma_position=0.1)
    want = atrous_oracle(gb.color[0], gb.normal[0], gb.position[0], iterations=5)
    assert rel(out[0], want) < 1e-4


def test_variance_guided_matches_oracle():
    c, n, x = buffers(seed=7)
    var = torch.rand(1, 1, 13, 17, generator=torch.Generator().manual_seed(1)) * 0.2
    out = atrous(c, n, x, iterations=3, variance=var)
    want = atrous_oracle(c[0], n[0], x[0], iterations=3, variance=var[0])
    assert rel(out[0], want) < 1e-5


@pytest.mark.parametrize("backend", ["c", "torch"])
@pytest.mark.parametrize("guided", [False, True])
def test_a_per_pixel_sigma_color_map_matches_the_oracle(backend, guided):
    """sigma_color as a (B, 1, H, W) map: each pixel's own σ weighs its neighbours (the oracle
    reads σ at the centre pixel), with and without a variance, in the C kernel (a colour-scale
    plane) and the torch code; a constant map is the scalar."""
    c, n, x = buffers(seed=31)
    g = torch.Generator().manual_seed(2)
    sigma = torch.where(torch.arange(17) < 8, 0.05, 2.0).expand(1, 1, 13, 17) * (0.5 + torch.rand(1, 1, 13, 17, generator=g))
    var = torch.rand(1, 1, 13, 17, generator=g) * 0.2 if guided else None
    with backends.use(backend):
        out = atrous(c, n, x, iterations=3, sigma_color=sigma, variance=var)
        ran = backends.status()["last"]["atrous"]["ran"]
        flat = atrous(c, n, x, iterations=3, sigma_color=torch.full((1, 1, 13, 17), 0.7), variance=var)
        scalar = atrous(c, n, x, iterations=3, sigma_color=0.7, variance=var)
    if backend == "c" and ran != "c":
        pytest.skip("the C kernels are not built here")
    want = atrous_oracle(c[0], n[0], x[0], iterations=3, sigma_color=sigma[0, 0],
                         variance=None if var is None else var[0])
    assert rel(out[0], want) < 1e-5
    assert rel(flat, scalar) < 1e-6
    with pytest.raises(ShapeError, match="sigma_color"):
        atrous(c, n, x, sigma_color=torch.ones(1, 1, 13, 16))


def test_gradients_reach_the_sigma_color_map():
    """float64 gradcheck with respect to a per-pixel σ map (kept > 0 by its parametrisation)."""
    c, n, x = (t.double()[..., :6, :7] for t in buffers(seed=4))
    u = torch.rand(1, 1, 6, 7, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda v: atrous(c, n, x, iterations=2, sigma_color=0.2 + v.square()), (u,), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("subsample", [2, 4])
def test_subsampled_inpainting_matches_oracle(subsample):
    c, n, x = buffers(H=19, W=21, seed=subsample)
    out = atrous(c, n, x, iterations=4, sigma_color=1.0, subsample=subsample)
    want = atrous_oracle(c[0], n[0], x[0], iterations=4, sigma_color=1.0, subsample=subsample)
    assert rel(out[0], want) < 1e-5
    assert (out > 0).all()  # every hole got filled


def test_energy_and_details():
    c, n, x = buffers(B=2, seed=9)
    out, details = atrous(c, n, x, iterations=3, sigma_color=0.3, return_details=True)
    assert len(details) == 3
    torch.testing.assert_close(c + sum(details), out, rtol=0, atol=1e-5)
    kept = atrous(c, n, x, iterations=3, sigma_color=0.3, energy=True)
    torch.testing.assert_close(kept.sum(dim=(2, 3)), c.sum(dim=(2, 3)), rtol=1e-5, atol=0)
    want = atrous_oracle(c[1], n[1], x[1], iterations=3, sigma_color=0.3, energy=True)
    assert rel(kept[1], want) < 1e-5


def test_constant_image_stays_constant():
    c, n, x = buffers()
    flat = torch.full_like(c, 0.7)
    torch.testing.assert_close(atrous(flat, n, x, iterations=5), flat, rtol=0, atol=1e-6)


def test_all_zero_weights_fall_back_to_centre():
    c, _n, x = buffers()
    out = atrous(c, None, x * 1e3, iterations=3, sigma_position=1e-6, color_weight=False)
    torch.testing.assert_close(out, c)  # every neighbour's weight underflows: the centre remains
    tiny = torch.rand(1, 3, 3, 3)
    out = atrous(tiny, iterations=2, subsample=4)  # the only sample is (0, 0): holes take its value
    torch.testing.assert_close(out, tiny[:, :, :1, :1].expand_as(tiny))


def test_fireflies_and_offset_positions_stay_finite():
    c, n, x = buffers(H=24, W=24)
    c[0, :, 5, 5] = 1e6
    out = atrous(c, n, x + 1e4, iterations=5, sigma_color=1.0)
    assert torch.isfinite(out).all()
    want = atrous_oracle(c[0], n[0], (x + 1e4)[0], iterations=5, sigma_color=1.0)
    assert rel(out[0], want) < 1e-3


@pytest.mark.parametrize("H, W", [(1, 1), (5, 5), (3, 8), (2, 1)])
def test_tiny_images_smaller_than_the_dilation(H, W):
    c, n, x = buffers(H=H, W=W)
    out = atrous(c, n, x, iterations=5, sigma_color=0.5)
    assert rel(out[0], atrous_oracle(c[0], n[0], x[0], iterations=5, sigma_color=0.5)) < 1e-5


def test_noncontiguous_inputs():
    c, n, x = buffers(B=2, H=12, W=15)
    want = atrous(c, n, x, iterations=3)
    got = atrous(c.transpose(2, 3), n.transpose(2, 3), x.transpose(2, 3), iterations=3)
    torch.testing.assert_close(got, want.transpose(2, 3))
    e = c[:1].expand(2, -1, -1, -1)
    torch.testing.assert_close(atrous(e, n[:1].expand(2, -1, -1, -1), x[:1].expand(2, -1, -1, -1), iterations=3)[1],
                               want[0])


def test_dtype_kept(dtype, device):
    c, n, x = buffers()
    out = atrous(c.to(device, dtype), n.to(device, dtype), x.to(device, dtype), iterations=3, sigma_color=1.0)
    assert out.dtype == dtype and out.device.type == device.type
    tol = {torch.float16: 1e-2, torch.bfloat16: 3e-2}.get(dtype, 1e-5)
    want = atrous_oracle(c[0].to(dtype).double(), n[0].to(dtype).double(), x[0].to(dtype).double(),
                         iterations=3, sigma_color=1.0)
    assert rel(out[0].cpu(), want) < tol


def test_gradcheck():
    c, n, x = (t[:, :, :6, :7].double().requires_grad_() for t in buffers())
    sig = torch.tensor([0.5], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda a, b, p, s: atrous(a, b, p, iterations=2, sigma_color=s), (c, n, x, sig))


@pytest.mark.parametrize("case", ["scalar", "map", "colour only", "geometry only", "one channel"])
@pytest.mark.parametrize("backend", ["c", "torch"])
def test_level_gradients_match_autograd_through_the_torch_levels(case, backend, monkeypatch):
    """The written-out level gradients (ATrousLevel: compiled forward and backward for float32 on
    the CPU, or the torch written-out form) against autograd through the torch code's levels in
    float64, for the colour, the guides and a σ_rt (scalar or map) at once, 4 levels."""
    from torchgi.backends.torch_code import filter_atrous

    c, n, x = buffers(B=2, H=21, W=26, seed=7)
    if case == "one channel":
        c = c[:, :1]
    sig = 0.3 + torch.rand(2, 1, 21, 26) if case == "map" else torch.tensor([0.4, 0.7])
    kw = {"colour only": {"sigma_normal": None, "sigma_position": None},
          "geometry only": {"color_weight": False}}.get(case, {})
    g = torch.randn(c.shape, generator=torch.Generator().manual_seed(2))

    def grads(dtype, by_level):
        ts = [t.to(dtype).requires_grad_() for t in (c, n, x, sig)]
        monkeypatch.setattr(filter_atrous, "level_backward", lambda desc: by_level)
        out = atrous(*ts[:3], iterations=4, sigma_color=ts[3], **kw)
        monkeypatch.undo()
        got = torch.autograd.grad((out * g.to(dtype)).sum(), ts, allow_unused=True)
        return [torch.zeros_like(t) if d is None else d for t, d in zip(ts, got)]

    want = grads(torch.float64, False)
    with backends.use(backend):
        got = grads(torch.float32, True)
    if backend == "c":
        assert backends.status()["last"]["atrous_level_grad"]["ran"] == (
            "c" if backends.status()["c"].startswith("compiled kernels in use") else "torch")
    for a, b in zip(got, want):
        assert float((a.double() - b).abs().max()) <= 1e-4 * max(1.0, float(b.abs().max()))


def test_learnable_module_gradients_match_autograd_through_the_torch_levels(monkeypatch):
    """ATrous(learnable=True): the gradients of its three σ's (through the levels' guide multipliers
    and colour scales) by the level functions in float32 against autograd through the torch levels."""
    from torchgi.backends.torch_code import filter_atrous

    c, n, x = buffers(B=2, H=19, W=24, seed=5)

    def grads(dtype, by_level):
        f = ATrous(3, sigma_color=0.5, sigma_normal=0.2, sigma_position=0.3, learnable=True).to(dtype)
        monkeypatch.setattr(filter_atrous, "level_backward", lambda desc: by_level)
        out = f(c.to(dtype), n.to(dtype), x.to(dtype))
        monkeypatch.undo()
        return torch.autograd.grad(out.square().sum(), list(f.parameters()))

    for a, b in zip(grads(torch.float32, True), grads(torch.float64, False)):
        assert float((a.double() - b).abs().max()) <= 1e-4 * max(1.0, float(b.abs().max()))


def test_level_gradcheck_float64():
    """float64 gradcheck of the written-out level gradients (the torch form), all inputs at once."""
    c, n, x = (t[:, :, :6, :7].double().requires_grad_() for t in buffers(seed=3))
    sig = (0.3 + torch.rand(1, 1, 6, 7, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b, p, s: atrous(a, b, p, iterations=2, sigma_color=s), (c, n, x, sig))


def test_bad_inputs():
    c, n, x = buffers()
    with pytest.raises(ShapeError, match=r"normal: expected shape \(B, 3, H, W\)"):
        atrous(c, n[:, :2])
    with pytest.raises(ShapeError, match="position: dimension W"):
        atrous(c, n, x[..., :5])
    with pytest.raises(DTypeError, match="normal is torch.float64 but color is torch.float32"):
        atrous(c, n.double())
    with pytest.raises(ValueError, match="iterations: expected an int >= 1"):
        atrous(c, iterations=0)
    with pytest.raises(ValueError, match="subsample: expected a power of two"):
        atrous(c, subsample=3)
    with pytest.raises(RangeError, match="sigma_normal: expected finite values > 0"):
        atrous(c, n, sigma_normal=0.0)
    for bad_sigma in (float("inf"), float("nan"), torch.tensor([float("nan")]), torch.tensor(-1.0), "0.1", True):
        with pytest.raises(RangeError, match="sigma_position: expected finite values > 0"):
            atrous(c, n, x, sigma_position=bad_sigma)
    with pytest.raises(ShapeError, match=r"sigma_color: expected a float or shape \(1,\)"):
        atrous(c, sigma_color=torch.ones(3))
    with pytest.raises(RangeError, match="variance: expected values >= 0"):
        atrous(c, variance=-torch.ones(1, 1, 13, 17))
    bad = c.clone()
    bad[0, 1, 2, 3] = float("nan")
    with pytest.raises(NonFiniteError, match="color: expected finite values, found 1 NaN"):
        atrous(bad, n, x)
    with pytest.warns(UserWarning, match="color: replaced 1 non-finite"):
        assert torch.isfinite(atrous(bad, n, x, sanitize=True)).all()


def test_module_and_per_batch_sigmas():
    c, n, x = buffers(B=2, seed=11)
    m = ATrous(iterations=2, sigma_color=0.5, sigma_normal=0.2, sigma_position=None)
    assert "iterations=2" in repr(m) and "sigma_color" in dict(m.named_buffers())
    torch.testing.assert_close(m(c, n, x), atrous(c, n, x, iterations=2, sigma_color=0.5, sigma_normal=0.2,
                                                  sigma_position=None))
    per = atrous(c, n, x, iterations=2, sigma_color=torch.tensor([0.5, 2.0]))
    assert rel(per[1], atrous_oracle(c[1], n[1], x[1], iterations=2, sigma_color=2.0)) < 1e-5
    # issue 71: the learnable sigma's gradient against central differences (float64), not only finite
    learn = ATrous(iterations=2, sigma_color=0.5, learnable=True).double()
    c, n, x = c.double(), n.double(), x.double()
    loss = lambda: learn(c, n, x).square().sum()
    check_parameter_gradient(loss, learn.parametrizations.sigma_color.original)


def test_learnable_sigmas_stay_in_range_under_any_step():
    """σ = softplus(a free parameter): 5 SGD steps at lr 10 (which drove a plain Parameter below
    0, then RangeError) leave every σ > 0 and the filter working; printing warns nothing."""
    import warnings

    c, n, x = buffers(seed=5)
    m = ATrous(iterations=2, sigma_color=0.5, sigma_normal=0.2, sigma_position=0.3, learnable=True)
    assert abs(float(m.sigma_position.detach()) - 0.3) < 1e-6
    opt = torch.optim.SGD(m.parameters(), lr=10.0)
    for _ in range(5):
        opt.zero_grad()
        (m(c, n, x) - 3 * c).square().sum().backward()
        opt.step()
    for name in ("sigma_color", "sigma_normal", "sigma_position"):
        assert float(getattr(m, name).detach()) > 0, name
    assert bool(torch.isfinite(m(c, n, x)).all())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert "sigma_color=" in repr(m)


def test_pointwise_formulation_matches_oracle():
    """The per-channel pointwise level (what fused=True compiles), run eagerly."""
    from torchgi.backends.torch_code import filter_atrous as mod

    c, n, x = buffers(seed=21)
    real = mod._compiled_iteration
    try:
        mod._compiled_iteration = lambda: mod._iteration  # same code path, no compiler
        with backends.use("torch"):  # else the compiled C kernel takes the call
            out = atrous(c, n, x, iterations=3, sigma_color=0.5, variance=torch.full_like(c[:, :1], 0.05),
                         fused=True)
    finally:
        mod._compiled_iteration = real
    want = atrous_oracle(c[0], n[0], x[0], iterations=3, sigma_color=0.5, variance=np.full((1, 13, 17), 0.05))
    assert rel(out[0], want) < 1e-5


@pytest.mark.slow
def test_fused_compiled_path_matches_oracle():
    """torch.compile of the level (about 80 s of compiling on 2 cores with a cold inductor cache,
    once per process: one graph serves every level). A second size of contiguous tensors reuses
    the dynamic-shape graph (cropped views, whose strides differ, would compile it again: 80 s more)."""
    from torch._dynamo.utils import counters

    c, n, x = buffers(H=20, W=23, seed=5)
    small = [t[..., :11, :17].contiguous() for t in (c, n, x)]
    with backends.use("torch"):  # else the compiled C kernel takes the call
        out = atrous(c, n, x, iterations=3, sigma_color=0.5, fused=True)
        graphs = counters["stats"]["unique_graphs"]
        other = atrous(*small, iterations=3, sigma_color=0.5, fused=True)
    assert counters["stats"]["unique_graphs"] == graphs  # no second compile for the new size
    assert rel(out[0], atrous_oracle(c[0], n[0], x[0], iterations=3, sigma_color=0.5)) < 1e-5
    want = atrous_oracle(small[0][0], small[1][0], small[2][0], iterations=3, sigma_color=0.5)
    assert rel(other[0], want) < 1e-5
