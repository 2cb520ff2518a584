"""One checklist for every public filter op, as kornia's ``BaseTester``: the Module equals the
function, the input dtype and device are kept, hostile inputs are refused by name, the gradient
matches finite differences (float64). Each op's oracle (float64 brute force) and its ONNX export
are in its own file (``test_<op>.py``, ``tests/test_onnx.py``)."""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable

import pytest
import torch

from torchgi import filters
from torchgi.core import NonFiniteError, ShapeError
from torchgi.filters.blend import default_net as blend_net
from torchgi.filters.pyramid import default_net as pyramid_net


def _inputs(B: int = 1, H: int = 12, W: int = 10, dtype: torch.dtype = torch.float32,
            device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(3)

    def r(c: int) -> torch.Tensor:
        return torch.rand(B, c, H, W, generator=g, dtype=torch.float64).to(dtype=dtype, device=device)

    normal = torch.nn.functional.normalize(r(3) - 0.5, dim=1)
    return {"x": r(3) + 0.1, "guide": r(4), "normal": normal, "position": r(3), "depth": r(1) + 0.5,
            "kernels": r(25) + 0.05}


# name -> (function of the inputs, Module of the inputs, the input the gradient is checked for)
CASES: dict[str, tuple[Callable, Callable, str]] = {
    "box": (lambda t: filters.box(t["x"], 2), lambda t: filters.Box(2)(t["x"]), "x"),
    "guided": (lambda t: filters.guided(t["x"], t["guide"], radius=2, eps=1e-2),
               lambda t: filters.Guided(radius=2, eps=1e-2)(t["x"], t["guide"]), "x"),
    "atrous": (lambda t: filters.atrous(t["x"], t["normal"], t["position"], iterations=2, sigma_color=1.0),
               lambda t: filters.ATrous(2, sigma_color=1.0)(t["x"], t["normal"], t["position"]), "x"),
    "cross_bilateral": (lambda t: filters.cross_bilateral(t["x"], [t["normal"]], radius=2, sigma_space=1.0,
                                                          sigma_color=1.0, sigma_guides=[0.3]),
                        lambda t: filters.CrossBilateral(2, 1.0, 1.0, [0.3])(t["x"], t["normal"]), "x"),
    "apply_kernels": (lambda t: filters.apply_kernels(t["x"], t["kernels"], dilation=2, normalize=True),
                      lambda t: filters.ApplyKernels(2, True)(t["x"], t["kernels"]), "x"),
    "blend": (lambda t: filters.blend(t["x"], t["guide"]), lambda t: filters.Blend()(t["x"], t["guide"]), "x"),
    "pyramid": (lambda t: filters.pyramid(t["x"], t["guide"]), lambda t: filters.Pyramid()(t["x"], t["guide"]), "x"),
}


@pytest.mark.parametrize("op", sorted(CASES))
def test_the_module_equals_the_function(op):
    fn, module, _ = CASES[op]
    t = _inputs()
    assert torch.equal(module(t), fn(t))


@pytest.mark.parametrize("op", sorted(CASES))
@pytest.mark.parametrize("dt", [torch.float32, torch.float64])
def test_dtype_and_device_are_kept(op, dt, device):
    fn, _, _ = CASES[op]
    out = fn(_inputs(dtype=dt, device=device))
    assert out.dtype == dt and out.device.type == device.type and out.shape[-2:] == (12, 10)
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("op", sorted(CASES))
def test_hostile_inputs_are_refused_by_name(op):
    fn, _, name = CASES[op]
    t = _inputs()
    t[name] = t[name].clone()
    t[name][0, 0, 3, 4] = float("nan")
    with pytest.raises(NonFiniteError):
        fn(t)
    t = _inputs()
    t[name] = t[name][0]  # (C, H, W): no batch dimension
    with pytest.raises((ShapeError, ValueError)):
        fn(t)


# the learned ops in float64 need their network in float64 too (its float32 weights round the gradient);
# a copy: default_net() is the one shared network every Denoiser uses
@functools.cache
def _net64(default_net: Callable[[], torch.nn.Module]) -> torch.nn.Module:
    return copy.deepcopy(default_net()).double()


LEARNED64 = {
    "blend": lambda t: filters.blend(t["x"], t["guide"], net=_net64(blend_net)),
    "pyramid": lambda t: filters.pyramid(t["x"], t["guide"], net=_net64(pyramid_net)),
}


@pytest.mark.parametrize("op", sorted(CASES))
def test_the_gradient_matches_finite_differences(op):
    fn, _, name = CASES[op]
    fn = LEARNED64.get(op, fn)
    t = _inputs(H=8, W=9, dtype=torch.float64)
    src = t[name].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: fn({**t, name: v}), (src,), eps=1e-6, atol=1e-5, fast_mode=True)
    assert next(blend_net().parameters()).dtype == next(pyramid_net().parameters()).dtype == torch.float32


