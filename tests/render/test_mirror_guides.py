"""render(mirror_guides=...): the albedo and normal of the first non-specular hit behind a mirror,
checked on a hand-built scene whose answer is known by construction: a camera looks straight
down at a mirror floor (y = 0) under a coloured ceiling (y = 2, facing down)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchgi
from torchgi.core import RangeError
from torchgi.render.scene import MATERIALS, Camera, Mesh, Scene, Sky

pytest.importorskip("embreex", reason="the render extra is not installed")


def quad(y: float, size: float, up: bool) -> tuple[np.ndarray, np.ndarray]:
    s = size
    v = np.array([[-s, y, -s], [s, y, -s], [s, y, s], [-s, y, s]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 3, 2]]) if up else np.array([[0, 1, 2], [0, 2, 3]])
    return v, f


def mirror_room(floor_roughness: float, ceiling: bool = True) -> Scene:
    """A 2 x 2 mirror floor under a 40 x 40 ceiling of albedo (0.2, 0.4, 0.6); the camera at
    y = 1 looks down with a narrow field of view, so every pixel sees the floor."""
    meshes = [Mesh(*quad(0.0, 1.0, True), MATERIALS.build({"type": "glossy", "albedo": [0.9, 0.9, 0.9],
                                                           "roughness": floor_roughness}), name="floor")]
    if ceiling:
        meshes.append(Mesh(*quad(2.0, 20.0, False), MATERIALS.build({"type": "diffuse", "albedo": [0.2, 0.4, 0.6]}),
                           name="ceiling"))
    camera = Camera((0.0, 1.0, 0.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, -1.0), fov=20.0, resolution=(8, 8))
    return Scene(camera, meshes, [Sky((1.0, 1.0, 1.0))])


def test_a_mirror_shows_the_guides_of_what_it_reflects():
    """Floor roughness 0.01 < 0.05: every pixel's albedo is the ceiling's and its normal faces the
    reflected ray (down, -y); the first hit's guides without the flag: the floor's albedo, normal
    +y. Depth and position stay the floor's."""
    scene = mirror_room(0.01)
    first = torchgi.render(scene, spp=1, bounces=0)
    behind = torchgi.render(scene, spp=1, bounces=0, mirror_guides=0.05)
    assert torch.allclose(first.albedo, torch.tensor([0.9, 0.9, 0.9]).view(1, 3, 1, 1).expand_as(first.albedo))
    assert torch.allclose(first.normal[:, 1], torch.ones(1, 8, 8))
    assert torch.allclose(behind.albedo, torch.tensor([0.2, 0.4, 0.6]).view(1, 3, 1, 1).expand_as(behind.albedo))
    assert torch.allclose(behind.normal[:, 1], -torch.ones(1, 8, 8), atol=1e-6)
    assert torch.equal(behind.depth, first.depth) and torch.equal(behind.position, first.position)


def test_rough_surfaces_and_mirrors_of_the_background_keep_their_own_guides():
    """A floor of roughness 0.3 is not a mirror at 0.05; a mirror that shows only the sky keeps
    the mirror's own albedo and normal."""
    rough = mirror_room(0.3)
    assert torch.equal(torchgi.render(rough, spp=1, bounces=0, mirror_guides=0.05).albedo,
                       torchgi.render(rough, spp=1, bounces=0).albedo)
    open_sky = mirror_room(0.01, ceiling=False)
    g = torchgi.render(open_sky, spp=1, bounces=0, mirror_guides=0.05)
    assert torch.allclose(g.albedo, torch.full_like(g.albedo, 0.9))
    assert torch.allclose(g.normal[:, 1], torch.ones(1, 8, 8))


@pytest.mark.parametrize("bad", [0.0, -0.1, 1.5, float("nan"), True, "0.1"])
def test_bad_values_are_refused_by_name(bad):
    with pytest.raises(RangeError, match="mirror_guides"):
        torchgi.render(mirror_room(0.01), spp=1, mirror_guides=bad)
