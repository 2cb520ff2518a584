"""Shared fixtures: ``device`` and ``dtype``, and ``meshes_dir`` (the package's meshes).

Choose with ``--device cpu,cuda`` / ``--dtype float32,float16`` or the environment variables
``TORCHGI_TEST_DEVICE`` / ``TORCHGI_TEST_DTYPE`` (comma-separated). Defaults: cpu; float32,
float16 and bfloat16 (the dtype-keeping tests are small: half precision runs in every run).
A requested device that is absent is skipped, never silently replaced.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

import torchgi

_DTYPES = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32, "float64": torch.float64}


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", default=os.environ.get("TORCHGI_TEST_DEVICE", "cpu"))
    parser.addoption("--dtype", default=os.environ.get("TORCHGI_TEST_DTYPE", "float32,float16,bfloat16"))


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", metafunc.config.getoption("--device").split(","), indirect=True)
    if "dtype" in metafunc.fixturenames:
        metafunc.parametrize("dtype", metafunc.config.getoption("--dtype").split(","), indirect=True)


@pytest.fixture
def device(request: pytest.FixtureRequest) -> torch.device:
    name = request.param
    if name.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip("CUDA requested but not available")
    return torch.device(name)


@pytest.fixture
def dtype(request: pytest.FixtureRequest) -> torch.dtype:
    if request.param not in _DTYPES:
        raise pytest.UsageError(f"--dtype: unknown {request.param!r}; known: {', '.join(_DTYPES)}")
    return _DTYPES[request.param]


# Tolerances per dtype for comparisons against float64 references (rtol, atol).
TOL = {
    torch.float16: (1e-2, 1e-2),
    torch.bfloat16: (5e-2, 5e-2),
    torch.float32: (1e-5, 1e-6),
    torch.float64: (1e-10, 1e-12),
}


@pytest.fixture
def tol(dtype: torch.dtype) -> tuple[float, float]:
    return TOL[dtype]


# The meshes made by others that ship in the package (torchgi/meshes), the default mesh root of
# scene files' ``mesh:`` entries. Tests read these copies: a TORCHGI_MESHES set outside is dropped
# (a test that needs it sets it with monkeypatch).
MESHES = str(Path(torchgi.__file__).resolve().parent / "meshes")
os.environ.pop("TORCHGI_MESHES", None)


@pytest.fixture(scope="session")
def meshes_dir() -> str:
    """The package's meshes made by others (the Cornell box and the Stanford models)."""
    return MESHES
