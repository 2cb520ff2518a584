"""The exportable form of the Denoiser (:meth:`torchgi.Denoiser.deploy`): its pipeline with every
choice fixed, as plain tensor code for ONNX export - with or without an emission input - and the
hole filling that keeps a graph's output finite. Each method's exported filter is its
:meth:`torchgi.methods.Method.deployed_filter`.
"""

from __future__ import annotations

from typing import Any

import torch

from torchgi import light, methods
from torchgi.backends.torch_code.filter_box import box_pool
from torchgi.core.check import check_option, check_positive, is_recording
from torchgi.filters import box
from torchgi.settings import PIPELINE

__all__ = ["DeployedDenoiser", "DeployedDenoiserWithoutEmission", "deployed"]


def _fill_holes(tensors: list[torch.Tensor]) -> list[torch.Tensor]:
    """``tensors`` (each ``(B, C, H, W)``) with every pixel that is NaN/Inf in any channel of any
    of them made a hole: all its inputs replaced by the mean of the finite pixels within
    ``PIPELINE.hole_radius`` (normalised convolution; 0 where there is none), so nothing
    non-finite reaches the filter and the hole's output comes from its neighbours. Plain
    tensor ops (exportable); finite inputs pass unchanged.

    The filling runs only where the sum of every input is not finite (one reduction per input;
    in a graph an ``If``): NaN/Inf anywhere make it so, and so can finite values whose sum
    overflows, for which the filling changes nothing. Clean inputs skip its full-resolution passes.

    Example:
        >>> x = torch.ones(1, 1, 3, 3); x[0, 0, 1, 1] = float("nan")
        >>> _fill_holes([x])[0][0, 0, 1].tolist()
        [1.0, 1.0, 1.0]
    """
    maybe = torch.isfinite(torch.stack([t.sum() for t in tensors]).sum())
    if not is_recording():
        return list(tensors) if bool(maybe) else _filled(tensors)
    # (a branch of a cond may return no view of its inputs nor two views of one tensor: clones)
    return list(torch.cond(maybe, lambda *ts: tuple(t.clone() for t in ts),
                           lambda *ts: tuple(t.clone() for t in _filled(list(ts))), tuple(tensors)))


def _filled(tensors: list[torch.Tensor]) -> list[torch.Tensor]:
    """:func:`_fill_holes`' filling, on every pixel."""
    ok = torch.stack([torch.isfinite(t).all(1, keepdim=True) for t in tensors]).all(0)
    w = ok.to(tensors[0].dtype)
    clean = torch.where(ok, torch.cat(tensors, 1), 0.0)  # one select, one box over every channel
    sums = box_pool(torch.cat([clean, w], 1), PIPELINE.hole_radius)  # (the torch code: inside a graph's If)
    # 0 where no finite pixel is near (the sums are 0 there); ``clean + (1 - w) filled`` is the
    # input itself where finite, exactly, and the fill in a hole
    filled = clean + (1 - w) * (sums[:, :-1] / sums[:, -1:].clamp_min(1e-6))
    return list(filled.split([t.shape[1] for t in tensors], 1))


