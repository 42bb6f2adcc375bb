"""Steps `export@<group>` (stage `evaluate@<group>`) and `export_fused` (stage `report`): ONNX graphs.

``ftcal export MODELS METRICS LABELLED OUT --group G`` (a step of stage ``evaluate@<group>``) takes
the model that `evaluate@<group>` recommends (``recommended`` of ``METRICS/<group>/<headline>.json``;
``export.models.<group>`` overrides it), whichever its family (`pipeline.calib.registry`), and
writes ``OUT/groups/<group>/``: ``<group>.float32.onnx``, ``<group>.float64.onnx`` (the group's graph,
`pipeline.export.graph`: input ``inputs`` (N, S x 7 or 13) raw wrench, temperature [, accelerometer,
gyroscope] per sensor, output ``calibrated`` (N, S x 6), normalisation inside) and the group's
``manifest.json`` (an export directory of its own). ``ftcal export ... --fused`` (a step of stage ``report``)
assembles every group's export: the fused graph of every group (``all.float32.onnx``, ``all.float64.onnx``:
one call per sample for all sensors) and ``OUT/manifest.json`` (`pipeline.export.manifest`: inputs and
outputs (order, names, units, source topics), sensors, each group's model and its training provenance, the
checks; the same in each file's ONNX metadata). Without either option, both: every group, then the
assembly. One group's change re-exports that group and the light assembly only.

Every graph is checked with onnxruntime on every test sample of its groups before anything is written
(`pipeline.export.check`): float32 against the project's float32 prediction within
``export.tolerance_float32_ulps`` float32 steps, float64 against the project's own model in float64 within
``export.tolerance_float64`` N/Nm. Outputs are replaced atomically. Each run logs its files to MLflow under
``onnx/``; a group's run tags the registered training version of its exported network
(``ftcal-<group>-<inputs>``) with its graphs, the assembly registers the whole export as a version of
``ftcal-onnx``.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import ConfigError, DataError

STAGE = "export"
GROUPS_DIR = "groups"  # OUT/groups/<group>: each group's export
C_DIR = "c"  # beside each graph: its C calibrator (pipeline.export.csource)
C_NOTHING = "not_calibrated.txt"  # in the fused graph's C_DIR when no group is calibrated: why


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


def choose_models(
    groups: list[str], report: Path, overrides: dict[str, str], only: list[str] | None = None
) -> dict[str, str]:
    """group -> model to export, for the groups `only` (default all): ``export.models`` where given, else
    evaluate's recommendation (``deployed`` of the files ``<report>/<group>/*.json``, the evaluate@<group>
    metrics, `pipeline.evaluation.answer`; a sensor left out of its group has a "not calibrated" file,
    skipped)."""
    from pipeline.calib.exact import NOT_CALIBRATED_TEXT

    unknown = sorted(set(overrides) - set(groups))
    if unknown:
        raise ConfigError(f"export.models.{unknown[0]}: not a group of train.groups ({', '.join(groups)})")
    chosen = {}
    for group in groups if only is None else only:
        name = overrides.get(group)
        if not name:
            files = sorted((report / group).glob("*.json")) or [report / group / "<headline>.json"]
            try:
                for path in files:
                    row = json.loads(path.read_text(encoding="utf-8"))
                    name = None if row.get("verdict") == NOT_CALIBRATED_TEXT else row.get("deployed")
                    if name is not None:
                        break
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


def _config(params: Any) -> tuple[Any, dict[str, float]]:
    from pipeline.core.config import ExportParams, stage_section

    cfg = stage_section(params, STAGE, ExportParams)
    tolerance = {"float32": cfg.tolerance_float32_ulps, "float64": cfg.tolerance_float64}
    return cfg, tolerance | {"c": cfg.tolerance_float32_ulps}


def _c_calibrator(directory: Path, models: list[Any], entry: dict[str, Any], measure: Any) -> dict[str, Any]:
    """Write the graph's C calibrator into `directory` (`pipeline.export.csource`) and check it, compiled
    with the system's cc, as the float32 graph is (`measure`: {"c": session} -> its check); where there is
    no compiler, the check says so."""
    from pipeline.core.io import write_text
    from pipeline.export import cbuild, csource

    for name, text in csource.generate(models, entry).items():
        write_text(directory / name, text)
    (directory / C_NOTHING).unlink(missing_ok=True)  # an earlier export's note that nothing was calibrated
    if cbuild.compiler() is None:
        return {"skipped": "no C compiler (cc) here to build it"}
    n_state = int(entry["state"]["shape"][0]) if "state" in entry else 0
    built = cbuild.c_session(directory, len(entry["inputs"]), len(entry["outputs"]), n_state)
    return measure({"c": built})["c"]


def _training_logs(model: Any, models_dir: Path, labelled: Path) -> list[Path]:
    """The labelled tables a group model was trained on (train and validation logs of its metrics.json)."""
    from pipeline.calib.split import table_name
    from pipeline.export.trained import read_metrics

    metrics = read_metrics(models_dir)
    logs = [*(metrics.get("logs") or {}).get("train", []), *(metrics.get("logs") or {}).get("val", [])]
    paths = [labelled / f"{name}.parquet" for name in dict.fromkeys(table_name(log) for log in logs)]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise DataError(f"{missing[0]}: training log of {model.group} not found (for the data hash)")
    return paths


def _training(client: Any, model: Any, models_dir: Path, paths: list[Path]) -> dict[str, Any]:
    """A group model's provenance for the manifest: its training logs' hash and its MLflow run."""
    from pipeline.export import manifest
    from pipeline.export.registry import train_run
    from pipeline.export.trained import read_metrics

    run = train_run(client, model.group, read_metrics(models_dir))
    return manifest.training(model, manifest.data_sha256(paths), run)


def _serials(params: Any, model: Any, paths: list[Path]) -> dict[str, str | None]:
    """Sensor -> the serial its calibration belongs to: its training logs', else robot.serials
    (`pipeline.export.identity`)."""
    from pipeline.export.identity import training_serials
    from pipeline.logs import schema as S
    from pipeline.logs.tables import read_table_metadata

    experiments = {str(p): read_table_metadata(p).get(S.META_EXPERIMENT.decode()) or {} for p in paths}
    return training_serials(experiments, model.sensors, params.robot.serials)


def _imu_axes(model: Any, paths: list[Path]) -> dict[str, list[str] | None]:
    """Sensor -> the IMU axis map ingest applied to its board in its training logs
    (`pipeline.export.identity.training_imu_axes`)."""
    from pipeline.export.identity import training_imu_axes
    from pipeline.logs import schema as S
    from pipeline.logs.tables import read_table_metadata

    ingests = {str(p): read_table_metadata(p).get(S.META_INGEST.decode()) or {} for p in paths}
    return training_imu_axes(ingests, model.sensors)


def _check_dirs(*paths: tuple[Path, str]) -> None:
    for path, what in paths:
        if not path.is_dir():
            raise DataError(f"{path}: {what} directory not found")


def run_group(
    params: Any,
    group: str,
    models_dir: str | Path,
    report: str | Path,
    labelled_dir: str | Path,
    out_dir: str | Path,
) -> ExportResult:
    """Export one group into `out_dir`/groups/<group>/ (module docstring)."""
    import mlflow

    from pipeline.calib.exact import LEFT_OUT, NOT_CALIBRATED
    from pipeline.core.io import atomic_dir, write_json
    from pipeline.core.tracking import stage_run
    from pipeline.export import check, manifest, wbd
    from pipeline.export.registry import ARTIFACT_DIR, tag_network
    from pipeline.export.trained import read_group, read_metrics

    t0 = time.perf_counter()
    cfg, tolerance = _config(params)
    models_dir, labelled, out = Path(models_dir), Path(labelled_dir), Path(out_dir) / GROUPS_DIR / group
    _check_dirs((models_dir, "models"), (labelled, "labelled"))
    groups = group_names(params)
    if group not in groups:
        raise ConfigError(f"train.groups has no group {group!r} ({', '.join(groups)})")
    if (why := _not_calibrated(models_dir / group)) is not None:
        return _export_nothing(params, group, why, out, t0)
    name = choose_models(groups, Path(report), cfg.models, [group])[group]  # this group's evaluation only
    model = read_group(models_dir / group, name, group)
    samples = check.load_samples(models_dir / group, model, labelled)
    stage_params = {
        STAGE: {k: v for k, v in vars(cfg).items() if k != "models"},
        "group": group,
        "model": name,
    }
    with stage_run(f"{STAGE}@{group}", stage_params) as active:
        client = mlflow.MlflowClient()
        paths = _training_logs(model, models_dir / group, labelled)
        training = _training(client, model, models_dir / group, paths)
        serials, imu_axes = _serials(params, model, paths), _imu_axes(model, paths)
        entry, graphs = manifest.build_graph(
            group, [model], params.topics, params.robot.urdf, {group: training}, serials, imu_axes
        )
        entry["check"] = check.check_group(graphs, samples)
        check.assert_within(group, entry["check"], tolerance)
        with atomic_dir(out) as tmp:
            measure = lambda c: check.check_group(c, samples)  # noqa: E731
            entry["check"]["c"] = _c_calibrator(tmp / C_DIR, [model], entry, measure)
            check.assert_within(group, {"c": entry["check"]["c"]}, tolerance)
            entry = manifest.write_graphs(tmp, group, entry, graphs)
            doc = manifest.document(params.robot.urdf, {group: entry}, fused=None)
            doc[wbd.KEY] = _wbd_terms(models_dir / group, group, name, Path(report))
            left_out = read_metrics(models_dir / group).get(LEFT_OUT)
            if left_out:  # sensors of the group without an exact label: nothing exported for them
                doc[NOT_CALIBRATED] = dict(left_out)
            write_json(tmp / manifest.MANIFEST_FILE, doc)
        _log_checks(doc)
        mlflow.set_tags({"group": group, "model": name, "out_dir": str(out)})
        mlflow.log_artifacts(str(out), ARTIFACT_DIR)
        registered = tag_network(client, active, group, entry)
        run_id = active.info.run_id
    files = sorted(p.name for p in out.iterdir())
    return ExportResult(out, doc, files, time.perf_counter() - t0, run_id, registered)


def _wbd_terms(model_dir: Path, group: str, deployed: str, report: Path) -> dict[str, Any]:
    """The group's wholeBodyDynamics configuration values (`pipeline.export.wbd`): its affine map per
    sensor, and per headline what that map costs beside the deployed model (from evaluate's report.json,
    ``<report>/../groups/<group>/report.json``, where there is one)."""
    from pipeline.core.io import read_json
    from pipeline.evaluation.params import GROUP_REPORT
    from pipeline.export import wbd
    from pipeline.export.trained import read_group

    try:
        affine = read_group(model_dir, wbd.AFFINE_NAME, group)
    except DataError as exc:
        return {"sensors": {}, "why_not": str(exc)}
    entry: dict[str, Any] = {"model": wbd.AFFINE_NAME, "sensors": wbd.group_terms(affine)}
    evaluated = report.parent / "groups" / group / GROUP_REPORT
    if evaluated.is_file():
        tables = read_json(evaluated, "an evaluation report").get("tables") or {}
        entry["fallback"] = wbd.fallback_cost(tables, deployed)
    return entry


def _not_calibrated(model_dir: Path) -> str | None:
    """Why train@<group> calibrated nothing for the group of `model_dir`, None if it did."""
    from pipeline.calib.exact import not_calibrated
    from pipeline.export.trained import read_metrics

    return not_calibrated(read_metrics(model_dir)) if (model_dir / "metrics.json").is_file() else None


def _export_nothing(params: Any, group: str, why: str, out: Path, t0: float) -> ExportResult:
    """A group that is not calibrated: its export directory holds a manifest saying why, and no graph."""
    from pipeline.calib.exact import NOT_CALIBRATED
    from pipeline.core.io import atomic_dir, write_json
    from pipeline.export import manifest

    doc = {**manifest.document(params.robot.urdf, {}, fused=None), NOT_CALIBRATED: {group: why}}
    with atomic_dir(out) as tmp:
        write_json(tmp / manifest.MANIFEST_FILE, doc)
    return ExportResult(out, doc, [manifest.MANIFEST_FILE], time.perf_counter() - t0)


def run_fused(
    params: Any, models_dir: str | Path, labelled_dir: str | Path, out_dir: str | Path
) -> ExportResult:
    """The fused graph of the groups' exports under `out_dir`/groups and `out_dir`/manifest.json."""
    import mlflow

    from pipeline.calib.exact import NOT_CALIBRATED
    from pipeline.core.io import write_json
    from pipeline.core.tracking import stage_run
    from pipeline.export import check, manifest, wbd
    from pipeline.export.registry import ARTIFACT_DIR, register_export
    from pipeline.export.trained import read_group

    t0 = time.perf_counter()
    _, tolerance = _config(params)
    models_dir, labelled, out = Path(models_dir), Path(labelled_dir), Path(out_dir)
    _check_dirs((models_dir, "models"), (labelled, "labelled"))
    entries, uncalibrated = {}, {}
    for group in group_names(params):
        doc = manifest.read_manifest(out / GROUPS_DIR / group)
        uncalibrated.update(doc.get(NOT_CALIBRATED) or {})
        if group in uncalibrated:  # not calibrated: nothing to fuse
            continue
        if group not in doc["graphs"]:
            raise DataError(
                f"{out / GROUPS_DIR / group}: no graph of {group} (run `dvc repro evaluate@{group}`)"
            )
        entry = dict(doc["graphs"][group])
        entry["files"] = {d: f"{GROUPS_DIR}/{group}/{f}" for d, f in entry["files"].items()}
        entries[group] = entry
    if not entries:
        return _fuse_nothing(params, out, uncalibrated, t0)
    models = [read_group(models_dir / g, e["models"][g], g) for g, e in entries.items()]
    samples = [check.load_samples(models_dir / m.group, m, labelled) for m in models]
    trainings = {g: e["training"][g] for g, e in entries.items()}
    serials = {s: v for e in entries.values() for s, v in (e.get("serials") or {}).items()}
    imu_axes = {s: v for e in entries.values() for s, v in (e.get("imu_axes") or {}).items()}
    with stage_run(f"{STAGE}_fused", {"models": {g: e["models"][g] for g, e in entries.items()}}) as active:
        entry, graphs = manifest.build_graph(
            manifest.FUSED, models, params.topics, params.robot.urdf, trainings, serials, imu_axes
        )
        entry["check"] = check.check_fused(graphs, samples, models)
        measure = lambda c: check.check_fused(c, samples, models)  # noqa: E731
        entry["check"]["c"] = _c_calibrator(out / C_DIR, models, entry, measure)
        check.assert_within(manifest.FUSED, entry["check"], tolerance)
        entries[manifest.FUSED] = manifest.write_graphs(out, manifest.FUSED, entry, graphs)
        doc = manifest.document(params.robot.urdf, entries)
        if uncalibrated:  # groups and sensors without an exact label, and why: nothing exported for them
            doc[NOT_CALIBRATED] = uncalibrated
        doc[wbd.KEY] = _write_wbd(out, params.robot.urdf, dict(entries[manifest.FUSED]["models"]))
        write_json(out / manifest.MANIFEST_FILE, doc)  # last: it names (and hashes) the files above
        _log_checks(doc)
        for name in (*entries[manifest.FUSED]["files"].values(), wbd.FILE, manifest.MANIFEST_FILE):
            mlflow.log_artifact(str(out / name), ARTIFACT_DIR)
        mlflow.log_artifacts(str(out / GROUPS_DIR), f"{ARTIFACT_DIR}/{GROUPS_DIR}")
        mlflow.log_artifacts(str(out / C_DIR), f"{ARTIFACT_DIR}/{C_DIR}")  # the fused C calibrator
        registered = register_export(mlflow.MlflowClient(), active, doc)
        run_id = active.info.run_id
    files = sorted(p.name for p in out.iterdir())
    return ExportResult(out, doc, files, time.perf_counter() - t0, run_id, registered)


