"""A clone stands alone: every scene config renders with nothing beside the repository and no
environment variable, and no tracked file points outside the repository."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
import torch

import torchgi

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted(p for p in (ROOT / "configs" / "scenes").rglob("*.yaml") if p.name != "sets.yaml")
# what lies outside a clone: the folder beside the checkout, its data, and the notes kept there
# (cited as "DESIGN.md", "DESIGN §2", "STYLE habit 5"); this file names them, so it is not read
OUTSIDE = re.compile(r"\.\./shared|shared/data|DESIGN\.md|\bDESIGN\b|\bSTYLE\b")


def test_every_scene_config_renders_from_the_package_meshes(monkeypatch):
    """Each ``configs/scenes/**/*.yaml`` (sets.yaml names sets, not a scene) loads with
    TORCHGI_MESHES unset and renders, at 8x8, 1 spp and one bounce, an image that is finite and
    not black; a sequence renders its first two frames (the second moves its camera or meshes)."""
    monkeypatch.delenv("TORCHGI_MESHES", raising=False)
    assert len(CONFIGS) >= 25  # the scene configs of configs/scenes and its sub-folders
    bad = []
    for path in CONFIGS:
        scene = torchgi.load_scene(path).with_resolution(8, 8)
        if "sequences" in path.parts:
            frames = list(torchgi.render_sequence(scene, 2, spp=1, bounces=1, seed=0))
        else:
            frames = [torchgi.render(scene, spp=1, bounces=1, seed=0)]
        for gb in frames:
            if not (torch.isfinite(gb.color).all() and float(gb.color.amax()) > 0 and bool(gb.hit.any())):
                bad.append(str(path.relative_to(ROOT)))
    assert bad == []


def _tracked_text_files() -> list[Path]:
    """The files git tracks in the repository, without binaries (a NUL byte in the first 8 KiB)."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60)
    except (OSError, subprocess.CalledProcessError) as exc:
        pytest.skip(f"not a git checkout ({exc}): no tracked files to read")
    files = [ROOT / name for name in out.stdout.decode().split("\0") if name]
    return [p for p in files if p.is_file() and b"\0" not in p.read_bytes()[:8192]]


def test_no_tracked_file_points_outside_the_repository():
    """A clone has no folder beside it: no tracked text file names one (or the notes kept there;
    the design the project follows is docs/design.md)."""
    files = [p for p in _tracked_text_files() if p != Path(__file__).resolve()]
    assert len(files) > 100  # the package, tests, configs and docs
    found = [f"{p.relative_to(ROOT)}:{i}: {m.group()}" for p in files
             for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1)
             for m in OUTSIDE.finditer(line)]
    assert found == []
