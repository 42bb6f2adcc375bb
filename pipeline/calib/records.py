"""What train@<group> writes for evaluate (the train -> evaluate contract) and logs to MLflow."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from pipeline.calib.cuts import cut_sums_np
from pipeline.calib.data import Group, GroupData
from pipeline.calib.models import GroupNet
from pipeline.core.io import write_atomic
from pipeline.logs import schema as S


@dataclass
class TrainResult:
    group: str
    metrics: dict[str, Any]  # as in metrics.json
    seconds: float
    mlflow_run: str  # id of the stage's MLflow run
    files: list[str] = field(default_factory=list)  # written in the output directory


def write_predictions(
    path: Path, group: Group, data: GroupData, log_names: Sequence[str], preds: Mapping[str, np.ndarray]
) -> None:
    cols: dict[str, Any] = {
        S.LOG: pa.array(np.asarray(log_names, dtype=object)[data.log], pa.string()),
        S.STAMP: pa.array(data.stamp, pa.int64()),
        S.TIME: pa.array(data.time, pa.float64()),
    }
    for s, sensor in enumerate(group.sensors):
        for a, c in enumerate(S.wrench_cols(S.EXPECTED, sensor)):
            cols[c] = pa.array(data.labels[:, s, a])
        cols[S.switch_col(sensor)] = pa.array(data.switches[:, s].astype(np.uint8))
    if group.pair is not None:
        for a, c in enumerate(S.wrench_cols(S.EXPECTED, group.pair)):
            cols[c] = pa.array(data.sum_label[:, a])
        cols[S.switch_col(group.pair)] = pa.array(data.sum_switch.astype(np.uint8))
    for c, cut in enumerate(group.cuts):
        for a, col in enumerate(S.wrench_cols(S.EXPECTED, cut.label)):
            cols[col] = pa.array(data.cut_labels[:, c, a])
        cols[S.switch_col(cut.label)] = pa.array(data.cut_switches[:, c].astype(np.uint8))
    # the predictions of every sensor and foot pair, what evaluate scores; not the sums of a group's other
    # cut sets (read by nothing: the legs' 6 besides the two feet were 40 % of the file)
    pairs = tuple(cut for cut in group.cuts if cut.pair is not None)
    for model, pred in preds.items():
        sums = cut_sums_np(pairs, pred, data.poses) if pairs else None
        for k, cut in enumerate(pairs):
            for a, col in enumerate(S.prediction_cols(model, cut.label)):
                cols[col] = pa.array(sums[:, k, a])
        for s, sensor in enumerate(group.sensors):
            for a, c in enumerate(S.prediction_cols(model, sensor)):
                cols[c] = pa.array(pred[:, s, a])
        if group.pair is not None:
            total = np.einsum("sij,nsj->ni", group.transforms, pred)
            for a, c in enumerate(S.prediction_cols(model, group.pair)):
                cols[c] = pa.array(total[:, a])
    table = pa.table(cols).replace_schema_metadata(
        {b"ftcal.train": json.dumps({"group": group.name, "models": list(preds)}).encode()}
    )
    write_atomic(path, lambda tmp: pq.write_table(table, tmp, compression="zstd"))


def log_trial_run(
    group: str, name: str
) -> Callable[[int, dict[str, Any], list[dict[str, float]], str, float], None]:
    """A callback that records one trial as a nested MLflow run (params, per-epoch metrics, state) of the
    active run."""
    import mlflow
    from mlflow.entities import Metric, Param

    def log(
        index: int, values: dict[str, Any], history: list[dict[str, float]], state: str, seconds: float
    ) -> None:
        client = mlflow.MlflowClient()
        parent = mlflow.active_run()
        run = client.create_run(
            parent.info.experiment_id,
            run_name=f"{group} {name} trial {index + 1}",
            tags={
                "mlflow.parentRunId": parent.info.run_id,
                "group": group,
                "network": name,
                "trial": str(index + 1),
                "state": state,
            },
        )
        now = int(time.time() * 1000)
        metrics = [
            Metric(k, float(h[k]), now, int(h["epoch"]))
            for h in history
            if h["epoch"] >= 0  # epoch -1 (the affine start) is in best_val_rmse
            for k in ("loss", "val_rmse")
        ]
        metrics.append(Metric("seconds", seconds, now, 0))
        if history:
            metrics.append(Metric("best_val_rmse", min(h["val_rmse"] for h in history), now, 0))
        client.log_batch(
            run.info.run_id, metrics=metrics, params=[Param(k, str(v)) for k, v in values.items()]
        )
        client.set_terminated(run.info.run_id, "FINISHED" if state == "COMPLETE" else "KILLED")

    return log


def log_network(
    group: Group, name: str, model: GroupNet, example: np.ndarray, info: Mapping[str, Any]
) -> dict[str, str]:
    """Log a network in MLflow's pt2 format (no pickle) with signature and input example; register it.

    Returns the registered model version: {name, version, model_id} (what evaluate links to).
    """
    import mlflow
    import mlflow.pytorch
    from mlflow.models import infer_signature

    example = example.astype(np.float32)
    with torch.no_grad():
        output = model(torch.from_numpy(example)).numpy()
    logged = mlflow.pytorch.log_model(
        model,
        name=name,
        signature=infer_signature(example, output),
        input_example=example,
        serialization_format="pt2",
        registered_model_name=f"ftcal-{group.name}-{model.config.n_inputs}",
        pip_requirements=[f"torch=={torch.__version__.split('+')[0]}"],
        metadata=dict(info),
    )
    return {
        "name": f"ftcal-{group.name}-{model.config.n_inputs}",
        "version": str(logged.registered_model_version),
        "model_id": str(logged.model_id or ""),
    }


def flatten_metrics(prefix: str, errors: Mapping[str, Any]) -> dict[str, float]:
    out: dict[str, float] = {}
    for k, v in errors.items():
        if isinstance(v, Mapping):
            out.update(flatten_metrics(f"{prefix}.{k}", v))
        elif isinstance(v, int | float) and math.isfinite(v):
            out[f"{prefix}.{k}"] = float(v)
    return out
