
import pytest
import torch

from tests.helpers import check_parameter_gradient, rel_error
from tests.helpers import rel_range as rel_err
from torchgi import GBuffer, backends
from torchgi.core import DeviceError, DTypeError, NonFiniteError, RangeError, ShapeError
from torchgi.filters import Guided, guide_from_gbuffer, guided

from ..oracles import box_oracle, fast_guided_oracle, guided_oracle, scene


@pytest.mark.parametrize("n", [1, 2, 3, 4])
@pytest.mark.parametrize("r", [0, 1, 2, 4, 5])  # the C kernel sums r <= 4 directly, wider by prefix sums
def test_matches_float64_oracle(n, r):
    p, I = scene(2, 37, 53, n, seed=n + r)
    want = guided_oracle(p, I, r, 0.01)
    assert rel_err(guided(p, I, radius=r, eps=0.01), want) < 1e-5  # CPU compiled kernel, float32
    with backends.use("torch"):
        assert rel_err(guided(p, I, radius=r, eps=0.01), want) < 1e-5  # CPU torch fast path, float32
    p64 = p.double().requires_grad_()  # autograd: GuidedFunction (its forward through the seam)
    assert rel_err(guided(p64, I.double(), radius=r, eps=0.01).detach(), want) < 1e-10


@pytest.mark.parametrize("s", [2, 3])
def test_subsampled_matches_float64_oracle(s, device):
    # odd sizes: partial s x s blocks at the right and bottom edges
    p, I = scene(2, 37, 53, 4, seed=s)
    want = fast_guided_oracle(p, I, 6, 0.01, s)
    out = guided(p.to(device), I.to(device), radius=6, eps=0.01, subsample=s)
    assert out.shape == p.shape and out.device.type == device.type
    assert rel_err(out.cpu(), want) < 1e-5  # CPU: the fast path; CUDA: the box_pool path
    p64 = p.double().requires_grad_()
    got = guided(p64, I.double(), radius=6, eps=0.01, subsample=s)
    assert rel_err(got.detach(), want) < 1e-10
    assert torch.autograd.gradcheck(lambda a: guided(a, I[:1, :, :7, :9].double(), radius=2, eps=0.05, subsample=s),
                                    (p64[:1, :1, :7, :9].detach().requires_grad_(),))
    with pytest.raises(RangeError, match="subsample"):
        guided(p, I, radius=2, subsample=0)


@pytest.mark.parametrize("offset", [0.0, 1e3, 1e4])
def test_full_hd_with_offset_guides(offset):
    """docs/design.md, Numerics / issue 5: 1920x1080, 4-channel guide, r = 24, within 1e-3 of float64."""
    p, I = scene(1, 1080, 1920, 4, seed=3)
    I = (I + offset).float()  # the float32 input both sides see
    out = guided(p, I, radius=24, eps=0.01)
    assert torch.isfinite(out).all()
    err = rel_err(out, guided_oracle(p, I, 24, 0.01))
    assert err < 1e-3, err


def test_per_channel_and_per_batch_eps():
    p, I = scene(2, 20, 24, 4, seed=5)
    eps = torch.tensor([0.01, 0.02, 0.01, 0.03])
    torch.testing.assert_close(guided(p, I, radius=3, eps=eps).double(), guided_oracle(p, I, 3, eps), rtol=0, atol=1e-5)
    eps_b = torch.tensor([[0.01, 0.02, 0.01, 0.03], [0.1, 0.1, 0.2, 0.05]])
    out = guided(p, I, radius=3, eps=eps_b)
    for b in range(2):
        torch.testing.assert_close(out[b : b + 1].double(), guided_oracle(p[b : b + 1], I[b : b + 1], 3, eps_b[b]),
                                   rtol=0, atol=1e-5)


@pytest.mark.parametrize("eps", [0.0, 0.01])
@pytest.mark.parametrize("value", [0.0, 0.5, 1e4])
def test_constant_guide_is_double_box(eps, value):
    p, _ = scene(1, 30, 41, 1)
    I = torch.full((1, 2, 30, 41), value)
    want = box_oracle(box_oracle(p, 4), 4)  # a = 0, b = mean(p): q = mean(mean(p))
    assert rel_err(guided(p, I, radius=4, eps=eps), want) < 1e-6


