"""The affine and play parts of a graph, every sensor's in a few operations, and the play models' state.

Every affine or play part (`pipeline.export.trained.LinearPart` of order 1: the affine map, with play
widths the play model) is ``f = x[:6] + c + A x[:k] + B z``: the standardisation folded into the weights
(``A = W_1 / scale``, ``c = W_0 - A offset``) and z the play states of its raw wrench, ``z = (xm - y) / r``
(xm its wrench columns, one per play operator of width r, y the operators' outputs). The parts of a graph
are computed together, in float64 also inside a float32 graph (as the project computes them): one Gemm of
the input columns for every ``x[:6] + c + A x + (B / r) xm``, and for the play models one Gather of xm
(N, M), one Scan over the rows running every operator at once (``y_t = clip(y_{t-1}, xm_t - r, xm_t +
r)``, a NaN of ``y_{t-1}`` a fresh start: ``y = xm``) and one MatMul of ``(B / r) y``, subtracted: 9
operations for every sensor (a control loop's call costs per operation, `pipeline.export.graph`). In real
arithmetic exactly the project's model; in float64 within 1e-12 N of it.

The rows of a call are consecutive samples (in time order); the state is the play outputs after the last
row (``state_out`` (M,)), which the next call takes as its ``state`` input (M,), whose default is NaN
everywhere: a caller that feeds ``inputs`` alone starts afresh at its first row (and a NaN reading
restarts its operators). Column j of the state
belongs to the sensor, raw axis and width of `state_layout`'s entry j (per sensor, width k and axis a in the
order of `pipeline.core.play.play_features`); one sensor's columns can be carried alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pipeline.export.trained import WRENCH, GroupModel, LinearPart

STATE, STATE_OUT = "state", "state_out"  # the graph's state input (default NaN) and output, (M,)
AXES = ("fx", "fy", "fz", "tx", "ty", "tz")


def stackable(part: Any) -> bool:
    """Whether `part` is an affine or play part (a linear part of order 1): computed in the stack."""
    return isinstance(part, LinearPart) and int(part.powers.sum(axis=1).max(initial=0)) <= 1


def state_layout(models: Sequence[GroupModel]) -> list[dict[str, Any]]:
    """The state's columns in a graph of `models` side by side: {index, sensor, axis, width, unit}."""
    out: list[dict[str, Any]] = []
    for m in models:
        for sensor, part in zip(m.sensors, m.parts, strict=True):
            if not stackable(part) or part.widths is None:
                continue
            for row in part.widths:
                for a, width in enumerate(row):
                    unit = "N" if a < 3 else "Nm"
                    out.append(
                        {
                            "index": len(out),
                            "sensor": sensor,
                            "axis": AXES[a],
                            "width": float(width),
                            "unit": unit,
                        }
                    )
    return out


def folded(part: LinearPart) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A (6, k), c (6,), B (6, 6 K) or (6, 0)) of an affine or play part (module docstring)."""
    k = part.powers.shape[1]
    order = np.argmax(part.powers[1:], axis=1)  # the input each linear column multiplies
    linear = np.zeros((WRENCH, k))
    linear[:, order] = part.weights[:, 1 : 1 + k] / part.scale[order]
    bias = part.weights[:, 0] - linear @ part.offset
    return linear, bias, part.weights[:, 1 + k :]


def stack_linear(b: Any, x: str, width: int, parts: Sequence[tuple[int, LinearPart]]) -> tuple[str, int]:
    """(calibrated wrenches (N, 6 P) of the affine and play `parts` [(first input column, part)] of x (N,
    `width`) in the graph of builder `b` (`pipeline.export.graph`), in float64; the state's size M (0: no
    play part)). With M > 0 the graph gets the ``state`` input and ``state_out`` output (module docstring;
    `build` declares them)."""
    from onnx import TensorProto

    n = len(parts)
    gemm, bias = np.zeros((width, WRENCH * n)), np.zeros(WRENCH * n)
    play_w, play_cols, widths = [], [], []
    for j, (lo, part) in enumerate(parts):
        a, c, w_play = folded(part)
        out = slice(j * WRENCH, (j + 1) * WRENCH)
        gemm[lo : lo + a.shape[1], out] = a.T
        gemm[lo + np.arange(WRENCH), out.start + np.arange(WRENCH)] += 1.0  # the raw wrench itself
        bias[out] = c
        if part.widths is not None:
            # B z = B (xm - y) / r: the xm part folded into the Gemm, the y part after the Scan
            cols, r = np.tile(lo + np.arange(WRENCH), len(part.widths)), part.widths.reshape(-1)
            block = np.zeros((len(cols), WRENCH * n))
            block[:, out] = (w_play / r).T
            np.add.at(gemm, cols, block)
            play_cols.append(cols)
            widths.append(r)
            play_w.append(block)
    original = b.dtype
    b.dtype = np.dtype(np.float64)
    try:
        x64 = b.op("Cast", [x], "linear_x64", to=TensorProto.DOUBLE) if original == np.float32 else x
        y = b.op("Gemm", [x64, b.const("linear_a", gemm), b.const("linear_c", bias)], "linear_affine")
        size = int(sum(len(c) for c in play_cols))
        if size:
            ys = _play(b, x64, np.concatenate(play_cols), np.concatenate(widths), original == np.float32)
            held = b.op("MatMul", [ys, b.const("play_b", np.concatenate(play_w))], "play_held")
            y = b.op("Sub", [y, held], "linear_play")
    finally:
        b.dtype = original
    out = b.op("Cast", [y], "linear_calibrated", to=TensorProto.FLOAT) if original == np.float32 else y
    return out, size


def _play(b: Any, x64: str, columns: np.ndarray, widths: np.ndarray, float32: bool) -> str:
    """(N, M) the play outputs y after each row of x64's `columns` (one per operator, float64), the
    operators of `widths` run over the rows by one Scan from the ``state`` input; the last: ``state_out``."""
    from onnx import TensorProto, helper, numpy_helper

    xm = b.op("Gather", [x64, b.const("play_columns", columns, np.int64)], "play_inputs", axis=1)
    m = len(columns)
    state = b.op("Cast", [STATE], "state64", to=TensorProto.DOUBLE) if float32 else STATE
    double = TensorProto.DOUBLE
    body = helper.make_graph(
        [
            helper.make_node("IsNaN", ["y"], ["fresh"]),
            helper.make_node("Where", ["fresh", "x", "y"], ["start"]),
            helper.make_node("Add", ["x", "r"], ["high"]),
            helper.make_node("Sub", ["x", "r"], ["low"]),
            helper.make_node("Min", ["start", "high"], ["capped"]),
            helper.make_node("Max", ["capped", "low"], ["y_next"]),
            helper.make_node("Identity", ["y_next"], ["y_row"]),
        ],
        "play_step",
        [helper.make_tensor_value_info(v, double, [m]) for v in ("y", "x")],
        [helper.make_tensor_value_info(v, double, [m]) for v in ("y_next", "y_row")],
        [numpy_helper.from_array(np.asarray(widths, dtype=np.float64), "r")],
    )
    ys = b._name("play_outputs")
    last = STATE_OUT if not float32 else b._name("play_last")
    b.nodes.append(helper.make_node("Scan", [state, xm], [last, ys], name=ys, body=body, num_scan_inputs=1))
    if float32:
        b.op("Cast", [last], output=STATE_OUT, to=TensorProto.FLOAT)
    return ys
