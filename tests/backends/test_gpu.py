"""The Triton back end (torchgi.backends.triton_kernels: an À-Trous level, the guided filter, the box filter)
against the float64 oracles: on CUDA when the device is asked for (``--device cuda``), and on
the CPU through Triton's interpreter (a subprocess with ``TRITON_INTERPRET=1``) where Triton is
installed. The interpreter runs the kernels as Python, so a third check compiles every kernel
for an sm_90 GPU offline (Triton's own ptxas, no GPU needed): what the GPU compiler accepts,
and that no variant spills registers."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.helpers import last_backend, rel_range
from tests.oracles import ATROUS_CASES, atrous_case, atrous_error, box_oracle, fast_guided_oracle, guided_oracle, scene
from torchgi import backends
from torchgi.backends import triton_kernels as gpu
from torchgi.backends.triton_kernels import accumulation as accumulation_kernels
from torchgi.backends.triton_kernels import filter_atrous as atrous_kernels
from torchgi.backends.triton_kernels import filter_guided as guided_kernels
from torchgi.backends.triton_kernels import filter_guided_grad as guided_grad_kernels
from torchgi.backends.triton_kernels import filter_kernels as kernel_kernels
from torchgi.filters import atrous, box, guided


def _cuda_with_triton(device: torch.device) -> None:
    """Skip unless the run is on CUDA with Triton."""
    if device.type != "cuda":
        pytest.skip("the CUDA run; the CPU checks the same kernels through the interpreter below")
    if gpu.triton is None:
        pytest.skip("no Triton")


@pytest.mark.parametrize("C", [1, 2, 3])
@pytest.mark.parametrize("case", ATROUS_CASES)
def test_triton_kernel_matches_oracle_on_cuda(device, C, case, monkeypatch):
    _cuda_with_triton(device)
    c, n, x, kw = atrous_case(C, case)
    out = atrous(c.to(device), n.to(device), x.to(device),
                 **{k: v.to(device) if torch.is_tensor(v) else v for k, v in kw.items()})
    assert last_backend("atrous") == "triton" and out.device.type == "cuda"
    assert atrous_error(out, c, n, x, kw) < 2e-5  # GPU exp is not correctly rounded


_INTERPRETED = """
import sys, torch
sys.path.insert(0, {root!r})
from tests.oracles import ATROUS_CASES, atrous_case, atrous_error
from torchgi import backends
from torchgi.filters import atrous
assert backends.status()["triton"].endswith("interpreter"), "interpreter not active"
worst = 0.0
for C, case in [(3, case) for case in ATROUS_CASES] + [(1, "cnx"), (1, "variance"), (2, "c")]:
    c, n, x, kw = atrous_case(C, case)
    worst = max(worst, atrous_error(atrous(c, n, x, **kw), c, n, x, kw))
    assert backends.status()["last"]["atrous"]["ran"] == "triton"
print(worst)
"""


_INTERPRETED_GUIDED = """
import sys, torch
sys.path.insert(0, {root!r})
from tests.oracles import box_oracle, fast_guided_oracle, guided_oracle, scene
from tests.helpers import rel_range as rel
from torchgi import backends
from torchgi.filters import box, guided
calls = []
def ran():
    calls.append(backends.status()["last"]["guided"]["ran"])
worst = 0.0
# guide channels 1-4, source channels 1/3, r = 0, windows past the image, one pixel, offset guides
for B, H, W, n, Cs, r, offset in [(2, 9, 13, 4, 3, 2, 0.0), (1, 20, 30, 2, 1, 40, 0.0), (1, 7, 11, 1, 3, 0, 0.0),
                                  (1, 12, 10, 3, 1, 3, 1e3), (1, 1, 1, 2, 1, 3, 0.0)]:
    p, I = scene(B, H, W, n, seed=H)
    p, I = p[:, :Cs], I + offset
    want = guided_oracle(p, I, r, 0.01)
    got = guided(p, I, radius=r, eps=0.01)
    ran()
    worst = max(worst, rel(got, want) if H * W > 1 else float((got - p).abs().max()))
