"""The methods registry and per-instance settings: a new method is one class and one
registration; each Denoiser instance reads its own settings, checked on construction."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

import torchgi
from torchgi import light, methods
from torchgi.denoise import Denoiser
from torchgi.filters import box
from torchgi.settings import DEFAULTS, Settings


@pytest.fixture(scope="module")
def gb():
    return torchgi.render(torchgi.scenes.cornell(32), spp=1, bounces=1, seed=4)


def test_a_new_method_is_one_class_and_one_registration(gb):
    """A method that halves the light: the Denoiser runs the shared pipeline around it, which by
    hand is ``light.restore`` with that filter (1 spp: no back-off)."""

    class Halve(methods.Method):
        name = "halve-test"

        def filter(self, x, gb, surface, raw=None, *, workspace=None):
            return x / 2, None

    methods.register(Halve)
    try:
        assert "halve-test" in methods.names() and "halve-test" not in methods.names(exportable=True)
        out = Denoiser("halve-test")(gb)
        surface = light.surface_mask(gb.hit, gb.albedo)
        want = light.restore(gb.color, gb.emission, None, gb.albedo, surface, lambda x: x / 2, 4.0, box)
        assert torch.equal(out, want)
        with pytest.raises(ValueError, match="already registered"):
            methods.register(Halve)
        with pytest.raises(ValueError, match="only .* deploy"):
            Denoiser("halve-test").deploy()
    finally:
        methods._REGISTRY.pop("halve-test")
    with pytest.raises(ValueError, match="method"):
        Denoiser("halve-test")
    with pytest.raises(TypeError, match="method"):
        methods.register(int)


def test_the_registry_says_what_each_method_is():
    assert methods.names() == ("pyramid", "blend", "kpn", "guided", "atrous", "bilateral", "none")
    assert methods.names(learned=True) == ("pyramid", "blend", "kpn")
    assert methods.names(temporal=True) == ("pyramid", "blend", "guided")
    assert methods.names(tiles=True) == ("pyramid", "kpn", "guided")
    assert {n: methods.get(n).needs for n in methods.names() if methods.get(n).needs} == {
        "pyramid": ("depth",), "blend": ("depth",), "kpn": ("depth",), "atrous": ("position",)}
    assert [methods.get(n).firefly() for n in methods.names()] == [4.0, 4.0, 4.0, 4.0, 2.0, 2.0, 4.0]


def test_settings_are_per_instance(gb):
    """A lower firefly bound changes this instance's output and no other's; the defaults given
    explicitly change nothing (bit for bit)."""
    four = torchgi.render(torchgi.scenes.cornell(32), spp=4, bounces=1, seed=4)
    low = DEFAULTS.replace(guided={"firefly": 1.5})
    for method in ("guided", "pyramid"):
        default = Denoiser(method)(four)
        assert torch.equal(Denoiser(method, settings=DEFAULTS)(four), default)
        changed = Denoiser(method, settings=low)(four)
        assert not torch.equal(changed, default)
        assert torch.equal(Denoiser(method)(four), default)
    assert "settings={'guided.firefly': 1.5}" in repr(Denoiser(settings=low))
    assert "settings" not in repr(Denoiser())
    assert Denoiser(settings=low).deploy(spp=1).firefly == 1.5


def test_the_back_off_switch_is_a_setting():
    """pipeline.back_off=False: no back-off, no choice among radii, in the eager and deployed forms."""
    gb = torchgi.render(torchgi.scenes.cornell(32), spp=4, bounces=1, seed=4)
    off = DEFAULTS.replace(pipeline={"back_off": False})
    plain = Denoiser("guided", radius=Denoiser("guided").deploy(frame=gb).params["radius"])
    assert torch.equal(Denoiser("guided", settings=off)(gb), plain(gb.replace(variance=None)))
    assert "radii" not in Denoiser("guided", settings=off).deploy(frame=gb).params
    assert not Denoiser("guided", settings=off).deploy(frame=gb).variance


@pytest.mark.parametrize("change, error", [
    ({"guided": {"radius": 0}}, ValueError), ({"guided": {"radius": 2.5}}, TypeError),
    ({"guided": {"eps": math.nan}}, ValueError), ({"temporal": {"alpha": 1.5}}, ValueError),
    ({"atrous": {"max_iterations": True}}, TypeError), ({"pipeline": {"back_off": 1}}, TypeError),
    ({"pipeline": {"light": 4.0}}, ValueError), ({"guided": {"choose_noise": 1.0}}, ValueError),
    ({"guided": {"radiuss": 3}}, TypeError), ({"colour": {}}, TypeError),
])
def test_bad_settings_are_refused_by_name(change, error):
    group, fields = next(iter(change.items()))
    with pytest.raises(error, match=f"{group}|{next(iter(fields), group)}"):
        DEFAULTS.replace(**change)


def test_settings_are_frozen_and_typed():
    with pytest.raises(dataclasses.FrozenInstanceError):
        DEFAULTS.guided = DEFAULTS.guided
    with pytest.raises(TypeError, match="settings"):
        Denoiser(settings={"guided": {}})
    with pytest.raises(TypeError, match="settings.guided"):
        Settings(guided=DEFAULTS.atrous)
    assert DEFAULTS.replace(temporal={"follow": 0.0}).changes() == {"temporal.follow": 0.0}


class _Blur(methods.Method):
    """A toy method registered by a test: a 3x3 box blur of the light, exportable and usable by
    the TemporalDenoiser, with a parameter of its own there."""

    name = "toy-blur"
    params = ("radius",)
    temporal = exportable = True

    @classmethod
    def temporal_params(cls, temporal):
        return {"radius": 2}

    def filter(self, x, gb, surface, raw=None, *, workspace=None):
        return box(x, self.params.get("radius", 1)), None

    def deploy(self, spp, samples, frame, variance, sigma_position):
        return {"radius": self.params.get("radius", 1), "samples": samples or spp}, None

    @staticmethod
    def deployed_filter(params, net, x, normal, geometry, radius=None, raw=None):
        return box(x, params["radius"])


@pytest.fixture
def toy_method():
    methods.register(_Blur)
    yield _Blur
    methods._REGISTRY.pop(_Blur.name)


def test_a_method_registered_later_is_seen_by_every_consumer(toy_method, tmp_path, capsys):
    """Issue 68: ``METHODS``, ``EXPORTABLE``, ``DENOISERS`` and ``temporal.SPATIAL`` were copies
    made at import, so a method registered later was found by ``Denoiser(name)`` only. Every
    consumer now asks the registry when it runs: the Denoiser, ``from_config``, the CLI's
    choices, ``deploy`` and the TemporalDenoiser (with the method's own ``temporal_params``)."""
    from torchgi.cli import build_parser
    from torchgi.temporal import TemporalDenoiser

    g = torch.Generator().manual_seed(0)
    c, a, n, d = (torch.rand(1, k, 12, 10, generator=g) for k in (3, 3, 3, 1))
    n = n * 2 - 1
    eager = Denoiser("toy-blur")(color=c, albedo=a, normal=n, depth=d)
    assert not torch.equal(eager, Denoiser("none")(color=c, albedo=a, normal=n, depth=d))
    assert torch.equal(Denoiser.from_config({"type": "toy-blur"})(color=c, albedo=a, normal=n, depth=d), eager)
    args = build_parser().parse_args(["denoise", "x.exr", "--method", "toy-blur", "--out", "y.exr"])
    assert args.method == "toy-blur"
    deployed = Denoiser("toy-blur").deploy(spp=1)
    assert deployed.params["radius"] == 1 and deployed(c, torch.zeros_like(c), a, n, d).shape == c.shape
    temporal = TemporalDenoiser(spatial="toy-blur")
    assert temporal.spatial.method == "toy-blur" and temporal.spatial.filter_params == {"radius": 2}
