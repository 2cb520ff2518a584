"""The public surface: names that other code, benchmarks and checks call must stay (the stable API:
docs/architecture.md, "The stable API")."""

import importlib

import pytest

import torchgi

PUBLIC = {
    "torchgi": ["GBuffer", "Denoiser", "TemporalDenoiser", "render", "render_sequence", "render_to", "load_scene", "scenes",
                "__version__"],
    "torchgi.methods": ["Method", "register", "get", "names"],
    "torchgi.settings": ["Settings", "DEFAULTS", "PipelineSettings", "GuidedSettings", "ATrousSettings",
                         "BilateralSettings", "TemporalSettings", "describe"],
    "torchgi.backends": ["use", "status"],
    "torchgi.render": ["render", "render_guides", "load_scene", "scenes", "Scene", "Camera", "Material", "Mesh",
                       "PointLight", "Sky"],
    "torchgi.data": ["run_job", "load_config", "ShardDataset", "FilterFeatures"],
    "torchgi.core": [
        "check_shape", "check_same_device", "check_finite", "check_floating", "check_range",
        "check_option", "require", "Registry", "TorchGIError", "ShapeError", "DeviceError",
        "DTypeError", "NonFiniteError", "LayerError", "ExrError", "ConfigError",
    ],
    "torchgi.io": ["read_exr", "write_exr", "read_aovs", "find_aovs", "write_png"],
    "torchgi.metrics": ["mse", "relmse", "psnr", "ssim", "flip", "tonemap"],
    "torchgi.filters": ["atrous", "ATrous", "guided", "Guided", "box", "Box", "cross_bilateral", "CrossBilateral",
                        "guide_from_gbuffer"],
    "torchgi.sampling": ["importance_map", "allocate", "exclusive_scan", "adaptive_render", "adaptive_counts", "geometry_importance", "merge_rounds"],
    "torchgi.export": ["export_onnx", "export_denoiser", "export_temporal", "OrtSession", "OrtDenoiser"],
    "torchgi.cli": ["main"],
}


@pytest.mark.parametrize("module", sorted(PUBLIC))
def test_public_names(module):
    mod = importlib.import_module(module)
    for name in PUBLIC[module]:
        assert hasattr(mod, name), f"{module}.{name} disappeared"
    exported = mod.__all__
    assert set(PUBLIC[module]) <= set(exported) | {"__version__"}
    for name in exported:
        assert hasattr(mod, name), f"{module}.__all__ lists {name} but it does not exist"


def test_errors_subclass_builtins():
    from torchgi import core

    assert issubclass(core.ShapeError, ValueError)
    assert issubclass(core.DTypeError, TypeError)
    assert issubclass(core.NonFiniteError, ValueError)
    assert issubclass(core.ExtraNotInstalledError, ImportError)
    for err in (core.ShapeError, core.DeviceError, core.LayerError, core.ExrError):
        assert issubclass(err, core.TorchGIError)


def test_version_matches_metadata():
    from importlib.metadata import version

    assert version("torchgi") == torchgi.__version__
