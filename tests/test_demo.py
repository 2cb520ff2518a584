"""``torchgi demo``: it runs end to end on the extras its help names, reports relMSE, SSIM and FLIP
for every Denoiser method, labels its picture, and never overwrites its files unasked."""

from __future__ import annotations

import argparse
import importlib.metadata as md
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from torchgi import methods
from torchgi.cli import build_parser

pytest.importorskip("embreex")
pytest.importorskip("OpenEXR")
pytest.importorskip("flip_evaluator")

_RUN = """
import json, sys
from torchgi.cli import main
code = main(sys.argv[1:])
names = sorted({m.split(".")[0] for m in sys.modules} - set(sys.stdlib_module_names))
print("MODULES " + json.dumps(names))
sys.exit(code)
"""


def _closure(name: str, extras: set[str]) -> set[str]:
    """The distributions ``name[extras]`` needs, transitively (normalised names), read from the
    installed metadata: an independent account of what an extra brings."""
    norm = lambda n: re.sub(r"[-_.]+", "-", n).lower()
    seen, todo = set(), [(name, frozenset(extras))]
    while todo:
        dist, wanted = todo.pop()
        key = (norm(dist), wanted)
        if key in seen:
            continue
        seen.add(key)
        try:
            requires = md.requires(dist) or []
        except md.PackageNotFoundError:
            continue
        for text in requires:
            req = Requirement(text)
            envs = [{"extra": e} for e in wanted] or [{"extra": ""}]
            if req.marker is None or any(req.marker.evaluate(env) for env in envs):
                todo.append((req.name, frozenset(req.extras)))
    return {d for d, _ in seen}


def _demo(tmp_path: Path, *flags: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _RUN, "demo", "--out", str(tmp_path), "--size", "24",
                           "--ref-spp", "16", *flags], check=False, capture_output=True, text=True, timeout=600)


def test_demo_reports_every_method_on_the_extras_it_names_and_never_overwrites(tmp_path):
    run = _demo(tmp_path)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    header = next(line.split() for line in lines if line.startswith("method"))
    assert header[1:5] == ["relMSE", "SSIM", "FLIP", "ms"]  # not MSE: the light source's pixels carry MSE
    rows = {line.split()[0]: line.split()[1:5] for line in lines if line.split()[:1] and line.split()[0] in
            {"noisy", *methods.names()}}
    assert set(rows) == {"noisy", *methods.names()} - {"none"}  # every method ("none" is the noisy row)
    for method in ("guided", "atrous", "pyramid"):
        assert float(rows[method][0]) < float(rows["noisy"][0])  # relMSE: the filters help
    for method in ("guided", "pyramid"):  # at 24² À-Trous' widest taps blur past the noise in FLIP
        assert float(rows[method][2]) < float(rows["noisy"][2])
    assert (tmp_path / "demo.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "noisy.exr").is_file() and (tmp_path / "reference.exr").is_file()

    # the extra the help names brings every distribution the demo imported
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    help_text = next(a.help for a in sub._choices_actions if a.dest == "demo")
    named = set(re.findall(r"\.\[([a-z,]+)\]", help_text)[0].split(","))
    allowed = _closure("torchgi", named) | {"torchgi"}
    imported = json.loads(next(line for line in lines if line.startswith("MODULES "))[8:])
    dists = md.packages_distributions()
    needed = {re.sub(r"[-_.]+", "-", d).lower() for m in imported for d in dists.get(m, [])}
    assert needed <= allowed, f"the demo imports {sorted(needed - allowed)}, not in torchgi[{','.join(named)}]"

    before = (tmp_path / "demo.png").read_bytes()
    again = _demo(tmp_path)
    assert again.returncode != 0 and "--overwrite" in again.stderr and "demo.png" in again.stderr
    assert (tmp_path / "demo.png").read_bytes() == before
