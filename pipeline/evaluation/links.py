"""What evaluate takes from the train stage's ``metrics.json`` beyond scores, and how it links MLflow.

The train -> evaluate contract (written by `pipeline.stages.train`, see `pipeline.calib.records`):
``networks.<nn>.history`` is the best trial's epochs ``[{epoch, loss, val_rmse}]``; ``mlflow.run_id`` is the
train@<group> run; ``mlflow.models.<nn>`` is the registered model version ``{name, version, model_id}``.
Runs and models are found by these ids only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from pipeline.core.errors import DataError
from pipeline.evaluation.params import LABELS, TRAIN_METRICS, TRUTH
from pipeline.evaluation.results import GroupResult


def read_train_links(result: GroupResult, train: Mapping[str, Any]) -> None:
    """Fill `result`'s loss histories, training run id and model versions from the training metrics."""
    where = f"models/{result.group}/{TRAIN_METRICS}"
    for network, info in (train.get("networks") or {}).items():
        history = info.get("history")
        if not isinstance(history, list):
            raise DataError(f"{where}: networks.{network}.history missing (retrain the group)")
        result.histories[network] = [
            {"epoch": float(h["epoch"]), "loss": float(h["loss"]), "val_rmse": float(h["val_rmse"])}
            for h in history
        ]
    result.history_source = where if result.histories else "none"
    links = train.get("mlflow") or {}
    result.train_run = links.get("run_id")
    result.model_versions = {str(k): dict(v) for k, v in (links.get("models") or {}).items()}


def log_model_metrics(result: GroupResult) -> None:
    """Log each evaluated network's test errors and noise ratio against its MLflow logged model (model_id),
    so the model's page lists them with this run; tag the model versions with this run.

    A model version missing from the tracking store (an MLflow store other than the one train logged to)
    is reported by a warning, not an error: the scores are still valid.
    """
    import mlflow

    client = mlflow.MlflowClient()
    run_id = mlflow.active_run().info.run_id
    r = result
    for network, mv in r.model_versions.items():
        values = {
            "test_rmse_labels": r.headline_rmse(LABELS, network),
            "test_rmse_truth": r.headline_rmse(TRUTH, network),
            "noise_ratio": r.noise.ratio.get(network),
        }
        values = {
            f"{r.group}.{network}.{k}": v for k, v in values.items() if v is not None and math.isfinite(v)
        }
        try:
            if mv.get("model_id") and values:
                mlflow.log_metrics(values, model_id=mv["model_id"])
            client.set_model_version_tag(mv["name"], mv["version"], "evaluate_run", run_id)
            flagged = str(network in r.noise.flagged).lower()
            client.set_model_version_tag(mv["name"], mv["version"], "noise_flagged", flagged)
        except mlflow.exceptions.MlflowException as exc:
            import warnings

            warnings.warn(
                f"{r.group}: model {mv.get('name')} v{mv.get('version')} not in this MLflow store ({exc})",
                stacklevel=2,
            )
