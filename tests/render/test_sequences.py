"""Camera animation and motion vectors (issue 19): camera paths (in Python and in a scene file's
YAML), ``render_sequence`` frames with their own seeds, motion vectors that reproject each pixel's
first hit within 0.05 px (checked by an independent trace), and a sequence frame against Mitsuba 3."""

from __future__ import annotations

import math
import os

import pytest
import torch

import torchgi
from tests.helpers import SEQUENCES, sliding_cornell
from torchgi.core.errors import ConfigError
from torchgi.render import CameraPath, scenes

pytest.importorskip("embreex")


def first_hits(scene, camera, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """World positions ``(3, N)`` where rays of ``camera`` through image points ``(xs, ys)`` (pixels,
    continuous) first hit the scene: an independent trace, not the motion code."""
    from torchgi.render.engine import _context
    from torchgi.render.integrators.common import guides

    W, H = camera.resolution
    px, py = xs.floor().clamp(0, W - 1), ys.floor().clamp(0, H - 1)
    jitter = torch.stack([xs - px, ys - py]).float()
    return guides(_context(scene.arrays(), camera, 0, 0), (py * W + px).long(), jitter)["position"]


# ------------------------------------------------------------------------------ camera paths
def test_camera_path_interpolates_keyframes_and_holds_outside():
    scene = scenes.cornell(8)
    cam = scene.camera
    path = CameraPath((1.0, 3.0), ((0, 0, -5), (4, 2, -5)), ((0, 0, 0), (0, 2, 0)), (40.0, 60.0))
    mid = path.at(cam, 1.5)  # a quarter of the way
    assert mid.position == (1.0, 0.5, -5.0) and mid.look_at == (0.0, 0.5, 0.0) and mid.fov == 45.0
    assert path.at(cam, 0.0).position == (0.0, 0.0, -5.0) and path.at(cam, 9.0).position == (4.0, 2.0, -5.0)
    scene.path = path
    assert scene.times_of(3) == [1.0, 2.0, 3.0] and scene.times_of(1) == [1.0]
    with pytest.raises(ConfigError, match="increase"):
        CameraPath((0.0, 0.0), ((0, 0, 1),) * 2, ((0, 0, 0),) * 2, (40.0, 40.0))


def test_yaml_camera_path(tmp_path, meshes_dir):
    scene = torchgi.load_scene(os.path.join(SEQUENCES, "cornell_slide.yaml"))
    assert scene.path is not None and scene.path.duration == (0.0, 1.0)
    assert scene.camera.position == scene.path.positions[0]  # the base pose defaults to the first keyframe
    bad = tmp_path / "bad.yaml"
    bad.write_text("camera: {path: [{time: 0, position: [0, 0, 1], look_at: [0, 0, 0], speed: 2}]}\n"
                   "meshes: []\n")
    with pytest.raises(ConfigError, match=r"camera.path\[0\].*speed"):
        torchgi.load_scene(bad)


def test_render_sequence_frames_are_renders_of_the_path_with_their_own_seeds():
    from torchgi.render.engine import frame_seed

    scene = sliding_cornell(16)
    gbs = list(torchgi.render_sequence(scene, 3, spp=2, seed=5))
    assert len(gbs) == 3 and not gbs[0].motion.any() and gbs[2].motion.abs().max() > 0.5
    again = torchgi.render(scene.at(1.0), spp=2, seed=frame_seed(5, 2))
    assert torch.equal(gbs[2].color, again.color) and torch.equal(gbs[2].normal, again.normal)
    assert len({frame_seed(5, k) for k in range(100)}) == 100


@pytest.mark.parametrize("scene_fn", [sliding_cornell, scenes.sky])
def test_motion_reprojects_first_hits_within_005_px(scene_fn):
    # Every pixel whose first hit is visible in both frames: the previous camera's ray through
    # pixel + motion meets the same point. Misses (sky): the same direction.
    scene = scene_fn(48)
    if scene.path is None:  # the sky scene: turn and move the camera
        c = scene.camera
        scene.path = CameraPath((0.0, 1.0), (c.position, (c.position[0] + 0.6, c.position[1], c.position[2] - 0.3)),
                                (c.look_at, (c.look_at[0] + 0.5, c.look_at[1] + 0.1, c.look_at[2])), (c.fov, c.fov))
    prev_cam, gb = scene.at(0.0).camera, list(torchgi.render_sequence(scene, 2))[1]
    W = H = 48
    m = gb.motion[0].reshape(2, -1).double()
    xs = (torch.arange(W * H) % W).double() + 0.5 + m[0]
    ys = (torch.arange(W * H) // W).double() + 0.5 + m[1]
    inside = (xs >= 0) & (xs < W) & (ys >= 0) & (ys < H)
    hit = gb.hit.reshape(-1)
    pos = gb.position[0].reshape(3, -1).double()
    found = first_hits(scene, prev_cam, xs, ys).double()
    centre = torch.tensor(prev_cam.position, dtype=torch.float64)[:, None]
    px_size = (pos - centre).norm(dim=0) * 2 * math.tan(math.radians(prev_cam.fov) / 2) / W
    err = (found - pos).norm(dim=0) / px_size  # in pixels of the previous frame
    visible = inside & hit & (err < 1.0)  # hidden in the previous frame: another surface, far away
    assert float(visible.sum()) > 0.8 * float((inside & hit).sum())
    assert float(err[visible].max()) < 0.05
    sky = ~hit & inside
    if sky.any():  # background: the previous camera's ray through pixel + motion has the same direction
        from torchgi.render.camera import camera_rays

        _, now = camera_rays(scene.at(1.0).camera, torch.arange(W * H), None)
        px, py = xs.floor(), ys.floor()
        _, then = camera_rays(prev_cam, (py * W + px).long()[sky], torch.stack([xs - px, ys - py]).float()[:, sky])
        a, b = now[:, sky].double(), then.double()
        angle = torch.atan2(torch.linalg.cross(a, b, dim=0).norm(dim=0), (a * b).sum(0))
        assert float(angle.max() / (2 * math.tan(math.radians(prev_cam.fov) / 2) / W)) < 0.05


@pytest.mark.slow
def test_sequence_frame_matches_mitsuba(meshes_dir):
    pytest.importorskip("mitsuba")
    from tests.oracles import mean_z, z_pass_rate
    from torchgi.render.mitsuba import render_mitsuba

    scene = torchgi.load_scene(os.path.join(SEQUENCES, "cornell_slide.yaml")).with_resolution(40, 40)
    ours = torch.cat([list(torchgi.render_sequence(scene, 2, spp=32, seed=100 + s))[1].color for s in range(10)])
    ref = torch.cat([render_mitsuba(scene.at(1.0), spp=32, bounces=1, seed=s) for s in range(10)])
    assert z_pass_rate(ours, ref) >= 0.975 and mean_z(ours, ref) < 3.5
