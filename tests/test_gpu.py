"""The Triton kernel of an À-Trous level (torchgi.filters.gpu) against the float64 oracle: on
CUDA when the device is asked for (``--device cuda``), and on the CPU through Triton's
interpreter (a subprocess with ``TRITON_INTERPRET=1``) where Triton is installed."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.oracles import ATROUS_CASES, atrous_case, atrous_error
from torchgi.filters import atrous, gpu, native


@pytest.mark.parametrize("C", [1, 2, 3])
@pytest.mark.parametrize("case", ATROUS_CASES)
def test_triton_kernel_matches_oracle_on_cuda(device, C, case, monkeypatch):
    if device.type != "cuda":
        pytest.skip("the CUDA run; the CPU checks the same kernel through the interpreter below")
    if gpu.triton is None:
        pytest.skip("no Triton")
    calls = []
    real = gpu.atrous_level
    monkeypatch.setattr(gpu, "atrous_level", lambda *a, **k: calls.append(1) or real(*a, **k))
    c, n, x, kw = atrous_case(C, case)
    out = atrous(c.to(device), n.to(device), x.to(device),
                 **{k: v.to(device) if torch.is_tensor(v) else v for k, v in kw.items()})
    assert len(calls) == 3 and out.device.type == "cuda"
    assert atrous_error(out, c, n, x, kw) < 2e-5  # GPU exp is not correctly rounded


_INTERPRETED = """
import sys, torch
sys.path.insert(0, {root!r})
from tests.oracles import ATROUS_CASES, atrous_case, atrous_error
from torchgi.filters import atrous, gpu
assert gpu.applies(torch.zeros(1)), "interpreter not active"
worst = 0.0
for C, case in [(3, case) for case in ATROUS_CASES] + [(1, "cnx"), (1, "variance"), (2, "c")]:
    c, n, x, kw = atrous_case(C, case)
    worst = max(worst, atrous_error(atrous(c, n, x, **kw), c, n, x, kw))
print(worst)
"""


def test_triton_kernel_matches_oracle_in_the_interpreter():
    pytest.importorskip("triton")
    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, TRITON_INTERPRET="1", TORCHGI_NATIVE="1")
    # the C kernels would take CPU calls first: the interpreted run switches them off by hand
    code = _INTERPRETED.replace("from torchgi.filters import atrous, gpu",
                                "from torchgi.filters import atrous, gpu, native\nnative.library = lambda: None")
    proc = subprocess.run([sys.executable, "-c", code.format(root=root)], capture_output=True, text=True, env=env,
                          cwd=root, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert float(proc.stdout.split()[-1]) < 2e-6


def test_kernels_off_inside_disabled():
    with native.disabled():
        assert not gpu.applies(torch.zeros(1, device="cuda" if torch.cuda.is_available() else "cpu"))
