"""The networks of a graph, stacked: S multilayer perceptrons of one signature (inputs, depth, activations)
evaluated together, one operation per layer for all of them (`pipeline.export.graph`: why, and the layouts).

A network here is anything with ``in_offset`` (n,), ``in_scale`` (n,), ``out_scale`` (6,) and ``layers``
(`pipeline.calib.parts.Dense`): ``out_scale * mlp((x - in_offset) / in_scale)``, the memoryless networks'
correction (`pipeline.calib.parts.NetworkPart`) and the windowed networks' (`pipeline.export.trained
.WindowPart`). Hidden widths are padded with zero units, the normalisation folded into the first layer's
weights and the output scale into the last's (exact in real arithmetic; in float32 within an ulp of torch's
result); in float32 a grouped 1-D convolution per layer, in float64 a batched MatMul.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pipeline.export.trained import WRENCH, Dense


def activation(b: Any, x: str, layer: Dense, hint: str) -> str:
    if layer.activation is None:
        return x
    if layer.activation == "relu":
        return b.op("Relu", [x], hint)
    if layer.activation == "leaky_relu":
        if b.dtype == np.float32:  # the float attribute alpha is exact only in float32
            return b.op("LeakyRelu", [x], hint, alpha=float(layer.alpha))
        return b.op(
            "Where",
            [b.op("Greater", [x, b.const("zero", 0.0)]), x, b.op("Mul", [x, b.const("alpha", layer.alpha)])],
            hint,
        )
    if layer.activation == "tanh":
        return b.op("Tanh", [x], hint)
    if layer.activation == "elu":  # onnxruntime has no float64 Elu: alpha (exp(x) - 1) where x <= 0
        negative = b.op(
            "Mul", [b.const("alpha", layer.alpha), b.op("Sub", [b.op("Exp", [x]), b.const("one", 1.0)])]
        )
        return b.op("Where", [b.op("Greater", [x, b.const("zero", 0.0)]), x, negative], hint)
    raise ValueError(f"unknown activation {layer.activation!r}")


def stacked_weights(parts: Sequence[Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per layer, the (S, out, in) weights and (S, out) biases (float64) of S networks of one signature
    with the normalisation folded into the first layer (``W / in_scale``, ``b - W @ (in_offset / in_scale)``)
    and the output scale into the last (``out_scale * W``, ``out_scale * b``); hidden widths padded with
    zero units (zero weights in and out: an exact extension, act(0) = 0 and its outgoing weights are 0)."""
    depth = len(parts[0].layers)
    widths = [max(p.layers[k].weight.shape[0] for p in parts) for k in range(depth)]
    out = []
    for k in range(depth):
        n_in = parts[0].layers[0].weight.shape[1] if k == 0 else widths[k - 1]
        w = np.zeros((len(parts), widths[k], n_in))
        bias = np.zeros((len(parts), widths[k]))
        for s, p in enumerate(parts):
            wk, bk = p.layers[k].weight, p.layers[k].bias
            if k == 0:
                wk = wk / p.in_scale[None, :]
                bk = bk - wk @ p.in_offset
            if k == depth - 1:
                wk, bk = p.out_scale[:, None] * wk, p.out_scale * bk
            w[s, : wk.shape[0], : wk.shape[1]], bias[s, : len(bk)] = wk, bk
        out.append((w, bias))
    return out


def stacked_mlp(b: Any, x: str, n_inputs: int, parts: Sequence[Any], per_sample: bool = False) -> str:
    """The outputs (N, 6 S) ``out_scale * mlp((x_s - in_offset) / in_scale)`` of S networks of one signature
    (`parts`: each with in_offset, in_scale, out_scale and layers) on x (N, S `n_inputs`), network s reading
    x[:, s n_inputs : (s + 1) n_inputs]: each layer one operation for all S (`_stack`)."""
    s_count = len(parts)
    conv = b.dtype == np.float32
    if conv and per_sample:  # (N, S n, 1): samples as the batch, channels network after network
        h = b.op("Reshape", [x, b.const("shape", [0, s_count * n_inputs, 1], np.int64)], "stack_inputs")
    elif conv:  # (1, S n, N): samples along the length
        h = b.op("Transpose", [x], perm=[1, 0])
        h = b.op("Reshape", [h, b.const("shape", [1, s_count * n_inputs, -1], np.int64)], "stack_inputs")
    else:  # (S, N, n)
        h = b.op("Reshape", [x, b.const("shape", [0, s_count, n_inputs], np.int64)], "stack_inputs")
        h = b.op("Transpose", [h], perm=[1, 0, 2])
    for k, (w, bias) in enumerate(stacked_weights(parts)):
        if conv:
            weight, bias = b.const(f"w{k}", w.reshape(-1, w.shape[2], 1)), b.const(f"b{k}", bias.reshape(-1))
            h = b.op("Conv", [h, weight, bias], f"layer{k}", group=s_count)
            if parts[0].layers[k].activation not in (None, "relu"):  # unfused: see the module's notes
                h = b.op("Reshape", [h, b.const("shape", [0, s_count * w.shape[1], -1], np.int64)])
        else:
            h = b.op("MatMul", [h, b.const(f"w{k}", np.ascontiguousarray(w.transpose(0, 2, 1)))])
            h = b.op("Add", [h, b.const(f"b{k}", bias[:, None, :])], f"layer{k}")
        h = activation(b, h, parts[0].layers[k], f"act{k}")
    if conv and per_sample:  # (N, 6 S, 1) -> (N, 6 S)
        return b.op("Reshape", [h, b.const("shape", [0, s_count * WRENCH], np.int64)])
    if conv:  # (1, 6 S, N) -> (N, 6 S)
        h = b.op("Reshape", [h, b.const("shape", [s_count * WRENCH, -1], np.int64)])
        return b.op("Transpose", [h], perm=[1, 0])
    h = b.op("Transpose", [h], perm=[1, 0, 2])  # (S, N, 6) -> (N, 6 S)
    return b.op("Reshape", [h, b.const("shape", [0, s_count * WRENCH], np.int64)])
