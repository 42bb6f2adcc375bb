"""One group's training run: fit the baselines, search the networks, score, write outputs, log to MLflow.

What the outputs hold is the train -> evaluate contract (`pipeline.calib.records`, README "Models").
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.calib.crossval import cross_validate
from pipeline.calib.data import concat
from pipeline.calib.exact import NOT_CALIBRATED, NotCalibrated, not_calibrated_record
from pipeline.calib.excitation import group_excitation
from pipeline.calib.fidelity import group_fidelity
from pipeline.calib.fit import (
    Prepared,
    fit_beside,
    fit_plain_affine,
    mlflow_metrics,
    network_info,
    prepare,
    score,
)
from pipeline.calib.linear import LinearBaseline
from pipeline.calib.memory import describe
from pipeline.calib.models import WRENCH, save_model
from pipeline.calib.params import LS_AFFINE
from pipeline.calib.records import TrainResult, log_network, log_trial_run, write_predictions
from pipeline.calib.registry import RAW, WIN, nn_name
from pipeline.calib.search import NetResult, code_digest, data_digest, search_network
from pipeline.calib.studies import open_storage, storage_url
from pipeline.calib.training import flat_inputs, one_thread, predict, predict_inputs
from pipeline.calib.window import WindowFit, fit_windowed, window_memory
from pipeline.core.config import Params
from pipeline.core.io import write_json
from pipeline.core.progress import ProgressLog


@dataclass
class Fitted:
    """Every model of a group with its validation and test predictions (N, S, 6) and timings (s)."""

    baselines: dict[str, LinearBaseline]
    nets: dict[str, NetResult]
    preds: dict[str, dict[str, np.ndarray]]  # split (val, test) -> model -> predictions
    timings: dict[str, float] = field(default_factory=dict)
    cv: dict[str, Any] = field(default_factory=dict)  # `pipeline.calib.crossval.cross_validate`
    window: WindowFit | None = None  # the windowed network, where the group trains one


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
    """The baselines, the Optuna search of every network size of the group (studies in a journal under
    `studies`, or in the database of ``train.storage``) and the cross-validation; nothing logged (the
    trials are logged to MLflow by `write_outputs`)."""
    gp, group = prep.gp, prep.group
    data = {"val": prep.val, "test": prep.test}
    fitted = Fitted({}, {}, {k: {RAW: d.x[:, :, :WRENCH].copy()} for k, d in data.items()})
    identity = study_identity(params, prep)
    url = storage_url(prep.cfg.storage)
    # the networks' searches are independent: one forked process per core (`forked_map`, the same bits as
    # one after the other), each with its own connection to the studies, the polynomial baselines fitted
    # beside them
    quiet = ProgressLog(ui.enabled)  # lines, no bars, from a forked search

    def search(n_inputs: int, start: LinearBaseline) -> NetResult:
        one_thread()
        storage = open_storage(url, studies, prep.cfg.heartbeat)
        return search_network(
            gp, group, prep.train, prep.val, n_inputs, params.seed, storage, identity, quiet, None, start
        )

    jobs = [partial(search, n) for n in gp.inputs]
    labels = [f"search of the {n}-input network" for n in gp.inputs]
    fitted.baselines, searches, seconds = fit_beside(gp, group, prep.train, prep.seed, jobs, labels)
    t = time.perf_counter()
    for name, model in fitted.baselines.items():
        for k, d in data.items():
            fitted.preds[k][name] = model.predict(d.x, d.memory)
    fitted.timings["baselines"] = seconds + time.perf_counter() - t
    ui.line(f"{group.name}: baselines fitted on {len(prep.train)} samples in {seconds:.1f} s")
    if prep.memory:
        ui.line(describe(group.name, prep.memory))
    fitted.window = fit_windowed(gp, group, prep.train, prep.val, fitted.baselines, prep.seed)
    if fitted.window is not None:
        model, fitted.timings[WIN] = fitted.window.model, fitted.window.seconds
        for k, d in data.items():
            fitted.preds[k][WIN] = model.predict(d.x, window_memory(model.base, d))
        info = fitted.window.info()
        ui.line(
            f"{group.name}: windowed network val RMSE {info['val_rmse_labelled']:.4g} (epoch "
            f"{info['best_epoch'] + 1}) {fitted.timings[WIN]:.1f} s"
        )
    for n_inputs, result in zip(gp.inputs, searches, strict=True):
        name = nn_name(n_inputs)
        t = time.perf_counter()
        fitted.nets[name] = result
        for k, d in data.items():
            fitted.preds[k][name] = predict(result.model, d)
        fitted.timings[name] = result.seconds + time.perf_counter() - t
    t = time.perf_counter()
    fitted.cv = cross_validate(prep, fitted.preds["val"], fitted.nets, prep.cfg.selection_margin, ui)
    fitted.timings["cross_validation"] = time.perf_counter() - t
    if prep.recorded:  # no truth: the plain least-squares affine map beside the models, never a candidate
        every = concat([prep.train, prep.val])  # a lab's script fits on all its training data: no selection
        plain = fit_plain_affine(gp, group, every.subset(every.labelled()), prep.seed)
        fitted.baselines[LS_AFFINE] = plain
        for k, d in data.items():
            fitted.preds[k][LS_AFFINE] = plain.predict(d.x)
    return fitted


def write_outputs(prep: Prepared, fitted: Fitted, out: Path, run_id: str, t0: float) -> TrainResult:
    """Write `out` (metrics.json, networks, baselines.json, predictions.parquet) and log to MLflow."""
    import mlflow

    group, timings = prep.group, fitted.timings
    metrics = score(prep, fitted.preds, fitted.nets, fitted.cv)
    metrics["excitation"] = group_excitation(
        group.sensors, prep.train.x, prep.train.labels, prep.train.switches, prep.train.log, prep.train.stamp
    )
    predictors = {RAW: (lambda x: x[:, :, :WRENCH].copy(), 7)}
    predictors.update({name: (b.predict, 7) for name, b in fitted.baselines.items()})
    memory = {name: prep.val.memory for name, b in fitted.baselines.items() if b.memory}
    for name, r in fitted.nets.items():
        predictors[name] = (lambda x, m=r.model: predict_inputs(m, x), r.model.config.n_inputs)
    if fitted.window is not None:
        predictors[WIN] = (fitted.window.model.predict, 7)
        memory[WIN] = window_memory(fitted.window.model.base, prep.val)
    # on the validation samples' inputs only (no label, no truth): what selection may look at
    metrics["fidelity"] = group_fidelity(predictors, prep.val.x, list(group.sensors), prep.gp.push, memory)
    out.mkdir(parents=True, exist_ok=True)
    files = ["metrics.json", "baselines.json", "predictions.parquet"]
    example = prep.test.subset(np.arange(min(5, len(prep.test))))
    versions: dict[str, dict[str, str]] = {}
    for name, r in fitted.nets.items():
        info = network_info(prep, r, metrics, name)
        save_model(out / name, r.model, info)
        files += [f"{name}.json", f"{name}.pt"]
        t = time.perf_counter()
        log = log_trial_run(group.name, name)
        for record in r.trials:
            log(*record)
        columns = {k: info[k] for k in ("group", "sensors", "input_columns", "output_columns")}
        x = flat_inputs(example, r.model.config.n_inputs)
        versions[name] = log_network(group, name, r.model, x, columns)
        timings[f"log_{name}"] = time.perf_counter() - t
    write_json(out / "baselines.json", {name: b.to_dict() for name, b in fitted.baselines.items()})
    if fitted.window is not None:
        write_json(out / f"{WIN}.json", fitted.window.model.to_dict())
        files.append(f"{WIN}.json")
        metrics["windowed"] = fitted.window.info()
    write_predictions(out / "predictions.parquet", group, prep.test, prep.log_names, fitted.preds["test"])
    timings["total"] = time.perf_counter() - t0
    metrics["seconds"] = timings
    metrics["notes"] = prep.notes  # e.g. a network not trained, and why
    # how evaluate finds this run and the registered networks (by id, never by matching values)
    metrics["mlflow"] = {"run_id": run_id, "models": versions}
    write_json(out / "metrics.json", metrics)
    mlflow.log_metrics(mlflow_metrics(group, metrics))
    mlflow.set_tag("best_on_validation", metrics["best_on_validation"])
    if prep.notes:
        mlflow.set_tag("notes", "\n".join(prep.notes)[:5000])
    for name in ("metrics.json", "baselines.json"):
        mlflow.log_artifact(str(out / name))
    return TrainResult(group.name, metrics, time.perf_counter() - t0, run_id, files)


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
