"""One group's training run: fit the baselines, search the networks, score, write outputs, log to MLflow.

What the outputs hold is the train -> evaluate contract (`pipeline.calib.records`, README "Models").
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.calib.crossval import cross_validate
from pipeline.calib.data import concat
from pipeline.calib.exact import NOT_CALIBRATED, NotCalibrated, not_calibrated_record
from pipeline.calib.excitation import group_excitation
from pipeline.calib.families.base import Family, Saving, Search, Task, Trained
from pipeline.calib.fidelity import group_fidelity
from pipeline.calib.fit import Prepared, mlflow_metrics, prepare, score
from pipeline.calib.fitting import fit_fold, fit_plain_affine, training
from pipeline.calib.linear import LinearBaseline
from pipeline.calib.memory import describe
from pipeline.calib.params import LS_AFFINE
from pipeline.calib.records import TrainResult, write_predictions
from pipeline.calib.search import code_digest, data_digest
from pipeline.calib.studies import storage_url
from pipeline.calib.training import one_thread
from pipeline.core.config import Params
from pipeline.core.io import write_json
from pipeline.core.progress import ProgressLog


@dataclass
class Fitted:
    """Every model of a group (fold 0, in the families' order) with its validation and test predictions
    (N, S, 6) and timings (s)."""

    models: dict[str, Trained]
    preds: dict[str, dict[str, np.ndarray]]  # split (val, test) -> model -> predictions
    timings: dict[str, float] = field(default_factory=dict)
    cv: dict[str, Any] = field(default_factory=dict)  # `pipeline.calib.crossval.cross_validate`
    reference: LinearBaseline | None = None  # recorded logs: the plain least-squares affine map (LS_AFFINE)


def study_identity(params: Params, prep: Prepared) -> dict[str, Any]:
    """Everything a study's result depends on, but n_trials (more trials extend a study); the stage and
    `ftcal worker` name a study after it."""
    return {
        "group": {k: v for k, v in asdict(prep.gp).items() if k != "n_trials"},
        "seed": params.seed,
        "split": {k: prep.split[k] for k in ("train", "val", "test")},  # the search runs on fold 0
        "data": data_digest(prep.train, prep.val),
        "code": code_digest(),
        "torch": torch.__version__,
    }


def fit_models(params: Params, prep: Prepared, studies: Path, ui: ProgressLog) -> Fitted:
    """Every family's models of the group on fold 0 (`pipeline.calib.fitting.fit_fold`: the networks'
    Optuna searches with their studies in a journal under `studies`, or in the database of
    ``train.storage``), then the cross-validation; nothing logged (`write_outputs` logs)."""
    url = storage_url(prep.cfg.storage)
    quiet = ProgressLog(ui.enabled)  # lines, no bars, from a forked search
    search = Search(params.seed, url, studies, prep.cfg.heartbeat, study_identity(params, prep), quiet)
    task = Task(prep.gp, prep.group, prep.train, prep.val, prep.seed, search=search)
    if prep.memory:
        ui.line(describe(prep.group.name, prep.memory))
    models, timings = fit_fold(task, ui)
    data = {"val": prep.val, "test": prep.test}
    t = time.perf_counter()
    preds = {k: {name: m.predict(d) for name, m in models.items()} for k, d in data.items()}
    fitted = Fitted(models, preds, {**timings, "predictions": time.perf_counter() - t})
    ui.line(f"{prep.group.name}: {len(models)} models fitted on {len(prep.train)} samples")
    t = time.perf_counter()
    fitted.cv = cross_validate(prep, fitted.preds["val"], models, prep.cfg.selection_margin, ui)
    fitted.timings["cross_validation"] = time.perf_counter() - t
    if prep.recorded:  # no truth: the plain least-squares affine map beside the models, never a candidate
        every = concat([prep.train, prep.val])  # a lab's script fits on all its training data: no selection
        gp, group = prep.gp, prep.group
        fitted.reference = fit_plain_affine(gp, group, every.subset(every.labelled()), prep.seed)
        for k, d in data.items():
            fitted.preds[k][LS_AFFINE] = fitted.reference.predict(d.x)
    return fitted


def write_outputs(prep: Prepared, fitted: Fitted, out: Path, run_id: str, t0: float) -> TrainResult:
    """Write `out` (metrics.json, each family's files, baselines.json, predictions.parquet) and log to
    MLflow."""
    import mlflow

    group, timings = prep.group, fitted.timings
    metrics = score(prep, fitted.preds, fitted.cv)
    by_family = _by_family(prep, fitted.models)
    for family, models in by_family:
        metrics.update(family.record(models, prep.gp))
    metrics["excitation"] = group_excitation(
        group.sensors, prep.train.x, prep.train.labels, prep.train.switches, prep.train.log, prep.train.stamp
    )
    predictors, memory = {}, {}
    for name, m in fitted.models.items():
        predict, state = m.fidelity(prep.val)
        predictors[name] = (predict, m.n_inputs)
        if state is not None:
            memory[name] = state
    if fitted.reference is not None:
        predictors[LS_AFFINE] = (fitted.reference.predict, 7)
    # on the validation samples' inputs only (no label, no truth): what selection may look at
    metrics["fidelity"] = group_fidelity(predictors, prep.val.x, list(group.sensors), prep.gp.push, memory)
    out.mkdir(parents=True, exist_ok=True)
    example = prep.test.subset(np.arange(min(5, len(prep.test))))
    saving = Saving(out, group, example, metrics, timings=timings)
    for family, models in by_family:
        family.save(saving, models)
    if fitted.reference is not None:
        saving.baselines[LS_AFFINE] = fitted.reference.to_dict()
    write_json(out / "baselines.json", saving.baselines)
    files = ["metrics.json", "baselines.json", "predictions.parquet", *saving.files]
    write_predictions(out / "predictions.parquet", group, prep.test, prep.log_names, fitted.preds["test"])
    timings["total"] = time.perf_counter() - t0
    metrics["seconds"] = timings
    metrics["notes"] = prep.notes  # e.g. a network not trained, and why
    # how evaluate finds this run and the registered networks (by id, never by matching values)
    metrics["mlflow"] = {"run_id": run_id, "models": saving.versions}
    write_json(out / "metrics.json", metrics)
    mlflow.log_metrics(mlflow_metrics(group, metrics))
    mlflow.set_tag("best_on_validation", metrics["best_on_validation"])
    if prep.notes:
        mlflow.set_tag("notes", "\n".join(prep.notes)[:5000])
    for name in ("metrics.json", "baselines.json"):
        mlflow.log_artifact(str(out / name))
    return TrainResult(group.name, metrics, time.perf_counter() - t0, run_id, files)


def _by_family(prep: Prepared, models: dict[str, Trained]) -> list[tuple[Family, dict[str, Trained]]]:
    """(family, its models) of every family that trained for the group, simplest first."""
    out = []
    for family in training(prep.gp, prep.group):
        own = {n: models[n] for n in family.names(prep.gp, prep.group) if n in models}
        if own:
            out.append((family, own))
    return out


def write_not_calibrated(group: str, exc: NotCalibrated, out: Path, t0: float) -> TrainResult:
    """`out`/metrics.json saying why the group is not calibrated (nothing else), in a train@<group> run."""
    import mlflow

    from pipeline.core.tracking import stage_run

    metrics = not_calibrated_record(group, list(exc.left_out), exc)
    with stage_run(f"train@{group}", {"train": {"group": group}}) as run:
        mlflow.set_tags({"group": group, NOT_CALIBRATED: exc.reason})
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "metrics.json", metrics)
        mlflow.log_artifact(str(out / "metrics.json"))
        return TrainResult(group, metrics, time.perf_counter() - t0, run.info.run_id, ["metrics.json"])


def train_group(
    params: Params,
    group_name: str,
    in_dir: str | Path,
    out_dir: str | Path,
    studies: str | Path,
    *,
    progress: bool | None = None,
) -> TrainResult:
    """Run the stage for one group: read, split, fit, search, score, write `out_dir`, log to MLflow."""
    import mlflow

    from pipeline.core.tracking import stage_run

    t0 = time.perf_counter()
    src, out = Path(in_dir), Path(out_dir)
    try:
        prep = prepare(params, group_name, src)
    except NotCalibrated as exc:
        return write_not_calibrated(group_name, exc, out, t0)
    one_thread()  # and so does each training this process forks
    ui = ProgressLog(progress)
    own = {k: v for k, v in asdict(prep.gp).items() if k != "name"}
    stage_params = {
        "train": {
            "group": group_name,
            "val_logs": prep.cfg.val_logs,
            "folds": prep.cfg.folds,
            **own,
        },
        "seed": params.seed,
    }
    with stage_run(f"train@{group_name}", stage_params) as run, ui.running():
        mlflow.set_tags(
            {
                "group": group_name,
                "in_dir": str(src),
                "out_dir": str(out),
                "val_logs": ",".join(prep.split["val"]),
                "test_logs": ",".join(prep.split["test"]),
            }
        )
        fitted = fit_models(params, prep, Path(studies), ui)
        return write_outputs(prep, fitted, out, run.info.run_id, t0)
