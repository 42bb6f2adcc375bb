"""ONNX graphs of the calibration models, normalisation inside, in float32 or float64.

A graph has one input ``inputs`` (N, K) and one output ``calibrated`` (N, 6 S): the raw inputs of its
sensors side by side (each sensor's columns in the models' order: fx fy fz N, tx ty tz Nm, temperature
degC, [accelerometer x y z m/s^2, gyroscope x y z rad/s]) and the calibrated wrenches (fx..tz per sensor,
N and Nm, each in its sensor frame), sensor after sensor. N is dynamic (1 in a control loop). A second
input ``offsets`` (1, K), in the units of the inputs' columns, is subtracted from ``inputs`` before
anything else: the raw-side offset changes of a re-zeroing (`pipeline.export.offsets`; zero on the
columns other than the wrench's). It defaults to zeros (an initializer of the same name, which a caller
may override: onnxruntime's overridable initializers), so a caller that feeds ``inputs`` alone runs the
calibration as delivered, bit for bit; a robot's loop binds it once at start-up.

Per sensor, with x its columns (the forms of `pipeline.export.trained`):

- network: ``x[:, :6] + x[:, :7] @ A^T + a + out_scale * mlp((x - in_offset) / in_scale)`` (A, a: the
  affine map the network corrects). Networks of one signature (inputs, depth, activations; every network
  of the fused graph of a robot) are evaluated together, one operation per layer for all of them: hidden
  widths padded with zero units, the normalisation folded into the first layer's weights and the output
  scale into the last's (exact in real arithmetic; in float32 within an ulp of torch's result), in
  float32 a grouped 1-D convolution per layer, in float64 a batched MatMul; the affine maps one
  block-diagonal Gemm; ``(raw + affine) + correction`` in torch's order. A control loop's single sample
  costs per operation more than arithmetic (onnxruntime: ~0.4 us an operation on this project's
  reference machine), so few operations. Measured there (`benchmarks/infer_speed.py`), and kept so:
  onnxruntime fuses a ReLU into its convolution (faster), but its fused convolution + LeakyReLU is
  ~4 us slower a call than the two apart, so other activations follow a Reshape that keeps them apart;
  a graph laid out for one sample per call (``per_sample``: samples as the convolutions' batch, (N, C,
  1)) needs no Transpose but is ~2x slower on large batches than one laid out for batches (samples
  along the convolutions' length, (1, C, N)): the fused graph of an export is the control loop's,
  the groups' graphs are for batches (`ftcal calibrate`);
- affine and play: every sensor's at once, in float64 (`pipeline.export.linear`), the play models' state
  carried from row to row and call to call by the graph's ``state`` input and ``state_out`` output;
- windowed network: its play part and filters in the stack above (their state in the same ``state``), plus
  its network's correction of the raw wrench now, the filters' outputs and the temperature
  (`pipeline.export.window`);
- polynomial: ``x[:, :6] + phi((x[:, :7] - offset) / scale) @ W^T``, phi the monomials: the
  standardised inputs padded with a column of ones, gathered by an index table (P, order) and multiplied
  along the last axis (ReduceProd), so one Gather and one ReduceProd compute every monomial; in float64
  also inside a float32 graph (as the project computes them: float32 arithmetic would lose 1e-3 N);
- raw: ``x[:, :6]``.

The fused graph of several groups takes every sensor's inputs side by side (networks read their own
columns, other models theirs; outputs concatenated in sensor order), so a robot's loop makes one call per
sample for all its sensors. Opset 17 (onnxruntime >= 1.14).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pipeline.export.linear import STATE, STATE_OUT, linear_of, stack_linear, stackable
from pipeline.export.mlp import stacked_mlp
from pipeline.export.trained import (
    WRENCH,
    GroupModel,
    IdentityPart,
    LinearPart,
    NetworkPart,
    WindowPart,
)
from pipeline.export.window import add_corrections, window_corrections

OPSET = 17
INPUT, OUTPUT = "inputs", "calibrated"
OFFSETS = "offsets"  # (1, K) subtracted from the inputs; default zeros (module docstring)
DTYPES = ("float32", "float64")


class _Builder:
    """Collects nodes and constants of one graph; every tensor gets a unique name."""

    def __init__(self, dtype: str) -> None:
        self.dtype = np.dtype(dtype)
        self.nodes: list[Any] = []
        self.initializers: list[Any] = []
        self._count = 0

    def _name(self, hint: str) -> str:
        self._count += 1
        return f"{hint}_{self._count}"

    def const(self, hint: str, value: Any, dtype: Any = None) -> str:
        """A constant tensor (in the graph's float type unless `dtype` is given)."""
        from onnx import numpy_helper

        name = self._name(hint)
        array = np.asarray(value, dtype=dtype if dtype is not None else self.dtype)
        self.initializers.append(numpy_helper.from_array(array, name))
        return name

    def op(
        self,
        op_type: str,
        inputs: Sequence[str],
        hint: str | None = None,
        output: str | None = None,
        **attrs: Any,
    ) -> str:
        from onnx import helper

        out = output or self._name(hint or op_type.lower())
        self.nodes.append(helper.make_node(op_type, list(inputs), [out], name=out, **attrs))
        return out

    def columns(self, x: str, start: int, stop: int, hint: str) -> str:
        """x[:, start:stop]."""
        index = self.const(f"{hint}_columns", np.arange(start, stop), np.int64)
        return self.op("Gather", [x, index], hint, axis=1)


def monomial_index(powers: np.ndarray) -> np.ndarray:
    """(P, order) column indices into [z, 1] whose product is each monomial z^powers[p] (7 = the ones)."""
    powers = np.asarray(powers, dtype=np.int64)
    n_vars = powers.shape[1]
    order = max(int(powers.sum(axis=1).max(initial=0)), 1)
    index = np.full((len(powers), order), n_vars, dtype=np.int64)
    for p, row in enumerate(powers):
        factors = np.repeat(np.arange(n_vars), row)
        index[p, : len(factors)] = factors
    return index


def _linear(b: _Builder, x: str, part: LinearPart, hint: str) -> str:
    n_vars = part.powers.shape[1]
    z = b.op(
        "Div",
        [
            b.op("Sub", [b.columns(x, 0, n_vars, f"{hint}_x"), b.const(f"{hint}_offset", part.offset)]),
            b.const(f"{hint}_scale", part.scale),
        ],
    )
    pads = b.const("pads", [0, 0, 0, 1], np.int64)
    padded = b.op("Pad", [z, pads, b.const("one", 1.0)], f"{hint}_z1", mode="constant")
    gathered = b.op(
        "Gather", [padded, b.const(f"{hint}_monomials", monomial_index(part.powers), np.int64)], axis=1
    )
    phi = b.op("ReduceProd", [gathered], f"{hint}_phi", axes=[2], keepdims=0)
    return b.op(
        "MatMul",
        [phi, b.const(f"{hint}_weights", np.ascontiguousarray(part.weights.T))],
        f"{hint}_correction",
    )


def _sensor(b: _Builder, x: str, part: Any, hint: str) -> str:
    """One sensor's calibrated wrench (N, 6) from its inputs x (N, n_inputs)."""
    raw = b.columns(x, 0, WRENCH, f"{hint}_raw")
    if isinstance(part, IdentityPart):
        return b.op("Identity", [raw], f"{hint}_calibrated")
    if isinstance(part, LinearPart) and b.dtype == np.float32:
        # The project computes these models in float64 (a 4th-order polynomial in float32 loses 1e-3 N):
        # float32 in and out, float64 inside.
        from onnx import TensorProto

        b.dtype = np.dtype(np.float64)
        try:
            x64 = b.op("Cast", [x], f"{hint}_x64", to=TensorProto.DOUBLE)
            y64 = b.op("Add", [b.columns(x64, 0, WRENCH, f"{hint}_raw64"), _linear(b, x64, part, hint)])
        finally:
            b.dtype = np.dtype(np.float32)
        return b.op("Cast", [y64], f"{hint}_calibrated", to=TensorProto.FLOAT)
    elif isinstance(part, LinearPart):
        correction = _linear(b, x, part, hint)
    else:
        raise TypeError(f"cannot export a {type(part).__name__}")
    return b.op("Add", [raw, correction], f"{hint}_calibrated")


def _signature(part: Any, n_inputs: int) -> tuple | None:
    """Networks of one signature (inputs, depth, activations) are evaluated stacked, hidden widths padded
    with zeros to the widest; None: not a network."""
    if not isinstance(part, NetworkPart):
        return None
    return (n_inputs, tuple((layer.activation, layer.alpha) for layer in part.layers))


def _stack(
    b: _Builder,
    x: str,
    width: int,
    starts: Sequence[int],
    n_inputs: int,
    parts: Sequence[NetworkPart],
    per_sample: bool = False,
) -> str:
    """Calibrated wrenches (N, 6 S) of S networks of one signature, each layer one operation for all S:
    a grouped 1-D convolution in float32 (group = network; samples along the length, or as the batch if
    `per_sample`; bias inside, and a ReLU, which onnxruntime fuses), a batched MatMul over (S, N, n) in
    float64 (onnxruntime's Conv is float32 only): one matrix product per network for a batch of N
    samples as for one. The affine maps are one block-diagonal Gemm on x; ``(raw + affine) +
    correction`` in torch's order. `width`: x's columns; the networks read
    x[:, starts[s] : starts[s] + n_inputs]."""
    s_count = len(parts)
    columns = np.concatenate([np.arange(lo, lo + n_inputs) for lo in starts])
    if not np.array_equal(columns, np.arange(width)):  # not every column of x, in order
        x = b.op("Gather", [x, b.const("stack_columns", columns, np.int64)], axis=1)
    raw_columns = (np.arange(s_count)[:, None] * n_inputs + np.arange(WRENCH)).reshape(-1)
    raw = b.op("Gather", [x, b.const("raw_columns", raw_columns, np.int64)], "stack_raw", axis=1)
    affine_w = np.zeros((s_count * n_inputs, s_count * WRENCH))  # block-diagonal, on each x[:, :k]
    for s, p in enumerate(parts):
        k = p.affine_weight.shape[1]  # 7, or 6 without temperature
        affine_w[s * n_inputs : s * n_inputs + k, s * WRENCH : (s + 1) * WRENCH] = p.affine_weight.T
    affine_b = np.concatenate([p.affine_bias for p in parts])
    affine = b.op("Gemm", [x, b.const("affine_w", affine_w), b.const("affine_b", affine_b)], "stack_affine")
    start = b.op("Add", [raw, affine], "stack_start")
    correction = stacked_mlp(b, x, n_inputs, parts, per_sample)
    return b.op("Add", [start, correction], "stack_calibrated")


def _all(b: _Builder, x: str, models: Sequence[GroupModel], per_sample: bool) -> tuple[str, int, int]:
    """Output (N, 6 S) of every sensor of `models` (input columns side by side); the number of inputs; the
    size of the state (`pipeline.export.linear`; 0: none).

    Networks of equal signature are stacked (`_stack`, a single network too), the affine and play parts
    too (`stack_linear`), with the windowed networks' play parts and filters, whose networks' corrections
    follow (`pipeline.export.window`); the other models run alone; a final Gather restores the sensor order
    when stacking changed it.
    """
    sensors, start = [], 0  # (input start, n_inputs, part, name)
    for m in models:
        for sensor, part in zip(m.sensors, m.parts, strict=True):
            sensors.append((start, m.n_inputs, part, sensor))
            start += m.n_inputs
    stacks: dict[Any, list[int]] = {}
    for k, (_, n, part, _) in enumerate(sensors):
        key = "linear" if stackable(linear_of(part)) else _signature(part, n)
        stacks.setdefault(key if key is not None else ("alone", k), []).append(k)
    outs, order, state = [], [], 0
    for key, members in stacks.items():
        if key == "linear":
            entries = [(sensors[k][0], linear_of(sensors[k][2])) for k in members]
            stack = stack_linear(b, x, start, entries)
            state = stack.state_size
            windowed = [j for j, k in enumerate(members) if isinstance(sensors[k][2], WindowPart)]
            pieces = [(stack.out, list(range(len(members))))]
            if windowed:
                picked = [(sensors[members[j]][0], sensors[members[j]][2], stack.first[j]) for j in windowed]
                correction = window_corrections(b, x, start, stack.outputs, picked, per_sample)
                pieces = add_corrections(b, stack.out, len(members), windowed, correction)
            outs += [p[0] for p in pieces]
            order += [members[j] for p in pieces for j in p[1]]
            continue
        if _signature(sensors[members[0]][2], sensors[members[0]][1]) is not None:
            picked = [sensors[k] for k in members]
            starts, parts = [s[0] for s in picked], [s[2] for s in picked]
            outs.append(_stack(b, x, start, starts, picked[0][1], parts, per_sample))
        else:
            lo, n, part, sensor = sensors[members[0]]
            inputs = x if (lo, n) == (0, start) else b.columns(x, lo, lo + n, f"{sensor}_inputs")
            outs.append(_sensor(b, inputs, part, sensor))
        order += members
    out = outs[0] if len(outs) == 1 else b.op("Concat", outs, "concat", axis=1)
    if order != sorted(order):
        columns = np.concatenate([np.arange(k * WRENCH, (k + 1) * WRENCH) for k in np.argsort(order)])
        out = b.op("Gather", [out, b.const("sensor_order", columns, np.int64)], "in_sensor_order", axis=1)
    return out, start, state


def build(
    models: Sequence[GroupModel], dtype: str, metadata: dict[str, str], name: str, per_sample: bool = False
) -> Any:
    """The ONNX ModelProto of `models` (one group, or several fused) in `dtype` with `metadata` props;
    `per_sample`: float32 networks laid out for one sample per call (a control loop), else for batches
    (float64 graphs have one layout)."""
    from onnx import TensorProto, checker, helper, numpy_helper

    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {DTYPES}, got {dtype!r}")
    b = _Builder(dtype)
    n_in = sum(len(m.sensors) * m.n_inputs for m in models)
    b.initializers.append(numpy_helper.from_array(np.zeros((1, n_in), dtype=b.dtype), OFFSETS))
    shifted = b.op("Sub", [INPUT, OFFSETS], "rezeroed")
    out, start, state = _all(b, shifted, models, per_sample)
    if b.nodes[-1].output[0] == out:  # name the last result the graph's output (no extra Identity)
        b.nodes[-1].output[0] = OUTPUT
    else:
        b.op("Identity", [out], output=OUTPUT)
    elem = TensorProto.FLOAT if dtype == "float32" else TensorProto.DOUBLE
    n_out = sum(len(m.sensors) for m in models) * WRENCH
    inputs = [
        helper.make_tensor_value_info(INPUT, elem, ["N", start]),
        helper.make_tensor_value_info(OFFSETS, elem, [1, start]),
    ]
    outputs = [helper.make_tensor_value_info(OUTPUT, elem, ["N", n_out])]
    if state:  # the play models' state: default NaN (a fresh start), `pipeline.export.linear`
        b.initializers.append(numpy_helper.from_array(np.full(state, np.nan, dtype=b.dtype), STATE))
        inputs.append(helper.make_tensor_value_info(STATE, elem, [state]))
        outputs.append(helper.make_tensor_value_info(STATE_OUT, elem, [state]))
    graph = helper.make_graph(b.nodes, name, inputs, outputs, b.initializers)
    model = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name="ftcal",
        doc_string=(__doc__ or "").split("\n\n")[1],
    )
    helper.set_model_props(model, metadata)
    checker.check_model(model, full_check=True)
    return model


def empty(dtype: str, metadata: dict[str, str], name: str) -> Any:
    """The ONNX ModelProto of an export that calibrates no sensor: ``inputs`` (N, 0) -> ``calibrated`` (N,
    0) in `dtype`, with `metadata` props (they say why). What the pipeline writes where its graphs' files
    must exist but no group could be calibrated."""
    from onnx import TensorProto, checker, helper

    elem = TensorProto.FLOAT if dtype == "float32" else TensorProto.DOUBLE
    graph = helper.make_graph(
        [helper.make_node("Identity", [INPUT], [OUTPUT])],
        name,
        [helper.make_tensor_value_info(INPUT, elem, ["N", 0])],
        [helper.make_tensor_value_info(OUTPUT, elem, ["N", 0])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="ftcal")
    helper.set_model_props(model, metadata)
    checker.check_model(model, full_check=True)
    return model
