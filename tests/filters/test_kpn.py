"""The multi-resolution kernel-predicting network (torchgi/filters/kpn.py) against hand-computed
cases and a float64 brute force: its features, an output that can be the input, the kernels it
applies and its gradients."""

import math

import numpy as np
import pytest
import torch

from torchgi.filters.kpn import FEATURES, KPNet, kpn_denoise, kpn_features


def set_heads(net: KPNet, full: str, coarse: str = "centre", composite: float = -40.0) -> KPNet:
    """Heads with zero weights and chosen biases: ``full``/``coarse`` kernels "centre" (one tap)
    or "uniform"; ``composite`` the compositor weights' logit (-40: the finer scale alone)."""
    def logits(taps: int, kind: str) -> torch.Tensor:
        b = torch.zeros(taps, dtype=torch.float64)
        if kind == "centre":
            b[taps // 2] = 40.0
        return b

    with torch.no_grad():
        for head in (net.head1, net.head2, net.head3):
            head.weight.zero_()
        net.head1.bias.copy_(torch.cat([logits(9, full).repeat_interleave(4), logits(25, coarse),
                                        torch.full((2,), composite, dtype=torch.float64)]))
        net.head2.bias.copy_(torch.cat([logits(25, coarse), torch.full((1,), composite, dtype=torch.float64)]))
        net.head3.bias.copy_(torch.cat([logits(25, coarse), torch.zeros(1, dtype=torch.float64)]))
    return net


def inputs(seed: int = 0, size: int = 32, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    color = torch.rand(2, 3, size, size, generator=g, dtype=dtype) * 4
    albedo = torch.rand(2, 3, size, size, generator=g, dtype=dtype) * 0.9 + 0.05
    normal = torch.nn.functional.normalize(torch.randn(2, 3, size, size, generator=g, dtype=dtype), dim=1)
    depth = torch.rand(2, 1, size, size, generator=g, dtype=dtype) + 1
    emission = torch.zeros(2, 3, size, size, dtype=dtype)
    variance = torch.rand(2, 3, size, size, generator=g, dtype=dtype)
    return kpn_features(color, albedo, normal, depth, emission, variance, torch.tensor([1.0, 16.0], dtype=dtype))


def test_features_by_hand():
    color = torch.full((1, 3, 2, 2), 0.5, dtype=torch.float64)
    albedo = torch.full((1, 3, 2, 2), 0.5, dtype=torch.float64)
    albedo[..., 0, 0] = 0.01  # under the floor: filtered as colour
    emission = torch.full((1, 3, 2, 2), 0.1, dtype=torch.float64)
    depth = torch.tensor([[[[1.0, math.e], [0.0, 1.0]]]], dtype=torch.float64)  # one miss
    f, irr, alb = kpn_features(color, albedo, torch.zeros_like(color), depth, emission, None, 4.0)
    assert f.shape == (1, FEATURES, 2, 2) and f.dtype == torch.float64
    assert irr[0, 0, 0, 0].item() == pytest.approx(0.4) and irr[0, 0, 0, 1].item() == pytest.approx(0.8)
    assert alb[0, :, 0, 0].tolist() == [1.0, 1.0, 1.0]
    assert f[0, 0, 0, 1].item() == pytest.approx(math.log1p(0.8))
    assert f[0, 3].sum().item() == 0  # no variance given: 0
    assert f[0, 4].unique().item() == pytest.approx(2 / 6)  # log2(4) / 6
    # log depth less its mean over the hits (0, 1, 0 -> mean 1/3); a miss is 0
    assert f[0, 11].flatten().tolist() == pytest.approx([-1 / 3, 2 / 3, 0.0, -1 / 3])
    assert f[0, 12, 0, 0].item() == pytest.approx(math.log1p(0.1))


def test_output_can_be_the_input():
    f, irr, _ = inputs()
    for composite in (-40.0, 40.0):  # the compositor at either end: coarse scales replace nothing
        net = set_heads(KPNet((8, 8, 8)).double(), "centre", "centre", composite)
        out = kpn_denoise(net, f, irr).detach()
        assert out.dtype == torch.float64
        torch.testing.assert_close(out, irr, rtol=1e-9, atol=1e-12)


def brute_box3(x: np.ndarray) -> np.ndarray:
    """The 3x3 mean over the taps inside the image, by loops in float64."""
    H, W = x.shape[2:]
    out = np.zeros_like(x)
    for i in range(H):
        for j in range(W):
            win = x[:, :, max(i - 1, 0):i + 2, max(j - 1, 0):j + 2]
            out[:, :, i, j] = win.mean((2, 3))
    return out


def test_full_scale_kernels_against_brute_force():
    f, irr, _ = inputs(1)
    net = set_heads(KPNet((8, 8, 8)).double(), "uniform", "centre", -40.0)
    out = kpn_denoise(net, f, irr).detach()
    np.testing.assert_allclose(out.numpy(), brute_box3(irr.numpy()), rtol=1e-9, atol=1e-12)


def test_compositor_against_its_formula():
    """a = 1 everywhere, box kernels at 1/2 and centre taps elsewhere: coarse to fine,
    f_s + a (up(f_{s+1}) - up(down f_s)) with f_1 the 5x5 mean (brute force) of down(x), so the
    output is x + up(f_1 + up(down down x) - up(down f_1)) - up(down x)."""
    f, irr, _ = inputs(2)
    net = set_heads(KPNet((8, 8, 8)).double(), "centre", "centre", 40.0)
    with torch.no_grad():  # 1/2-scale kernels uniform over their 5x5 taps
        net.head1.bias[36:61] = 0.0
    out = kpn_denoise(net, f, irr).detach()

    def down(a):
        return a.reshape(*a.shape[:2], a.shape[2] // 2, 2, a.shape[3] // 2, 2).mean((3, 5))

    def up(a):
        return torch.nn.functional.interpolate(torch.from_numpy(a), scale_factor=2.0, mode="bilinear",
                                               align_corners=False).numpy()

    x = irr.numpy()
    d1 = down(x)
    f1 = np.zeros_like(d1)
    for i in range(d1.shape[2]):
        for j in range(d1.shape[3]):
            f1[:, :, i, j] = d1[:, :, max(i - 2, 0):i + 3, max(j - 2, 0):j + 3].mean((2, 3))
    ref = x + up(f1 + up(down(d1)) - up(down(f1))) - up(d1)
    np.testing.assert_allclose(out.numpy(), ref, rtol=1e-9, atol=1e-12)


def test_gradients_against_finite_differences():
    torch.manual_seed(0)
    f, irr, _ = inputs(3, size=16)
    net = KPNet((4, 4, 4)).double()
    irr = irr[:1, :1].clone().requires_grad_(True)
    feats = f[:1].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: kpn_denoise(net, a, b), (feats, irr), eps=1e-6, atol=1e-6,
                                    fast_mode=True)


def test_saved_weights_read_back_bit_for_bit(tmp_path):
    """``SavedNet.save`` writes each weight as its shortest float32 decimal: :meth:`load` must
    give the very same float32 bits (random weights, including sub-normal and huge values)."""
    torch.manual_seed(3)
    net = KPNet()
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn_like(p) * torch.logspace(-40, 30, p.numel()).view_as(p).to(p.dtype))
    net.save(tmp_path / "w.json", {"script": "test"})
    back = KPNet.load(tmp_path / "w.json")
    for (name, a), b in zip(net.state_dict().items(), back.state_dict().values()):
        assert torch.equal(a.view(torch.int32), b.view(torch.int32)), name
    assert back.provenance == {"script": "test"}
