"""onnxruntime's CPU kernels, one small graph per way of writing a step of the exported Denoiser.

    python scripts/bench_ort_ops.py --out out/bench-ort-ops [--rounds 15]

Each row builds a one- or few-node ONNX graph (opset 18) at the size the step has in the exported
default Denoiser at 1920x1080 (the half-resolution guided filter's planes at 960x540) and times
it in onnxruntime (default threads: one per core) on random inputs: the median ms of ``--rounds``
calls after 3 untimed ones. The pairs are the choices ``torchgi.core.exported``,
``backends.torch_code.filter_box`` and ``light.median_level`` / ``light.choose`` make when a graph
is exported (docs/benchmarks/onnx.md). Writes ``ops.csv``, ``ops.json`` and ``ops.md``.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from benchmark_utils import markdown_table, metadata, write_results

H, W = 1080, 1920


def _session(nodes, inputs, consts=()):
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info(n, TensorProto.FLOAT, a.shape) for n, a in inputs],
                              [helper.make_tensor_value_info(nodes[-1].output[0], TensorProto.FLOAT, None)],
                              [numpy_helper.from_array(np.asarray(v), k) for k, v in consts])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    return ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])


def _time(nodes, inputs, consts, rounds):
    s = _session(nodes, inputs, consts)
    feed = dict(inputs)
    for _ in range(3):
        s.run(None, feed)
    ts = []
    for _ in range(rounds):
        t = time.perf_counter()
        s.run(None, feed)
        ts.append((time.perf_counter() - t) * 1e3)
    return sorted(ts)[len(ts) // 2]


def cases():
    """(step, way, nodes, inputs, constants) for every row."""
    from onnx import TensorProto
    from onnx.helper import make_node as n

    rng = np.random.default_rng(0)
    r = lambda *shape: rng.random(shape, dtype=np.float32)
    x3, m1 = r(1, 3, H, W), r(1, 1, H, W)
    half, one = ("half", np.float32(0.5)), ("one", np.float32(1.0))
    gt = n("Greater", ["m", "half"], ["c"])
    cast = n("Cast", ["c"], ["f"], to=TensorProto.FLOAT)
    yield ("select, 3 channels, 1-channel mask", "Where", [gt, n("Where", ["c", "x", "y"], ["q"])],
           [("x", x3), ("y", x3 * 2), ("m", m1)], [half])
    yield ("select, 3 channels, 1-channel mask", "a m + b (1 - m) (exported.where)",
           [gt, cast, n("Mul", ["x", "f"], ["a"]), n("Sub", ["one", "f"], ["g"]), n("Mul", ["y", "g"], ["b"]),
            n("Add", ["a", "b"], ["q"])], [("x", x3), ("y", x3 * 2), ("m", m1)], [half, one])
    yield ("select, 1 channel, a number", "Where", [gt, n("Where", ["c", "m", "one"], ["q"])], [("m", m1)], [half, one])
    yield ("select, 1 channel, a number", "a m + (1 - m) (exported.where)",
           [gt, cast, n("Mul", ["m", "f"], ["a"]), n("Sub", ["one", "f"], ["g"]), n("Add", ["a", "g"], ["q"])],
           [("m", m1)], [half, one])
    yield ("channel maximum of 3", "ReduceMax", [n("ReduceMax", ["x", "ax"], ["q"], keepdims=1)], [("x", x3)],
           [("ax", np.array([1]))])
    yield ("channel maximum of 3", "3 Slice + 2 Max (exported.channel_max)",
           [n("Slice", ["x", f"s{i}", f"e{i}", "ax"], [f"c{i}"]) for i in range(3)]
           + [n("Max", ["c0", "c1"], ["c01"]), n("Max", ["c01", "c2"], ["q"])], [("x", x3)],
           [("ax", np.array([1]))] + [(f"s{i}", np.array([i])) for i in range(3)] + [(f"e{i}", np.array([i + 1])) for i in range(3)])
    for k, planes, h, w in ((3, 1, H, W), (7, 1, H, W), (17, 1, H, W), (5, 29, H // 2, W // 2)):
        rad, x = k // 2, r(planes, 1, h, w)
        step = f"box mean {k}x{k}, {planes} plane{'s' if planes > 1 else ''} of {w}x{h}"
        yield (step, "two separable AveragePool",
               [n("AveragePool", ["x"], ["a"], kernel_shape=[1, k], pads=[0, rad, 0, rad], count_include_pad=0),
                n("AveragePool", ["a"], ["q"], kernel_shape=[k, 1], pads=[rad, 0, rad, 0], count_include_pad=0)], [("x", x)], [])
        yield (step, "one square AveragePool (box_pool, exported)",
               [n("AveragePool", ["x"], ["q"], kernel_shape=[k, k], pads=[rad] * 4, count_include_pad=0)], [("x", x)], [])
    for cip in (1, 0):
        yield ("2x2 block means, 3 channels", f"AveragePool ceil_mode=1 count_include_pad={cip}"
               + (" (block_mean)" if cip == 0 else ""),
               [n("AveragePool", ["x"], ["q"], kernel_shape=[2, 2], strides=[2, 2], ceil_mode=1, count_include_pad=cip)],
               [("x", x3)], [])
    v = r(1, (H // 4) * (W // 4))
    for k, way in ((v.shape[1], "TopK of all"), (v.shape[1] // 2 + 1, "TopK of the lower half (median_level, exported)")):
        yield (f"median of {v.shape[1]} values", way, [n("TopK", ["v", "k"], ["q", "i"], largest=0)], [("v", v)],
               [("k", np.array([k]))])
    c = r(1, 15, H // 2, W // 2)
    yield ("bilinear x2 of 15 coefficient planes", "Resize, (1, 15, h, w)",
           [n("Resize", ["x", "", "sc"], ["q"], mode="linear", coordinate_transformation_mode="half_pixel")],
           [("x", c)], [("sc", np.array([1, 1, 2, 2], np.float32))])
    yield ("bilinear x2 of 15 coefficient planes", "Resize, (1, h, w, 15)",
           [n("Resize", ["x", "", "sc"], ["q"], mode="linear", coordinate_transformation_mode="half_pixel")],
           [("x", np.ascontiguousarray(c.transpose(0, 2, 3, 1)))], [("sc", np.array([1, 2, 2, 1], np.float32))])
    e2 = r(1, 2, H, W)
    yield ("weights of two radii", "Softmax over channels", [n("Softmax", ["x"], ["q"], axis=1)], [("x", e2)], [])
    yield ("weights of two radii", "two Sigmoid + Concat (light.choose)",
           [n("Slice", ["x", "s0", "e0", "ax"], ["a"]), n("Slice", ["x", "s1", "e1", "ax"], ["b"]), n("Sub", ["b", "a"], ["d"]),
            n("Sigmoid", ["d"], ["w0"]), n("Neg", ["d"], ["nd"]), n("Sigmoid", ["nd"], ["w1"]),
            n("Concat", ["w0", "w1"], ["q"], axis=1)], [("x", e2)],
           [("ax", np.array([1])), ("s0", np.array([0])), ("e0", np.array([1])), ("s1", np.array([1])), ("e1", np.array([2]))])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench-ort-ops")
    ap.add_argument("--rounds", type=int, default=15)
    args = ap.parse_args()
    rows = []
    for step, way, nodes, inputs, consts in cases():
        rows.append({"step": step, "way": way, "ms": _time(nodes, inputs, consts, args.rounds)})
        print(rows[-1], flush=True)
    out = Path(args.out)
    meta = metadata(os.cpu_count() or 1) | {"onnxruntime": __import__("onnxruntime").__version__, "args": vars(args)}
    write_results(rows, meta, out, "ops")
    (out / "ops.md").write_text(markdown_table(rows, ["step", "way", "ms"]) + "\n")


if __name__ == "__main__":
    main()
