"""Procedural scenes (``torchgi.scenes.procedural``) and solid albedo textures: the same scene
for a seed everywhere, none equal to a tuning or judged scene, textures evaluated identically by
the torch and C tracers and as a numpy reference computes them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchgi
from tests.helpers import scene_fingerprint
from tests.render.test_scene_sets import MITSUBA_CORNELL, load, read_sets
from torchgi import backends
from torchgi.core.errors import ConfigError
from torchgi.render import scenes
from torchgi.render.scene import MATERIALS, Camera, Mesh, Scene, Sky
from torchgi.render.textures import Texture, lattice_hash, texture_weight
from torchgi.render.tiles import guide_rays_op


def _hash_np(i, j, k) -> np.ndarray:
    """tracer.c's lattice hash in numpy uint32 arithmetic (the reference of the torch one)."""
    with np.errstate(over="ignore"):
        u = lambda v: np.asarray(v, np.int64).astype(np.uint32)
        h = (u(i) * np.uint32(0x8DA6B343)) ^ (u(j) * np.uint32(0xD8163841)) ^ (u(k) * np.uint32(0xCB1AB31F))
        h ^= h >> np.uint32(16)
        h *= np.uint32(0x7FEB352D)
        h ^= h >> np.uint32(15)
        h *= np.uint32(0x846CA68B)
        h ^= h >> np.uint32(16)
    return (h >> np.uint32(8)).astype(np.float64) / 16777216.0


def _weight_np(code: int, q: np.ndarray) -> np.ndarray:
    """Texture.__doc__'s patterns at scaled points ``q (N, 3)`` in float64."""
    f = np.floor(q)
    c = f.astype(np.int64)
    if code == 1:
        return ((c.sum(1)) & 1).astype(np.float64)
    if code == 2:
        return (np.floor(q[:, 0] + q[:, 2]).astype(np.int64) & 1).astype(np.float64)
    w = (q - f) ** 2 * (3 - 2 * (q - f))
    out = np.zeros(len(q))
    for corner in range(8):
        d = [(corner >> a) & 1 for a in range(3)]
        weight = np.prod([w[:, a] if d[a] else 1 - w[:, a] for a in range(3)], axis=0)
        out += weight * _hash_np(c[:, 0] + d[0], c[:, 1] + d[1], c[:, 2] + d[2])
    return out


def test_lattice_hash_matches_uint32_arithmetic_including_negative_cells():
    rng = np.random.default_rng(0)
    ijk = rng.integers(-(2**20), 2**20, size=(3, 1000))
    ours = lattice_hash(*(torch.from_numpy(v) for v in ijk)).double().numpy()
    np.testing.assert_array_equal(ours, _hash_np(*ijk).astype(np.float32))
    assert 0.4 < ours.mean() < 0.6 and ours.min() >= 0 and ours.max() < 1


@pytest.mark.parametrize("code", [1, 2, 3])
def test_texture_weight_matches_the_float64_reference(code):
    rng = np.random.default_rng(code)
    q = rng.uniform(-20, 20, size=(5000, 3)).astype(np.float32)
    ours = texture_weight(torch.full((5000,), code), torch.from_numpy(q.T.copy())).double().numpy()
    np.testing.assert_allclose(ours, _weight_np(code, q.astype(np.float64)), atol=2e-6)


def test_checker_stripes_and_noise_by_hand():
    p = torch.tensor([[0.5, 1.5, 0.5, 0.0], [0.5, 0.5, 0.5, 0.0], [0.5, 0.5, 1.5, 0.0]])
    assert texture_weight(torch.ones(4, dtype=torch.long), p).tolist() == [0.0, 1.0, 1.0, 0.0]  # cell sums 0, 1, 1, 0
    assert texture_weight(torch.full((4,), 2), p).tolist() == [1.0, 0.0, 0.0, 0.0]  # floor(x + z): 1, 2, 2, 0
    lattice = torch.tensor([[3.0], [-2.0], [7.0]])  # at a lattice point the noise is that point's value
    expected = float(lattice_hash(*(torch.tensor([v]) for v in (3, -2, 7))))
    assert float(texture_weight(torch.tensor([3]), lattice)) == pytest.approx(expected, abs=1e-7)
    assert float(texture_weight(torch.tensor([0]), p[:, :1])) == 0.0


def _checker_plane(size: int, kind: str = "checker") -> Scene:
    tex = Texture(kind, (0.1, 0.2, 0.3), 3.0)
    floor = Mesh(np.array([[-2, 0, -2], [-2, 0, 2], [2, 0, 2], [2, 0, -2]], float), np.array([[0, 1, 2], [0, 2, 3]]),
                 MATERIALS.get("diffuse")((0.9, 0.8, 0.7), texture=tex), "floor")
    return Scene(Camera((0.3, 1.5, 1.7), (0.1, 0, 0.2), resolution=(size, size)), [floor], [Sky((1, 1, 1))])


