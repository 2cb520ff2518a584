import pytest
import torch

from tests.helpers import rel_error as rel
from torchgi.core import DTypeError, NonFiniteError, RangeError, ShapeError
from torchgi.filters import CrossBilateral, cross_bilateral

from ..oracles import bilateral_oracle


def data(H=11, W=14, seed=0):
    g = torch.Generator().manual_seed(seed)
    color = torch.rand(1, 3, H, W, generator=g)
    normal = torch.nn.functional.normalize(torch.randn(1, 3, H, W, generator=g), dim=1)
    depth = torch.rand(1, 1, H, W, generator=g) * 3
    return color, normal, depth



@pytest.mark.parametrize("radius, sigma_color", [(0, 0.3), (1, 0.3), (3, None), (6, 0.5)])
def test_matches_per_pixel_oracle(radius, sigma_color):
    c, n, d = data(seed=radius)
    kw = {"radius": radius, "sigma_space": 2.0, "sigma_color": sigma_color, "sigma_guides": [0.3, 0.5]}
    out = cross_bilateral(c, [n, d], **kw)
    assert rel(out[0], bilateral_oracle(c[0], [n[0], d[0]], **kw)) < 1e-5


def test_matches_kornia_joint_bilateral_inside_the_image():
    kornia = pytest.importorskip("kornia")
    c, n, _ = data(H=20, W=24, seed=3)
    r = 3
    ours = cross_bilateral(c, [n], radius=r, sigma_space=1.5, sigma_color=None, sigma_guides=[0.4])
    theirs = kornia.filters.joint_bilateral_blur(c, n, 2 * r + 1, 0.4, (1.5, 1.5), color_distance_type="l2")
    inner = (slice(None), slice(None), slice(r, -r), slice(r, -r))  # borders differ (reflect vs shrink)
    torch.testing.assert_close(ours[inner], theirs[inner], rtol=1e-5, atol=1e-6)


def test_constant_stays_constant_and_dtype(dtype):
    c, n, _d = data()
    flat = torch.full_like(c, 0.25).to(dtype)
    out = cross_bilateral(flat, [n.to(dtype)], radius=2, sigma_space=1.0, sigma_color=0.1, sigma_guides=[0.1])
    assert out.dtype == dtype
    torch.testing.assert_close(out.float(), flat.float(), rtol=0, atol=1e-3)


def test_gradcheck():
    c, n, _ = (t[:, :, :5, :6].double().requires_grad_() for t in data())
    assert torch.autograd.gradcheck(
        lambda a, b: cross_bilateral(a, [b], radius=1, sigma_space=1.0, sigma_color=0.5, sigma_guides=[0.5]), (c, n))


def test_sigma_maps_match_the_per_pixel_oracle():
    """σ_s, σ_c and a guide's σ as per-pixel maps (the centre pixel's σ) against the float64
    oracle; maps that are constant give the floats' output; gradients reach the maps."""
    c, n, _ = data()
    H, W = c.shape[-2:]
    g = torch.Generator().manual_seed(8)
    maps = [0.5 + torch.rand(1, 1, H, W, generator=g) for _ in range(3)]
    out = cross_bilateral(c, [n], radius=2, sigma_space=maps[0], sigma_color=maps[1], sigma_guides=[maps[2]])
    want = bilateral_oracle(c[0], [n[0]], radius=2, sigma_space=maps[0][0, 0], sigma_color=maps[1][0, 0],
                            sigma_guides=[maps[2][0, 0]])
    assert rel(out[0], want) < 1e-5
    flat = [torch.full((1, 1, H, W), v) for v in (1.0, 0.3, 0.2)]
    torch.testing.assert_close(
        cross_bilateral(c, [n], radius=2, sigma_space=flat[0], sigma_color=flat[1], sigma_guides=[flat[2]]),
        cross_bilateral(c, [n], radius=2, sigma_space=1.0, sigma_color=0.3, sigma_guides=[0.2]))
    c64, n64 = (t[:, :, :5, :6].double() for t in (c, n))
    m = (0.4 + torch.rand(1, 1, 5, 6, dtype=torch.float64, generator=g)).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda v: cross_bilateral(c64, [n64], radius=1, sigma_space=v, sigma_color=v, sigma_guides=[v]), (m,))
    with pytest.raises(ShapeError, match="sigma_color"):
        cross_bilateral(c, radius=1, sigma_space=1.0, sigma_color=torch.ones(1, 1, H, W + 1))


def test_bad_inputs():
    c, n, d = data()
    with pytest.raises(ValueError, match="sigma_guides: expected one σ per guide"):
        cross_bilateral(c, [n, d], radius=1, sigma_space=1.0, sigma_color=0.1, sigma_guides=[0.1])
    with pytest.raises(RangeError, match="sigma_space: expected finite values > 0"):
        cross_bilateral(c, radius=1, sigma_space=0.0, sigma_color=0.1)
    with pytest.raises(DTypeError, match=r"guides\[0\] is torch.float64"):
        cross_bilateral(c, [n.double()], radius=1, sigma_space=1.0, sigma_color=0.1, sigma_guides=[0.1])
    bad = c.clone()
    bad[0, 0, 0, 0] = float("inf")
    with pytest.raises(NonFiniteError, match="color"):
        cross_bilateral(bad, radius=1, sigma_space=1.0, sigma_color=0.1)


def test_module():
    c, n, d = data()
    m = CrossBilateral(radius=2, sigma_space=1.0, sigma_color=0.3, sigma_guides=[0.2, 0.4])
    assert "radius=2" in repr(m)
    torch.testing.assert_close(m(c, n, d), cross_bilateral(c, [n, d], radius=2, sigma_space=1.0, sigma_color=0.3,
                                                           sigma_guides=[0.2, 0.4]))
