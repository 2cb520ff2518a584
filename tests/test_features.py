"""FilterFeatures on any device: batched and single samples agree, outputs follow the input."""

import torch

from torchgi.data import FilterFeatures
from torchgi.filters import atrous, guided


def sample(device, dtype, batch=None, seed=0):
    g = torch.Generator().manual_seed(seed)
    shape = (3, 20, 24) if batch is None else (batch, 3, 20, 24)
    out = {
        "color": torch.rand(shape, generator=g),
        "normal": torch.nn.functional.normalize(torch.randn(shape, generator=g), dim=-3),
        "position": torch.rand(shape, generator=g) * 3,
        "depth": torch.rand(shape[:-3] + (1,) + shape[-2:], generator=g) + 1,
    }
    return {k: v.to(device=device, dtype=dtype) for k, v in out.items()}


def test_filter_features_on_device(device, dtype):
    batch = sample(device, dtype, batch=2)
    out = FilterFeatures(("atrous", "guided"), radius=3, eps=1e-2, iterations=3)(batch)
    for key in ("atrous", "guided"):
        assert out[key].shape == (2, 3, 20, 24) and out[key].device == batch["color"].device
        assert out[key].dtype == dtype and bool(torch.isfinite(out[key]).all())
    # the transform is the library's filters, applied with the documented guides and σ_x
    guide = torch.cat([(batch["normal"] + 1) / 2, batch["depth"] / batch["depth"].amax()], 1)
    torch.testing.assert_close(out["guided"], guided(batch["color"], guide, radius=3, eps=1e-2))
    p = batch["position"]
    sigma = (float((p.amax((0, 2, 3)) - p.amin((0, 2, 3))).max()) / 10) ** 2
    torch.testing.assert_close(out["atrous"], atrous(batch["color"], batch["normal"], p, iterations=3,
                                                     sigma_position=sigma))


def test_filter_features_single_sample_equals_batch_of_one(device):
    s = sample(device, torch.float32)
    single = FilterFeatures(("guided",), radius=2)(s)["guided"]
    batched = FilterFeatures(("guided",), radius=2)({k: v[None] for k, v in s.items()})["guided"][0]
    torch.testing.assert_close(single, batched)
