"""The compiled CPU kernels (torchgi.filters.native) against the float64 oracles, on sizes where
both their vectorised interior and their tap-by-tap edges run, and their fallbacks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.oracles import ATROUS_CASES, atrous_case, atrous_error, atrous_oracle, guided_oracle
from torchgi.filters import atrous, guided, native
from torchgi.sampling import allocate, importance_map

pytestmark = pytest.mark.skipif(native._compiler() is None, reason="no C compiler: the kernels cannot be built")


@pytest.fixture
def spy(monkeypatch):
    """Counts the calls that reach the compiled kernels."""
    calls = {"atrous": 0, "guided": 0}
    real_level, real_guided = native.atrous_level, native.guided

    def level(*a, **k):
        calls["atrous"] += 1
        return real_level(*a, **k)

    def guide(*a, **k):
        calls["guided"] += 1
        return real_guided(*a, **k)

    monkeypatch.setattr(native, "atrous_level", level)
    monkeypatch.setattr(native, "guided", guide)
    return calls


def test_kernels_build_with_the_system_compiler():
    assert native.available(), native.status()
    assert native.status().startswith("compiled")
    lib = native.library()
    for d in (0.0, 0.5, 3.0, 20.0, 80.0):
        assert abs(lib.torchgi_exp_neg(d) - np.exp(-d)) <= 2e-7 * np.exp(-d)
    assert lib.torchgi_exp_neg(100.0) == 0.0  # below 1.2e-38: no weight


def rel(out: torch.Tensor, ref) -> float:
    ref = np.asarray(ref)
    return float(np.abs(out.double().numpy() - ref).max() / np.abs(ref).max())


# 70 px wide: at steps 1, 2, 4 the 16-pixel vector blocks cover the middle, the edges go tap by tap.
# C = 2 has no specialised kernel (the run-time-count path).
@pytest.mark.parametrize("C", [1, 2, 3])
@pytest.mark.parametrize("case", ATROUS_CASES)
def test_atrous_kernel_matches_oracle(spy, C, case):
    c, n, x, kw = atrous_case(C, case)
    out = atrous(c, n, x, **kw)
    assert spy["atrous"] == 3
    assert atrous_error(out, c, n, x, kw) < 2e-6


@pytest.fixture
def two_bands(monkeypatch):
    """Every image split into bands of rows on two threads, however small."""
    monkeypatch.setattr(native, "_MIN_BAND_PIXELS", 16)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(threads)


def test_atrous_kernel_batch_and_bands(spy, two_bands):
    g = torch.Generator().manual_seed(5)
    c = torch.rand(2, 3, 15, 70, generator=g)
    n = torch.nn.functional.normalize(torch.randn(2, 3, 15, 70, generator=g), dim=1)
    out = atrous(c, n, None, iterations=3, sigma_color=0.5)
    assert spy["atrous"] == 3
    for b in range(2):
        assert rel(out[b], atrous_oracle(c[b], n[b], None, iterations=3, sigma_color=0.5)) < 2e-6


@pytest.mark.parametrize("n", [1, 2, 3, 4])
@pytest.mark.parametrize("Cs", [1, 3, 5])
def test_guided_kernel_matches_oracle(spy, n, Cs):
    g = torch.Generator().manual_seed(10 * n + Cs)
    for H, W, r in ((1, 1, 0), (1, 9, 2), (7, 3, 40), (37, 53, 3), (37, 53, 12)):
        p = torch.rand(2, Cs, H, W, generator=g)
        I = torch.rand(2, n, H, W, generator=g) + 1e3  # offsets are centred away
        out = guided(p, I, radius=r, eps=0.01)
        ref = guided_oracle(p.double(), I.double(), r, 0.01)
        assert float((out.double() - ref).abs().max()) < 2e-6, (H, W, r)
    assert spy["guided"] == 5


def test_guided_kernel_bands_and_subsample(spy, two_bands):
    """Bands of 18 and 19 rows with windows of 25 rows; the half-resolution form."""
    from tests.oracles import fast_guided_oracle

    g = torch.Generator().manual_seed(3)
    p = torch.rand(2, 3, 37, 61, generator=g)
    I = torch.rand(2, 4, 37, 61, generator=g)
    out = guided(p, I, radius=12, eps=0.01)
    half = guided(p, I, radius=12, eps=0.01, subsample=2)
    assert spy["guided"] == 2
    assert float((out.double() - guided_oracle(p.double(), I.double(), 12, 0.01)).abs().max()) < 2e-6
    ref = fast_guided_oracle(p.double(), I.double(), 12, 0.01, 2)
    assert float((half.double() - ref).abs().max()) < 2e-6


def test_autograd_and_float64_take_the_torch_code(spy):
    p = torch.rand(1, 3, 20, 40, requires_grad=True)
    I = torch.rand(1, 4, 20, 40)
    guided(p, I, radius=3).sum().backward()
    assert p.grad is not None
    guided(p.detach().double(), I.double(), radius=3)
    atrous(p.detach().double(), iterations=2)
    assert spy == {"atrous": 0, "guided": 0}


def test_disabled_and_unbuildable_fall_back(monkeypatch, tmp_path):
    p = torch.rand(1, 3, 24, 50)
    I = torch.rand(1, 4, 24, 50)
    ref = guided_oracle(p.double(), I.double(), 4, 0.01)
    with native.disabled():
        assert not native.available() and native.status().startswith("disabled")
        assert float((guided(p, I, radius=4).double() - ref).abs().max()) < 1e-5
    # a compiler that fails: no library, a reason, the torch code
    monkeypatch.setenv("CC", "false")
    monkeypatch.setenv("TORCHGI_CACHE", str(tmp_path))
    monkeypatch.setattr(native, "_lib", None)
    monkeypatch.setattr(native, "_tried", False)
    monkeypatch.setattr(native, "_status", "not built yet")
    assert native.library() is None
    assert "unavailable" in native.status() and "false" in native.status()
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
