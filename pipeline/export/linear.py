"""The affine, play and arx parts of a graph, every sensor's in a few operations, and the memory's state.

Every affine, play or arx part (`pipeline.calib.parts.LinearPart` of order 1: the affine map, with play
widths the play model, with time constants the arx model) is ``f = x[:6] + c + A x[:k] + B z``: the
standardisation folded into the weights (``A = W_1 / scale``, ``c = W_0 - A offset``) and z the states of its
operators on the raw wrench, ``z = (xm - y) / s`` (xm its wrench columns, one per operator, y the operators'
outputs, s a play operator's width or 1 for a filter). The parts of a graph are computed together, in float64
also inside a float32 graph (as the project computes them): one Gemm of the input columns for every
``x[:6] + c + A x + (B / s) xm``, and for the models with memory one Gather of xm (N, M), one Scan over the
rows running every operator at once (`pipeline.core.lowpass.memory_step`: ``y_t = clip(y' + alpha (xm_t -
y'), xm_t - r, xm_t + r)``, y' = ``y_{t-1}`` or at a fresh start, a NaN, xm_t; a play operator has alpha = 0
and r its width, a filter r infinite) and one MatMul of ``(B / s) y``, subtracted: 9 operations for every
sensor (a control loop's call costs per operation, `pipeline.export.graph`). In real arithmetic exactly the
project's model; in float64 within 1e-12 N of it.

The rows of a call are consecutive samples (in time order; for filters `period` s apart, the manifest's
``period_s``); the state is the operators' outputs after the last row (``state_out`` (M,)), which the next
call takes as its ``state`` input (M,), whose default is NaN everywhere: a caller that feeds ``inputs`` alone
starts afresh at its first row (and a NaN reading restarts its operators). Column j of the state belongs to
the sensor, raw axis and operator of `state_layout`'s entry j (per sensor, the play operators then the
filters, each operator's 6 axes in order, as `pipeline.core.lowpass.memory_of`); one sensor's columns can be
carried alone.

A windowed network (`pipeline.calib.parts.WindowPart`) computes its play part here, with its filters
among the operators (their weights zero: the play model does not read them); its network reads their outputs
(`pipeline.export.window`), so its state is the operators' like the others'.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.core.errors import DataError
from pipeline.core.lowpass import operator_columns
from pipeline.export.trained import WRENCH, GroupModel, LinearPart, WindowPart

STATE, STATE_OUT = "state", "state_out"  # the graph's state input (default NaN) and output, (M,)
AXES = ("fx", "fy", "fz", "tx", "ty", "tz")


def stackable(part: Any) -> bool:
    """Whether `part` is an affine, play or arx part (a linear part of order 1): computed in the stack."""
    return isinstance(part, LinearPart) and int(part.powers.sum(axis=1).max(initial=0)) <= 1


def linear_of(part: Any) -> Any:
    """The part computed in the linear stack for `part`: a windowed network's play part, else itself."""
    return part.play if isinstance(part, WindowPart) else part


def state_layout(models: Sequence[GroupModel]) -> list[dict[str, Any]]:
    """The state's columns in a graph of `models` side by side: {index, sensor, axis, unit, and a play
    operator's ``width`` (in the unit) or a filter's ``time_constant_s``}."""
    out: list[dict[str, Any]] = []
    for m in models:
        for sensor, part in zip(m.sensors, m.parts, strict=True):
            part = linear_of(part)
            if not stackable(part) or not part.state_size:
                continue
            widths = np.reshape(part.widths, -1) if part.widths is not None else ()
            operators = [("width", float(w)) for w in widths]
            for tau in part.time_constants if part.time_constants is not None else ():
                operators += [("time_constant_s", float(tau))] * WRENCH
            for j, (key, value) in enumerate(operators):
                a = j % WRENCH
                unit = "N" if a < 3 else "Nm"
                out.append({"index": len(out), "sensor": sensor, "axis": AXES[a], key: value, "unit": unit})
    return out


def state_period(models: Sequence[GroupModel]) -> float | None:
    """The sample period (s) the filters of `models` run at (None: no filter); DataError if they differ
    (groups trained on logs of other rates: export them apart)."""
    parts = [linear_of(p) for m in models for p in m.parts]
    periods = {float(p.period) for p in parts if isinstance(p, LinearPart) and p.time_constants is not None}
    if len(periods) > 1:
        raise DataError(f"filters trained at different sample periods share no graph: {sorted(periods)} s")
    return periods.pop() if periods else None


