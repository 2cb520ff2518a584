"""Supersampling with guide rays: the 4-neighbour lookup against a float64 brute force, a hand
case, the composite, and the renderer's guide / eye rays."""

from __future__ import annotations

import pytest
import torch

from torchgi.core import DeviceError, DTypeError, ShapeError
from torchgi.supersample import EyeSamples, composite, distribute


def _random_samples(B: int, S: int, H: int, W: int, seed: int) -> tuple[EyeSamples, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    # few distinct normals and depths, so ties and exact matches occur
    normals = torch.nn.functional.normalize(torch.randn(4, 3, generator=g), dim=1)
    gn = normals[torch.randint(0, 4, (B, H, W), generator=g)].permute(0, 3, 1, 2)
    gd = torch.randint(1, 4, (B, 1, H, W), generator=g).float()
    eye = EyeSamples(
        offset=torch.rand(B, S, 2, H, W, generator=g),
        normal=normals[torch.randint(0, 4, (B, S, H, W), generator=g)].permute(0, 1, 4, 2, 3),
        depth=torch.randint(1, 4, (B, S, 1, H, W), generator=g).float() + 0.5 * torch.rand(B, S, 1, H, W, generator=g),
        albedo=torch.rand(B, S, 3, H, W, generator=g),
        emission=torch.rand(B, S, 3, H, W, generator=g),
        direct=torch.rand(B, S, 3, H, W, generator=g),
    )
    return eye, gn, gd


def _oracle(filtered, gn, gd, eye):
    """Per eye ray, in float64 Python loops: the similarity of docs/design.md, Supersampling, over the 4 guide rays."""
    B, C, H, W = filtered.shape
    S = eye.offset.shape[1]
    out = torch.zeros(B, S, C, H, W, dtype=torch.float64)
    for b in range(B):
        for s in range(S):
            for y in range(H):
                for x in range(W):
                    ox, oy = float(eye.offset[b, s, 0, y, x]), float(eye.offset[b, s, 1, y, x])
                    x0 = x if ox >= 0.5 else x - 1
                    y0 = y if oy >= 0.5 else y - 1
                    cand = [(min(max(yy, 0), H - 1), min(max(xx, 0), W - 1))
                            for yy, xx in ((y0, x0), (y0, x0 + 1), (y0 + 1, x0), (y0 + 1, x0 + 1))]
                    na, da = eye.normal[b, s, :, y, x].double(), float(eye.depth[b, s, 0, y, x])
                    dn = [float(((na - gn[b, :, yy, xx].double()) ** 2).sum()) for yy, xx in cand]
                    dd = [abs(da - float(gd[b, 0, yy, xx])) for yy, xx in cand]
                    sn = [1 - v / max(dn) if max(dn) > 0 else 1.0 for v in dn]
                    sd = [1 - v / max(dd) if max(dd) > 0 else 1.0 for v in dd]
                    score = [a * c for a, c in zip(sn, sd)]
                    best = max(range(4), key=lambda i: (score[i], -i))  # first of the best
                    out[b, s, :, y, x] = filtered[b, :, cand[best][0], cand[best][1]].double()
    return out


def test_distribute_matches_a_brute_force_lookup(device):
    B, S, H, W = 2, 3, 5, 6
    eye, gn, gd = _random_samples(B, S, H, W, seed=1)
    filtered = torch.rand(B, 3, H, W, generator=torch.Generator().manual_seed(2))
    on = EyeSamples(*(getattr(eye, f).to(device) for f in ("offset", "normal", "depth", "albedo", "emission",
                                                           "direct")))
    got = distribute(filtered.to(device), gn.to(device), gd.to(device), on)
    assert got.device.type == device.type
    assert torch.equal(got.cpu().double(), _oracle(filtered, gn, gd, eye))


def test_distribute_picks_the_matching_neighbour():
    H = W = 4
    gn = torch.zeros(1, 3, H, W)
    gn[:, 2] = 1.0  # every guide ray faces +z ...
    gn[0, :, 2, 1] = torch.tensor([1.0, 0.0, 0.0])  # ... but the one below-left of the sample
    gd = torch.ones(1, 1, H, W)
    light = torch.arange(16.0).view(1, 1, H, W)
    eye = EyeSamples(
        offset=torch.full((1, 1, 2, H, W), 0.2),  # up and left of every pixel centre
        normal=torch.tensor([1.0, 0.0, 0.0]).view(1, 1, 3, 1, 1).expand(1, 1, 3, H, W),
        depth=torch.ones(1, 1, 1, H, W), albedo=torch.ones(1, 1, 3, H, W),
        emission=torch.zeros(1, 1, 3, H, W), direct=torch.zeros(1, 1, 3, H, W),
    )
    got = distribute(light, gn, gd, eye)[0, 0, 0]
    # pixel (2, 2): guide rays (1,1), (1,2), (2,1), (2,2) -> (2,1) matches the normal: light 9
    assert float(got[2, 2]) == 9.0
    # pixel (0, 0): all four candidates clamp to (0, 0)
    assert float(got[0, 0]) == 0.0
    # pixel (3, 2): (2,1) is a candidate again, and matches
    assert float(got[3, 2]) == 9.0


def test_composite_is_the_mean_of_the_samples():
    eye, _, _ = _random_samples(1, 2, 3, 3, seed=3)
    own = torch.rand(1, 3, 3, 3)
    alb = torch.rand(1, 3, 3, 3)
    light = torch.rand(1, 3, 3, 3)
    dist = torch.rand(1, 2, 3, 3, 3)
    got = composite(own, alb, light, eye.direct, eye.albedo, dist)
    want = (own + alb * light + eye.direct[:, 0] + eye.albedo[:, 0] * dist[:, 0]
            + eye.direct[:, 1] + eye.albedo[:, 1] * dist[:, 1]) / 3
    torch.testing.assert_close(got, want)


def test_bad_input():
    eye, gn, gd = _random_samples(1, 2, 4, 4, seed=4)
    with pytest.raises(ShapeError, match="guide_depth"):
        distribute(torch.rand(1, 3, 4, 4), gn, gd[..., :3], eye)
    with pytest.raises(ShapeError, match="samples.offset"):
        distribute(torch.rand(1, 3, 5, 4), gn[..., :1, :].expand(1, 3, 5, 4), gd[..., :1, :].expand(1, 1, 5, 4), eye)
    with pytest.raises(ShapeError, match="direct"):
        EyeSamples(eye.offset, eye.normal, eye.depth, eye.albedo, eye.emission, eye.direct[:, :1])
    with pytest.raises(DTypeError, match="depth"):
        EyeSamples(eye.offset, eye.normal, eye.depth.long(), eye.albedo, eye.emission, eye.direct)
    if torch.cuda.is_available():
        with pytest.raises(DeviceError):
            EyeSamples(eye.offset.cuda(), eye.normal, eye.depth, eye.albedo, eye.emission, eye.direct)


def test_render_guide_rays_and_denoiser():
    pytest.importorskip("embreex", reason="the render extra is not installed")
    import torchgi
    from torchgi.denoise import Denoiser
    from torchgi.render import render_guide_rays, render_guides

    scene = torchgi.scenes.cornell(24)
    gb, eye = render_guide_rays(scene, spp=9, bounces=1, seed=5)
    guides = render_guides(scene)
    for name in ("albedo", "normal", "depth", "hit"):
        assert torch.equal(getattr(gb, name), getattr(guides, name))  # the guide rays are the centre rays
    assert eye.offset.shape == (1, 8, 2, 24, 24)
    assert float(eye.offset.min()) >= 0 and float(eye.offset.max()) < 1 and float(eye.offset.std()) > 0.2
    # eye rays are unbiased estimates of direct light: their mean over the image agrees with a
    # 256 spp render's within 3 % (measured 0.2-1 % over 3 seeds; emission, a few light pixels'
    # coverage, varies by 10 %)
    ref = torchgi.render(scene, spp=256, bounces=1, seed=6)
    assert abs(float(eye.direct.mean()) / float(ref.direct.mean()) - 1) < 0.03
    again = render_guide_rays(scene, spp=9, bounces=1, seed=5)
    assert torch.equal(again[0].indirect, gb.indirect) and torch.equal(again[1].direct, eye.direct)
    out = Denoiser("guided").supersample(gb, eye)
    assert out.shape == (1, 3, 24, 24) and torch.isfinite(out).all() and (out >= 0).all()
    # "none", papers' split: the plain mean of the samples' own light plus albedo x raw indirect
    raw = Denoiser("none", filter_direct=False).supersample(gb, eye)
    assert abs(float(raw.mean()) / float(ref.color.mean()) - 1) < 0.1
    with pytest.raises(ShapeError, match="gb.indirect"):
        Denoiser("guided").supersample(gb.replace(indirect=None, color=gb.color), eye)
    for bad in ({"spp": 0}, {"bounces": -1}, {"seed": 1 << 32}, {"integrator": "bdpt"}, {"chunk_size": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            render_guide_rays(scene, **{"spp": 2, **bad})
