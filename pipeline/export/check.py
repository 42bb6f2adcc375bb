"""Checks of exported graphs with onnxruntime against the project's own predictions on the test samples.

A float32 graph is compared with the project's own prediction from the same float32 inputs: for
networks the test predictions the train stage wrote (``predictions.parquet``, what `evaluate` scores:
torch in float32), for the linear models (computed in float64) the model on the float32-rounded inputs.
Its difference to the stored predictions is reported too: for a linear model it adds the rounding of
the inputs to float32 (up to ~1e-4 N on a 500 N wrench, float32's resolution). A float64 graph is
compared with the project's model in float64 on the same inputs. Differences are reported absolute, in N
and Nm (the maximum over every sample and output column), and for float32 also in float32 steps (ulps) at
each sensor's largest |output| on the samples: float32's resolution grows with the wrench (6.1e-5 N at
512 N, 2.4e-4 N at 2 kN), so the float32 check is relative to it, the float64 one absolute.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import DataError
from pipeline.export.trained import PREDICTIONS_FILE, WRENCH, GroupModel, prediction_columns


@dataclass
class Samples:
    """A group's test samples: inputs x (N, K) float64 in the graph's column order, the stored predictions
    (N, 6 S) of the exported model, the project's prediction from float32 inputs and its float64 one."""

    x: np.ndarray
    stored: np.ndarray
    reference32: np.ndarray
    reference: np.ndarray

    def target(self, dtype: str) -> np.ndarray:
        return self.reference32 if dtype == "float32" else self.reference


def session(model: Any, threads: int = 1) -> Any:
    """An onnxruntime CPU session of a ModelProto (or serialized bytes, or a path) on `threads` threads.

    Every graph optimisation on (onnxruntime's default, stated: the graphs rely on its fusion of each
    layer's Conv with bias and activation into one kernel). Other options (denormals as zero, no thread
    spinning, memory arena and pattern, sequential execution) measured no difference on one thread.
    Warnings are not logged: onnxruntime warns at every load that the ``offsets`` input has a default
    (`pipeline.export.graph`), which is the point of it.
    """
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3  # errors only
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    data = model if isinstance(model, bytes | str | Path) else model.SerializeToString()
    return ort.InferenceSession(
        str(data) if isinstance(data, Path) else data, options, providers=["CPUExecutionProvider"]
    )


def run(sess: Any, x: np.ndarray, offsets: np.ndarray | None = None) -> np.ndarray:
    """Outputs of a session on inputs x (N, K), cast to the graph's input type; `offsets` (1, K), in the
    inputs' units, fed to the graph's ``offsets`` input (None: its default, zeros)."""
    from pipeline.export.graph import OFFSETS

    dtype = np.float32 if sess.get_inputs()[0].type == "tensor(float)" else np.float64
    feed = {sess.get_inputs()[0].name: np.ascontiguousarray(x, dtype=dtype)}
    if offsets is not None:
        feed[OFFSETS] = np.ascontiguousarray(np.reshape(offsets, (1, -1)), dtype=dtype)
    return sess.run(None, feed)[0]


def load_samples(model_dir: Path, model: GroupModel, labelled_dir: Path) -> Samples:
    """The group's test samples (those of ``predictions.parquet``) with their inputs from the labelled tables.

    Raises:
        DataError: a table or column is missing, or a sample of the predictions is not in its labelled table.
    """
    import pandas as pd

    from pipeline.logs import schema as S

    path = model_dir / PREDICTIONS_FILE
    stored_cols = [c for s in model.sensors for c in prediction_columns(model.name, s)]
    try:
        pred = pd.read_parquet(path, columns=[S.LOG, S.STAMP, *stored_cols])
    except FileNotFoundError:
        raise DataError(f"{path}: not found") from None
    except (OSError, ValueError, KeyError) as exc:
        raise DataError(f"{path}: no predictions of {model.name}: {exc}") from None
    parts = []
    for log, rows in pred.groupby(S.LOG, sort=False):
        table = labelled_dir / f"{log}{S.PARQUET_SUFFIX}"
        try:
            inputs = pd.read_parquet(table, columns=[S.STAMP, *model.input_columns])
        except FileNotFoundError:
            raise DataError(f"{table}: not found (test log {log} of {path})") from None
        except (OSError, ValueError, KeyError) as exc:
            raise DataError(f"{table}: not the inputs of {model.group}: {exc}") from None
        merged = rows.merge(inputs, on=S.STAMP, how="left", validate="one_to_one")
        if merged[model.input_columns].isna().any().any():
            raise DataError(f"{table}: test samples of {path} have no finite inputs there")
        parts.append(merged)
    if not parts:
        raise DataError(f"{path}: no test samples")
    frame = pd.concat(parts, ignore_index=True)
    x = frame[model.input_columns].to_numpy(np.float64)
    stored = frame[stored_cols].to_numpy(np.float64)
    rounded = x.astype(np.float32).astype(np.float64)
    return Samples(
        x, stored, stored if model.family == "network" else model.reference(rounded), model.reference(x)
    )