def _write_wbd(out: Path, robot: str, models: dict[str, str]) -> dict[str, Any]:
    """Write ``out``/wholebodydynamics.xml from the groups' manifests' affine maps; the manifest's entry:
    the file, per sensor its values and per group what the map costs beside the deployed model."""
    from pipeline.core.io import write_text
    from pipeline.export import manifest, wbd

    sensors, fallback = {}, {}
    for group in models:
        entry = manifest.read_manifest(out / GROUPS_DIR / group).get(wbd.KEY) or {}
        sensors.update(entry.get("sensors") or {})
        fallback[group] = entry.get("fallback") or entry.get("why_not") or {}
    write_text(out / wbd.FILE, wbd.fragment(sensors, wbd.about(robot, models)))
    return {
        "file": wbd.FILE,
        "model": wbd.AFFINE_NAME,
        "models": models,
        "sensors": sensors,
        "fallback": fallback,
    }


def _fuse_nothing(params: Any, out: Path, uncalibrated: dict[str, str], t0: float) -> ExportResult:
    """No group is calibrated: manifest.json says why per group (and sensor), and the fused graph's files
    are graphs of no sensor (`pipeline.export.graph.empty`: zero columns in and out), the C calibrator's
    folder and the wholeBodyDynamics configuration say so, so that nothing stale is deployed and the
    stage's outputs exist."""
    import json

    from pipeline.calib.exact import NOT_CALIBRATED
    from pipeline.core.io import write_json, write_text
    from pipeline.export import csource, graph, manifest, wbd

    why = {"ftcal.robot": params.robot.urdf, NOT_CALIBRATED: json.dumps(uncalibrated)}
    for dtype in graph.DTYPES:
        model = graph.empty(dtype, why, f"ftcal_{manifest.FUSED}_nothing_calibrated")
        manifest.write_graphs(out, manifest.FUSED, {}, {dtype: model})
    note = "ftcal: nothing calibrated: " + "; ".join(f"{g}: {w}" for g, w in uncalibrated.items())
    for stale in (csource.HEADER, csource.SOURCE):  # no C calibrator of an earlier export left to deploy
        (out / C_DIR / stale).unlink(missing_ok=True)
    write_text(out / C_DIR / C_NOTHING, note + "\n")
    write_text(out / wbd.FILE, wbd.fragment({}, note))
    doc = {**manifest.document(params.robot.urdf, {}, fused=None), NOT_CALIBRATED: uncalibrated}
    write_json(out / manifest.MANIFEST_FILE, doc)
    files = sorted(p.name for p in out.iterdir() if p.is_file())
    return ExportResult(out, doc, files, time.perf_counter() - t0)


