"""The C back end (torchgi.backends.c_kernels) beyond the grid of tests/backends/test_backends.py: its build,
bands of rows on two threads, a forked child, and the fall-backs when it is off or cannot be built."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.helpers import last_backend
from tests.helpers import rel_error as rel
from tests.oracles import atrous_oracle, guided_oracle
from torchgi import backends
from torchgi.backends import c_kernels as native
from torchgi.filters import atrous, guided
from torchgi.sampling import allocate, importance_map

pytestmark = pytest.mark.skipif(native.build._compiler() is None, reason="no C compiler: the kernels cannot be built")


def test_kernels_build_with_the_system_compiler():
    assert native.describe().startswith("compiled kernels in use"), native.describe()
    lib = native.library()
    for d in (0.0, 0.5, 3.0, 20.0, 80.0):
        assert abs(lib.torchgi_exp_neg(d) - np.exp(-d)) <= 2e-7 * np.exp(-d)
    assert lib.torchgi_exp_neg(100.0) == 0.0  # below 1.2e-38: no weight
    # issue 71: with a compiler here the C back end must run every op family's float32 CPU calls
    # (a back end that silently declines would leave the "C kernel ran" tests on the torch code)
    assert {op: ran for op, (ran, _) in backends.plan("cpu").items() if ran != "c"} == {}
    from torchgi.filters import box

    box(torch.rand(1, 2, 9, 7), 2)
    assert backends.status()["last"]["box"]["ran"] == "c"



@pytest.fixture
def two_bands(monkeypatch):
    """Every image split into bands of rows on two threads, however small."""
    monkeypatch.setattr(native.runtime, "_MIN_BAND_PIXELS", 16)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(threads)


def test_atrous_kernel_batch_and_bands(two_bands):
    g = torch.Generator().manual_seed(5)
    c = torch.rand(2, 3, 15, 70, generator=g)
    n = torch.nn.functional.normalize(torch.randn(2, 3, 15, 70, generator=g), dim=1)
    out = atrous(c, n, None, iterations=3, sigma_color=0.5)
    assert last_backend("atrous") == "c"
    for b in range(2):
        assert rel(out[b], atrous_oracle(c[b], n[b], None, iterations=3, sigma_color=0.5)) < 2e-6


def test_guided_kernel_bands_and_subsample(two_bands):
    """Bands of 18 and 19 rows with windows of 25 rows; the half-resolution form."""
    from tests.oracles import fast_guided_oracle

    g = torch.Generator().manual_seed(3)
    p = torch.rand(2, 3, 37, 61, generator=g)
    I = torch.rand(2, 4, 37, 61, generator=g)
    out = guided(p, I, radius=12, eps=0.01)
    assert last_backend("guided") == "c"
    half = guided(p, I, radius=12, eps=0.01, subsample=2)
    assert last_backend("guided") == "c"
    assert float((out.double() - guided_oracle(p.double(), I.double(), 12, 0.01)).abs().max()) < 2e-6
    ref = fast_guided_oracle(p.double(), I.double(), 12, 0.01, 2)
    assert float((half.double() - ref).abs().max()) < 2e-6


def test_autograd_runs_the_kernels_float64_the_torch_code():
    p = torch.rand(1, 3, 20, 40, requires_grad=True)
    I = torch.rand(1, 4, 20, 40)
    guided(p, I, radius=3).sum().backward()  # GuidedFunction: the forward and the backward compiled
    assert p.grad is not None
    assert last_backend("guided") == "c" and last_backend("guided_grad") == "c"
    guided(p.detach().double(), I.double(), radius=3)
    assert backends.status()["last"]["guided"]["skipped"]["c"] == "the C kernels take float32"
    atrous(p.detach().double(), iterations=2)
    assert last_backend("atrous") == "torch"


def test_disabled_and_unbuildable_fall_back(monkeypatch, tmp_path):
    p = torch.rand(1, 3, 24, 50)
    I = torch.rand(1, 4, 24, 50)
    ref = guided_oracle(p.double(), I.double(), 4, 0.01)
    with backends.use("torch"):
        assert backends.status()["c"].startswith("switched off")
        assert float((guided(p, I, radius=4).double() - ref).abs().max()) < 1e-5
    # a compiler that fails: no library, a reason, the torch code
    monkeypatch.setenv("CC", "false")
    monkeypatch.setenv("TORCHGI_CACHE", str(tmp_path))
    monkeypatch.setattr(native.build, "_lib", None)
    monkeypatch.setattr(native.build, "_tried", False)
    monkeypatch.setattr(native.build, "_status", "not built yet")
    assert native.library() is None
    assert "unavailable" in native.describe() and "false" in native.describe()
    assert float((guided(p, I, radius=4).double() - ref).abs().max()) < 1e-5
    assert list(tmp_path.iterdir()) == []  # the failed build left no file behind


def _importance_in_child(queue) -> None:
    torch.set_num_threads(1)  # as the renderer's and data generation's forked workers do
    g = torch.Generator().manual_seed(3)
    n = torch.nn.functional.normalize(torch.randn(1, 3, 40, 300, generator=g), dim=1)
    imp = importance_map(n, torch.rand(1, 3, 40, 300, generator=g), window=4)
    queue.put((imp.numpy(), allocate(imp, 3 * imp.numel()).numpy()))  # pickled, not shared


def test_forked_child_with_one_thread_runs_the_kernels(two_bands):
    """A parent that ran the kernels on OpenMP threads forks; the child (one torch thread) runs
    them on its calling thread (libgomp's pool does not survive a fork) and gets the parent's
    result."""
    import multiprocessing

    g = torch.Generator().manual_seed(3)
    n = torch.nn.functional.normalize(torch.randn(1, 3, 40, 300, generator=g), dim=1)
    want = importance_map(n, torch.rand(1, 3, 40, 300, generator=g), window=4)  # two bands in the parent
    counts = allocate(want, 3 * want.numel())
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_importance_in_child, args=(queue,))
    child.start()
    got, got_counts = queue.get(timeout=60)
    child.join(timeout=60)
    assert child.exitcode == 0
    np.testing.assert_array_equal(got, want.numpy())
    np.testing.assert_array_equal(got_counts, counts.numpy())
