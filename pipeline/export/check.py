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

A graph with memory (a ``state`` input, `pipeline.export.linear`) is checked on whole test logs: each log's
rows with finite inputs in time order, one call per log from a fresh state, against the project's model
run over the same rows (``bounds``: where each log starts); and again in calls of `CHUNK` rows, each
taking the state the call before returned (``state_carry``: the largest difference between the two runs).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.calib.registry import family_of
from pipeline.core.errors import DataError
from pipeline.export.trained import PREDICTIONS_FILE, WRENCH, GroupModel, prediction_columns

CHUNK = 997  # rows per call of the state-carrying run of a graph with memory (module docstring)


@dataclass
class Samples:
    """A group's test samples: inputs x (N, K) float64 in the graph's column order, the stored predictions
    (N, 6 S) of the exported model (NaN on rows without one), the project's prediction from float32 inputs
    and its float64 one; for a model with memory the first row of each log's sequence (`bounds`) and every
    row's (log, stamp) (`keys`, (N, 2) int64: the log's index in `logs`, ns)."""

    x: np.ndarray
    stored: np.ndarray
    reference32: np.ndarray
    reference: np.ndarray
    bounds: np.ndarray | None = None
    keys: np.ndarray | None = None

    def target(self, dtype: str) -> np.ndarray:
        return self.reference32 if dtype in FLOAT32 else self.reference


FLOAT32 = ("float32", "c")  # the float32 graph and the generated C calibrator take float32 rows


def session(model: Any, threads: int = 1) -> Any:
    """An onnxruntime CPU session of a ModelProto (or serialized bytes, or a path) on `threads` threads.

    Every graph optimisation on (onnxruntime's default, stated: the graphs rely on its fusion of each
    layer's Conv with bias and activation into one kernel). Other options (denormals as zero, no thread
    spinning, memory arena and pattern, sequential execution) measured no difference on one thread.
    Warnings are not logged: onnxruntime warns at every load that the ``offsets`` input has a default
    (`pipeline.export.graph`), which is the point of it.
    """
    import onnxruntime as ort

    if hasattr(model, "get_inputs"):  # already a session (the compiled C calibrator's)
        return model
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
    inputs' units, fed to the graph's ``offsets`` input (None: its default, zeros). A graph with memory
    starts afresh (its rows: consecutive samples)."""
    return run_state(sess, x, offsets)[0]


def run_state(
    sess: Any, x: np.ndarray, offsets: np.ndarray | None = None, state: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """(outputs, the state after the last row, None for a memoryless graph) of a session on the
    consecutive samples x (N, K) from `state` (M,) (None: a fresh start); `offsets` as `run`'s."""
    from pipeline.export.graph import OFFSETS
    from pipeline.export.linear import STATE, STATE_OUT

    dtype = np.float32 if sess.get_inputs()[0].type == "tensor(float)" else np.float64
    feed = {sess.get_inputs()[0].name: np.ascontiguousarray(x, dtype=dtype)}
    if offsets is not None:
        feed[OFFSETS] = np.ascontiguousarray(np.reshape(offsets, (1, -1)), dtype=dtype)
    if state is not None:
        feed[STATE] = np.ascontiguousarray(np.reshape(state, -1), dtype=dtype)
    names = [o.name for o in sess.get_outputs()]
    out = sess.run(None, feed)
    return out[0], (out[names.index(STATE_OUT)] if STATE_OUT in names else None)