p, I = scene(1, 13, 17, 4, seed=9)
worst = max(worst, rel(guided(p, I, radius=4, eps=0.01, subsample=2), fast_guided_oracle(p, I, 4, 0.01, 2)))
# per-image, per-channel eps
p2, I2 = scene(2, 9, 13, 4, seed=3)
eps_b = torch.tensor([[0.01, 0.02, 0.01, 0.03], [0.1, 0.1, 0.2, 0.05]])
got = guided(p2, I2, radius=2, eps=eps_b)
worst = max([worst] + [rel(got[b : b + 1], guided_oracle(p2[b : b + 1], I2[b : b + 1], 2, eps_b[b])) for b in range(2)])
# hostile: a constant guide at eps = 0 (a = 0, q = box(box(p))), a constant source stays constant
flat = torch.full((1, 2, 13, 17), 1e4)
worst = max(worst, rel(guided(p, flat, radius=3, eps=0.0), box_oracle(box_oracle(p.double(), 3), 3)))
const = guided(torch.full((1, 3, 13, 17), 7.5), I, radius=3, eps=0.0)
worst = max(worst, float((const - 7.5).abs().max()) / 7.5)
assert calls == ["triton"] * 5, calls
x = torch.rand(2, 3, 11, 140) + 5  # absolute errors: r = 200 averages the whole image
box_err = max(float((box(x, r).double() - box_oracle(x.double(), r)).abs().max()) for r in (0, 5, 200))
assert backends.status()["last"]["box"]["ran"] == "triton"
print(worst, box_err)
"""


_INTERPRETED_RESTORE = """
import torch, torchgi
from torchgi import backends
from torchgi.denoise import Denoiser
gb = torchgi.render(torchgi.scenes.cornell(40).with_resolution(40, 36), spp=1, bounces=1, seed=3)
full = {{"color": gb.color, "albedo": gb.albedo, "normal": gb.normal, "depth": gb.depth, "emission": gb.emission}}
conductor = {{**full, "albedo": gb.albedo * torch.linspace(1, 8, 40)}}  # another renderer's "albedo" above 1
cases = [({{}}, full), ({{"subsample": 2}}, conductor), ({{"subsample": 3}}, {{k: v for k, v in full.items() if k != "emission"}}),
         ({{"filter_direct": False, "subsample": 2}}, {{**full, "direct": gb.direct, "indirect": gb.indirect,
                                                      "hit": gb.hit}})]
worst = 0.0
for params, inputs in cases:
    d = Denoiser("guided", **params)
    with backends.use("triton"):
        out = d(**inputs)
    assert backends.status()["last"]["restore"]["ran"] == "triton"
    with backends.use("torch"):
        ref = d(**{{k: v.double() if v.is_floating_point() else v for k, v in inputs.items()}})
    worst = max(worst, float(((out.double() - ref).abs() / (ref.abs() + 1e-3)).max()))
print(worst)
"""


_INTERPRETED_TEMPORAL = """
import torch, torchgi
from torchgi import backends
from torchgi.render import CameraPath
from torchgi.temporal import TemporalDenoiser
scene = torchgi.scenes.cornell(16).with_resolution(16, 14)
p = scene.camera.position
scene.path = CameraPath((0.0, 1.0), (p, (p[0] + 60, p[1], p[2] + 40)), ((278, 273, 0), (290, 270, 0)), (39.3, 39.3))
gbs = list(torchgi.render_sequence(scene, 2, spp=1, seed=4))
with backends.use("triton"):
    den = TemporalDenoiser()
    out = [den(gb) for gb in gbs][-1]
assert backends.status()["last"]["restore"]["ran"] == "triton"
assert backends.status()["last"]["accumulate"]["ran"] == "triton"
with backends.use("torch"):
    den = TemporalDenoiser()
    ref = [den(gb.to(dtype=torch.float64)) for gb in gbs][-1]
