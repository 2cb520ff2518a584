"""The back-end seam: every back end x op x dtype against the float64 oracles, and the seam's own
rules (order, the context-local switch, the reasons status() gives).

On the CPU the grid runs the C kernels (``c``) and the torch code (``torch``); with ``--device
cuda`` the Triton kernels (``triton``) instead of ``c``. float16 is computed in float32, so it
takes the float32 back end; float64 takes the torch code whatever is allowed.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from tests.helpers import last_backend, rel_error, rel_range
from tests.oracles import (
    ATROUS_CASES,
    atrous_case,
    atrous_error,
    box_oracle,
    fast_guided_oracle,
    guided_oracle,
    scene,
    upsample,
)
from tests.sampling.test_sampling import geometry, hamilton_oracle, importance_oracle
from torchgi import backends
from torchgi.core import OptionError
from torchgi.filters import atrous, box, guided
from torchgi.sampling import allocate, importance_map

DTYPES = [torch.float32, torch.float16, torch.float64]
# float16 rounds the inputs and outputs: its tolerance is its own rounding; float64's is the
# oracle's own rounding with guides offset by 1e3
TOL = {torch.float32: 2e-6, torch.float16: 2e-3, torch.float64: 1e-9}


def _expected(backend: str, dtype: torch.dtype, op: str, device: torch.device) -> str:
    """The back end that must run ``op`` when ``backend`` is allowed."""
    if backend == "torch" or dtype == torch.float64 and op != "allocate":
        return "torch"
    if device.type == "cuda":
        return "triton" if op in ("box", "guided", "atrous") else "torch"
    return "c"


@pytest.fixture(params=["compiled", "torch"])
def backend(request, device):
    if request.param == "compiled":
        name = "triton" if device.type == "cuda" else "c"
        why = backends.status()[name]
        if not (why.startswith(("compiled kernels in use", "Triton "))):
            pytest.skip(f"{name}: {why}")
        with backends.use(name):
            yield name
    else:
        with backends.use("torch"):
            yield "torch"


def _quantised(t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``t`` rounded to ``dtype`` and back to float64: the oracle's input for a low-precision case."""
    return t.to(dtype).double()


@pytest.mark.parametrize("dt", DTYPES)
def test_box_grid(backend, device, dt):
    x = torch.rand(2, 3, 23, 70, generator=torch.Generator().manual_seed(1)) + 2
    for r in (0, 3, 40):
        got = box(x.to(device, dt), r)
        assert got.dtype == dt and last_backend("box") == _expected(backend, dt, "box", device)
        # the torch code's float32 prefix sums run to ~200 here: 6e-6 of rounding
        assert rel_error(got, box_oracle(_quantised(x, dt), r)) < 5 * TOL[dt]


@pytest.mark.parametrize("dt", DTYPES)
@pytest.mark.parametrize("n", [1, 2, 3, 4])
@pytest.mark.parametrize("Cs", [1, 3, 5])
def test_guided_grid(backend, device, dt, n, Cs):
    """Windows past the image, one pixel, r = 0, guides offset by 1e3 (centred away)."""
    g = torch.Generator().manual_seed(10 * n + Cs)
    for H, W, r in ((1, 1, 0), (1, 9, 2), (7, 3, 40), (37, 53, 3), (37, 53, 12)):
        p = torch.rand(2, Cs, H, W, generator=g)
        I = torch.rand(2, n, H, W, generator=g) + (1e3 if dt != torch.float16 else 10.0)
        got = guided(p.to(device, dt), I.to(device, dt), radius=r, eps=0.01)
        assert got.dtype == dt and last_backend("guided") == _expected(backend, dt, "guided", device)
        ref = guided_oracle(_quantised(p, dt), _quantised(I, dt), r, 0.01)
        assert float((got.double().cpu() - ref).abs().max()) < 10 * TOL[dt], (H, W, r)


@pytest.mark.parametrize("dt", [torch.float32, torch.float64])
def test_guided_subsampled_grid(backend, device, dt):
    p, I = scene(2, 37, 53, 4, seed=1)
    got = guided(p.to(device, dt), I.to(device, dt), radius=6, eps=0.01, subsample=2)
    assert last_backend("guided") == _expected(backend, dt, "guided", device)
    assert rel_range(got, fast_guided_oracle(p, I, 6, 0.01, 2)) < 10 * TOL[dt]


