"""Shared Optuna studies (`pipeline.calib.studies`, `ftcal worker`) on a real PostgreSQL server: the stage
and 4 worker processes finish one group's search with exactly n_trials trials, every one logged once as a
child of the stage's run on an MLflow server on PostgreSQL; a worker killed with SIGKILL mid-trial costs one
trial that another process runs again."""

from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pipeline.calib import studies
from pipeline.calib.pruning import SlotPruner
from pipeline.core.config import load_params
from pipeline.core.errors import ConfigError
from tests.factories.labelled import LEG, LOGS, write_labelled_log
from tests.factories.params import TRAIN_PARAMS, write_params
from tests.pgserver import create_database

pytestmark = pytest.mark.slow  # several processes share one Optuna study

ROOT = Path(__file__).resolve().parents[1]


def _states(study: Any) -> dict[str, int]:
    out: dict[str, int] = {}
    for t in study.get_trials(deepcopy=False):
        out[t.state.name] = out.get(t.state.name, 0) + 1
    return out


def test_storage_url_from_params_or_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(studies.ENV_STORAGE, raising=False)
    assert studies.storage_url(None) is None
    assert studies.storage_url("postgresql://u:p@h:5432/d") == "postgresql+psycopg://u:p@h:5432/d"
    monkeypatch.setenv(studies.ENV_STORAGE, "sqlite:///x.db")
    assert studies.storage_url("postgresql://u@h/d") == "sqlite:///x.db"  # the environment wins
    monkeypatch.setenv(studies.ENV_STORAGE, "redis://h")
    with pytest.raises(ConfigError, match=f"{studies.ENV_STORAGE} must be null .* got 'redis://h'"):
        studies.storage_url(None)
    assert studies.redact("postgresql://u:secret@h:5432/d") == "postgresql://u:***@h:5432/d"


def test_bad_storage_in_params_names_the_key(tmp_path: Path) -> None:
    train = copy.deepcopy(TRAIN_PARAMS)
    train["storage"] = "journal.log"
    from pipeline.calib.params import TrainParams
    from pipeline.core.config import stage_section

    with pytest.raises(ConfigError, match="train.storage must be null"):
        stage_section(load_params(write_params(tmp_path, train)), "train", TrainParams)


_KILLABLE_WORKER = """
import sys, time
from pathlib import Path
import optuna
from pipeline.calib import studies
url, name, marker = sys.argv[1:4]
def objective(trial):
    trial.suggest_float("x", 0.0, 1.0)
    Path(marker).write_text(str(trial.number))
    time.sleep(600)  # killed before it returns
studies.run_worker(studies.open_storage(url, Path(), 1), name, None, objective, 4,
                   lambda i: optuna.samplers.RandomSampler(seed=i), wait=60)
"""


def test_sigkilled_worker_costs_one_trial(pg_url: str, tmp_path: Path) -> None:
    import optuna

    url = studies.storage_url(create_database(pg_url, "kill"))
    storage = studies.open_storage(url, tmp_path, heartbeat=1)
    study = studies.open_study(storage, "kill", None, 4, {"x": 0.5})
    marker = tmp_path / "running"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-c", _KILLABLE_WORKER, url, "kill", str(marker)]
    worker = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not marker.exists():
            assert worker.poll() is None, worker.stderr.read() if worker.stderr else ""
            assert time.monotonic() < deadline, "the worker never started a trial"
            time.sleep(0.2)
    finally:
        worker.send_signal(signal.SIGKILL)
        worker.wait()
    killed = int(marker.read_text())
    assert _states(study) == {"RUNNING": 1, "WAITING": 3}

    ran: list[int] = []

    def objective(trial: Any) -> float:
        ran.append(studies.trial_index(trial))
        return trial.suggest_float("x", 0.0, 1.0)

    t0 = time.monotonic()
    assert studies.run_trials(study, objective, 4, lambda i: optuna.samplers.RandomSampler(seed=i)) == 4
    assert time.monotonic() - t0 < 30
    trials = study.get_trials(deepcopy=False)
    assert _states(study) == {"FAIL": 1, "COMPLETE": 4}  # nothing left RUNNING or WAITING
    (failed,) = [t for t in trials if t.state.name == "FAIL"]
    assert failed.number == killed == 0
    (retry,) = [t for t in trials if t.system_attrs.get("failed_trial") == killed]
    assert retry.state.name == "COMPLETE" and retry.params == failed.params == {"x": 0.5}
    assert sorted(ran) == [0, 1, 2, 3]  # every slot once, the killed one under its own index