whole = float(((out.double() - ref).abs() / (ref.abs() + 1e-3)).max())
# the accumulation alone on the second frame, fireflies bounded, against the float64 torch code
from torchgi.settings import TEMPORAL as T
gb = gbs[1]
with backends.use("triton"):
    den = TemporalDenoiser()
    den(gbs[0])
    st = den.state
def op(st, x, bound, gb):
    return backends.AccumulateOp(x, bound, gb.motion, gb.normal, gb.depth, gb.hit, *st.tensors(), T.alpha,
                                 T.max_history, T.normal_tolerance, T.depth_tolerance)
x, bound = gb.color, gb.color.mean(1, keepdim=True) * 1.5
with backends.use("triton"):
    got = backends.run(op(st, x, bound, gb))
assert backends.status()["last"]["accumulate"]["ran"] == "triton"
with backends.use("torch"):
    want = backends.run(op(type(st)(*(t.double() for t in st.tensors())), x.double(), bound.double(),
                           gb.to(dtype=torch.float64)))
assert float((want[:, 8] - want[:, 9]).abs().max()) > 0  # histories of several lengths
print(whole, float((got.double() - want).abs().max() / want.abs().max()))
"""


def _interpret(code: str) -> list[float]:
    """Run ``code`` (formatted with the repository root) with the Triton interpreter on and the C
    kernels off (they would take CPU calls first); returns the numbers of the last line it prints."""
    pytest.importorskip("triton")
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ, TRITON_INTERPRET="1", TORCHGI_NATIVE="1")
    code = "from torchgi.backends import c_kernels\nc_kernels.build.library = lambda: None\n" + code.format(root=root)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=root,
                          timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return [float(v) for v in proc.stdout.splitlines()[-1].split()]


def test_triton_kernel_matches_oracle_in_the_interpreter():
    (worst,) = _interpret(_INTERPRETED)
    assert worst < 2e-6


def test_triton_guided_and_box_match_oracle_in_the_interpreter():
    guided_err, box_err = _interpret(_INTERPRETED_GUIDED)
    assert guided_err < 2e-6 and box_err < 1e-6


_INTERPRETED_KERNELS = """
import sys, torch
sys.path.insert(0, {root!r})
from tests.oracles import apply_kernels_oracle
from torchgi import backends
from torchgi.filters import apply_kernels
worst = 0.0
for k, d, normalize in ((3, 1, False), (5, 2, True), (3, 5, True)):
    g = torch.Generator().manual_seed(k + d)
    x, w = torch.rand(2, 3, 11, 14, generator=g), torch.rand(2, k * k, 11, 14, generator=g) + 0.05
    gr = torch.randn(2, 3, 11, 14, generator=g)
    x64, w64 = x.double().requires_grad_(), w.double().requires_grad_()
    want = apply_kernels_oracle(x64, w64, d, normalize)
    wg = torch.autograd.grad((want * gr.double()).sum(), (x64, w64))
    xs, ws = x.clone().requires_grad_(), w.clone().requires_grad_()
    with backends.use("triton"):
        out = apply_kernels(xs, ws, dilation=d, normalize=normalize)
        got = torch.autograd.grad((out * gr).sum(), (xs, ws))
    assert backends.status()["last"]["apply_kernels_grad"]["ran"] == "triton"
    for a, b in [(out, want.detach())] + list(zip(got, wg)):
        worst = max(worst, float((a.double() - b).abs().max()) / max(1.0, float(b.abs().max())))
