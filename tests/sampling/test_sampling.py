import contextlib
import math

import numpy as np
import pytest
import torch

from torchgi import backends
from torchgi.core import NonFiniteError, RangeError
from torchgi.sampling import allocate, exclusive_scan, importance_map


def geometry(B=2, H=9, W=11, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = torch.nn.functional.normalize(torch.randn(B, 3, H, W, generator=g), dim=1)
    n[:, :, :, : W // 2] = torch.tensor([0.0, 1.0, 0.0])[:, None, None]  # a flat floor on the left
    x = torch.rand(B, 3, H, W, generator=g) + 50.0
    hit = torch.rand(B, 1, H, W, generator=g) > 0.15
    return n, x, hit


def importance_oracle(n, x, hit, window, sn, sx):
    n, x, hit = n.double().numpy(), x.double().numpy(), hit.numpy()
    B, _, H, W = n.shape
    out = np.zeros((B, 1, H, W))
    lo, hi = -(window // 2), (window - 1) // 2
    for b in range(B):
        for py in range(H):
            for px in range(W):
                if not hit[b, 0, py, px]:
                    continue
                total = count = 0.0
                for qy in range(py + lo, py + hi + 1):
                    for qx in range(px + lo, px + hi + 1):
                        if 0 <= qy < H and 0 <= qx < W and hit[b, 0, qy, qx]:
                            dn = ((n[b, :, py, px] - n[b, :, qy, qx]) ** 2).sum() / sn
                            dx = ((x[b, :, py, px] - x[b, :, qy, qx]) ** 2).sum() / sx
                            total += math.exp(-dn - dx)
                            count += 1
                out[b, 0, py, px] = 1 - total / count
    return out


@pytest.mark.parametrize("window", [2, 3, 4, 7, 10])
@pytest.mark.parametrize("W", [11, 45])  # 45: the compiled kernel's vector blocks run as well as its edges
def test_importance_matches_oracle(window, W, device):
    n, x, hit = geometry(H=7, W=W, seed=window)
    want = importance_oracle(n, x, hit, window, 0.2, 0.5)
    everywhere = importance_oracle(n, x, torch.ones_like(hit), window, 0.2, 0.5)
    n, x, hit_d = n.to(device), x.to(device), hit.to(device)
    for kernel in (True, False):  # the compiled CPU kernel (where it builds) and the torch code
        with contextlib.nullcontext() if kernel else backends.use("torch"):
            got = importance_map(n, x, window=window, sigma_normal=0.2, sigma_position=0.5, hit=hit_d).cpu()
            np.testing.assert_allclose(got.double().numpy(), want, atol=2e-6)
            assert (got[~hit] == 0).all()
            got = importance_map(n, x, window=window, sigma_normal=0.2, sigma_position=0.5).cpu()
            np.testing.assert_allclose(got.double().numpy(), everywhere, atol=2e-6)


def test_allocation_invariants():
    g = torch.Generator().manual_seed(3)
    q = torch.rand(3, 1, 17, 23, generator=g) ** 3
    q[1] = 0.0  # no importance at all: spread evenly
    mask = torch.rand(3, 1, 17, 23, generator=g) > 0.2
    budget = 4 * 17 * 23
    counts = allocate(q, budget, min_samples=1, mask=mask)
    assert counts.dtype == torch.int64
    assert (counts.flatten(1).sum(1) == budget).all()  # exact, the paper leaves it short
    assert (counts[mask] >= 1).all() and (counts[~mask] == 0).all()
    for b in range(3):
        m = mask[b].flatten().numpy()
        qb = q[b].flatten().double().numpy() * m
        spare = budget - m.sum()
        share = qb / qb.sum() if qb.sum() > 0 else m / m.sum()
        expected = 1 + share * spare
        got = counts[b].flatten().numpy()
        assert np.all(np.abs(got[m] - expected[m]) < 1)  # largest remainder: within one sample
        if qb.sum() > 0:  # chi-square of the spare samples against the importance shares
            e = share[m] * spare
            chi2 = (((got[m] - 1) - e) ** 2 / np.maximum(e, 1e-9))[e > 1].sum()
            assert chi2 < 0.05 * (e > 1).sum()


def hamilton_oracle(q: np.ndarray, eligible: np.ndarray, budget: int, min_samples: int) -> np.ndarray:
    """Largest-remainder apportionment in float64, remainders to the lowest index on ties."""
    q = np.where(eligible, q, 0.0)
    spare = budget - min_samples * eligible.sum()
    share = q / q.sum() if q.sum() > 0 else eligible / eligible.sum()
    exact = share * spare
    n = np.floor(exact)
    left = int(np.rint(spare - n.sum()))
    order = np.lexsort((np.arange(q.size), -np.where(eligible, exact - n, -1.0)))  # remainder desc, index asc
    n[order[:left]] += 1
    return np.where(eligible, n + min_samples, 0).astype(np.int64)


@pytest.mark.parametrize("qtype", [torch.float32, torch.float64])
def test_allocation_matches_hamilton_oracle(qtype, device):
    """Eighths sum exactly in any order, so both code paths and the oracle see the same shares;
    many pixels share a value, so the remainders tie in long runs."""
    g = torch.Generator().manual_seed(7)
    q = torch.randint(0, 9, (3, 1, 61, 89), generator=g).to(qtype) / 8
    q[1] = 0.0
    mask = torch.rand(3, 1, 61, 89, generator=g) > 0.25
    mask[2] = True
    cases = [(3 * 61 * 89 + 7, 1, mask), (10 * 61 * 89 - 1, 2, mask), (61 * 89, 0, mask), (2 * 61 * 89 + 5, 1, None)]
    for budget, min_samples, m in cases:
        for kernel in (True, False):  # the compiled CPU kernel (where it builds) and the torch code
            with contextlib.nullcontext() if kernel else backends.use("torch"):
                counts = allocate(q.to(device), budget, min_samples=min_samples,
                                  mask=None if m is None else m.to(device)).cpu()
            for b in range(3):
                eligible = np.ones(61 * 89, dtype=bool) if m is None else m[b].flatten().numpy()
                want = hamilton_oracle(q[b].flatten().double().numpy(), eligible, budget, min_samples)
                np.testing.assert_array_equal(counts[b].flatten().numpy(), want)


def test_ties_are_deterministic():
    counts = allocate(torch.ones(1, 1, 1, 5), 7, min_samples=1)
    assert counts.flatten().tolist() == [2, 2, 1, 1, 1]  # remainders to the lowest indices


def test_exclusive_scan():
    counts = torch.randint(0, 5, (2, 1, 4, 6), generator=torch.Generator().manual_seed(0))
    flat = counts.flatten(1).numpy()
    want = np.cumsum(flat, axis=1) - flat
    assert exclusive_scan(counts).flatten(1).numpy().tolist() == want.tolist()


def test_bad_inputs():
    q = torch.rand(1, 1, 4, 4)
    with pytest.raises(RangeError, match=r"budget: 15 samples cannot give min_samples=1 to 16 pixels"):
        allocate(q, 15)
    with pytest.raises(RangeError, match="importance: expected values >= 0.0"):
        allocate(q - 1, 100)
    bad = q.clone()
    bad[0, 0, 1, 1] = float("nan")
    with pytest.raises(NonFiniteError, match="importance"):
        allocate(bad, 100)
    n, x, _ = geometry()
    with pytest.raises(RangeError, match="window: expected an int >= 2"):
        importance_map(n, x, window=1)
    with pytest.raises(RangeError, match="window: expected 2..10"):
        importance_map(n, x, window=11)


def test_batches_visit_every_sample_once_whatever_the_batch_size():
    from torchgi.sampling import sample_batches

    counts = allocate(torch.rand(2, 1, 6, 7, generator=torch.Generator().manual_seed(4)) ** 2, 3 * 42)
    seen = {}
    for bs in (1, 5, 64, 10_000):
        pairs = [(b.image, p, s) for b in sample_batches(counts, bs) for p, s in zip(b.pixel.tolist(), b.sample.tolist())]
        assert all(len(b.pixel) <= bs for b in sample_batches(counts, bs))
        seen[bs] = pairs
    assert seen[1] == seen[5] == seen[64] == seen[10_000]
    want = [(b, p, s) for b in range(2) for p, n in enumerate(counts[b].flatten().tolist()) for s in range(n)]
    assert seen[1] == want  # each pixel drawn exactly counts[p] times, sample indices 0..n-1
    # chi-square of the draws against the counts (exact here: the statistic is 0)
    draws = np.bincount([p for b, p, _ in want if b == 0], minlength=42)
    expected = counts[0].flatten().numpy()
    assert ((draws - expected) ** 2 / np.maximum(expected, 1)).sum() == 0


def test_accumulate_is_a_per_pixel_sum():
    from torchgi.sampling import accumulate

    g = torch.Generator().manual_seed(5)
    pixel = torch.sort(torch.randint(0, 9, (50,), generator=g)).values
    values = torch.randn(50, 3, generator=g, dtype=torch.float64)
    want = torch.zeros(9, 3, dtype=torch.float64).index_add_(0, pixel, values)
    torch.testing.assert_close(accumulate(values, pixel, 9), want)
    with pytest.raises(ValueError, match="ascending"):
        accumulate(values, pixel.flip(0), 9)


def test_importance_fused_matches_eager():
    n, x, _ = geometry()
    hit = torch.rand(n.shape[0], 1, *n.shape[2:], generator=torch.Generator().manual_seed(2)) > 0.2
    with backends.use("torch"):  # the compiled CPU kernel would take both calls
        eager = importance_map(n, x, window=3, hit=hit)
        fused = importance_map(n, x, window=3, hit=hit, fused=True)
    torch.testing.assert_close(fused, eager, rtol=1e-5, atol=1e-6)


def test_renderer_traces_exactly_the_allocated_samples(monkeypatch):
    # The renderer's sample-to-pixel map: every pixel's samples are traced exactly
    # counts[p] times with sample indices 0..counts[p]-1 (a chi-square statistic of 0).
    pytest.importorskip("embreex")
    import torchgi
    from torchgi.render import engine

    traced = []
    real = engine.INTEGRATORS["path"]

    def spy(ctx, pixel, sample, *, stream=0, record="all"):
        if record == "all":
            traced.append((pixel.clone(), sample.clone()))
        return real(ctx, pixel, sample, stream=stream, record=record)

    monkeypatch.setitem(engine.INTEGRATORS, "path", spy)
    scene = torchgi.scenes.cornell(12)
    g = torchgi.render.render_guides(scene)
    imp = importance_map(g.normal, g.position, window=4, sigma_position=400.0, hit=g.hit)
    counts = allocate(imp, 3 * int(g.hit.sum()), min_samples=1, mask=g.hit)
    with torchgi.backends.use("torch"):  # the spy sits in the torch integrator
        torchgi.render(scene, counts, bounces=1, workers=1, chunk_size=1024)
    pixel = torch.cat([p for p, _ in traced])
    sample = torch.cat([s for _, s in traced])
    draws = torch.bincount(pixel, minlength=144).numpy()
    expected = counts.flatten().numpy()
    assert ((draws - expected) ** 2 / np.maximum(expected, 1)).sum() == 0
    for p in range(144):
        assert sorted(sample[pixel == p].tolist()) == list(range(int(expected[p])))


def test_adaptive_render_spends_the_exact_budget():
    pytest.importorskip("embreex")
    import torchgi
    from torchgi.sampling import adaptive_render

    scene = torchgi.scenes.cornell_glossy(16)
    for share in (0.0, 0.5):
        gb, counts = adaptive_render(scene, rate=3.0, bounces=1, seed=1, variance_share=share)
        hit = gb.hit
        assert int(counts.sum()) == round(3.0 * int(hit.sum()))
        assert int(counts[hit].min()) >= 1 and int(counts[~hit].sum()) == 0
        assert torch.equal(gb.spp, counts.clamp_min(1))  # a pixel given none: one sample of what a miss shows
        assert bool(torch.isfinite(gb.indirect).all()) and float(gb.variance.min()) >= 0
    with pytest.raises(RangeError, match="variance_share"):
        adaptive_render(scene, rate=3.0, variance_share=1.0)
    with pytest.raises(RangeError, match="rate"):
        adaptive_render(scene, rate=0.0)


def test_merged_rounds_hold_the_pooled_mean_and_variance_of_their_samples():
    # Against float64 numpy on the two rounds' samples put together: counts 1 (no variance of its
    # own), 0 (a round that holds nothing there) and several.
    from torchgi.buffers import GBuffer
    from torchgi.sampling import merge_rounds

    g = np.random.default_rng(3)
    counts = [(1, 1), (1, 4), (3, 0), (0, 2), (5, 7), (2, 1)]
    samples = [[g.random((3, n)) * 4 for n in pair] for pair in counts]  # per pixel, per round (3, n)
    rounds = []
    for r in range(2):
        light = np.array([s[r].mean(1) if s[r].size else np.zeros(3) for s in samples]).T  # (3, pixels)
        var = np.array([s[r].var(1, ddof=1) / s[r].shape[1] if s[r].shape[1] > 1 else np.zeros(3)
                        for s in samples]).T
        t = lambda a: torch.tensor(a, dtype=torch.float32).view(1, 3, 1, -1)
        zero = torch.zeros(1, 3, 1, len(counts))
        n = torch.tensor([pair[r] for pair in counts]).view(1, 1, 1, -1)
        rounds += [GBuffer(emission=zero, direct=zero, indirect=t(light), variance=t(var), spp=n.clamp_min(1)), n]
    m = merge_rounds(*rounds)
    for p, s in enumerate(samples):
        x = np.concatenate(s, 1)
        np.testing.assert_allclose(m.color[0, :, 0, p].numpy(), x.mean(1), rtol=1e-5)
        want = x.var(1, ddof=1) / x.shape[1] if x.shape[1] > 1 else np.zeros(3)
        np.testing.assert_allclose(m.variance[0, :, 0, p].numpy(), want, rtol=1e-4, atol=1e-7)
        assert int(m.spp[0, 0, 0, p]) == x.shape[1]
