"""Back ends: every kernel of torchgi chosen in one place.

An op (box, guided, the upsampling and application of linear-model coefficients, atrous, per-pixel kernels and their gradients, importance, allocate, the Denoiser's guide statistics, edge share
and restore pipeline, the pyramid's block means and mixes, the temporal accumulation, and a tile of the renderer's path tracer) is described by a small dataclass in one
convention (:class:`BoxOp`, :class:`GuidedOp`, :class:`ATrousOp`, :class:`ImportanceOp`,
:class:`AllocateOp`); :func:`run` hands it to the first back end that supports it, in the
order ``c`` (compiled CPU kernels, :mod:`torchgi.backends.c_kernels`), ``triton`` (CUDA,
:mod:`torchgi.backends.triton_kernels`), ``torch`` (the reference: autograd, tracing, ONNX
export, float64; :mod:`torchgi.backends.torch_code`). :func:`use` restricts the choice inside
a block (context-local), :func:`status` says what each back end can do here and which one ran
each op last, and why the others did not. ``TORCHGI_NATIVE=0`` in the environment switches
the compiled back ends off for the process.

Example:
    >>> import torch
    >>> from torchgi import backends
    >>> from torchgi.filters import box
    >>> with backends.use("torch"):
    ...     _ = box(torch.rand(1, 1, 8, 8), 2)
    >>> backends.status()["last"]["box"]["ran"]
    'torch'
"""

from torchgi.backends.autograd_ops import BoxMean, KernelApply, box_mean, window_counts
from torchgi.backends.base import (
    NAMES,
    ORDER,
    Accumulated,
    AccumulateOp,
    AllocateOp,
    AppliedMeansOp,
    ApplyKernelsGradOp,
    ApplyKernelsOp,
    ATrousLevelGradOp,
    ATrousLevelOp,
    ATrousOp,
    BackOffOp,
    BlockMeanOp,
    BoxOp,
    Changed,
    ChangeOp,
    ChooseOp,
    EdgeShareOp,
    FineBandOp,
    GuidedOp,
    GuideRaysOp,
    GuideSpec,
    GuideStats,
    GuideStatsOp,
    HistoryOp,
    ImportanceOp,
    LightInOp,
    LightOutOp,
    MixHalfOp,
    ModelResidualOp,
    PathOp,
    RestoreOp,
    TraceSetup,
    UpsampleApplyOp,
    chunks,
    embree_started,
    enabled,
    mark_embree_started,
    plan,
    run,
    select,
    status,
    use,
)

__all__ = [
    "NAMES",
    "ORDER",
    "ATrousLevelGradOp",
    "ATrousLevelOp",
    "ATrousOp",
    "AccumulateOp",
    "Accumulated",
    "AllocateOp",
    "AppliedMeansOp",
    "ApplyKernelsGradOp",
    "ApplyKernelsOp",
    "BackOffOp",
    "BlockMeanOp",
    "BoxMean",
    "BoxOp",
    "ChangeOp",
    "Changed",
    "ChooseOp",
    "EdgeShareOp",
    "FineBandOp",
    "GuideRaysOp",
    "GuideSpec",
    "GuideStats",
    "GuideStatsOp",
    "GuidedOp",
    "HistoryOp",
    "ImportanceOp",
    "KernelApply",
    "LightInOp",
    "LightOutOp",
    "MixHalfOp",
    "ModelResidualOp",
    "PathOp",
    "RestoreOp",
    "TraceSetup",
    "UpsampleApplyOp",
    "box_mean",
    "chunks",
    "embree_started",
    "enabled",
    "mark_embree_started",
    "plan",
    "run",
    "select",
    "status",
    "use",
    "window_counts",
]