print(worst)
"""


_INTERPRETED_LEVELS = """
import sys, torch
sys.path.insert(0, {root!r})
from torchgi import backends
from torchgi.filters import atrous
from torchgi.backends.torch_code import filter_atrous
worst = 0.0
g = torch.Generator().manual_seed(3)
c, x = torch.rand(2, 3, 5, 7, generator=g), torch.rand(2, 3, 5, 7, generator=g)
n = torch.nn.functional.normalize(torch.randn(2, 3, 5, 7, generator=g), dim=1)
gr = torch.randn(2, 3, 5, 7, generator=g)
for sig, kw in ((torch.tensor([0.4, 0.7]), {{"sigma_position": None}}), (0.3 + torch.rand(2, 1, 5, 7, generator=g), {{}})):
    def grads(dtype, by_level, backend):
        ts = [t.to(dtype).requires_grad_() for t in (c, n, x, sig)]
        filter_atrous.level_backward, keep = (lambda desc: by_level), filter_atrous.level_backward
        with backends.use(backend):
            out = atrous(*ts[:3], iterations=2, sigma_color=ts[3], **kw)
            got = torch.autograd.grad((out * gr.to(dtype)).sum(), ts, allow_unused=True)
        filter_atrous.level_backward = keep
        return [torch.zeros_like(t) if d is None else d for t, d in zip(ts, got)]
    want = grads(torch.float64, False, "torch")
    got = grads(torch.float32, True, "triton")
    assert backends.status()["last"]["atrous_level_grad"]["ran"] == "triton"
    assert backends.status()["last"]["atrous_level"]["ran"] == "triton"
    for a, b in zip(got, want):
        worst = max(worst, float((a.double() - b).abs().max()) / max(1.0, float(b.abs().max())))
print(worst)
"""


def test_triton_atrous_level_gradients_match_autograd_in_the_interpreter():
    """The Triton À-Trous level and its gradients (colour, guides, σ_rt value or map) against
    autograd through the torch levels in float64."""
    (worst,) = _interpret(_INTERPRETED_LEVELS)
    assert worst < 1e-4


_INTERPRETED_GUIDED_GRAD = """
import sys, torch
sys.path.insert(0, {root!r})
from tests.oracles import guided_oracle
from torchgi import backends
from torchgi.filters import guided
worst = 0.0
for n, C, r, B in ((1, 1, 1, 1), (4, 3, 2, 2), (3, 2, 3, 1), (2, 3, 1, 1)):
    g = torch.Generator().manual_seed(n + r)
    p, I = torch.rand(B, C, 9, 13, generator=g), torch.rand(B, n, 9, 13, generator=g)
    eps, gr = torch.linspace(0.01, 0.03, n), torch.randn(B, C, 9, 13, generator=g)
    x, y, e = p.double().requires_grad_(), I.double().requires_grad_(), eps.double().requires_grad_()
    want = torch.autograd.grad((guided_oracle(x, y, r, e) * gr.double()).sum(), (x, y, e))
    x, y, e = p.clone().requires_grad_(), I.clone().requires_grad_(), eps.clone().requires_grad_()
    with backends.use("triton"):
        got = torch.autograd.grad((guided(x, y, radius=r, eps=e) * gr).sum(), (x, y, e))
    assert backends.status()["last"]["guided_grad"]["ran"] == "triton"
    for a, b in zip(got, want):
        worst = max(worst, float((a.double() - b).abs().max() / b.abs().max()))
