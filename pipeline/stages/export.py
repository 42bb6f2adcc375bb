"""Stage `export`: the recommended calibration of every sensor group as ONNX graphs a robot can run.

``ftcal export MODELS METRICS LABELLED OUT`` takes, per group of ``train.groups``, the model that
`evaluate@<group>` recommends (``recommended`` of ``METRICS/<group>.json``; ``export.models.<group>``
overrides it), whichever its family (network, polynomial, affine, raw), and writes ``OUT``:

- ``<group>.float32.onnx``, ``<group>.float64.onnx``: the group's graph (`pipeline.export.graph`):
  input ``inputs`` (N, S x 7 or 13) raw wrench, temperature [, accelerometer, gyroscope] per sensor, output
  ``calibrated`` (N, S x 6), normalisation inside;
- ``all.float32.onnx``, ``all.float64.onnx``: every group fused, one call per sample for all sensors;
- ``manifest.json``: inputs and outputs (order, names, units, source topics), sensors, the model and its
  training provenance (logs, data hash, MLflow run, test errors) and the checks (`pipeline.export.manifest`;
  the same in each file's ONNX metadata).

Every graph is checked with onnxruntime on every test sample of its groups before anything is written
(`pipeline.export.check`): float32 against the stored test predictions within ``export.tolerance_float32``,
float64 against the project's own model in float64 within ``export.tolerance_float64``. The output
directory is replaced whole, atomically. The MLflow run ``export`` logs the files under ``onnx/``, registers
them as a version of the registered model ``ftcal-onnx``, and tags the registered training version of each
exported network (``ftcal-<group>-<inputs>``) with where its ONNX graphs are.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import ConfigError, DataError

STAGE = "export"
REGISTERED_MODEL = "ftcal-onnx"
ARTIFACT_DIR = "onnx"


@dataclass
class ExportResult:
    out_dir: Path
    manifest: dict[str, Any]
    files: list[str]
    seconds: float
    run_id: str | None = None
    registered: dict[str, str] = field(default_factory=dict)  # model name -> version


def group_names(params: Any) -> list[str]:
    """The sensor groups: the keys of ``train.groups`` in params.yaml."""
    groups = (
        (params.raw.get("train") or {}).get("groups") if isinstance(params.raw.get("train"), dict) else None
    )
    if not isinstance(groups, dict) or not groups:
        raise ConfigError(
            f"{params.raw.get('__file__', 'params.yaml')}: train.groups must list the sensor groups"
        )
    return [str(g) for g in groups]


def choose_models(groups: list[str], report: Path, overrides: dict[str, str]) -> dict[str, str]:
    """group -> model to export: ``export.models`` where given, else evaluate's recommendation
    (``recommended`` of the files ``<report>/<group>/*.json``, the evaluate@<group> metrics)."""
    unknown = sorted(set(overrides) - set(groups))
    if unknown:
        raise ConfigError(f"export.models.{unknown[0]}: not a group of train.groups ({', '.join(groups)})")
    chosen = {}
    for group in groups:
        name = overrides.get(group)
        if not name:
            files = sorted((report / group).glob("*.json"))
            path = files[0] if files else report / group / "<headline>.json"
            try:
                name = json.loads(path.read_text(encoding="utf-8")).get("recommended")
            except FileNotFoundError:
                raise DataError(f"{path}: not found (run `dvc repro evaluate@{group}`)") from None
            except (OSError, ValueError, AttributeError) as exc:
                raise DataError(f"{path}: not evaluate's metrics of {group}: {exc}") from None
            if not name or name == "none":
                raise DataError(
                    f"{path}: no recommended model for {group} (every model flagged); "
                    f"name one in export.models.{group}"
                )
        chosen[group] = str(name)
    return chosen


def _train_run(client: Any, group: str, metrics: dict[str, Any]) -> str | None:
    """The train@<group> MLflow run that wrote models/<group>: metrics.json's ``mlflow_run``, else the
    latest run of that stage whose logged test RMSE of every model equals metrics.json's."""
    import math

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


def _register(client: Any, run: Any, manifest: dict[str, Any]) -> dict[str, str]:
    """Register the exported files as a version of REGISTERED_MODEL; tag the exported networks' versions."""
    import mlflow

    registered = {}
    try:
        client.get_registered_model(REGISTERED_MODEL)
    except mlflow.exceptions.MlflowException:
        client.create_registered_model(
            REGISTERED_MODEL, description="ftcal calibrations as ONNX (manifest.json)"
        )
    groups = {g: t["model"] for g, t in manifest["graphs"]["all"]["training"].items()}
    version = client.create_model_version(
        REGISTERED_MODEL,
        f"{run.info.artifact_uri}/{ARTIFACT_DIR}",
        run_id=run.info.run_id,
        tags={f"model.{g}": name for g, name in groups.items()},
        description="one graph per group and one fused graph; see manifest.json",
    )
    registered[REGISTERED_MODEL] = str(version.version)
    for group, entry in manifest["graphs"].items():
        training = entry["training"].get(group)
        if training is None or training["family"] != "network" or not training.get("mlflow_run"):
            continue
        name = f"ftcal-{group}-{training['inputs_per_sensor']}"
        for mv in client.search_model_versions(f"name = '{name}' and run_id = '{training['mlflow_run']}'"):
            for dtype, file in entry["files"].items():
                client.set_model_version_tag(
                    name, mv.version, f"onnx.{dtype}", f"runs:/{run.info.run_id}/{ARTIFACT_DIR}/{file}"
                )
            client.set_model_version_tag(
                name, mv.version, "onnx.registered", f"{REGISTERED_MODEL}/{version.version}"
            )
            registered[name] = str(mv.version)
    return registered


def _replace_dir(tmp: Path, out: Path) -> None:
    """Move the finished directory `tmp` to `out`, replacing an older export."""
    old = out.with_name(f".{out.name}.{os.getpid()}.old")
    if out.exists():
        os.replace(out, old)
    os.replace(tmp, out)
    shutil.rmtree(old, ignore_errors=True)


def run(
    params: Any, models_dir: str | Path, report: str | Path, labelled_dir: str | Path, out_dir: str | Path
) -> ExportResult:
    """Export, check, write `out_dir` and log to MLflow (module docstring)."""
    import mlflow

    from pipeline.core.config import ExportParams, stage_section
    from pipeline.core.tracking import stage_run
    from pipeline.export import check, manifest
    from pipeline.export.trained import read_group, read_metrics

    t0 = time.perf_counter()
    cfg = stage_section(params, STAGE, ExportParams)
    models_dir, labelled, out = Path(models_dir), Path(labelled_dir), Path(out_dir)
    for path, what in ((models_dir, "models"), (labelled, "labelled")):
        if not path.is_dir():
            raise DataError(f"{path}: {what} directory not found")
    groups = group_names(params)
    chosen = choose_models(groups, Path(report), cfg.models)
    models = [read_group(models_dir / g, chosen[g], g) for g in groups]
    samples = [check.load_samples(models_dir / m.group, m, labelled) for m in models]
    tolerance = {"float32": cfg.tolerance_float32, "float64": cfg.tolerance_float64}
    robot = params.robot.urdf

    stage_params = {
        STAGE: {"tolerance_float32": cfg.tolerance_float32, "tolerance_float64": cfg.tolerance_float64}
    }
    stage_params["models"] = chosen
    with stage_run(STAGE, stage_params) as active:
        client = mlflow.MlflowClient()
        trainings = {}
        for m in models:
            metrics = read_metrics(models_dir / m.group)
            logs = [
                *(metrics.get("logs") or {}).get("train", []),
                *(metrics.get("logs") or {}).get("val", []),
            ]
            paths = [labelled / f"{log}.parquet" for log in logs]
            missing = [p for p in paths if not p.is_file()]
            if missing:
                raise DataError(f"{missing[0]}: training log of {m.group} not found (for the data hash)")
            trainings[m.group] = manifest.training(
                m, manifest.data_sha256(paths), _train_run(client, m.group, metrics)
            )

        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        try:
            built = manifest.build_graphs(models, params.topics, robot, trainings)
            for name, (entry, graphs) in built.items():
                if name == manifest.FUSED:
                    entry["check"] = check.check_fused(graphs, samples)
                else:
                    entry["check"] = check.check_group(graphs, samples[groups.index(name)])
                check.assert_within(name, entry["check"], tolerance)
            doc = manifest.write_export(tmp, robot, built)
            _replace_dir(tmp, out)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        files = sorted(p.name for p in out.iterdir())
        mlflow.log_metrics(
            {
                f"check.{name}.{dtype}.max_abs_diff": r["max_abs_diff"]
                for name, e in doc["graphs"].items()
                for dtype, r in e["check"].items()
            }
        )
        mlflow.set_tags({f"model.{g}": n for g, n in chosen.items()} | {"out_dir": str(out)})
        mlflow.log_artifacts(str(out), ARTIFACT_DIR)
        registered = _register(client, active, doc)
        run_id = active.info.run_id
    return ExportResult(out, doc, files, time.perf_counter() - t0, run_id, registered)


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    result = run(load_params(args.params), args.models, args.report, args.labelled, args.out)
    worst = {
        dtype: max(e["check"][dtype]["max_abs_diff"] for e in result.manifest["graphs"].values())
        for dtype in ("float32", "float64")
    }
    models = ", ".join(f"{g} {e['models'][g]}" for g, e in result.manifest["graphs"].items() if g != "all")
    print(
        f"export: {models} -> {result.out_dir} ({len(result.files)} files); onnxruntime vs the project's "
        f"predictions on the test samples: max |diff| {worst['float32']:.2g} (float32), "
        f"{worst['float64']:.2g} (float64) N/Nm; registered {REGISTERED_MODEL} "
        f"version {result.registered.get(REGISTERED_MODEL)} ({result.seconds:.0f} s)"
    )
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal export MODELS METRICS LABELLED OUT`."""
    parser = subparsers.add_parser(
        STAGE,
        help="the recommended models as ONNX graphs with a manifest",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument(
        "models", type=Path, help="directory of the groups' model directories (models/<group>)"
    )
    parser.add_argument(
        "report", type=Path, help="evaluate's metrics.json (the recommended model of each group)"
    )
    parser.add_argument(
        "labelled", type=Path, help="directory of labelled <log>.parquet tables (test inputs)"
    )
    parser.add_argument("out", type=Path, help="output directory of the ONNX files and manifest.json")
    add_params_option(parser)
    parser.set_defaults(func=_cmd)