def test_one_flat_channel_changes_nothing_at_eps_zero():
    p, I = scene(1, 40, 40, 2)
    flat = torch.cat([I, torch.full_like(I[:, :1], 0.25)], 1)
    torch.testing.assert_close(guided(p, flat, radius=3, eps=0.0), guided(p, I, radius=3, eps=0.0), rtol=0, atol=1e-4)


def test_constant_source_stays_constant():
    _, I = scene(1, 25, 30, 4)
    out = guided(torch.full((1, 3, 25, 30), 7.5), I, radius=4, eps=0.0)
    torch.testing.assert_close(out, torch.full_like(out, 7.5), rtol=0, atol=1e-5)


def test_tiny_odd_and_oversized_windows():
    p, I = scene(1, 1, 1, 3)
    torch.testing.assert_close(guided(p, I, radius=3), p)  # one pixel: no variance, q = p
    for H, W, r in [(7, 13, 2), (5, 6, 9), (2, 50, 30), (6, 5, 3), (4, 3, 1), (9, 7, 3)]:
        p, I = scene(1, H, W, 3, seed=H)
        assert rel_err(guided(p, I, radius=r, eps=0.01), guided_oracle(p, I, r, 0.01)) < 1e-5


def test_noncontiguous_inputs():
    p, I = scene(2, 24, 30, 3)
    want = guided(p, I, radius=3)
    torch.testing.assert_close(guided(p.transpose(2, 3), I.transpose(2, 3), radius=3), want.transpose(2, 3))
    cl = p.contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(guided(cl, I, radius=3), want)
    e = p[:1].expand(2, -1, -1, -1)
    torch.testing.assert_close(guided(e, I[:1].expand(2, -1, -1, -1), radius=3)[1], want[0])


def test_hdr_fireflies_stay_finite_and_accurate():
    p, I = scene(1, 40, 50, 4)
    p[0, :, 10, 10] = 1e6
    p[0, 1, 30, 7] = -5.0  # negative values are allowed (e.g. signed residuals)
    out = guided(p, I, radius=5)
    assert torch.isfinite(out).all()
    assert rel_err(out, guided_oracle(p, I, 5, 0.01)) < 1e-5


def test_half_precision_keeps_dtype(dtype, device):
    p, I = scene(1, 30, 40, 4)
    out = guided(p.to(device, dtype), I.to(device, dtype), radius=4)
    assert out.dtype == dtype and out.device.type == device.type
    tol = {torch.float16: 1e-2, torch.bfloat16: 3e-2}.get(dtype, 1e-5)
    assert rel_err(out.cpu(), guided_oracle(p.to(dtype), I.to(dtype), 4, 0.01)) < tol


def test_gradcheck_src_guide_eps():
    p, I = scene(1, 6, 7, 2)
    p, I = p.double().requires_grad_(), I.double().requires_grad_()
    eps = torch.tensor([0.05, 0.02], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, e: guided(a, b, radius=1, eps=e), (p, I, eps))


def _oracle_gradients(p, I, r, eps, g):
    """Autograd through the float64 oracle (torch.linalg.solve, cumulative-sum boxes) and through
    :func:`guided` in the inputs' dtype: the gradients of ``Σ g · out`` for src, guide and eps."""
    want = torch.autograd.grad((guided_oracle(x := p.double().requires_grad_(), y := I.double().requires_grad_(), r,
                                              e := eps.double().requires_grad_()) * g.double()).sum(), (x, y, e))
    got = torch.autograd.grad((guided(x := p.clone().requires_grad_(), y := I.clone().requires_grad_(), radius=r,
                                      eps=(e := eps.clone().requires_grad_())) * g).sum(), (x, y, e))
    return got, want


@pytest.mark.parametrize("n, C, r", [(1, 1, 2), (4, 3, 4), (3, 2, 9)])
def test_float32_gradients_match_float64_oracle(n, C, r):
    """The backward (``GuidedGradOp``: the C kernel for float32 on the CPU, and the torch code)
    against autograd through the float64 oracle for src, guide and a per-channel eps."""
    p, I = scene(2, 23, 31, n, seed=n * r)
    eps = torch.linspace(0.01, 0.03, n)
    g = torch.randn(2, C, 23, 31, generator=torch.Generator().manual_seed(1))
    got, want = _oracle_gradients(p[:, :C], I, r, eps, g)
    for a, b in zip(got, want):
        assert rel_error(a, b) < 2e-4
    if backends.status()["c"].startswith("compiled kernels in use"):
        assert backends.status()["last"]["guided"]["ran"] == "c"
        assert backends.status()["last"]["guided_grad"]["ran"] == "c"
    with backends.use("torch"):
        got, want = _oracle_gradients(p[:, :C], I, r, eps, g)
    assert backends.status()["last"]["guided_grad"]["ran"] == "torch"
    for a, b in zip(got, want):
        assert rel_error(a, b) < 2e-4