def _log_checks(doc: dict[str, Any]) -> None:
    import mlflow

    mlflow.log_metrics(
        {
            f"check.{name}.{dtype}.{k}": v
            for name, e in doc["graphs"].items()
            if "check" in e
            for dtype, r in e["check"].items()
            for k, v in r.items()
            if k.startswith("max_")
        }
    )


def run(
    params: Any, models_dir: str | Path, report: str | Path, labelled_dir: str | Path, out_dir: str | Path
) -> ExportResult:
    """Every group's export, then the fused graph and manifest (what the stages do one by one)."""
    cfg, _ = _config(params)
    groups = group_names(params)
    calibrated = [g for g in groups if _not_calibrated(Path(models_dir) / g) is None]
    # every calibrated group's model known before anything is written
    choose_models(groups, Path(report), cfg.models, calibrated)
    _check_dirs((Path(models_dir), "models"), (Path(labelled_dir), "labelled"))
    for group in groups:
        run_group(params, group, models_dir, report, labelled_dir, out_dir)
    return run_fused(params, models_dir, labelled_dir, out_dir)


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    params = load_params(args.params)
    if args.group:
        result = run_group(params, args.group, args.models, args.report, args.labelled, args.out)
    elif args.fused:
        result = run_fused(params, args.models, args.labelled, args.out)
    else:
        result = run(params, args.models, args.report, args.labelled, args.out)
    graphs = result.manifest["graphs"]
    left = (result.manifest.get("not_calibrated") or {}).items()
    uncalibrated = "".join(f"; {g} not calibrated, nothing exported: {why}" for g, why in left)
    if not graphs:
        what = "graphs of no sensor" if args.fused else "no graph"
        print(f"export: {what} written to {result.out_dir}{uncalibrated}")
        return 0
    checks = {
        d: max(e["check"][d][k] for e in graphs.values())
        for d, k in (("float32", "max_ulps"), ("float64", "max_abs_diff"))
    }
    models = ", ".join(f"{g} {e['models'][g]}" for g, e in graphs.items() if g in e["models"])
    c_checks = [e["check"].get("c") or {} for e in graphs.values()]
    skipped = next((c["skipped"] for c in c_checks if "skipped" in c), None)
    c_line = f"C calibrator {skipped}" if skipped else (
        f"C calibrator {max(c.get('max_ulps', 0.0) for c in c_checks):.2g} float32 steps"
    )  # fmt: skip
    print(
        f"export: {models} -> {result.out_dir} ({len(result.files)} files); onnxruntime vs the project's "
        f"predictions on the test samples: max |diff| {checks['float32']:.2g} float32 steps, "
        f"{checks['float64']:.2g} N/Nm (float64); {c_line} ({result.seconds:.0f} s){uncalibrated}"
    )
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal export MODELS METRICS LABELLED OUT [--group G | --fused]`."""
    parser = subparsers.add_parser(
        STAGE,
        help="the recommended models as ONNX graphs with a manifest",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument(
        "models", type=Path, help="directory of the groups' model directories (models/<group>)"
    )
    parser.add_argument(
        "report",
        type=Path,
        help="evaluate's metrics directory (<group>/<headline>.json: the recommended model)",
    )
    parser.add_argument(
        "labelled", type=Path, help="directory of labelled <log>.parquet tables (test inputs)"
    )
    parser.add_argument("out", type=Path, help="output directory of the ONNX files and manifest.json")
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--group", default=None, help="export this group only, into OUT/groups/<group>")
    which.add_argument(
        "--fused", action="store_true", help="assemble the groups' exports: fused graph, manifest"
    )
    add_params_option(parser)
    parser.set_defaults(func=_cmd)