@pytest.mark.parametrize("dt", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [1, 4])
def test_upsample_apply_grid(backend, device, dt, n):
    """Coefficients at half resolution upsampled and applied: the oracle's bilinear weights
    (pixel centres aligned, clamped) in float64, odd and even sizes, one pixel."""
    g = torch.Generator().manual_seed(n)
    for H, W in ((1, 1), (9, 14), (37, 53)):
        c = torch.randn(2, n + 1, 3, (H + 1) // 2, (W + 1) // 2, generator=g)
        I = torch.randn(2, n, H, W, generator=g)
        got = backends.run(backends.UpsampleApplyOp(c.to(device, dt), I.to(device, dt)))
        assert last_backend("upsample_apply") == _expected(backend, dt, "upsample_apply", device)
        up = upsample(c, 2, (H, W))
        ref = up[:, n] + (up[:, :n] * I.double()[:, :, None]).sum(1)
        assert got.dtype == dt and rel_error(got, ref) < 10 * TOL[dt], (H, W)


@pytest.mark.parametrize("dt", [torch.float32, torch.float64])
@pytest.mark.parametrize("C", [1, 2, 3])
@pytest.mark.parametrize("case", ATROUS_CASES)
def test_atrous_grid(backend, device, dt, C, case):
    """70 px wide: at steps 1, 2, 4 the C kernel's 16-pixel vector blocks cover the middle and
    the edges go tap by tap; C = 2 has no specialised C kernel."""
    c, n, x, kw = atrous_case(C, case)
    move = {k: v.to(device, dt) if torch.is_tensor(v) else v for k, v in kw.items()}
    out = atrous(c.to(device, dt), n.to(device, dt), x.to(device, dt), **move)
    assert out.dtype == dt and last_backend("atrous") == _expected(backend, dt, "atrous", device)
    assert atrous_error(out.cpu(), c, n, x, kw) < (2e-5 if device.type == "cuda" else 2e-6)


@pytest.mark.parametrize("dt", [torch.float32, torch.float64])
@pytest.mark.parametrize("window", [2, 4, 7])
def test_importance_grid(backend, device, dt, window):
    n, x, hit = geometry(H=7, W=45, seed=window)  # 45: the C kernel's vector blocks and its edges
    want = importance_oracle(n, x, hit, window, 0.2, 0.5)
    got = importance_map(n.to(device, dt), x.to(device, dt), window=window, sigma_normal=0.2,
                         sigma_position=0.5, hit=hit.to(device))
    assert last_backend("importance") == _expected(backend, dt, "importance", device)
    np.testing.assert_allclose(got.double().cpu().numpy(), want, atol=2e-6)


@pytest.mark.parametrize("dt", [torch.float32, torch.float64])
def test_allocate_grid(backend, device, dt):
    """Eighths sum exactly in any order, so every back end and the oracle see the same shares."""
    g = torch.Generator().manual_seed(7)
    q = torch.randint(0, 9, (2, 1, 31, 45), generator=g).to(dt) / 8
    mask = torch.rand(2, 1, 31, 45, generator=g) > 0.25
    counts = allocate(q.to(device), 3 * 31 * 45 + 7, min_samples=1, mask=mask.to(device)).cpu()
    assert last_backend("allocate") == _expected(backend, dt, "allocate", device)
    for b in range(2):
        want = hamilton_oracle(q[b].flatten().double().numpy(), mask[b].flatten().numpy(), 3 * 31 * 45 + 7, 1)
        np.testing.assert_array_equal(counts[b].flatten().numpy(), want)


def test_use_is_local_to_its_thread():
    """A ``use`` block in one thread leaves another thread's calls alone (a context variable)."""
    if not backends.status()["c"].startswith("compiled kernels in use"):
        pytest.skip("the C kernels are not built here")
    inside, seen = threading.Event(), {}

    def other():
        inside.wait(10)
        box(torch.rand(1, 1, 8, 8), 1)
        seen["other"] = backends.enabled("c")

    t = threading.Thread(target=other)
    t.start()
    with backends.use("torch"):
        inside.set()
        t.join(10)
        assert not backends.enabled("c")
    assert seen["other"] and backends.enabled("c")


def test_status_names_the_reasons():
    x = torch.rand(1, 1, 8, 8, dtype=torch.float64, requires_grad=True)
    box(x, 1)
    skipped = backends.status()["last"]["box"]["skipped"]
    assert last_backend("box") == "torch" and skipped["c"] == "the C kernels take float32"
    with backends.use("c"):
        box(x.detach().double(), 1)
        assert backends.status()["last"]["box"]["skipped"]["triton"].startswith("switched off")
    with pytest.raises(OptionError, match="cuda"):
        backends.use("cuda").__enter__()