class DeployedDenoiser(torch.nn.Module):
    """A :class:`Denoiser` with every choice fixed, as plain tensor code for ONNX export.

    ``forward(color, emission, albedo, normal, depth)`` for "pyramid", "blend" and "guided" and
    ``forward(color, emission, albedo, normal, position)`` for "atrous", all ``(B, C, H, W)``
    (:attr:`input_names`, by position or by name; :class:`DeployedDenoiserWithoutEmission` takes no emission), and with
    ``variance`` a last input ``variance (B, 1|3, H, W)`` (of the colour's mean, as
    ``GBuffer.variance``): the Denoiser's pipeline (:mod:`torchgi.denoise`'s docstring) with the
    fixed parameters, backed off toward the input as the eager call given a variance
    (:func:`torchgi.light.back_off`, for the fixed sample count ``params["samples"]`` >= 2; "guided"
    with ``params["radii"]``: the filter at each radius blended by :func:`torchgi.light.choose` first);
    surfaces are the pixels of non-zero albedo. With an emission input (zeros when no light source is in
    view) the light sources are those pixels, as in the eager call given one; without it they
    are found from the colour, as in the eager call given none. A pixel
    that is NaN/Inf in any input is a hole (:func:`_fill_holes`): the output is finite
    everywhere and, outside the hole's filter footprint, that of the clean input (an exported
    graph cannot raise). Built by :meth:`torchgi.Denoiser.deploy`.
    """

    emission = True  # the graph's inputs include an emission layer

    def __init__(self, method: str, params: dict[str, Any], net: torch.nn.Module | None = None,
                 variance: bool = False, firefly: float | None = None, spp: float | None = 1.0) -> None:
        super().__init__()
        check_option(method, "method", methods.names(exportable=True))
        kind = methods.get(method)
        if (net is None) == kind.learned:
            learned = ", ".join(repr(n) for n in methods.names(learned=True))
            raise ValueError(f"net: the learned methods ({learned}) need their network, the others none")
        if variance and not float(params.get("samples", 0)) >= 2:
            raise ValueError(f"variance: the back-off needs a sample count of 2 or more, got {params.get('samples')}")
        if firefly is not None:
            check_positive(firefly, "firefly")
        if spp is not None:
            check_positive(spp, "spp")
        self.method, self.params, self.net, self.variance = method, dict(params), net, variance
        self.spp = None if spp is None else float(spp)  # the render's sample count it is fixed for (None: unknown)
        self.firefly = kind.firefly() if firefly is None else float(firefly)  # fireflies clamped at this x local level
        self._kind = kind

    @property
    def input_names(self) -> tuple[str, ...]:
        last = self._kind.geometry
        return (("color",) + (("emission",) if self.emission else ()) + ("albedo", "normal", last)
                + (("variance",) if self.variance else ()))

    def forward(self, *inputs: torch.Tensor, **by_name: torch.Tensor) -> torch.Tensor:
        """The denoised ``(B, 3, H, W)`` colour from the :attr:`input_names`: by position in that
        order, by name, or the first ones by position and the rest by name.

        Example:
            >>> import torchgi
            >>> m = torchgi.Denoiser("guided").deploy(emission=False)
            >>> c, a, n, d = (torch.rand(1, k, 8, 8) for k in (3, 3, 3, 1))
            >>> torch.equal(m(c, a, n, d), m(depth=d, normal=n, albedo=a, color=c))
            True
        """
        named = dict(zip(self.input_names, _fill_holes(self._ordered(inputs, by_name)), strict=True))
        geometry = named[self._kind.geometry]
        return self._run(named["color"], named.get("emission"), named["albedo"], named["normal"], geometry,
                         named.get("variance"))

    def _ordered(self, inputs: tuple[torch.Tensor, ...], by_name: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        """The positional and named inputs of :meth:`forward` as one list in :attr:`input_names`
        order; an unknown name, a name also given by position, or a missing input is refused by name."""
        names = self.input_names
        expected = f"inputs {', '.join(names)}"
        if len(inputs) > len(names):
            raise ValueError(f"inputs: expected at most {len(names)} tensors ({expected}), got {len(inputs)}")
        for key in by_name:
            if key == "emission" and not self.emission:
                raise TypeError("emission: this module was deployed without an emission input (emission=False)")
            if key not in names:
                raise TypeError(f"{key}: not an input of this module ({expected})")
            if names.index(key) < len(inputs):
                raise TypeError(f"{key}: given by position and by name")
        given = dict(zip(names, inputs)) | by_name
        missing = [k for k in names if k not in given]
        if missing:
            raise ValueError(f"{', '.join(missing)}: required ({expected})")
        return [given[k] for k in names]

    def _run(self, color: torch.Tensor, emission: torch.Tensor | None, albedo: torch.Tensor, normal: torch.Tensor,
             geometry: torch.Tensor, variance: torch.Tensor | None = None) -> torch.Tensor:
        """The pipeline on hole-filled inputs (``emission`` None: light sources from the colour;
        ``variance`` None: no back-off); a method with a pipeline of its own runs its
        :meth:`~torchgi.methods.Method.deployed_run`."""
        if self._kind.own_pipeline:
            return self._kind.deployed_run(self.params, self.net, color, emission, albedo, normal, geometry, variance)
        surface = light.surface_mask(None, albedo)
        scene_level = light.level(color, emission, None, albedo, surface)

        def filter_fn(x: torch.Tensor, radius: int | None = None, raw: torch.Tensor | None = None) -> torch.Tensor:
            return self._kind.deployed_filter(self.params, self.net, x, normal, geometry, radius, raw)

        radii = self.params.get("radii", (None,)) if variance is not None else (None,)
        outs = [light.restore(color, emission, None, albedo, surface, lambda x, *raw, r=r: filter_fn(x, r, *raw),
                              self.firefly, box, scene_level, unclamped=self._kind.unclamped) for r in radii]
        if variance is None:
            return outs[0]
        emit = light.emitting(color, emission, albedo, surface, scene_level)
        out = outs[0] if len(outs) == 1 else light.choose(outs, list(radii), variance, emit, box)
        return light.back_off(out, color, variance, float(self.params["samples"]), emit, box)

    def metadata(self) -> dict[str, str]:
        """What an exported graph records of the renders it was built for (ONNX ``metadata_props``,
        read by :class:`torchgi.export.OrtDenoiser`): the method, the render's sample count
        (:attr:`spp`; "" where it was fixed from a frame without one) and the inputs.

        Example:
            >>> import torchgi
            >>> torchgi.Denoiser("guided").deploy(spp=4).metadata()["torchgi.spp"]
            '4.0'
        """
        return {"torchgi.method": self.method, "torchgi.spp": "" if self.spp is None else repr(self.spp),
                "torchgi.inputs": ",".join(self.input_names)}

    def extra_repr(self) -> str:
        return f"method={self.method!r}, " + ", ".join(f"{k}={v!r}" for k, v in self.params.items()) + (
            "" if self.emission else ", emission=False") + (", variance=True" if self.variance else "")


class DeployedDenoiserWithoutEmission(DeployedDenoiser):
    """:class:`DeployedDenoiser` for renders without an emission layer: ``forward(color, albedo,
    normal, depth | position[, variance])``; the light sources are found from the colour, as the eager
    Denoiser does without one. Built by :meth:`torchgi.Denoiser.deploy` with ``emission=False``.

    Example:
        >>> import torchgi
        >>> torchgi.Denoiser("guided").deploy(emission=False).input_names
        ('color', 'albedo', 'normal', 'depth')
    """

    emission = False


def deployed(method: str, params: dict[str, Any], net: torch.nn.Module | None, emission: bool,
             variance: bool = False, firefly: float | None = None, spp: float | None = 1.0) -> DeployedDenoiser:
    """The exportable module :meth:`torchgi.Denoiser.deploy` returns for ``method`` (one of
    ``methods.names(exportable=True)``) with its fixed ``params`` and network:
    :class:`DeployedDenoiser`, or :class:`DeployedDenoiserWithoutEmission` when ``emission`` is
    False; with ``variance`` a variance input and the back-off (``params["samples"]``: the
    render's sample count, >= 2); ``firefly`` the clamp factor (None: the method's default);
    ``spp`` the render's sample count it is fixed for (None: unknown), recorded in :meth:`~DeployedDenoiser.metadata`.

    Example:
        >>> deployed("guided", {"radius": 2, "eps": 1e-4}, None, emission=False)
        DeployedDenoiserWithoutEmission(method='guided', radius=2, eps=0.0001, emission=False)
    """
    kind = DeployedDenoiser if emission else DeployedDenoiserWithoutEmission
    return kind(method, params, net, variance, firefly, spp)
