import pytest
import torch

from torchgi.backends.torch_code import PlaneBoxer
from torchgi.backends.torch_code import box_pool as _box_pool
from torchgi.core import NonFiniteError, ShapeError
from torchgi.filters import Box, box

from ..oracles import box_oracle

SIZES = [(1, 1, 0), (1, 1, 5), (5, 7, 1), (5, 7, 3), (5, 7, 10), (17, 33, 0), (40, 3, 2), (33, 17, 16),
         (35, 50, 20), (16, 32, 15), (16, 32, 16), (16, 32, 17), (31, 47, 4), (64, 80, 7)]


@pytest.mark.parametrize("H, W, r", SIZES)
def test_reference_matches_avg_pool(H, W, r):
    x = torch.randn(2, 3, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(H * W + r))
    want = box_oracle(x, r)
    torch.testing.assert_close(box(x, r), want, rtol=1e-12, atol=1e-12)  # CPU fast path
    torch.testing.assert_close(_box_pool(x, r), want, rtol=1e-12, atol=1e-12)  # autograd/export path


def test_plane_boxer_matches_oracle_in_float32():
    x = torch.rand(300, 517, generator=torch.Generator().manual_seed(0))
    out = PlaneBoxer(300, 517, 24)(x, torch.empty_like(x))
    torch.testing.assert_close(out.double(), box_oracle(x[None, None], 24)[0, 0], rtol=0, atol=2e-6)


def test_dtype_device_and_gradient(device, dtype):
    x = torch.rand(1, 2, 9, 11, dtype=torch.float64, device=device)
    out = box(x.to(dtype), 2)
    assert out.dtype == dtype and out.device == x.device
    tol = {torch.float16: 2e-3, torch.bfloat16: 1e-2}.get(dtype, 1e-6)
    torch.testing.assert_close(out.double(), box_oracle(x.to(dtype), 2), rtol=tol, atol=tol)


def test_gradcheck():
    x = torch.rand(1, 2, 5, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: box(t, 2), (x,))


@pytest.mark.parametrize("H, W, r", [(9, 13, 2), (5, 7, 10), (64, 80, 7)])
def test_float32_gradient_matches_float64_oracle(H, W, r):
    """The box's backward (a box of g / N times N, through the seam: compiled for float32)
    against autograd through the float64 cumulative-sum oracle."""
    x = torch.rand(2, 3, H, W, generator=torch.Generator().manual_seed(r))
    g = torch.randn(2, 3, H, W, generator=torch.Generator().manual_seed(r + 1))
    x64 = x.double().requires_grad_()
    (want,) = torch.autograd.grad((box_oracle(x64, r) * g.double()).sum(), x64)
    x32 = x.clone().requires_grad_()
    (got,) = torch.autograd.grad((box(x32, r) * g).sum(), x32)
    torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-5)


def test_noncontiguous_inputs():
    x = torch.rand(2, 3, 20, 30)
    torch.testing.assert_close(box(x.transpose(2, 3), 3), box(x.transpose(2, 3).contiguous(), 3))
    e = torch.rand(1, 3, 1, 30).expand(2, 3, 20, 30)
    torch.testing.assert_close(box(e, 3), box(e.contiguous(), 3))


def test_errors():
    with pytest.raises(ShapeError, match=r"x: expected shape \(B, C, H, W\)"):
        box(torch.rand(3, 4, 4), 1)
    with pytest.raises(ValueError, match="radius: expected an int >= 0"):
        box(torch.rand(1, 1, 4, 4), -1)
    with pytest.raises(ValueError, match="radius"):
        box(torch.rand(1, 1, 4, 4), 1.5)
    x = torch.rand(1, 1, 4, 4)
    x[0, 0, 1, 1] = float("nan")
    with pytest.raises(NonFiniteError, match="x: expected finite values, found 1 NaN"):
        box(x, 1)


def test_module():
    m = Box(3)
    assert "radius=3" in repr(m)
    x = torch.rand(1, 2, 10, 10)
    torch.testing.assert_close(m(x), box(x, 3))
