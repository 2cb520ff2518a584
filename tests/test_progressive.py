import pytest
import torch

from torchgi.core import RangeError

pytest.importorskip("embreex")


def test_render_to_spends_exactly_the_rounds_samples_and_none_on_noise_free_pixels():
    # With a budget in samples (max_spp) rounds of 2 and 6 spp: 8 spp in all, counted exactly in
    # the merged spp; the sky seen directly is noise-free (its variance 0 from round 0): away
    # from the ground (the variance is 3x3-blurred) it gets no sample after round 0.
    import torchgi
    from torchgi import render_to

    scene = torchgi.scenes.sky(24)
    gb = render_to(scene, seconds=1e6, max_spp=8, bounces=1, seed=3, progress=False)
    assert int(gb.spp.sum()) == 8 * 24 * 24
    sky = ~gb.hit
    assert bool(sky.any()) and bool((gb.variance[sky.expand_as(gb.variance)] == 0).all())
    far = sky & (torch.nn.functional.max_pool2d((~sky).float(), 3, 1, 1) == 0)
    assert bool(far.any()) and bool((gb.spp[far] == 2).all()) and float(gb.spp[~sky].float().mean()) > 8
    flat = render_to(scene, seconds=1e6, max_spp=8, adaptive=False, bounces=1, seed=3, progress=False)
    assert int(flat.spp.sum()) == 8 * 24 * 24 and int(flat.spp.max()) - int(flat.spp.min()) <= 1
    # the merged colour is the mean of all of a pixel's samples: as good as a uniform render of
    # the same samples against a 256 spp reference, within noise
    ref = torchgi.render(scene, 256, bounces=1, seed=99).color[~sky.expand(-1, 3, -1, -1)]
    uniform = torchgi.render(scene, 8, bounces=1, seed=4).color[~sky.expand(-1, 3, -1, -1)]
    assert abs(float(gb.color[~sky.expand(-1, 3, -1, -1)].mean() / ref.mean()) - 1) < 0.05
    assert abs(float(uniform.mean() / ref.mean()) - 1) < 0.05


def test_render_to_a_target_is_deterministic_and_stops_at_its_estimate():
    import torchgi
    from torchgi import render_to

    scene = torchgi.scenes.cornell(16)
    a = render_to(scene, target=0.02, bounces=1, seed=5, progress=False)
    b = render_to(scene, target=0.02, bounces=1, seed=5, progress=False)
    assert torch.equal(a.color, b.color) and torch.equal(a.spp, b.spp)
    easy = render_to(scene, target=1e6, bounces=1, seed=5, progress=False)  # met after round 0
    assert int(easy.spp.max()) == 2 and int(a.spp.sum()) > int(easy.spp.sum())


def test_render_to_arguments():
    import torchgi
    from torchgi import render_to

    scene = torchgi.scenes.cornell(8)
    with pytest.raises(ValueError, match="seconds, target: give exactly one"):
        render_to(scene)
    with pytest.raises(ValueError, match="seconds, target: give exactly one"):
        render_to(scene, seconds=1.0, target=0.1)
    with pytest.raises(RangeError, match="seconds"):
        render_to(scene, seconds=0.0)
    with pytest.raises(RangeError, match="target"):
        render_to(scene, target=-1.0)
    with pytest.raises(RangeError, match="first_spp"):
        render_to(scene, seconds=1.0, first_spp=1)


