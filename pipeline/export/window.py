"""The windowed networks' part of a graph (family ``win``): their networks' corrections of their play parts.

A windowed sensor (`pipeline.calib.parts.WindowPart`) is its play part, computed with every affine, play
and arx part in the linear stack (`pipeline.export.linear`), where its exponential windows (first-order
low-pass filters of its raw wrench) run among the play operators, in the same Scan and the same ``state``,
plus a network's correction of z = [its raw wrench now, its filters' outputs after the row, its temperature
now] (`pipeline.calib.window`). Here: the corrections (N, 6 W) of the W windowed sensors from the graph's
inputs and the stack's operator outputs: one Cast (float32 graphs: the outputs are float64), one Concat,
one Gather of every network's z, the networks stacked as the memoryless ones (`pipeline.export.mlp`: a
grouped convolution per layer in float32, a batched MatMul in float64), then one Add onto their play parts'
outputs (`add_corrections`). A control loop's call costs per operation (`pipeline.export.graph`): a window
adds no Scan and no state of its own.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pipeline.export.mlp import stacked_mlp
from pipeline.export.trained import WRENCH, WindowPart


def window_corrections(
    b: Any, x: str, width: int, outputs: str, parts: Sequence[tuple[int, WindowPart, int]], per_sample: bool
) -> str:
    """The corrections (N, 6 W), in the graph's float type, of the windowed `parts` [(first input column,
    part, its first column of `outputs`)] from x (N, `width`: the graph's inputs) and `outputs` (N, M
    float64: the linear stack's operator outputs after each row, `pipeline.export.linear.LinearStack`)."""
    from onnx import TensorProto

    if b.dtype == np.float32:
        outputs = b.op("Cast", [outputs], "window_outputs32", to=TensorProto.FLOAT)
    both = b.op("Concat", [x, outputs], "window_sources", axis=1)
    columns = []
    for lo, p, first in parts:  # each sensor's [raw now, its filters' outputs, temperature now]
        k = p.play.powers.shape[1]  # 7, or 6 without temperature
        play = p.play.widths.size  # its play operators come first among its operators
        filters = WRENCH * len(p.play.time_constants)
        at = width + first + play + np.arange(filters)
        columns.append(np.r_[lo + np.arange(WRENCH), at, lo + np.arange(WRENCH, k)])
    z = b.op("Gather", [both, b.const("window_z", np.concatenate(columns), np.int64)], "window_z", axis=1)
    return _networks(b, z, [len(c) for c in columns], [p for _, p, _ in parts], per_sample)


def _networks(b: Any, z: str, widths: Sequence[int], parts: Sequence[WindowPart], per_sample: bool) -> str:
    """The corrections (N, 6 W) of the networks of `parts` on z (N, sum of `widths`: each part's inputs in
    turn), those of one signature (inputs, activations) stacked (`pipeline.export.mlp.stacked_mlp`)."""
    starts = np.r_[0, np.cumsum(widths)[:-1]]
    stacks: dict[tuple, list[int]] = {}
    for s, p in enumerate(parts):
        stacks.setdefault((widths[s], tuple((y.activation, y.alpha) for y in p.layers)), []).append(s)
    outs, order = [], []
    for (n_inputs, _), members in stacks.items():
        inputs = z
        if len(members) < len(parts):
            columns = np.concatenate([starts[s] + np.arange(n_inputs) for s in members])
            inputs = b.op("Gather", [z, b.const("window_stack", columns, np.int64)], axis=1)
        outs.append(stacked_mlp(b, inputs, n_inputs, [parts[s] for s in members], per_sample))
        order += members
    out = outs[0] if len(outs) == 1 else b.op("Concat", outs, "window_corrections", axis=1)
    if order != sorted(order):
        columns = np.concatenate([np.arange(k * WRENCH, (k + 1) * WRENCH) for k in np.argsort(order)])
        out = b.op("Gather", [out, b.const("window_order", columns, np.int64)], axis=1)
    return out


def add_corrections(
    b: Any, y: str, n_parts: int, windowed: Sequence[int], correction: str
) -> list[tuple[str, list[int]]]:
    """[(calibrated wrenches, the positions among the linear stack's parts they are of)] of the linear stack's
    outputs y (N, 6 `n_parts`) with `correction` (N, 6 W) added to the parts at positions `windowed`."""
    if len(windowed) == n_parts:
        return [(b.op("Add", [y, correction], "windowed_calibrated"), list(range(n_parts)))]
    others = [j for j in range(n_parts) if j not in windowed]

    def pick(positions: Sequence[int], hint: str) -> str:
        columns = np.concatenate([np.arange(j * WRENCH, (j + 1) * WRENCH) for j in positions])
        return b.op("Gather", [y, b.const(hint, columns, np.int64)], hint, axis=1)

    corrected = b.op("Add", [pick(windowed, "play_of_windowed"), correction], "windowed_calibrated")
    return [(pick(others, "linear_calibrated"), others), (corrected, list(windowed))]
