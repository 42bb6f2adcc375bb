"""Optuna search of one group network.

One study per network size, stored in a journal file under ``--studies`` (or, with ``train.storage`` or
``$FTCAL_OPTUNA_STORAGE``, in a database shared with ``ftcal worker GROUP`` processes:
`pipeline.calib.studies`) and named after a hash of everything that determines its result (group params except
n_trials, seed, validation logs, data, this code): a rerun after an interruption resumes it, a rerun
with more trials extends it. Trial k is seeded from (seed, group, inputs, k) and its sampler is a TPE sampler
seeded the same way. The first trial is the group's own params (the thesis's defaults); a `SlotPruner`
stops a trial whose validation error lags the slots before it by more than ``prune_margin``. With
``tpe_startup_trials`` = n_trials (the default) a search gives the same trials, the same pruned ones and the
same best whether one process ran it or several, in whatever order they finished, and whether or not it was
resumed (with fewer random trials, TPE's later draws depend on the trials finished when they are drawn).
When the search ends, the stage logs each of its trials to MLflow once, as a child of the stage's run, from
the record each trial left in the study, whichever process ran it.
"""

from __future__ import annotations

import hashlib
import json
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.calib.data import Group, GroupData, derive_seed
from pipeline.calib.linear import LinearBaseline
from pipeline.calib.models import GroupNet
from pipeline.calib.params import SEARCHABLE, GroupParams
from pipeline.calib.pruning import SlotPruner
from pipeline.calib.registry import nn_name
from pipeline.calib.studies import (
    finished_trials,
    join_study,
    load_trial_model,
    open_study,
    record_trial,
    run_trials,
    save_trial_model,
    trial_index,
    trial_record,
)
from pipeline.calib.training import NetSetting, train_network
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
    # every considered trial once, by slot: the arguments of a `TrialLog` call (logged by the caller's
    # process: the search may run in a forked one)
    trials: list[tuple[int, dict[str, Any], list[dict[str, float]], str, float]] = field(default_factory=list)
    seconds: float = 0.0  # wall time of the search


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


TrialLog = Callable[[int, dict[str, Any], list[dict[str, float]], str, float], None]