def _train_params(tmp_path: Path) -> Path:
    train = copy.deepcopy(TRAIN_PARAMS)
    train["heartbeat"] = 2
    train["groups"] = {LEG: {"sensor": LEG}}
    # trials long enough (1-2 s) that the workers, which start in a few s, take part under load; random
    # trials only (params.yaml's policy: tpe_startup_trials = n_trials)
    train["defaults"].update(n_trials=8, epochs=20, tpe_startup_trials=8, prune_startup_trials=3)
    return write_params(tmp_path, train)


def _pruned_in_order(study: Any, pruner: SlotPruner) -> dict[int, int | None]:
    """Slot -> the epoch one process running the slots in order prunes it at (None: run to the end), from
    the epochs' errors the study holds (a slot's errors do not depend on which process ran it)."""
    out: dict[int, int | None] = {}
    for t in sorted(study.get_trials(deepcopy=False), key=studies.trial_index):
        slot, errors = studies.trial_index(t), t.intermediate_values
        out[slot] = None
        for epoch in sorted(errors):
            if epoch < pruner.warmup or slot < pruner.startup:
                continue
            reference = pruner.reference(study, slot, epoch)
            best = min(v for e, v in errors.items() if e <= epoch)
            if reference and best > (1 + pruner.margin) * float(np.median(reference)):
                out[slot] = epoch
                break
    return out


def test_stage_and_four_workers_share_a_study(
    pg_url: str, mlflow_server: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mlflow import MlflowClient

    from pipeline.stages import train as T

    labelled = tmp_path / "labelled"
    for i, (name, kind, role) in enumerate(LOGS):
        write_labelled_log(labelled / f"{name}_{role}.parquet", kind, role, n=500, seed=i)
    params_path = _train_params(tmp_path)
    url = create_database(pg_url, "search")
    monkeypatch.setenv(studies.ENV_STORAGE, url)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", mlflow_server)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "pipeline.cli", "worker", LEG, str(labelled), "--params", str(params_path)]
    workers = [
        subprocess.Popen(
            [*cmd, "--wait", "300"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for _ in range(4)
    ]
    try:
        params = load_params(params_path)
        result = T.train_group(params, LEG, labelled, tmp_path / "out", tmp_path / "journal", progress=False)
        outputs = [w.communicate(timeout=300) for w in workers]
    finally:
        for w in workers:
            if w.poll() is None:
                w.kill()
    assert all(w.returncode == 0 for w in workers), [err[-2000:] for _, err in outputs]
    assert not (tmp_path / "journal" / studies.JOURNAL_FILE).exists()  # nothing went to the journal

    n = 8
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["best_on_validation"] in metrics["val"] and {"nn7", "nn13"} <= set(metrics["test"])
    storage = studies.open_storage(studies.storage_url(url), tmp_path, heartbeat=2)
    processes = set()
    for name in ("nn7", "nn13"):
        net = result.metrics["networks"][name]
        study = studies.join_study(storage, net["study"], None, wait=0)
        assert _states(study).keys() <= {"COMPLETE", "PRUNED"}  # none RUNNING, WAITING or FAILED
        trials = study.get_trials(deepcopy=False)
        assert len(trials) == n and sorted(studies.trial_index(t) for t in trials) == list(range(n))
        summaries = [out.strip().splitlines()[-1] for out, _ in outputs]  # "<group>: nn7 3 trials, ..."
        by_workers = sum(int(line.split(f" {name} ")[1].split(" ")[0]) for line in summaries)
        assert net["trials_run"] + by_workers == n and net["trials_reused"] == 0
        processes |= {t.user_attrs[studies.WORKER] for t in trials}
        # pruned as one process running the slots in order would, whichever process finished first
        pruned = {studies.trial_index(t): t.last_step if t.state.name == "PRUNED" else None for t in trials}
        gp = params.raw["train"]["defaults"]
        pruner = SlotPruner(gp["prune_startup_trials"], gp["prune_warmup_epochs"], gp["prune_margin"])
        assert pruned == _pruned_in_order(study, pruner)
    assert len(processes) >= 3, processes  # the stage's trials and at least two workers'

    client = MlflowClient(mlflow_server)
    run = client.get_run(result.mlflow_run)
    assert run.info.status == "FINISHED"
    assert {"metrics.json", "baselines.json"} <= {a.path for a in client.list_artifacts(run.info.run_id)}
    children = client.search_runs(
        [run.info.experiment_id], f"tags.mlflow.parentRunId = '{run.info.run_id}'", max_results=100
    )
    # every trial, whichever process ran it, is one child run of the stage's run, with its epochs
    logged = sorted((c.data.tags.get("network"), int(c.data.tags.get("trial"))) for c in children)
    assert logged == [(name, k + 1) for name in ("nn13", "nn7") for k in range(n)]
    assert all(c.data.metrics.get("best_val_rmse", 0) > 0 for c in children)
    for size in (7, 13):
        (version,) = client.search_model_versions(f"name = 'ftcal-{LEG}-{size}'")
        assert version.run_id == run.info.run_id
