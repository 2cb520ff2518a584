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
    # each sample filtered on its own: its features do not depend on its batch-mates
    for b in range(2):
        one = FilterFeatures(("atrous", "guided"), radius=3, eps=1e-2, iterations=3)({k: v[b] for k, v in batch.items()})
        for key in ("atrous", "guided"):
            torch.testing.assert_close(out[key][b], one[key])


def test_filter_features_use_the_denoisers_guide_and_sigma_rule():
    """A hand-computed case: positions 0.5 apart along x give a footprint of 0.5, so σ_x = (4 x 0.5)²;
    depth is divided by the sample's own maximum."""
    s = sample("cpu", torch.float32, batch=1)
    x = torch.arange(24.0).expand(1, 1, 20, 24) * 0.5
    s["position"] = torch.cat([x, 0 * x, 0 * x], 1)
    out = FilterFeatures(("atrous", "guided"), radius=3, eps=1e-2, iterations=3)(s)
    torch.testing.assert_close(out["atrous"], atrous(s["color"], s["normal"], s["position"], iterations=3,
                                                     sigma_position=4.0))
    guide = torch.cat([(s["normal"] + 1) / 2, s["depth"] / s["depth"].amax()], 1)
    torch.testing.assert_close(out["guided"], guided(s["color"], guide, radius=3, eps=1e-2))


def test_filter_features_single_sample_equals_batch_of_one(device):
    s = sample(device, torch.float32)
    single = FilterFeatures(("guided",), radius=2)(s)["guided"]
    batched = FilterFeatures(("guided",), radius=2)({k: v[None] for k, v in s.items()})["guided"][0]
    torch.testing.assert_close(single, batched)
