"""apply_kernels: the C kernels and the torch code against a float64 gathering oracle, forward and
gradients (autograd through the oracle), float64 gradcheck, hostile arguments."""

import pytest
import torch

from tests.helpers import last_backend, rel_error
from torchgi import backends
from torchgi.core import RangeError, ShapeError
from torchgi.filters import ApplyKernels, apply_kernels

from ..oracles import apply_kernels_oracle

CASES = [(3, 1, 9, 13), (5, 2, 16, 11), (5, 4, 7, 30), (3, 8, 6, 5), (7, 1, 20, 20)]  # k, dilation, H, W


def _inputs(k, H, W, seed=0, B=2, C=3):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(B, C, H, W, generator=g), torch.rand(B, k * k, H, W, generator=g) + 0.05


@pytest.mark.parametrize("normalize", [False, True])
@pytest.mark.parametrize("k, d, H, W", CASES)
@pytest.mark.parametrize("backend", ["c", "torch"])
def test_forward_and_gradients_match_float64_oracle(k, d, H, W, normalize, backend):
    """Forward, and the gradients of x and the weights against autograd through the oracle;
    with ``backend="c"`` the compiled forward and backward ran (where the kernels are built)."""
    x, w = _inputs(k, H, W, seed=k * d)
    g = torch.randn(2, 3, H, W, generator=torch.Generator().manual_seed(1))
    x64, w64 = x.double().requires_grad_(), w.double().requires_grad_()
    want = apply_kernels_oracle(x64, w64, d, normalize)
    want_grads = torch.autograd.grad((want * g.double()).sum(), (x64, w64))
    xs, ws = x.clone().requires_grad_(), w.clone().requires_grad_()
    with backends.use(backend):
        out = apply_kernels(xs, ws, dilation=d, normalize=normalize)
        grads = torch.autograd.grad((out * g).sum(), (xs, ws))
        no_grad = apply_kernels(x, w, dilation=d, normalize=normalize)
    assert rel_error(out, want.detach()) < 1e-6 and rel_error(no_grad, want.detach()) < 1e-6
    for a, b in zip(grads, want_grads):  # (a gradient may be 0 throughout: an absolute floor)
        assert float((a.double() - b).abs().max()) < 1e-5 * max(1.0, float(b.abs().max()))
    if backend == "c" and backends.status()["c"].startswith("compiled kernels in use"):
        assert last_backend("apply_kernels") == "c" and last_backend("apply_kernels_grad") == "c"


@pytest.mark.parametrize("normalize", [False, True])
def test_float64_gradcheck(normalize):
    x, w = _inputs(3, 5, 6, B=1, C=2)
    x, w = x.double().requires_grad_(), w.double().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: apply_kernels(a, b, dilation=2, normalize=normalize), (x, w))


def test_identity_and_dtype_kept(dtype, device):
    x = torch.rand(1, 3, 10, 12, device=device).to(dtype)
    w = torch.zeros(1, 25, 10, 12, device=device, dtype=dtype)
    w[:, 12] = 2.0
    out = apply_kernels(x, w, dilation=3, normalize=True)
    assert out.dtype == dtype and out.device == x.device
    torch.testing.assert_close(out, x)


def test_module_equals_function():
    x, w = _inputs(5, 8, 9)
    assert torch.equal(ApplyKernels(2, True)(x, w), apply_kernels(x, w, dilation=2, normalize=True))
    assert repr(ApplyKernels(2, True)) == "ApplyKernels(dilation=2, normalize=True)"


def test_bad_arguments_are_named():
    x, w = _inputs(3, 6, 7)
    with pytest.raises(ShapeError, match="weights: expected k² channels for an odd k"):
        apply_kernels(x, w[:, :8])
    with pytest.raises(ShapeError, match="weights"):
        apply_kernels(x, w[:, :, :5])
    with pytest.raises(RangeError, match="dilation: expected an int >= 1"):
        apply_kernels(x, w, dilation=0)
    with pytest.raises(RangeError, match="weights: a pixel's weights over the taps inside the image sum to 0"):
        apply_kernels(x, torch.zeros_like(w), normalize=True)