def test_compiled_gradients_in_bands_narrower_than_the_window():
    """The C backward cuts the rows into one band per thread, each recomputing 2r rows around it:
    4 bands of 12 rows at r = 9 (the window spans three bands) against the float64 oracle."""
    p, I = scene(1, 48, 2800, 4, seed=7)
    eps = torch.tensor([0.01, 0.02, 0.01, 0.03])
    g = torch.randn(1, 3, 48, 2800, generator=torch.Generator().manual_seed(2))
    threads = torch.get_num_threads()
    torch.set_num_threads(4)
    try:
        got, want = _oracle_gradients(p, I, 9, eps, g)
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(got, want):
        assert rel_error(a, b) < 2e-4
    if backends.status()["c"].startswith("compiled kernels in use"):
        assert backends.status()["last"]["guided_grad"]["ran"] == "c"


@pytest.mark.parametrize("channels", [1, 3])
def test_eps_map_matches_float64_oracle(channels):
    """A per-pixel ε map ``(B, 1 | G, H, W)`` (the torch code) against the float64 oracle with the
    same map on the diagonal of each pixel's system; a constant map gives the scalar's output."""
    p, I = scene(2, 19, 26, 3, seed=channels)
    eps = 0.002 + 0.05 * torch.rand(2, channels, 19, 26, generator=torch.Generator().manual_seed(5))
    assert rel_err(guided(p, I, radius=3, eps=eps), guided_oracle(p, I, 3, eps)) < 1e-5
    flat = torch.full((2, channels, 19, 26), 0.01)
    torch.testing.assert_close(guided(p, I, radius=3, eps=flat), guided(p, I, radius=3, eps=0.01), rtol=0, atol=2e-6)
    torch.testing.assert_close(guided(p, I, radius=6, eps=flat, subsample=2),
                               guided(p, I, radius=6, eps=0.01, subsample=2), rtol=0, atol=2e-6)


def test_eps_map_gradients():
    """float64 gradcheck with respect to an ε map; in float32 its gradient is finite and not 0."""
    p, I = scene(1, 7, 8, 2)
    e = (0.01 + 0.02 * torch.rand(1, 2, 7, 8, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda m: guided(p.double(), I.double(), radius=1, eps=m), (e,))
    p, I = scene(1, 64, 64, 4)
    m = torch.full((1, 1, 64, 64), 0.01, requires_grad=True)
    guided(p, I, radius=4, eps=m).square().sum().backward()
    assert torch.isfinite(m.grad).all() and m.grad.abs().amax() > 0


def test_no_nan_gradient_on_flat_guide_at_eps_zero():
    p = torch.rand(1, 3, 12, 12, requires_grad=True)
    I = torch.full((1, 4, 12, 12), 0.3, requires_grad=True)
    guided(p, I, radius=2, eps=0.0).square().sum().backward()
    assert torch.isfinite(p.grad).all() and torch.isfinite(I.grad).all()


def test_bad_inputs():
    p, I = scene(1, 8, 8, 4)
    with pytest.raises(ShapeError, match="guide: expected 1 to 4 channels, got 5"):
        guided(p, torch.rand(1, 5, 8, 8))
    with pytest.raises(ShapeError, match="guide: dimension W is 9"):
        guided(p, torch.rand(1, 4, 8, 9))
    with pytest.raises(DTypeError, match="guide is torch.float64 but src is torch.float32"):
        guided(p, I.double())
    with pytest.raises(DeviceError, match="guide is on meta but src is on cpu"):
        guided(p, I.to("meta"))
    with pytest.raises(ValueError, match="radius: expected an int >= 0"):
        guided(p, I, radius=-2)
    with pytest.raises(RangeError, match="eps: expected a finite float >= 0"):
        guided(p, I, eps=-0.1)
    for bad_eps in ([0.1, -0.1, 0.1, 0.1], [0.1, float("nan"), 0.1, 0.1], [float("inf")] * 4):
        with pytest.raises(RangeError, match="eps: expected finite values >= 0"):
            guided(p, I, eps=torch.tensor(bad_eps))
    with pytest.raises(ShapeError, match=r"eps: expected a float, shape \(4,\), \(1, 4\) or a map \(1, 1 or 4, 8, 8\); got \(3,\)"):
        guided(p, I, eps=torch.ones(3))
    bad = p.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="src: expected finite values, found 1 NaN"):
        guided(bad, I)
    badI = I.clone()
    badI[0, 2, 3, 3] = float("inf")
    with pytest.raises(NonFiniteError, match="guide: expected finite values, found 0 NaN and 1"):
        guided(p, badI)
    with pytest.warns(UserWarning, match="src: replaced 1 non-finite"):
        out = guided(bad, I, sanitize=True)
    assert torch.isfinite(out).all()