class _Search:
    """One network's Optuna study: opened (or resumed) by the stage or joined by a worker, run to n_trials
    by any number of processes (`pipeline.calib.studies`), its best trial's model loaded."""

    def __init__(
        self,
        gp: GroupParams,
        group: Group,
        data: tuple[GroupData, GroupData],
        start: LinearBaseline | None,
        n_inputs: int,
        seed: int,
        storage: Any,
        identity: Mapping[str, Any],
        progress: ProgressLog,
    ) -> None:
        self.gp, self.group, (self.train, self.val), self.start = gp, group, data, start
        self.n_inputs, self.seed, self.storage = n_inputs, seed, storage  # storage: studies.open_storage
        self.progress = progress
        self.name = nn_name(n_inputs)
        digest = json.dumps({**identity, "inputs": n_inputs}, sort_keys=True).encode()
        self.study_name = f"{group.name}-{self.name}-{hashlib.sha256(digest).hexdigest()[:16]}"

    def pruner(self) -> SlotPruner:
        """The pruner of the study (every process running its trials uses the same)."""
        gp = self.gp
        return SlotPruner(gp.prune_startup_trials, gp.prune_warmup_epochs, gp.prune_margin)

    def sampler(self, index: int) -> Any:
        """The TPE sampler of trial `index`, seeded from (seed, group, inputs, index); constant_liar: a
        process sees the trials others are running, not only finished ones (alone, it changes nothing)."""
        import optuna

        tpe_seed = derive_seed(self.seed, self.group.name, self.n_inputs, index, "tpe")
        return optuna.samplers.TPESampler(
            seed=tpe_seed, n_startup_trials=self.gp.tpe_startup_trials, constant_liar=True
        )

    def open(self) -> None:
        """Create or load the study with its n_trials slots (the first: the group's own params); trials
        left running by an interrupted run are failed and queued again."""
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
        first = {k: getattr(self.gp, k) for k in self.gp.search}
        self.study = open_study(self.storage, self.study_name, self.pruner(), self.gp.n_trials, first)

    def join(self, wait: float) -> None:
        """Load the study the stage opens (a worker's side), waiting up to `wait` s for it."""
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
        self.study = join_study(self.storage, self.study_name, self.pruner(), wait)

    def finished(self) -> list[Any]:
        """Complete and pruned trials, in the order they were created."""
        return finished_trials(self.study)

    def considered(self) -> list[Any]:
        """The finished trials of the first n_trials slots, by slot (whichever process ran them first)."""
        by_slot = sorted(self.finished(), key=lambda t: (trial_index(t), t.number))
        return by_slot[: self.gp.n_trials]

    def objective(self, trial: Any) -> float:
        """Train one trial's network; its validation error (the best epoch's)."""
        import optuna

        gp, ui, index = self.gp, self.progress, trial_index(trial)
        values = _suggest(trial, gp.search)
        setting = NetSetting.of(gp, self.n_inputs, values)
        trial_seed = derive_seed(self.seed, self.group.name, self.n_inputs, index)
        where = f"{self.group.name} {self.name} trial {index + 1}/{gp.n_trials}"
        epochs = ui.task(f"  trial {index + 1}/{gp.n_trials} epochs", setting.epochs)
        t0 = time.perf_counter()
        history: list[dict[str, float]] = []

        def on_epoch(epoch: int, loss: float, err: float) -> None:
            ui.update(epochs, advance=1, description=f"  trial {index + 1}/{gp.n_trials} val RMSE {err:.3g}")
            history.append({"epoch": epoch, "loss": loss, "val_rmse": err})
            trial.report(err, epoch)
            if trial.should_prune():
                raise optuna.TrialPruned()

        try:
            model, history = train_network(
                self.group, self.train, self.val, setting, trial_seed, on_epoch, self.start
            )
        except optuna.TrialPruned:
            last = history[-1]["val_rmse"]
            ui.line(f"{where}: pruned at epoch {len(history)} (val RMSE {last:.4g}) {_fmt(values)}")
            record_trial(trial, values, history, time.perf_counter() - t0)
            raise
        finally:
            ui.remove(epochs)
        best = min(history, key=lambda h: h["val_rmse"])
        save_trial_model(trial, model, {"values": values, "seed": trial_seed, "history": history})
        for key, value in (("index", index), ("seed", trial_seed), ("best_epoch", int(best["epoch"]))):
            trial.set_user_attr(key, value)
        seconds = time.perf_counter() - t0
        record_trial(trial, values, history, seconds)
        ui.line(
            f"{where}: val RMSE {best['val_rmse']:.4g} (epoch {int(best['epoch']) + 1}) {_fmt(values)} "
            f"{seconds:.1f} s"
        )
        return float(best["val_rmse"])

    def run(self) -> tuple[int, int]:
        """Run trials until n_trials have finished, counted over every process sharing the study;
        (trials run here now, trials finished before)."""
        gp, ui = self.gp, self.progress
        reused = min(len(self.finished()), gp.n_trials)
        bar = ui.task(f"{self.group.name} {self.name} trials", gp.n_trials)
        ui.update(bar, completed=reused)
        run = run_trials(
            self.study,
            self.objective,
            gp.n_trials,
            self.sampler,
            on_trial=lambda done: ui.update(bar, completed=min(done, gp.n_trials)),
        )
        ui.remove(bar)
        return run, reused

    def trial_records(self) -> list[tuple[int, dict[str, Any], list[dict[str, float]], str, float]]:
        """The `TrialLog` arguments of each of the first n_trials finished trials once, by slot, wherever it
        ran: a worker's trial is in the study (`record_trial`) when the search ends, whatever the worker's
        view of MLflow."""
        records = []
        for t in self.considered():
            record = trial_record(t)
            records.append(
                (trial_index(t), record["values"], record["history"], t.state.name, record["seconds"])
            )
        return records

    def best(self, run: int, reused: int) -> NetResult:
        """The lowest-validation-error complete trial among the first n_trials slots (a tie: the first
        slot), with its model."""
        considered = self.considered()
        complete = [t for t in considered if t.state.name == "COMPLETE"]
        best = min(complete, key=lambda t: (t.value, trial_index(t)))
        model, info = load_trial_model(best)
        return NetResult(
            model=model,
            trial=int(best.user_attrs["index"]) + 1,
            values=dict(info.get("values", {})),
            seed=int(best.user_attrs["seed"]),
            best_epoch=int(best.user_attrs["best_epoch"]),
            val_rmse=float(best.value),
            study=self.study_name,
            trials_run=run,
            trials_reused=reused,
            trials_pruned=sum(t.state.name == "PRUNED" for t in considered),
            history=list(info.get("history", [])),
        )


def search_network(
    gp: GroupParams,
    group: Group,
    train: GroupData,
    val: GroupData,
    n_inputs: int,
    seed: int,
    storage: Any,
    identity: Mapping[str, Any],
    progress: ProgressLog,
    log_trial: TrialLog | None = None,
    start: LinearBaseline | None = None,
) -> NetResult:
    """Optuna search of one network (see the module docstring) in `storage` (`studies.open_storage`);
    returns the best trial's model.

    `start`: the affine baseline the networks correct (see `pipeline.calib.training.train_network`).
    """
    t = time.perf_counter()
    search = _Search(gp, group, (train, val), start, n_inputs, seed, storage, identity, progress)
    search.open()
    result = search.best(*search.run())
    result.trials = search.trial_records()
    result.seconds = time.perf_counter() - t
    for record in result.trials if log_trial is not None else ():
        log_trial(*record)
    return result


def _fmt(values: Mapping[str, Any]) -> str:
    return " ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in values.items())
