import math

import numpy as np
import pytest
import torch

from torchgi import metrics
from torchgi.core import NonFiniteError, OptionError, ShapeError

skm = pytest.importorskip("skimage.metrics")


def pair(B=3, C=3, H=24, W=20, seed=0):
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(B, C, H, W, generator=g, dtype=torch.float64) * 4
    x = (ref + 0.3 * torch.randn(B, C, H, W, generator=g, dtype=torch.float64)).clamp_min(0)
    return x, ref


def test_mse_relmse_against_numpy(dtype):
    x, ref = pair()
    xn, rn = x.numpy(), ref.numpy()
    want_mse = ((xn - rn) ** 2).reshape(3, -1).mean(1)
    want_rel = ((xn - rn) ** 2 / (rn**2 + 0.01)).reshape(3, -1).mean(1)
    rtol = 1e-2 if dtype in (torch.float16, torch.bfloat16) else 1e-5
    got = metrics.mse(x.to(dtype), ref.to(dtype), reduction="none").double().numpy()
    np.testing.assert_allclose(got, want_mse, rtol=rtol)
    np.testing.assert_allclose(metrics.relmse(x.to(dtype), ref.to(dtype), reduction="none").double().numpy(),
                               want_rel, rtol=rtol)
    np.testing.assert_allclose(float(metrics.mse(x, ref)), want_mse.mean(), rtol=1e-12)


def test_psnr_against_skimage():
    x, ref = pair()
    want = [skm.peak_signal_noise_ratio(ref[i].numpy(), x[i].numpy(), data_range=4.0) for i in range(3)]
    np.testing.assert_allclose(metrics.psnr(x, ref, data_range=4.0, reduction="none").numpy(), want, rtol=1e-10)
    tx, tr = x / (1 + x), ref / (1 + ref)
    want = [skm.peak_signal_noise_ratio(tr[i].numpy(), tx[i].numpy(), data_range=1.0) for i in range(3)]
    np.testing.assert_allclose(metrics.psnr(x, ref, tonemap_method="reinhard", reduction="none").numpy(), want,
                               rtol=1e-10)
    with pytest.raises(ValueError, match="data_range: required"):
        metrics.psnr(x, ref)


def test_ssim_against_skimage():
    x, ref = pair()
    x, ref = x / (1 + x), ref / (1 + ref)
    want = [
        skm.structural_similarity(ref[i].permute(1, 2, 0).numpy(), x[i].permute(1, 2, 0).numpy(), data_range=1.0,
                                  gaussian_weights=True, sigma=1.5, use_sample_covariance=False, channel_axis=2)
        for i in range(3)
    ]
    np.testing.assert_allclose(metrics.ssim(x, ref, data_range=1.0, reduction="none").numpy(), want, rtol=1e-6)


def test_flip_orders_errors():
    pytest.importorskip("flip_evaluator")
    x, ref = pair(B=1, H=32, W=32)
    small = ref + 0.05 * (x - ref)
    assert float(metrics.flip(ref.float(), ref.float())) == 0.0
    f_small, f_big = float(metrics.flip(small.float(), ref.float())), float(metrics.flip(x.float(), ref.float()))
    assert 0 < f_small < f_big < 1
    with pytest.raises(ValueError, match="x: expected values >= 0.0"):
        metrics.flip(-ref.float(), ref.float())


def test_metric_input_errors():
    x, ref = pair()
    with pytest.raises(ShapeError, match="ref: dimension H"):
        metrics.mse(x, ref[:, :, :10])
    bad = x.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="x: expected finite values, found 1 NaN"):
        metrics.relmse(bad, ref)
    with pytest.raises(OptionError, match="reduction"):
        metrics.mse(x, ref, reduction="sum")
    with pytest.raises(ShapeError, match="window"):
        metrics.ssim(x[:, :, :8, :8], ref[:, :, :8, :8], data_range=1.0)


def test_mse_is_differentiable():
    x, ref = pair(B=1, H=4, W=4)
    x.requires_grad_(True)
    metrics.relmse(x, ref).backward()
    want = 2 * (x.detach() - ref) / (ref**2 + 0.01) / x.numel()
    torch.testing.assert_close(x.grad, want)


def test_temporal_metrics_hand_computed():
    ref = torch.ones(3, 1, 1, 1, 2)
    x = ref.clone()
    x[1, ..., 0] = 1.5  # the output flickers up by 0.5 in one of two pixels, then back
    tm = metrics.temporal(x, ref)
    # differences +0.5, -0.5 in one pixel of two over two steps, rMAE |d| / 0.01
    assert tm["trmae"] == pytest.approx(0.5 * 0.5 / 0.01)
    d = 1.5 / 2.5 - 0.5  # Reinhard of 1.5 minus Reinhard of 1
    assert tm["tpsnr"] == pytest.approx(10 * math.log10(1 / (d * d / 2)))
    assert metrics.temporal(x, ref, warmup=1)["trmae"] == pytest.approx(0.5 * 0.5 / 0.01)
    with pytest.raises(ValueError, match="warmup"):
        metrics.temporal(x, ref, warmup=2)
