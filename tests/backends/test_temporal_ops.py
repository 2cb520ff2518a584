"""The compiled temporal ops (torchgi.backends.temporal_ops: accumulate, change, history) against the
torch code: reprojection is torch's bilinear ``grid_sample`` where every tap counts, the C kernels in
float32 against the torch code in float64 (rows over several 256-px blocks, every branch reached),
and the torch code of the change test and the output history against pixels computed by hand."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tests.helpers import last_backend
from tests.helpers import sliding_sequence as _sequence
from torchgi.temporal import TemporalDenoiser, TemporalState


def _has_c() -> bool:
    from torchgi import backends

    return backends.select(backends.BoxOp(torch.ones(1, 1, 2, 2), 1))[0] == "c"


def _accumulate(state: TemporalState, x, motion, normal, depth, surface, bound=None) -> torch.Tensor:
    from torchgi import backends
    from torchgi.settings import TEMPORAL as T

    bound = torch.full_like(x[:, :1], 1e30) if bound is None else bound
    return backends.run(backends.AccumulateOp(x, bound, motion, normal, depth, surface, *state.tensors(), T.alpha,
                                              T.max_history, T.normal_tolerance, T.depth_tolerance))


@pytest.mark.parametrize("backend", ["torch", "c"])
def test_reprojection_is_bilinear_where_every_tap_counts(backend):
    # Flat guides (every tap passes): the history at pixel + motion is torch's bilinear
    # grid_sample of it, an independent implementation.
    from torchgi import backends

    B, H, W = 2, 9, 11
    g = torch.Generator().manual_seed(0)
    flat = torch.tensor([0.0, 0, 1]).view(1, 3, 1, 1).expand(B, 3, H, W).contiguous()
    state = TemporalState(torch.rand(B, 3, H, W, generator=g), torch.rand(B, 3, H, W, generator=g),
                          torch.rand(B, 2, H, W, generator=g), torch.full((B, 1, H, W), 3.0), flat,
                          torch.ones(B, 1, H, W), torch.ones(B, 1, H, W))
    motion = torch.tensor([1.3, -0.6]).view(1, 2, 1, 1).expand(B, 2, H, W).contiguous()
    x = torch.rand(B, 3, H, W, generator=g)
    if backend == "c" and not _has_c():
        pytest.skip("no C compiler")
    with backends.use(backend, "torch"):
        out = _accumulate(state, x, motion, flat, torch.ones(B, 1, H, W), torch.ones(B, 1, H, W, dtype=torch.bool))
    assert last_backend("accumulate") == backend
    ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    grid = torch.stack([(xs + 1.3) / W * 2 - 1, (ys - 0.6) / H * 2 - 1], -1).expand(B, H, W, 2)
    inner = (slice(None), slice(None), slice(1, H), slice(0, W - 2))  # all four taps inside
    light, output, moments = (torch.nn.functional.grid_sample(f, grid, align_corners=False)
                              for f in (state.light, state.output, state.moments))
    lum = (x * torch.tensor([0.2126, 0.7152, 0.0722]).view(1, 3, 1, 1)).sum(1, keepdim=True)
    a = 0.25  # length 3 + 1 frames: equal weights
    expect = torch.cat([light + a * (x - light), output, moments + a * (torch.cat([lum, lum * lum], 1) - moments),
                        torch.full_like(lum, 4.0), torch.full_like(lum, 3.0)], 1)
    assert torch.allclose(out[:, :10][inner], expect[inner], atol=1e-5)
    assert float(out[:, 9][:, :, -1].max()) == 0.0  # taps off the image: no history
    assert torch.equal(out[:, 8][:, :, -1], torch.ones(B, H))


def test_compiled_accumulation_matches_float64_torch_code():
    # a real sequence: edges, disocclusions, background; the C kernel in float32 against the
    # torch code in float64 (fireflies clamped at a bound too)
    from torchgi import backends

    if not _has_c():
        pytest.skip("no C compiler")
    gbs = _sequence(40, 3)
    state = TemporalDenoiser()
    state(gbs[0])
    st = state.state
    gb = gbs[1]
    x, bound = gb.color, gb.color.mean(1, keepdim=True) * 1.5
    args = (x, gb.motion, gb.normal, gb.depth, gb.hit)
    c = _accumulate(st, *args, bound=bound)
    with backends.use("torch"):
        ref = _accumulate(TemporalState(*(t.double() for t in st.tensors())), *(a if a.dtype == torch.bool
                          else a.double() for a in args), bound=bound.double())
    assert c.dtype == torch.float32 and float((c.double() - ref).abs().max() / ref.abs().max()) < 1e-5


@pytest.mark.parametrize("B, H, W", [(2, 3, 600), (1, 6, 257)])
def test_compiled_accumulation_over_several_blocks_of_a_row(B, H, W):
    # rows longer than the C walk's 256-px blocks (a partial last one), motion reaching past every
    # edge, each tap's tests (kind, normal, depth) passed and failed at random, fireflies above the
    # bound: the C kernel in float32 against the torch code in float64
    from torchgi import backends

    if not _has_c():
        pytest.skip("no C compiler")
    g = torch.Generator().manual_seed(3)

    def r(c: int, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(B, c, H, W, generator=g)

    normal = torch.nn.functional.normalize(r(3, -1, 1), dim=1)
    prev_normal = torch.nn.functional.normalize(normal + r(3, -0.1, 0.1), dim=1)
    depth = r(1, 1, 5)
    surface = r(1) > 0.2
    state = TemporalState(r(3, 0, 2), r(3, 0, 2), r(2, 0, 1), (r(1, 0, 8)).round(), prev_normal,
                          depth * r(1, 0.97, 1.05), (r(1) > 0.2).float())
    args = (r(3, 0, 3), torch.cat([r(1, -3, 3), r(1, -1.5, 1.5)], 1), normal, depth, surface)
    bound = r(1, 1, 4)
    c = _accumulate(state, *args, bound=bound)
    assert last_backend("accumulate") == "c"
    with backends.use("torch"):
        ref = _accumulate(TemporalState(*(t.double() for t in state.tensors())),
                          *(a if a.dtype == torch.bool else a.double() for a in args), bound=bound.double())
    found = ref[:, 9] > 0
    assert 0.15 < float(found.double().mean()) < 0.85  # pixels with a history and without
    assert float((c.double() - ref).abs().max() / ref.abs().max()) < 1e-5


def _change_and_history_ops(B: int, H: int, W: int, test: bool, seed: int = 0):
    """A ChangeOp and a HistoryOp on random inputs that reach every branch: drops from 0 to 1 (and
    changes with no noise), history lengths on both sides of ``variance_history``, pixels with and
    without a history, surfaces and background, fireflies above the bound."""
    from torchgi import backends

    g = torch.Generator().manual_seed(seed)

    def r(c: int, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(B, c, H, W, generator=g)

    step = torch.cat([r(3, 0, 2), r(3, 0, 2), r(1, 0, 1), r(1, 0, 2), (r(1, 0, 8) + 1).round(), r(1, 0, 6).round(),
                      r(1, 0, 0.5), r(1, 1, 5), r(1, 0, 1)], 1)
    now = r(1)
    near = torch.cat([now, now + r(1, -0.15, 0.15), r(1, 0, 0.05) * (r(1) > 0.1)], 1)  # some windows without noise
    wide = torch.cat([now, now + r(1, -0.02, 0.02), r(1, 0, 0.01)], 1)
    surface = r(1) > 0.3
    change = backends.ChangeOp(r(3, 0, 4), r(1, 0.5, 2), step, r(1, 0, 0.2), near if test else None,
                               wide if test else None, r(3, 0, 1.2), surface, r(3, 0, 0.3) * (r(1) > 0.8), (4, 16), 3.0, 4,
                               2.0)
    history = backends.HistoryOp(r(3, 0, 2), r(3, 0, 0.3) * (r(1) > 0.8), r(3, 0, 1.2), surface, r(1, -0.01, 0.3),
                                 r(3, 0, 3), (r(1, 0, 8) + 1).round(), r(1, 0, 6).round(), 4.0, 0.1)
    return change, history


@pytest.mark.parametrize("B, H, W, test", [(2, 7, 13, True), (1, 5, 300, True), (1, 6, 9, False)])
def test_compiled_change_and_history_match_float64_torch_code(B, H, W, test):
    # The C walks of the change test and the output history (float32, 256-pixel blocks: W = 300
    # crosses one) against the torch code of the same ops in float64, on inputs reaching every
    # branch; and the torch code against hand-computed pixels (below).
    from torchgi import backends

    if not _has_c():
        pytest.skip("no C compiler")
    change32, history32 = _change_and_history_ops(B, H, W, test)
    change64, history64 = (dataclasses.replace(op, **{f.name: getattr(op, f.name).double() for f in dataclasses.fields(op)
                                                      if torch.is_tensor(getattr(op, f.name))
                                                      and getattr(op, f.name).is_floating_point()})
                           for op in (change32, history32))  # the same values in float64
    mid = backends.run(change32)
    lit, image = backends.run(history32)
    assert last_backend("change") == "c" and last_backend("history") == "c"
    with backends.use("torch"):
        mid_ref = backends.run(change64)
        refs = backends.run(history64)
    for got, ref in ((mid, mid_ref), (lit, refs[0]), (image, refs[1])):  # (values up to ~5; moments' cancellation)
        assert got.dtype == torch.float32 and got.shape == ref.shape
        assert float(((got.double() - ref).abs() / (ref.abs() + 1e-2)).max()) < 1e-5
    if test:  # the inputs reach every branch of the drop
        drop = (mid_ref[:, 5:6] - change64.step[:, 8:9]) / (1 - change64.step[:, 8:9])
        assert float((mid_ref[:, 5:6] == 1).double().mean()) > 0.05 and float((mid_ref[:, 5:6] == change64.step[:, 8:9]).double().mean()) > 0.05
        assert bool(((drop > 0.01) & (drop < 0.99)).any())


def test_change_and_history_by_hand():
    # One pixel of each op, computed by hand (the torch code; the C walks are held to it above).
    from torchgi import backends
    from torchgi.backends import torch_code

    z = lambda c: torch.zeros(1, c, 1, 1, dtype=torch.float64)
    # light 2 accumulated over 4 frames (length 4, history 3), this frame 6: the luminance moved by
    # 0.5 in a 1-pixel window whose noise sigma is sqrt(0.01 / 1) = 0.1: 5 sigmas, beyond 3 + 1: a full drop
    step = torch.cat([z(3) + 2, z(3), z(1) + 2, z(1) + 5, z(1) + 4, z(1) + 3, z(1), z(1) + 4, z(1) + 6], 1)
    boxed = torch.cat([z(1) + 1.0, z(1) + 0.5, z(1) + 0.01], 1)
    op = backends.ChangeOp(z(3) + 6, z(1) + 100, step, z(1) + 0.02, boxed, z(3), z(3) + 0.5, z(1) == 0, z(3) + 1,
                           (0, 0), 3.0, 4)
    mid = torch_code.change(op)[0, :, 0, 0].tolist()
    # dropped: the light is the frame's (6), moments (6, 36), length 1, frames 1, so the spatial
    # variance 0.02 / 1 frame; colour 6 x 0.5 + 1 = 4
    assert mid == [6, 6, 6, 6, 36, 1, 1, 0.02, 4, 4, 4]
    # 2.5 sigmas: beyond 3 - 0.5 (no drop); with two windows, the larger drop counts: 0.5 of 4 sigmas
    near, wide = (torch.tensor([1.0, v, 0.01], dtype=torch.float64).view(1, 3, 1, 1) for v in (0.75, 0.65))
    op = backends.ChangeOp(z(3) + 6, z(1) + 100, step, z(1) + 0.02, near, wide, z(3) + 0.5, z(1) == 0, z(3), (0, 0),
                           3.0, 4)
    mid = torch_code.change(op)[0, :, 0, 0].tolist()
    assert abs(mid[0] - (2 + 0.5 * 4)) < 1e-12 and abs(mid[5] - (4 - 0.5 * 3)) < 1e-12
    # below the drop the history follows: a change of 0.1 = 1 sigma in the near window, gain
    # 0.1² / (0.1² + 3² x 0.01) = 0.1 with follow 3: scale 1 + 0.1 x 0.1 / 0.5 = 1.02 (no change in
    # the wide window: 1): light 2.04, moments (2 x 1.02, 5 x 1.02²), length and frames 4, the
    # moments' variance 5.202 - 2.04² = 1.0404 over 4 frames, colour 2.04 x 0.5
    near, wide = (torch.tensor([v, 0.5, 0.01], dtype=torch.float64).view(1, 3, 1, 1) for v in (0.6, 0.5))
    op = backends.ChangeOp(z(3) + 6, z(1) + 100, step, z(1) + 0.02, near, wide, z(3) + 0.5, z(1) == 0, z(3), (0, 0),
                           3.0, 4, 3.0)
    mid = torch_code.change(op)[0, :, 0, 0].tolist()
    expected = [2.04, 2.04, 2.04, 2.04, 5.202, 4, 4, 1.0404 / 4, 1.02, 1.02, 1.02]
    assert max(abs(a - b) for a, b in zip(mid, expected)) < 1e-12
    # the output history: lit (1 - 0) / 0.5 = 2, history 3 clamped to 2 + sqrt(4 x 0.25) = 3,
    # weight max(1 / 2, 0.1): 2.5, remodulated 1.25; no history (length 0): the frame's light
    lit, image = torch_code.history(backends.HistoryOp(z(3) + 1, z(3), z(3) + 0.5, z(1) == 0, z(1) + 0.25, z(3) + 3,
                                                       z(1) + 2, z(1) + 1, 4.0, 0.1))
    assert lit.flatten().tolist() == [2.5] * 3 and image.flatten().tolist() == [1.25] * 3
    lit, _ = torch_code.history(backends.HistoryOp(z(3) + 1, z(3), z(3) + 0.5, z(1) == 0, z(1) + 0.25, z(3) + 3,
                                                   z(1) + 2, z(1), 4.0, 0.1))
    assert lit.flatten().tolist() == [2.0] * 3