@pytest.mark.parametrize("call_spp", [0.25, 0.5, 0.7])  # the range measured on the tuning scenes
def test_render_to_seconds_fits_renders_that_cost_a_call_beside_their_samples(monkeypatch, call_spp):
    # A simulated clock: each render call takes call + n * per seconds (call = call_spp samples
    # per pixel's time, as the tracer's buffers and walk over every pixel cost), the Denoiser
    # d seconds below 3 spp and 5 d from 3 spp. The rounds planned for a budget T end, with the
    # final denoise, at most one eighth of a sample per pixel's time past T (the smallest round
    # the plan starts), and use most of it.
    import torchgi
    from torchgi import progressive

    scene = torchgi.scenes.cornell(16)
    pixels, per, d = 16 * 16, 1e-3, 0.01
    clock = [0.0]
    monkeypatch.setattr(progressive.time, "perf_counter", lambda: clock[0])
    real_round = progressive._Run.round

    def timed_round(self, counts, r):
        clock[0] += call_spp * pixels * per + float(counts.sum()) * per
        return real_round(self, counts, r)

    def denoiser(gb):  # a Denoiser that does five times the work from 3 spp (as "guided" chooses radii)
        clock[0] += d if float(gb.spp.float().mean()) < 3 else 5 * d
        return gb.color

    monkeypatch.setattr(progressive._Run, "round", timed_round)
    for T in (0.06 + 8 * pixels * per, 0.06 + 20 * pixels * per):
        clock[0] = 0.0
        gb = progressive.render_to(scene, seconds=T, bounces=1, seed=1, denoiser=denoiser, progress=False)
        denoiser(gb)
        assert clock[0] <= T + pixels * per / 8 + 1e-9
        assert clock[0] >= T - (2 + 2 * call_spp) * pixels * per  # at most about a round's call unused


def _two_halves(colour=(1.0, 1.0), per_sample=(1.0, 1.0), k=4, H=8, W=40):
    """A GBuffer whose left and right halves have the given colours and per-sample variances,
    ``k`` samples in every pixel (so ``variance`` = per-sample variance / k)."""
    from torchgi import GBuffer

    half = W // 2
    c = torch.ones(1, 3, H, W)
    s2 = torch.ones(1, 3, H, W)
    c[..., :half], c[..., half:] = colour
    s2[..., :half], s2[..., half:] = per_sample
    counts = torch.full((1, 1, H, W), k, dtype=torch.int64)
    gb = GBuffer(color=c, variance=s2 / k, albedo=torch.ones(1, 3, H, W), spp=counts)
    return gb, counts


def _interior_means(counts, W=40):
    """The mean new samples per pixel in each half away from the seam (the 3x3 and 5x5 blurs)."""
    half = W // 2
    return float(counts[..., 3:half - 3].float().mean()), float(counts[..., half + 3:-3].float().mean())


@pytest.mark.parametrize(("colour", "per_sample", "support", "want"), [
    ((1.0, 1.0), (1.0, 16.0), None, 1 / 4),  # shares sqrt(s²): 1 : 4 (without the root 1 : 16)
    ((1.0, 4.0), (1.0, 1.0), None, (16.01 / 1.01) ** 0.5),  # relMSE's weight 1 / (d² + 0.01)
    ((1.0, 1.0), (1.0, 1.0), (1.0, 1 / 16), 1 / 4),  # geometry: the share over sqrt(support)
])
def test_placement_follows_the_rule_by_hand(colour, per_sample, support, want):
    """Issue 71: removing the relMSE weight or the square root from the placement rule passed the
    tests. On two halves of hand-set colour, per-sample variance and filter support, a round's
    counts follow ``n ∝ sqrt(w s²) / sqrt(support)`` (the module docstring): each half's total
    after the round (away from the seam's blur) stands to the other's as computed here by hand.
    Measured: within 0.4 % of the ratio."""
    from torchgi.progressive import _counts

    gb, counts = _two_halves(colour, per_sample)
    sup = None
    if support is not None:
        sup = torch.ones(1, 1, 8, 40)
        sup[..., :20], sup[..., 20:] = support
    n = 100 * counts.numel()
    new = _counts(gb, counts, None, n, sup)
    assert int(new.sum()) == n
    left, right = _interior_means(new)
    # each half's samples after the round (the 4 it had and its new ones) stand as its share
    assert abs((left + 4) / (right + 4) / want - 1) < 0.03, (left, right)


def test_render_to_geometry_places_by_the_filter_support():
    """``geometry=True`` is not ignored: the same seed and target with and without it give other
    sample counts (the share divided by the support's root), the same total within a round."""
    pytest.importorskip("embreex")
    import torchgi

    scene = torchgi.scenes.cornell(24)
    plain = torchgi.render_to(scene, target=0.2, bounces=1, seed=3, progress=False)
    geo = torchgi.render_to(scene, target=0.2, bounces=1, seed=3, geometry=True, progress=False)
    assert not torch.equal(plain.spp, geo.spp)