def run_logs(sess: Any, x: np.ndarray, bounds: np.ndarray | None, chunk: int | None = None) -> np.ndarray:
    """A graph's outputs on several logs' rows x (N, K), each log from a fresh state (`bounds`: the first
    row of each; None: one sequence), in calls of `chunk` rows carrying the state (None: a call per log)."""
    starts = [0] if bounds is None else list(bounds)
    out = []
    for lo, hi in zip(starts, [*starts[1:], len(x)], strict=True):
        state = None
        for first in range(lo, hi, chunk or max(hi - lo, 1)):
            y, state = run_state(sess, x[first : min(hi, first + (chunk or hi))], state=state)
            out.append(y)
    return np.concatenate(out) if out else np.zeros((0, 0))


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
    for k, (log, rows) in enumerate(pred.groupby(S.LOG, sort=False)):
        table = labelled_dir / f"{log}{S.PARQUET_SUFFIX}"
        try:
            inputs = pd.read_parquet(table, columns=[S.STAMP, *model.input_columns])
        except FileNotFoundError:
            raise DataError(f"{table}: not found (test log {log} of {path})") from None
        except (OSError, ValueError, KeyError) as exc:
            raise DataError(f"{table}: not the inputs of {model.group}: {exc}") from None
        if model.memory:  # the whole log in time order: every reading (a temperature may be missing)
            columns, n = model.input_columns, model.n_inputs
            wrench = [c for k in range(0, len(columns), n) for c in columns[k : k + WRENCH]]
            merged = inputs[inputs[wrench].notna().all(axis=1)]
            merged = merged.merge(rows, on=S.STAMP, how="left", validate="one_to_one").assign(**{S.LOG: k})
            missing = merged[stored_cols].notna().all(axis=1) & merged[model.input_columns].isna().any(axis=1)
        else:
            merged = rows.merge(inputs, on=S.STAMP, how="left", validate="one_to_one")
            missing = merged[model.input_columns].isna().any(axis=1)
        if missing.any() or not len(merged):
            raise DataError(f"{table}: test samples of {path} have no finite inputs there")
        parts.append(merged)
    if not parts:
        raise DataError(f"{path}: no test samples")
    frame = pd.concat(parts, ignore_index=True)
    x = frame[model.input_columns].to_numpy(np.float64)
    stored = frame[stored_cols].to_numpy(np.float64)
    if not model.memory:
        rounded = x.astype(np.float32).astype(np.float64)
        return Samples(x, stored, stored if _float32(model) else model.reference(rounded), model.reference(x))
    keys = frame[[S.LOG, S.STAMP]].to_numpy(np.int64)
    bounds = np.flatnonzero(np.r_[True, keys[1:, 0] != keys[:-1, 0]])
    return Samples(x, stored, *_references(model, x, bounds), bounds, keys)


def _float32(model: GroupModel) -> bool:
    """Whether the model's stored predictions are its float32 computation (a network's)."""
    family = family_of(model.name)
    return family is not None and family.float32


