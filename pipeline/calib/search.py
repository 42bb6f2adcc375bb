"""Optuna search of one group network.

One study per network size, stored in a journal file under ``--studies`` and named after a hash of
everything that determines its result (group params except n_trials, seed, threads, validation logs, data,
this code): a rerun after an interruption resumes it, a rerun with more trials extends it. Trial k is
seeded from (seed, group, inputs, k) and its sampler is a TPE sampler seeded the same way, so the search is
reproducible whether or not it was resumed. The first trial is the group's own params (the thesis's
defaults); a MedianPruner stops trials whose validation error lags.
"""

from __future__ import annotations

import hashlib
import json
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.calib.data import Group, GroupData, derive_seed
from pipeline.calib.models import (
    GroupNet,
    save_model,
)
from pipeline.calib.params import SEARCHABLE, GroupParams, nn_name
from pipeline.calib.training import NetSetting, train_network
from pipeline.core.errors import DataError
from pipeline.core.progress import ProgressLog

_PACKAGE = Path(__file__).resolve().parent
# the bytes of the calib package are part of a study's identity


@dataclass
class NetResult:
    model: GroupNet
    trial: int  # 1-based, in the order trials finished (the same whether or not the search was resumed)
    values: dict[str, Any]
    seed: int
    best_epoch: int
    val_rmse: float
    study: str
    trials_run: int
    trials_reused: int
    trials_pruned: int
    history: list[dict[str, float]]  # the best trial's epochs: {epoch, loss, val_rmse}


def code_digest() -> str:
    h = hashlib.sha256()
    for path in sorted(_PACKAGE.glob("*.py")):
        h.update(path.read_bytes())
    return h.hexdigest()


def data_digest(*datas: GroupData) -> str:
    h = hashlib.sha256()
    for data in datas:
        for f in fields(data):
            value = getattr(data, f.name)
            if value is not None:
                h.update(np.ascontiguousarray(np.nan_to_num(value, nan=0.0)).tobytes())
    return h.hexdigest()


def _suggest(trial: Any, search: Mapping[str, Any]) -> dict[str, Any]:
    values: dict[str, Any] = {}
    for name, spec in search.items():
        if isinstance(spec, list):
            values[name] = trial.suggest_categorical(name, spec)
        elif SEARCHABLE[name] is int:
            values[name] = trial.suggest_int(name, spec["low"], spec["high"], log=bool(spec.get("log")))
        else:
            values[name] = trial.suggest_float(name, spec["low"], spec["high"], log=bool(spec.get("log")))
    return values


