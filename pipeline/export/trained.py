"""The one adapter between the train stage's output directory and the export: what a graph needs.

`read_group(models/<group>, name)` reads one model of a group (its family's ``read``,
`pipeline.calib.families.base.Family.read`) and returns a `GroupModel`: per sensor, the plain arrays of the
model (float64) in one of the forms of `pipeline.calib.parts`, and the project's own predictor for the
reference check. Nothing else of `pipeline.calib` or `pipeline.stages.train` is used by the export (but the
registry), so a change of their file formats or classes is adapted in the family only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pipeline.calib.parts import (
    ACTIVATIONS,
    WRENCH,
    Dense,
    GroupModel,
    IdentityPart,
    LinearPart,
    NetworkPart,
    Part,
    WindowPart,
    input_columns,
    output_columns,
    prediction_columns,
)
from pipeline.calib.registry import family_of, patterns
from pipeline.core.errors import DataError

__all__ = [
    "ACTIVATIONS",
    "WRENCH",
    "Dense",
    "GroupModel",
    "IdentityPart",
    "LinearPart",
    "NetworkPart",
    "Part",
    "WindowPart",
    "input_columns",
    "output_columns",
    "prediction_columns",
    "read_group",
    "read_metrics",
    "provenance",
]
METRICS_FILE = "metrics.json"
PREDICTIONS_FILE = "predictions.parquet"


def read_metrics(model_dir: Path) -> dict[str, Any]:
    """The group's ``metrics.json`` (validation/test errors, best_on_validation, sensors)."""
    from pipeline.core.io import read_json

    path = model_dir / METRICS_FILE
    metrics = read_json(path, "a metrics file", f"not found (is {model_dir} a train@<group> output?)")
    if not isinstance(metrics, dict) or not isinstance(metrics.get("sensors"), list):
        raise DataError(f"{path}: no 'sensors' list (not a train@<group> metrics file)")
    return metrics


def read_group(model_dir: str | Path, name: str, group: str | None = None) -> GroupModel:
    """Model `name` of the group trained into `model_dir` (see the module docstring).

    Raises:
        DataError: the directory is not a train output, the model is not in it, or its files are unusable.
    """
    model_dir = Path(model_dir)
    metrics = read_metrics(model_dir)
    group = group or str(metrics.get("group") or model_dir.name)
    sensors = tuple(str(s) for s in metrics["sensors"])
    family = family_of(name)
    if family is None:
        raise DataError(f"{model_dir}: unknown model {name!r} ({', '.join(patterns())})")
    model = family.read(model_dir, name, group, sensors)
    model.info.update(provenance(metrics, name))
    return model


def provenance(metrics: Mapping[str, Any], name: str) -> dict[str, Any]:
    """What the manifest says of a model's training: logs, sample counts, its test errors (N, Nm)."""

    def finite(v: Any) -> Any:
        return v if not isinstance(v, float) or math.isfinite(v) else None

    test = (metrics.get("test") or {}).get(name) or {}
    headline = str(metrics.get("headline") or "")
    keep = {k: finite(test.get(k)) for k in ("rmse", "rmse_labelled", "rmse_force", "rmse_torque")}
    per = {
        s: {k: finite(v) for k, v in (test.get(s) or {}).items() if k.startswith("rmse") or k == "samples"}
        for s in [*metrics["sensors"], headline]
    }
    return {
        "best_on_validation": metrics.get("best_on_validation"),
        "headline": headline,
        "logs": metrics.get("logs"),
        "samples": metrics.get("samples"),
        "test_metrics": {**keep, **{k: v for k, v in per.items() if v}},
        "mlflow_run": metrics.get("mlflow_run"),
    }