def _references(model: GroupModel, x: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(from float32 inputs, float64) the project's model over each log's rows (from `bounds`) of x."""
    rounded = x.astype(np.float32).astype(np.float64)
    edges = [*bounds, len(x)]
    parts = [
        (model.reference(rounded[a:b]), model.reference(x[a:b]))
        for a, b in zip(edges[:-1], edges[1:], strict=True)
    ]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def max_diff(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| over every element (N and Nm); inf if shapes differ or a value is not finite (the rows
    where `b` is NaN throughout are left out: no stored prediction there)."""
    if a.shape != b.shape:
        return float("inf")
    if b.ndim == 2 and np.isnan(b).all(axis=1).any():
        keep = ~np.isnan(b).all(axis=1)
        a, b = a[keep], b[keep]
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
    """The differences of outputs y from the target and the stored predictions, on the rows whose target
    is finite (a model with memory is run over readings without a temperature too: no output there)."""
    rows = np.isfinite(target).all(axis=1) if y.shape == target.shape else slice(None)
    y, target, stored = y[rows], target[rows], stored[rows]
    out = {"max_abs_diff": max_diff(y, target), "max_abs_diff_stored": max_diff(y, stored)}
    if dtype in FLOAT32:
        out["max_ulps"] = max_ulps(y, target)
    return out | {"samples": len(y)}


def check_group(graphs: Mapping[str, Any], samples: Samples) -> dict[str, dict[str, float]]:
    """{dtype: {max_abs_diff, max_abs_diff_stored, [max_ulps,] samples[, state_carry]}} of a group's graphs
    (module docstring)."""
    out = {}
    for dtype, graph in graphs.items():
        sess = session(graph)
        y = run_logs(sess, samples.x, samples.bounds)
        out[dtype] = _measure(y, dtype, samples.target(dtype), samples.stored)
        if samples.bounds is not None:
            rows = np.isfinite(y).all(axis=1)
            chunked = run_logs(sess, samples.x, samples.bounds, CHUNK)
            out[dtype]["state_carry"] = max_diff(chunked[rows], y[rows])
    return out


def check_fused(
    graphs: Mapping[str, Any], groups: Sequence[Samples], models: Sequence[GroupModel] = ()
) -> dict[str, dict[str, float]]:
    """The fused graphs on every group's test samples at once (groups with fewer samples repeat theirs);
    with a model of memory among `models` (the groups' models, in order), on the rows of each test log that
    every group has, each group's reference run over them (module docstring)."""
    if any(g.bounds is not None for g in groups):
        return _check_fused_logs(graphs, groups, models)
    n = max(len(g.x) for g in groups)
    take = [np.arange(n) % len(g.x) for g in groups]
    x = np.concatenate([g.x[k] for g, k in zip(groups, take, strict=True)], axis=1)
    stored = np.concatenate([g.stored[k] for g, k in zip(groups, take, strict=True)], axis=1)
    out = {}
    for dtype, graph in graphs.items():
        target = np.concatenate([g.target(dtype)[k] for g, k in zip(groups, take, strict=True)], axis=1)
        out[dtype] = _measure(run(session(graph), x), dtype, target, stored)
    return out


def _check_fused_logs(
    graphs: Mapping[str, Any], groups: Sequence[Samples], models: Sequence[GroupModel]
) -> dict[str, dict[str, float]]:
    """`check_fused` with memory: the memory groups' (log, stamp) rows that every group has (a memoryless
    group's test samples are a subset of the same logs' rows: those rows), in time order per log."""
    keyed = [g for g in groups if g.keys is not None]
    shared = set.intersection(*({tuple(k) for k in g.keys.tolist()} for g in keyed))
    common = np.array([k for k in keyed[0].keys.tolist() if tuple(k) in shared], dtype=np.int64)
    columns = []
    for g, model in zip(groups, models, strict=True):
        if g.keys is None:  # memoryless: the rows its own samples have, repeated to the common length
            take = np.arange(len(common)) % len(g.x)
            columns.append((g.x[take], g.reference32[take], g.reference[take], g.stored[take]))
            continue
        index = {tuple(k): i for i, k in enumerate(g.keys)}
        rows = np.array([index[tuple(k)] for k in common], dtype=np.int64)
        bounds = np.flatnonzero(np.r_[True, common[1:, 0] != common[:-1, 0]])
        columns.append((g.x[rows], *_references(model, g.x[rows], bounds), g.stored[rows]))
    x, ref32, ref, stored = (np.concatenate([c[k] for c in columns], axis=1) for k in range(4))
    bounds = np.flatnonzero(np.r_[True, common[1:, 0] != common[:-1, 0]])
    samples = Samples(x, stored, ref32, ref, bounds, common)
    return check_group(graphs, samples)


TOLERANCES = {
    "float32": ("max_ulps", "tolerance_float32_ulps", "float32 steps"),
    "float64": ("max_abs_diff", "tolerance_float64", "N/Nm"),
    "c": ("max_ulps", "tolerance_float32_ulps", "float32 steps"),  # the C calibrator: as the float32 graph
}


def assert_within(
    name: str, result: Mapping[str, Mapping[str, float]], tolerance: Mapping[str, float]
) -> None:
    """Raise DataError if a graph of `name` differs from its reference by more than its dtype's tolerance
    (`tolerance`: dtype -> float32 steps for float32, N/Nm for float64; see TOLERANCES)."""
    for dtype, r in result.items():
        if "skipped" in r:  # the C calibrator where no compiler is
            continue
        measure, key, unit = TOLERANCES[dtype]
        if not r[measure] <= tolerance[dtype]:
            raise DataError(
                f"export check failed: {name} {dtype} differs from the project's prediction by "
                f"{r[measure]:.3g} {unit} (max |diff| {r['max_abs_diff']:.3g} N/Nm) > export.{key} = "
                f"{tolerance[dtype]:g} on {r['samples']} test samples"
            )


RATE_TOLERANCE = 0.2  # a log's message period may differ from a graph's filters' by this fraction


def check_rate(topic: str, stamps_ns: np.ndarray, period_s: float) -> bool:
    """Whether the messages of `topic` (their stamps, ns) were checked: False with fewer than 10 steps; a
    DataError if they are not about `period_s` apart, the period a graph's filters (`pipeline.core.lowpass`:
    the arx family's, the win family's windows) were trained at."""
    steps = np.diff(np.sort(np.asarray(stamps_ns, dtype=np.int64))) / 1e9
    steps = steps[steps > 0]
    if len(steps) < 10:
        return False
    median = float(np.median(steps))
    if abs(median / period_s - 1.0) > RATE_TOLERANCE:
        raise DataError(
            f"{topic}: messages {median * 1e3:.3g} ms apart, but its calibration's filters (arx, win) "
            f"run at {period_s * 1e3:.3g} ms, the period of its training logs: retrain at this rate, or "
            "deploy a model without filters"
        )
    return True