def test_module_holds_eps_and_learns():
    m = Guided(radius=3, eps=torch.tensor([0.01, 0.02, 0.01, 0.03]))
    assert "radius=3" in repr(m) and "eps" in dict(m.named_buffers())
    p, I = scene(1, 16, 16, 4)
    torch.testing.assert_close(m(p, I), guided(p, I, radius=3, eps=m.eps))
    torch.testing.assert_close(m(p, I), guided(p, I, radius=3, eps=m.eps))  # reused workspace
    m.release()
    # issue 71: the learnable eps's gradient against central differences (float64), not only finite
    learn = Guided(radius=2, eps=0.05, learnable=True).double()
    p, I = p.double(), I.double()
    w = torch.rand(p.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    loss = lambda: (learn(p, I) * w).sum()
    check_parameter_gradient(loss, learn.parametrizations.eps.original)


def test_a_learnable_eps_stays_in_range_under_any_step():
    """eps = softplus(a free parameter): it reads back as given, and 5 SGD steps at lr 10 (which
    drove a plain Parameter below 0, then RangeError, in 2-5 steps) leave it > 0 and the filter
    working; printing warns nothing; a learnable eps of 0 is refused by name."""
    import warnings

    p, I = scene(1, 16, 16, 4)
    m = Guided(radius=2, eps=torch.tensor([0.01, 0.02, 0.01, 0.03]), learnable=True)
    torch.testing.assert_close(m.eps.detach(), torch.tensor([0.01, 0.02, 0.01, 0.03]))
    opt = torch.optim.SGD(m.parameters(), lr=10.0)
    for _ in range(5):
        opt.zero_grad()
        (m(p, I) - 2 * p).square().sum().backward()  # pulls eps down hard
        opt.step()
    assert bool((m.eps > 0).all()) and bool(torch.isfinite(m(p, I)).all())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert "eps=" in repr(m)
    with pytest.raises(ValueError, match="eps"):
        Guided(eps=0.0, learnable=True)


def test_guide_from_gbuffer():
    g = torch.Generator().manual_seed(0)
    normal = torch.nn.functional.normalize(torch.randn(2, 3, 6, 5, generator=g), dim=1)
    depth = torch.rand(2, 1, 6, 5, generator=g) * 8 + 1
    hit = torch.ones(2, 1, 6, 5, dtype=torch.bool)
    hit[1, 0, 0, 0] = False
    depth[1, 0, 0, 0] = 100.0  # background depth must not set the scale
    guide = guide_from_gbuffer(GBuffer(normal=normal, depth=depth, hit=hit))
    scale = float(depth[hit].max())
    torch.testing.assert_close(guide, torch.cat([(normal + 1) / 2, depth / scale], 1))
    guide = guide_from_gbuffer(GBuffer(normal=normal, depth=depth), depth_scale=10.0)
    torch.testing.assert_close(guide[:, 3:], depth / 10)
    flat_normal = torch.zeros(2, 3, 6, 5)
    flat_normal[:, 2] = 1
    assert guide_from_gbuffer(GBuffer(normal=flat_normal, depth=depth)).shape[1] == 1  # only depth varies
    with pytest.raises(ShapeError, match="needs gb.normal"):
        guide_from_gbuffer(GBuffer(depth=depth))
    with pytest.raises(RangeError, match="depth_scale"):
        guide_from_gbuffer(GBuffer(normal=normal, depth=depth), depth_scale=0.0)