@pytest.mark.parametrize("backend", ["torch", "c"])
@pytest.mark.parametrize("kind", ["checker", "noise"])
def test_albedo_guide_is_the_texture_at_each_hit(backend, kind):
    scene = _checker_plane(24, kind)
    if backend == "c" and backends.select(guide_rays_op(scene.arrays(), scene.camera))[0] != "c":
        pytest.skip("no compiled tracer here")
    with backends.use(backend):
        gb = torchgi.render(scene, spp=1, bounces=0, seed=0)
    hit = gb.hit[0, 0].numpy()
    q = gb.position[0].permute(1, 2, 0).numpy()[hit].astype(np.float64) * 3.0
    t = _weight_np(1 if kind == "checker" else 3, q)
    expected = np.array([0.9, 0.8, 0.7]) + t[:, None] * (np.array([0.1, 0.2, 0.3]) - [0.9, 0.8, 0.7])
    albedo = gb.albedo[0].permute(1, 2, 0).numpy()[hit]
    close = np.abs(albedo - expected).max(1) < 1e-4  # a cell edge may fall either side of a rounded position
    assert close.mean() > 0.97, close.mean()
    assert len(np.unique(np.round(albedo[:, 0], 3))) > 1  # the pattern is in the image


def test_compiled_tracer_matches_the_wavefronts_on_a_textured_procedural_scene():
    scene = scenes.procedural(1, 24)
    assert (scene.arrays().texture > 0).any()
    if backends.select(guide_rays_op(scene.arrays(), scene.camera))[0] != "c":
        pytest.skip("no compiled tracer here")
    ours = torchgi.render(scene, spp=4, bounces=2, seed=5)
    with backends.use("torch"):
        ref = torchgi.render(scene, spp=4, bounces=2, seed=5)
    for field in ("direct", "indirect", "albedo"):
        a, b = getattr(ours, field).double(), getattr(ref, field).double()
        assert ((a - b).abs() <= 1e-4 * (1 + b.abs())).double().mean() >= 0.995, field


def test_texture_config_errors_name_the_key():
    with pytest.raises(ConfigError, match="material.texture.type"):
        MATERIALS.build({"type": "diffuse", "texture": {"type": "marble"}})
    with pytest.raises(ConfigError, match="material.texture.scale"):
        MATERIALS.build({"type": "glossy", "texture": {"type": "checker", "scale": 0}})
    with pytest.raises(ConfigError, match="unknown key"):
        MATERIALS.build({"type": "diffuse", "texture": {"type": "checker", "size": 2}})
    m = MATERIALS.build({"type": "glossy", "roughness": 0.3, "texture": {"type": "stripes", "albedo2": 0.5}})
    assert m.texture == Texture("stripes", (0.5, 0.5, 0.5), 1.0) and m.roughness == 0.3


def test_mitsuba_conversion_refuses_a_texture(tmp_path):
    pytest.importorskip("mitsuba")
    from torchgi.render.mitsuba import to_mitsuba

    with pytest.raises(ConfigError, match="texture"):
        to_mitsuba(_checker_plane(8), tmp_path)
    assert "mesh_0" in to_mitsuba(scenes.procedural(1, 8, textures=False), tmp_path / "plain")


def test_a_seed_is_one_scene_and_seeds_differ():
    a, b = scenes.procedural(7, 16), scenes.procedural(7, 16)
    assert a.arrays().key == b.arrays().key and a.camera == b.camera
    assert scenes.procedural(8, 16).arrays().key != a.arrays().key
    plain = scenes.procedural(7, 16, textures=False)
    assert np.array_equal(plain.arrays().triangles, a.arrays().triangles) and not (plain.arrays().texture > 0).any()
    assert torchgi.load_scene("procedural:7").arrays().key == scenes.procedural(7).arrays().key
    with pytest.raises(ConfigError, match="procedural:<seed>"):
        torchgi.load_scene("procedural:x")


def test_the_draw_has_the_variety_it_promises():
    drawn = [scenes.procedural(s, 8) for s in range(40)]
    objects = [sum(1 for m in s.meshes if m.name.split("_")[0] in ("sphere", "box", "slats", "grid", "panel", "mesh"))
               for s in drawn]
    assert min(objects) >= 1 and max(objects) <= 20 and max(objects) >= 15
    codes = set(np.concatenate([s.arrays().texture for s in drawn]).tolist())
    assert codes == {0, 1, 2, 3}
    kinds = {type(li).__name__ for s in drawn for li in s.lights}
    assert kinds == {"PointLight", "Sky"}
    assert any(m.material.emissive for s in drawn for m in s.meshes)
    rough = [m.material.roughness for s in drawn for m in s.meshes if m.material.type == "glossy"]
    assert min(rough) < 0.03 and max(rough) > 0.5
    assert len({round(s.camera.fov) for s in drawn}) > 20


def test_no_procedural_scene_is_a_tuning_or_judged_scene():
    sets = read_sets()
    prints = [scene_fingerprint(load(e)) for name in ("tuning", "judged") for e in sets[name] if e != MITSUBA_CORNELL]
    for seed in [*range(0, 1000, 25), *range(100000, 100048, 8)]:
        camera, geometry = scene_fingerprint(scenes.procedural(seed, 8))
        for cam, geo in prints:
            assert camera != cam and not (geometry & geo), seed