def max_diff(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| over every element (N and Nm); inf if shapes differ or a value is not finite."""
    if a.shape != b.shape:
        return float("inf")
    d = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))
    return float(d.max()) if d.size and np.isfinite(d).all() else (0.0 if not d.size else float("inf"))


def max_ulps(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| in float32 steps at each sensor's largest |b| (columns in sensors of 6; inf if the
    shapes differ or a value is not finite)."""
    if a.shape != b.shape or a.shape[1] % WRENCH or not np.isfinite(a).all() or not np.isfinite(b).all():
        return float("inf")
    if not a.size:
        return 0.0
    n = a.shape[1] // WRENCH
    scale = np.abs(np.asarray(b, np.float64)).reshape(len(b), n, WRENCH).max(axis=(0, 2))
    step = np.spacing(scale.astype(np.float32)).astype(np.float64)  # float32 resolution at that scale
    d = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).reshape(len(a), n, WRENCH)
    return float((d / step[None, :, None]).max())


def _measure(y: np.ndarray, dtype: str, target: np.ndarray, stored: np.ndarray) -> dict[str, float]:
    out = {"max_abs_diff": max_diff(y, target), "max_abs_diff_stored": max_diff(y, stored)}
    if dtype == "float32":
        out["max_ulps"] = max_ulps(y, target)
    return out | {"samples": len(y)}


def check_group(graphs: Mapping[str, Any], samples: Samples) -> dict[str, dict[str, float]]:
    """{dtype: {max_abs_diff, max_abs_diff_stored, [max_ulps,] samples}} of a group's graphs (module
    docstring)."""
    out = {}
    for dtype, graph in graphs.items():
        y = run(session(graph), samples.x)
        out[dtype] = _measure(y, dtype, samples.target(dtype), samples.stored)
    return out


def check_fused(graphs: Mapping[str, Any], groups: Sequence[Samples]) -> dict[str, dict[str, float]]:
    """The fused graphs on every group's test samples at once (groups with fewer samples repeat theirs)."""
    n = max(len(g.x) for g in groups)
    take = [np.arange(n) % len(g.x) for g in groups]
    x = np.concatenate([g.x[k] for g, k in zip(groups, take, strict=True)], axis=1)
    stored = np.concatenate([g.stored[k] for g, k in zip(groups, take, strict=True)], axis=1)
    out = {}
    for dtype, graph in graphs.items():
        target = np.concatenate([g.target(dtype)[k] for g, k in zip(groups, take, strict=True)], axis=1)
        out[dtype] = _measure(run(session(graph), x), dtype, target, stored)
    return out


TOLERANCES = {"float32": ("max_ulps", "tolerance_float32_ulps", "float32 steps"), "float64": (
    "max_abs_diff", "tolerance_float64", "N/Nm")}  # fmt: skip


def assert_within(
    name: str, result: Mapping[str, Mapping[str, float]], tolerance: Mapping[str, float]
) -> None:
    """Raise DataError if a graph of `name` differs from its reference by more than its dtype's tolerance
    (`tolerance`: dtype -> float32 steps for float32, N/Nm for float64; see TOLERANCES)."""
    for dtype, r in result.items():
        measure, key, unit = TOLERANCES[dtype]
        if not r[measure] <= tolerance[dtype]:
            raise DataError(
                f"export check failed: {name} {dtype} differs from the project's prediction by "
                f"{r[measure]:.3g} {unit} (max |diff| {r['max_abs_diff']:.3g} N/Nm) > export.{key} = "
                f"{tolerance[dtype]:g} on {r['samples']} test samples"
            )