print(worst)
"""


def test_triton_guided_gradients_match_autograd_in_the_interpreter():
    """The Triton guided backward (source, guide, per-channel ε; 1 to 4 guide channels) against
    autograd through the float64 oracle."""
    (worst,) = _interpret(_INTERPRETED_GUIDED_GRAD)
    assert worst < 2e-4


def test_triton_apply_kernels_match_oracle_in_the_interpreter():
    """The Triton forward and gradients of apply_kernels against autograd through the float64 oracle."""
    (worst,) = _interpret(_INTERPRETED_KERNELS)
    assert worst < 1e-5


def test_triton_accumulation_matches_float64_torch_code_on_cuda(device):
    """The accumulation kernel on the GPU against the float64 torch code: random history, normals
    and motion (taps off the image, rejected and kept), fireflies at a bound."""
    _cuda_with_triton(device)
    from torchgi.settings import TEMPORAL as T

    g = torch.Generator().manual_seed(3)
    B, H, W = 2, 45, 61
    r = lambda c: torch.rand(B, c, H, W, generator=g)
    n = torch.nn.functional.normalize(r(3) - 0.3, dim=1)
    tensors = [r(3) * 4, r(1) + 1, (r(2) - 0.5) * 6, n, r(1) + 1, r(1) > 0.2, r(3), r(3), r(2), (r(1) * 8).round(),
               torch.nn.functional.normalize(n + 0.2 * r(3), dim=1), r(1) + 1, (r(1) > 0.2).float()]
    op = lambda ts: backends.AccumulateOp(*ts, T.alpha, T.max_history, T.normal_tolerance, T.depth_tolerance)
    got = backends.run(op([t.to(device) for t in tensors])).cpu()
    assert last_backend("accumulate") == "triton"
    with backends.use("torch"):
        want = backends.run(op([t if t.dtype == torch.bool else t.double() for t in tensors]))
    assert float((got.double() - want).abs().max() / want.abs().max()) < 1e-5


@pytest.mark.parametrize("n", [1, 3, 4])
@pytest.mark.parametrize("Cs", [1, 3])
def test_triton_guided_matches_oracle_on_cuda(device, n, Cs):
    _cuda_with_triton(device)
    full_hd = [(1080, 1920, 24, 1e4)] if n == 4 else []  # the float64 oracle takes seconds there
    for H, W, r, offset in [(37, 53, 5, 0.0), (120, 301, 40, 1e3)] + full_hd:
        p, I = scene(1, H, W, n, seed=n + Cs)
        p, I = p[:, :Cs].contiguous(), (I + offset).float()
        want = guided_oracle(p, I, r, 0.01)
        got = guided(p.to(device), I.to(device), radius=r, eps=0.01).cpu()
        assert last_backend("guided") == "triton"
        assert torch.isfinite(got).all()
        assert rel_range(got, want) < 1e-5
    p, I = scene(2, 37, 53, n, seed=1)
    got = guided(p[:, :Cs].to(device), I.to(device), radius=6, eps=0.01, subsample=2).cpu()
    want = fast_guided_oracle(p[:, :Cs], I, 6, 0.01, 2)
    assert rel_range(got, want) < 1e-5
    assert last_backend("guided") == "triton"
    x = torch.rand(2, 3, 70, 90)
    torch.testing.assert_close(box(x.to(device), 7).cpu().double(), box_oracle(x.double(), 7), rtol=0, atol=1e-6)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_triton_guided_gradients_match_autograd_on_cuda(device, n):
    """The Triton guided backward on the GPU (128 x 151, r 9; the grid has
    partial blocks) against autograd through the float64 oracle on the CPU."""
    _cuda_with_triton(device)
    p, I = scene(2, 128, 151, n, seed=n)
    eps, gr = torch.linspace(0.01, 0.03, n), torch.randn(2, 3, 128, 151, generator=torch.Generator().manual_seed(n))
    x, y, e = p.double().requires_grad_(), I.double().requires_grad_(), eps.double().requires_grad_()
    want = torch.autograd.grad((guided_oracle(x, y, 9, e) * gr.double()).sum(), (x, y, e))
    x, y, e = (t.to(device).requires_grad_() for t in (p, I, eps))
    got = torch.autograd.grad((guided(x, y, radius=9, eps=e) * gr.to(device)).sum(), (x, y, e))
    assert last_backend("guided_grad") == "triton"
    for a, b in zip(got, want):
        assert float((a.cpu().double() - b).abs().max() / b.abs().max()) < 2e-4


def test_kernels_off_inside_use_torch():
    with backends.use("torch"):
        box(torch.rand(1, 1, 4, 4, device="cuda" if torch.cuda.is_available() else "cpu"), 1)
        assert backends.status()["last"]["box"]["skipped"]["triton"].startswith("switched off")


def _variants():
    """Every Triton kernel with the compile-time arguments it is launched with (the À-Trous
    level: the common case and the one with every input)."""
    level = {"BH": atrous_kernels._BH, "BW": atrous_kernels._BW}
    return [
        (atrous_kernels._level, dict(C=C, N=True, X=True, CS=CS, V=V, VALID=VALID, UNROLL=atrous_kernels._unroll(C, V), **level), atrous_kernels._WARPS)
        for C, CS, V, VALID in ((3, 1, False, False), (3, 1, False, True), (3, 2, True, False), (4, 1, False, True),
                                (4, 2, True, True))
    ] + [
        (atrous_kernels._level, dict(C=1, N=False, X=False, CS=0, V=False, VALID=False, UNROLL=atrous_kernels._unroll(1, False), **level),
         atrous_kernels._WARPS),
        (guided_kernels._column_sums, {"CENTRE": True, "BW": guided_kernels._COL_BW, "UNROLL": guided_kernels._COL_UNROLL}, guided_kernels._COL_WARPS),
        (guided_kernels._column_sums, {"CENTRE": False, "BW": guided_kernels._COL_BW, "UNROLL": guided_kernels._COL_UNROLL}, guided_kernels._COL_WARPS),
        (guided_kernels._row_means, {"BH": guided_kernels._ROW_BH, "BW": guided_kernels._ROW_BW}, 4),
    ] + [(k, {"N": n, "BLOCK": guided_kernels._PIX}, 4) for k in (guided_kernels._solve, guided_kernels._apply) for n in (1, 2, 3, 4)
         ] + [(guided_grad_kernels._adjoint, {"N": n, "BLOCK": guided_kernels._PIX}, 4) for n in (1, 2, 3, 4)] + [
        (guided_grad_kernels._gradients, {"N": n, "DI": True, "BLOCK": guided_kernels._PIX}, 4) for n in (1, 2, 3, 4)] + [(accumulation_kernels._accumulate, {"BLOCK": accumulation_kernels._BLOCK}, 4)] + [
        (kernel_kernels._forward, {"NORMALIZE": True, "BLOCK": kernel_kernels._BLOCK}, 4),
        (kernel_kernels._gradients, {"NORMALIZE": True, "DX": True, "DW": True, "BLOCK": kernel_kernels._BLOCK}, 4),
        (atrous_kernels._level_grad, {"C": 3, "F": 6, "CS": 2, "DF": True, "DS": True,
                                      "BLOCK": atrous_kernels._GRAD_BLOCK}, 4)]


def test_kernels_compile_for_a_gpu_without_register_spills():
    """Triton compiles each kernel for sm_90 (an H100/H200) here, without a GPU; ptxas' resource
    report must show no spills (stack or local memory): the fully unrolled À-Trous tap loop
    used 255 registers and spilled."""
    triton = pytest.importorskip("triton")
    try:
        from triton.backends.compiler import GPUTarget
        from triton.compiler.compiler import ASTSource
    except ImportError:
        pytest.skip("this Triton has no ASTSource / GPUTarget")
    cuobjdump = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "cuobjdump"
    if not cuobjdump.exists():
        pytest.skip("this Triton ships no cuobjdump")
    floats = {"cmul", "unit", "tiny", "alpha", "cap", "ntol", "dtol", "lr", "lg", "lb"}
    for fn, constants, warps in _variants():
        signature = {a: "constexpr" if a in constants else "*i32" if a == "tab_ptr" else "*u8" if a == "surf_ptr"
                     else "*fp32" if a.endswith("_ptr") else "fp32" if a in floats else "i32" for a in fn.arg_names}
        try:
            source = ASTSource(fn, signature, constants)
        except TypeError as err:  # another Triton's ASTSource arguments: nothing to learn here
            pytest.skip(f"this Triton's ASTSource takes other arguments: {err}")
        kernel = triton.compile(source, target=GPUTarget("cuda", 90, 32), options={"num_warps": warps})
        cubin = Path(os.environ.get("TMPDIR", "/tmp")) / f"torchgi_{os.getpid()}.cubin"
        cubin.write_bytes(kernel.asm["cubin"])
        try:
            report = subprocess.run([str(cuobjdump), "-res-usage", str(cubin)], capture_output=True, text=True,
                                    check=True).stdout
        finally:
            cubin.unlink()
        usage = dict(item.split(":") for line in report.splitlines() if "REG:" in line for item in line.split())
        assert usage["STACK"] == "0" and usage["LOCAL"] == "0", (fn.__name__, constants, usage)
        assert int(usage["REG"]) <= 128, (fn.__name__, constants, usage)


def test_value_checks_step_aside_while_a_cuda_graph_is_captured(monkeypatch):
    """Under capture nothing may read tensor values on the host: the NaN/Inf and range checks
    are skipped (as while tracing); shapes are still checked."""
    from torchgi.core import NonFiniteError, ShapeError, is_recording

    bad = torch.rand(1, 3, 9, 11)
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(NonFiniteError):
        guided(bad, torch.rand(1, 2, 9, 11), radius=2)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_current_stream_capturing", lambda: True)
    assert is_recording()
    guided(bad, torch.rand(1, 2, 9, 11), radius=2, eps=torch.tensor([0.01, -1.0]))  # no read back, no error
    atrous(bad, iterations=2, sigma_color=torch.tensor([float("nan")]))
    with pytest.raises(ShapeError):
        guided(bad, torch.rand(1, 2, 9, 12), radius=2)


def test_filters_replay_in_a_cuda_graph(device):
    """atrous and guided (the Triton kernels) captured once in a CUDA graph and replayed on new
    inputs give what eager calls give: no host synchronisation inside either call."""
    if device.type != "cuda":
        pytest.skip("needs CUDA")
    g = torch.Generator().manual_seed(4)
    c, n, x = (torch.rand(1, 3, 96, 128, generator=g).to(device) for _ in range(3))
    guide = torch.rand(1, 4, 96, 128, generator=g).to(device)

    def run():
        return atrous(c, n, x, iterations=3, sigma_color=1.0), guided(c, guide, radius=8, eps=0.01)

    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(2):  # warm-up: Triton compiles, tables and tap weights land on the device
            run()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out_a, out_g = run()
    for seed in (5, 6):
        g = torch.Generator().manual_seed(seed)
        for t in (c, n, x, guide):
            t.copy_(torch.rand(t.shape, generator=g).to(device))
        graph.replay()
        want_a, want_g = run()
        torch.testing.assert_close(out_a, want_a, rtol=0, atol=1e-6)
        torch.testing.assert_close(out_g, want_g, rtol=0, atol=1e-6)


def test_triton_pipeline_matches_the_float64_torch_code_in_the_interpreter():
    """The fused guided pipeline (RestoreOp) of the Triton back end: every branch (light sources
    with and without an emission input, kept direct light, hit, 1/2 and 1/3 resolution)."""
    pytest.importorskip("embreex")
    (worst,) = _interpret(_INTERPRETED_RESTORE)
    assert worst < 5e-4  # measured 1.3e-4 (the C back end: 1.5e-4 at full, 1.7e-3 at 1/3 resolution)


def test_temporal_denoiser_on_the_triton_pipeline_in_the_interpreter():
    """The TemporalDenoiser's CUDA path (its accumulation and the guided pipeline in Triton)
    against the float64 torch code, two frames of a moving camera; and the accumulation kernel
    alone on the second frame (edges, disocclusions, background, fireflies at a bound)."""
    pytest.importorskip("embreex")
    worst, accumulation = _interpret(_INTERPRETED_TEMPORAL)
    assert worst < 2e-4  # measured 9.0e-6 with the accumulation in the torch code
    assert accumulation < 1e-5  # as the C kernel's test (tests/backends/test_temporal_ops.py)