def search_network(
    gp: GroupParams,
    group: Group,
    train: GroupData,
    val: GroupData,
    n_inputs: int,
    seed: int,
    studies: Path,
    identity: Mapping[str, Any],
    progress: ProgressLog,
    log_trial: Callable[[int, dict[str, Any], list[dict[str, float]], str, float], None] | None = None,
) -> NetResult:
    """Optuna search of one network (see the module docstring); returns the best trial's model."""
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend
    from optuna.trial import TrialState

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    name = nn_name(n_inputs)
    key = hashlib.sha256(json.dumps({**identity, "inputs": n_inputs}, sort_keys=True).encode()).hexdigest()[
        :16
    ]
    study_name = f"{group.name}-{name}-{key}"
    studies.mkdir(parents=True, exist_ok=True)
    storage = JournalStorage(JournalFileBackend(str(studies / "optuna.journal")))
    pruner = optuna.pruners.MedianPruner(
        n_startup_trials=gp.prune_startup_trials, n_warmup_steps=gp.prune_warmup_epochs
    )
    study = optuna.create_study(
        study_name=study_name, storage=storage, direction="minimize", pruner=pruner, load_if_exists=True
    )
    study_id = storage.get_study_id_from_name(study_name)
    for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):  # left by an interrupted run
        storage.set_trial_state_values(
            storage.get_trial_id_from_study_id_trial_number(study_id, t.number), TrialState.FAIL
        )
    done_states = (TrialState.COMPLETE, TrialState.PRUNED)

    def finished() -> list[Any]:
        return sorted(study.get_trials(deepcopy=False, states=done_states), key=lambda t: t.number)

    reused = min(len(finished()), gp.n_trials)
    if not finished() and not study.get_trials(deepcopy=False, states=(TrialState.WAITING,)):
        study.enqueue_trial({k: getattr(gp, k) for k in gp.search})  # trial 0: the group's own params
    trial_dir = studies / study_name
    bar = progress.task(f"{group.name} {name} trials", gp.n_trials)
    progress.update(bar, completed=reused)

    def objective(trial: Any) -> float:
        index = len(finished())
        values = _suggest(trial, gp.search)
        setting = NetSetting.of(gp, n_inputs, values)
        trial_seed = derive_seed(seed, group.name, n_inputs, index)
        epochs = progress.task(f"  trial {index + 1}/{gp.n_trials} epochs", setting.epochs)
        t0 = time.perf_counter()
        history: list[dict[str, float]] = []

        def on_epoch(epoch: int, loss: float, err: float) -> None:
            progress.update(
                epochs, advance=1, description=f"  trial {index + 1}/{gp.n_trials} val RMSE {err:.3g}"
            )
            history.append({"epoch": epoch, "loss": loss, "val_rmse": err})
            trial.report(err, epoch)
            if trial.should_prune():
                raise optuna.TrialPruned()

        try:
            model, history = train_network(group, train, val, setting, trial_seed, on_epoch)
        except optuna.TrialPruned:
            state = "PRUNED"
            progress.line(
                f"{group.name} {name} trial {index + 1}/{gp.n_trials}: pruned at epoch "
                f"{len(history)} (val RMSE {history[-1]['val_rmse']:.4g}) {_fmt(values)}"
            )
            if log_trial is not None:
                log_trial(index, values, history, state, time.perf_counter() - t0)
            raise
        finally:
            progress.remove(epochs)
        best = min(history, key=lambda h: h["val_rmse"])
        info = {"values": values, "seed": trial_seed, "history": history}
        save_model(trial_dir / f"trial_{trial.number:04d}", model, info)
        trial.set_user_attr("index", index)
        trial.set_user_attr("seed", trial_seed)
        trial.set_user_attr("best_epoch", int(best["epoch"]))
        trial.set_user_attr("file", f"trial_{trial.number:04d}")
        progress.line(
            f"{group.name} {name} trial {index + 1}/{gp.n_trials}: val RMSE {best['val_rmse']:.4g} "
            f"(epoch {int(best['epoch']) + 1}) {_fmt(values)} {time.perf_counter() - t0:.1f} s"
        )
        if log_trial is not None:
            log_trial(index, values, history, "COMPLETE", time.perf_counter() - t0)
        return float(best["val_rmse"])

    run = 0
    while len(finished()) < gp.n_trials:
        index = len(finished())
        study.sampler = optuna.samplers.TPESampler(
            seed=derive_seed(seed, group.name, n_inputs, index, "tpe"), n_startup_trials=gp.tpe_startup_trials
        )
        study.optimize(objective, n_trials=1)
        run += 1
        progress.update(bar, completed=min(len(finished()), gp.n_trials))
    progress.remove(bar)
    considered = finished()[: gp.n_trials]
    complete = [t for t in considered if t.state == TrialState.COMPLETE]
    best = min(complete, key=lambda t: (t.value, t.number))
    from pipeline.calib.models import load_model

    path = trial_dir / best.user_attrs["file"]
    try:
        model, info = load_model(path)
    except DataError as exc:
        raise DataError(f"{exc} (the Optuna study {study_name} lost its weights: delete {studies})") from None
    return NetResult(
        model=model,
        trial=int(best.user_attrs["index"]) + 1,
        values=dict(info.get("values", {})),
        seed=int(best.user_attrs["seed"]),
        best_epoch=int(best.user_attrs["best_epoch"]),
        val_rmse=float(best.value),
        study=study_name,
        trials_run=run,
        trials_reused=reused,
        trials_pruned=sum(t.state == TrialState.PRUNED for t in considered),
        history=list(info.get("history", [])),
    )


def _fmt(values: Mapping[str, Any]) -> str:
    return " ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in values.items())