# every filter with its default arguments (the required ones only), every differentiable input
DEFAULTS: dict[str, tuple[Callable, list[str]]] = {
    "box": (lambda t: filters.box(t["x"], 2), ["x"]),
    "apply_kernels": (lambda t: filters.apply_kernels(t["x"], t["kernels"]), ["x", "kernels"]),
    "guided": (lambda t: filters.guided(t["x"], t["guide"]), ["x", "guide"]),
    "atrous": (lambda t: filters.atrous(t["x"], t["normal"], t["position"]), ["x", "normal", "position"]),
    "cross_bilateral": (lambda t: filters.cross_bilateral(t["x"], [t["normal"]], radius=2, sigma_space=1.0,
                                                          sigma_color=0.5, sigma_guides=[0.3]), ["x", "normal"]),
    **{k: (v, ["x", "guide"]) for k, v in LEARNED64.items()},
}


@pytest.mark.parametrize("op", sorted(DEFAULTS))
def test_float64_gradcheck_with_default_arguments(op):
    """float64 gradcheck of each filter with its defaults (the bilateral has none: it is given its
    σ's): the full Jacobian with respect to the colour (where À-Trous' default σ_rt, the image's
    maximum, enters; the learned ops' many small guided filters make it take too long for them),
    a random projection of it (fast mode) with respect to every tensor input."""
    fn, names = DEFAULTS[op]
    t = _inputs(H=4, W=5, dtype=torch.float64)
    args = tuple(t[k].clone().requires_grad_(True) for k in names)
    if op not in LEARNED64:
        assert torch.autograd.gradcheck(lambda v: fn({**t, names[0]: v}), args[:1])
    assert torch.autograd.gradcheck(lambda *v: fn({**t, **dict(zip(names, v))}), args, fast_mode=True)


def _run_float32_and_64(op: str, backend: str) -> tuple[list[torch.Tensor], list[torch.Tensor], dict[str, str]]:
    """The op with its defaults on every differentiable input: the float32 output and gradients
    of a weighted sum under ``backends.use(backend)`` and which back end ran each kernel, and the
    float64 oracle's (the torch code; the learned ops with their network in float64)."""
    from torchgi import backends
    from torchgi.backends import base

    fn, names = DEFAULTS[op]
    out = {}
    for dt, f, use in ((torch.float64, fn, "torch"), (torch.float32, CASES[op][0] if op in LEARNED64 else fn, backend)):
        t = _inputs(dtype=dt)
        args = {k: t[k].clone().requires_grad_(True) for k in names}
        base._last.clear()
        with backends.use(use):
            y = f({**t, **args})
            w = torch.rand(y.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64).to(dt)
            (y * w).sum().backward()
        out[dt] = ([y.detach().double()] + [args[k].grad.double() for k in names],
                   {o: ran for o, (ran, _) in base._last.items()})
    return out[torch.float32][0], out[torch.float64][0], out[torch.float32][1]


@pytest.mark.parametrize("op", sorted(DEFAULTS))
@pytest.mark.parametrize("backend", ["c", "torch"])
def test_every_back_end_forward_and_backward_against_float64(op, backend):
    """Issue 71: the gradchecks above run in float64, which only the torch code takes, so a
    broken compiled backward (a zeroed weight gradient in the C ``apply_kernels_grad``) passed
    them. Here each back end this machine has computes the float32 forward and the gradients of
    every differentiable input, against the float64 oracle (measured: at most 3.6e-5 relative,
    the pyramid's guide gradient); where a compiler is, the C kernels must have run."""
    from torchgi.backends.c_kernels import build

    if backend == "c" and build._compiler() is None:
        pytest.skip("no C compiler: the C kernels cannot be built")
    got, want, ran = _run_float32_and_64(op, backend)
    for k, (a, b) in enumerate(zip(got, want, strict=True)):
        assert float((a - b).norm() / b.norm()) < (1e-5 if k == 0 else 1e-4), (op, k)
    if backend == "c" and op != "cross_bilateral":  # (the bilateral filter has no compiled kernel)
        assert "c" in ran.values(), ran