def folded(part: LinearPart) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A (6, k), c (6,), B (6, M) or (6, 0)) of an affine, play or arx part (module docstring)."""
    k = part.powers.shape[1]
    order = np.argmax(part.powers[1:], axis=1)  # the input each linear column multiplies
    linear = np.zeros((WRENCH, k))
    linear[:, order] = part.weights[:, 1 : 1 + k] / part.scale[order]
    bias = part.weights[:, 0] - linear @ part.offset
    return linear, bias, part.weights[:, 1 + k :]


@dataclass(frozen=True)
class LinearStack:
    """What `stack_linear` adds to a graph."""

    out: str  # (N, 6 P) the parts' calibrated wrenches, in the graph's float type
    state_size: int  # M: the operators' state (0: no part with memory)
    outputs: str | None  # (N, M) float64: the operators' outputs after each row (None: M = 0)
    first: list[int]  # per part, its first column of `outputs` (-1: none)


def stack_linear(b: Any, x: str, width: int, parts: Sequence[tuple[int, LinearPart]]) -> LinearStack:
    """The calibrated wrenches of the affine, play and arx `parts` [(first input column, part)] of x (N,
    `width`) in the graph of builder `b` (`pipeline.export.graph`), computed in float64, and their operators'
    outputs (`LinearStack`). With operators the graph gets the ``state`` input and ``state_out`` output
    (module docstring; `build` declares them)."""
    from onnx import TensorProto

    n = len(parts)
    gemm, bias = np.zeros((width, WRENCH * n)), np.zeros(WRENCH * n)
    play_w, play_cols, radii, gains, first = [], [], [], [], []
    size = 0
    for j, (lo, part) in enumerate(parts):
        a, c, w_play = folded(part)
        out = slice(j * WRENCH, (j + 1) * WRENCH)
        gemm[lo : lo + a.shape[1], out] = a.T
        gemm[lo + np.arange(WRENCH), out.start + np.arange(WRENCH)] += 1.0  # the raw wrench itself
        bias[out] = c
        first.append(size if part.state_size else -1)
        if part.state_size:
            # B z = B (xm - y) / s: the xm part folded into the Gemm, the y part after the Scan
            radius, alpha, scale = operator_columns(part.widths, part.time_constants, part.period)
            cols = np.tile(lo + np.arange(WRENCH), len(radius) // WRENCH)
            block = np.zeros((len(cols), WRENCH * n))
            block[:, out] = (w_play / scale).T
            np.add.at(gemm, cols, block)
            play_cols.append(cols)
            radii.append(radius)
            gains.append(alpha)
            play_w.append(block)
            size += len(cols)
    original = b.dtype
    b.dtype = np.dtype(np.float64)
    try:
        x64 = b.op("Cast", [x], "linear_x64", to=TensorProto.DOUBLE) if original == np.float32 else x
        y = b.op("Gemm", [x64, b.const("linear_a", gemm), b.const("linear_c", bias)], "linear_affine")
        ys = None
        if size:
            operators = np.concatenate(radii), np.concatenate(gains)
            ys = _play(b, x64, np.concatenate(play_cols), *operators, original == np.float32)
            held = b.op("MatMul", [ys, b.const("play_b", np.concatenate(play_w))], "play_held")
            y = b.op("Sub", [y, held], "linear_play")
    finally:
        b.dtype = original
    out = b.op("Cast", [y], "linear_calibrated", to=TensorProto.FLOAT) if original == np.float32 else y
    return LinearStack(out, size, ys, first)


def _play(b: Any, x64: str, columns: np.ndarray, radius: np.ndarray, alpha: np.ndarray, float32: bool) -> str:
    """(N, M) the operators' outputs y after each row of x64's `columns` (one per operator, float64), the
    operators of `radius` and `alpha` (M,) run over the rows by one Scan from the ``state`` input (the filter
    step only where some alpha is not 0); the last: ``state_out``."""
    from onnx import TensorProto, helper, numpy_helper

    xm = b.op("Gather", [x64, b.const("play_columns", columns, np.int64)], "play_inputs", axis=1)
    m = len(columns)
    state = b.op("Cast", [STATE], "state64", to=TensorProto.DOUBLE) if float32 else STATE
    double = TensorProto.DOUBLE
    constants = [numpy_helper.from_array(np.asarray(radius, dtype=np.float64), "r")]
    nodes = [
        helper.make_node("IsNaN", ["y"], ["fresh"]),
        helper.make_node("Where", ["fresh", "x", "y"], ["start"]),
    ]
    moved = "start"
    if np.any(alpha):  # the filters: start + alpha (x - start)
        constants.append(numpy_helper.from_array(np.asarray(alpha, dtype=np.float64), "alpha"))
        nodes += [
            helper.make_node("Sub", ["x", "start"], ["gap"]),
            helper.make_node("Mul", ["gap", "alpha"], ["step"]),
            helper.make_node("Add", ["start", "step"], ["moved"]),
        ]
        moved = "moved"
    nodes += [
        helper.make_node("Add", ["x", "r"], ["high"]),
        helper.make_node("Sub", ["x", "r"], ["low"]),
        helper.make_node("Min", [moved, "high"], ["capped"]),
        helper.make_node("Max", ["capped", "low"], ["y_next"]),
        helper.make_node("Identity", ["y_next"], ["y_row"]),
    ]
    body = helper.make_graph(
        nodes,
        "memory_step",
        [helper.make_tensor_value_info(v, double, [m]) for v in ("y", "x")],
        [helper.make_tensor_value_info(v, double, [m]) for v in ("y_next", "y_row")],
        constants,
    )
    ys = b._name("play_outputs")
    last = STATE_OUT if not float32 else b._name("play_last")
    b.nodes.append(helper.make_node("Scan", [state, xm], [last, ys], name=ys, body=body, num_scan_inputs=1))
    if float32:
        b.op("Cast", [last], output=STATE_OUT, to=TensorProto.FLOAT)
    return ys
