"""The export in MLflow's model registry: where a group's training run is, and what points at its graphs.

A group's export run tags the registered training version of its exported network (``ftcal-<group>-<inputs>``)
with ``onnx.float32`` / ``onnx.float64`` (``runs:/<run>/onnx/<file>``); the fused export's run registers the
whole export directory as a version of ``ftcal-onnx`` and tags those training versions with it.
"""

from __future__ import annotations

import math
from typing import Any

from pipeline.calib.registry import NETWORK

REGISTERED_MODEL = "ftcal-onnx"
ARTIFACT_DIR = "onnx"


def train_run(client: Any, group: str, metrics: dict[str, Any]) -> str | None:
    """The train@<group> MLflow run that wrote models/<group>: metrics.json's ``mlflow_run``, else the
    latest run of that stage whose logged test RMSE of every model equals metrics.json's."""
    if metrics.get("mlflow_run"):
        return str(metrics["mlflow_run"])
    experiment = client.get_experiment_by_name("ftcal")
    if experiment is None:
        return None
    runs = client.search_runs(
        [experiment.experiment_id],
        f"tags.`dvc.stage` = 'train@{group}'",
        order_by=["attributes.start_time DESC"],
    )
    test = metrics.get("test") or {}

    def same(logged: dict[str, float], name: str, errors: dict[str, Any]) -> bool:
        a, b = logged.get(f"test.{name}.rmse"), errors.get("rmse")
        return a is not None and b is not None and math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)

    for r in runs:
        measured = [(n, e) for n, e in test.items() if isinstance(e.get("rmse"), float)]
        if measured and all(same(r.data.metrics, n, e) for n, e in measured):
            return r.info.run_id
    return None


def _trained_versions(client: Any, group: str, entry: dict[str, Any]) -> list[tuple[str, Any]]:
    """(name, version) of the registered training versions of the group's exported network, if any."""
    training = entry["training"].get(group)
    if training is None or training.get("kind") != NETWORK or not training.get("mlflow_run"):
        return []
    name = f"ftcal-{group}-{training['inputs_per_sensor']}"
    query = f"name = '{name}' and run_id = '{training['mlflow_run']}'"
    return [(name, mv) for mv in client.search_model_versions(query)]


def tag_network(client: Any, run: Any, group: str, entry: dict[str, Any]) -> dict[str, str]:
    """Tag the training version of a group's exported network with its graphs in `run`'s artifacts."""
    registered = {}
    for name, mv in _trained_versions(client, group, entry):
        for dtype, file in entry["files"].items():
            client.set_model_version_tag(
                name, mv.version, f"onnx.{dtype}", f"runs:/{run.info.run_id}/{ARTIFACT_DIR}/{file}"
            )
        registered[name] = str(mv.version)
    return registered


def register_export(client: Any, run: Any, manifest: dict[str, Any]) -> dict[str, str]:
    """Register the export directory logged under `run` as a version of REGISTERED_MODEL; tag the exported
    networks' training versions with it."""
    import mlflow

    try:
        client.get_registered_model(REGISTERED_MODEL)
    except mlflow.exceptions.MlflowException:
        client.create_registered_model(
            REGISTERED_MODEL, description="ftcal calibrations as ONNX (manifest.json)"
        )
    fused = manifest["fused"]
    groups = {g: t["model"] for g, t in manifest["graphs"][fused]["training"].items()}
    version = client.create_model_version(
        REGISTERED_MODEL,
        f"{run.info.artifact_uri}/{ARTIFACT_DIR}",
        run_id=run.info.run_id,
        tags={f"model.{g}": name for g, name in groups.items()},
        description="one graph per group and one fused graph; see manifest.json",
    )
    registered = {REGISTERED_MODEL: str(version.version)}
    for group, entry in manifest["graphs"].items():
        for name, mv in _trained_versions(client, group, entry):
            client.set_model_version_tag(
                name, mv.version, "onnx.registered", f"{REGISTERED_MODEL}/{version.version}"
            )
            registered[name] = str(mv.version)
    return registered
