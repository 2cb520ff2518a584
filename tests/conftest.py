"""Shared fixtures: ``device`` and ``dtype`` (STYLE habit 5).

Choose with ``--device cpu,cuda`` / ``--dtype float32,float16`` or the environment variables
``TORCHGI_TEST_DEVICE`` / ``TORCHGI_TEST_DTYPE`` (comma-separated). Defaults: cpu, float32.
A requested device that is absent is skipped, never silently replaced.
"""

from __future__ import annotations

import os
import subprocess

import pytest
import torch

_DTYPES = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32, "float64": torch.float64}


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", default=os.environ.get("TORCHGI_TEST_DEVICE", "cpu"))
    parser.addoption("--dtype", default=os.environ.get("TORCHGI_TEST_DTYPE", "float32"))


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


def _find_meshes() -> str | None:
    """The shared mesh folder: :func:`torchgi.render.mesh_root` ($TORCHGI_MESHES, else
    ``shared/data/meshes`` beside the checkout) when it exists, else (a clone made from a local
    checkout) the one beside that checkout."""
    from torchgi.render import mesh_root

    if os.environ.get("TORCHGI_MESHES") or mesh_root().is_dir():
        return str(mesh_root()) if mesh_root().is_dir() else None
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        origin = subprocess.run(["git", "config", "--get", "remote.origin.url"], capture_output=True, text=True,
                                cwd=here, timeout=10, check=False).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    candidate = os.path.join(os.path.dirname(os.path.abspath(origin)), "shared", "data", "meshes") if origin else ""
    return candidate if origin and os.path.isdir(origin) and os.path.isdir(candidate) else None


MESHES = _find_meshes()
if MESHES is not None:  # scene files name their shared meshes relative to this root
    os.environ["TORCHGI_MESHES"] = MESHES
NO_MESHES = "the shared mesh folder is absent: set TORCHGI_MESHES to the folder of the shared meshes"


@pytest.fixture(scope="session")
def meshes_dir() -> str:
    """Real meshes made by others (never copied into the project); skipped when absent."""
    if MESHES is None:
        pytest.skip(NO_MESHES)
    return MESHES
