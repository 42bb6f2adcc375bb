"""Optuna studies shared by any number of processes: storage, slots, heartbeats, the trial loop.

A network search is one Optuna study. Where it lives:

- by default a journal file (``<studies dir>/optuna.journal``): one machine, no server;
- with ``train.storage`` in params.yaml or ``$FTCAL_OPTUNA_STORAGE`` (which wins) set to a database URL
  (``postgresql://user:password@host:5432/db``): every process on every machine that reaches the database
  with the same code, data and params joins the same study, the DVC stage and any number of
  ``ftcal worker GROUP`` processes.

Exactly n_trials trials: the stage that creates a study enqueues n_trials *slots* (WAITING trials; the first
holds the group's own params, the others none, so the sampler draws them). A process only ever runs a slot
it claimed with the storage's atomic WAITING -> RUNNING update, never a trial of its own: however many
processes race, the study never holds more than n_trials trials that count. A rerun with a larger n_trials
enqueues the missing slots.

A process killed mid-trial: on a database the running trial records a heartbeat every ``train.heartbeat``
seconds; a trial silent for twice that long is marked FAIL by the next process that looks and re-enqueued
once more as a slot with the same params (`optuna.storages.RetryHeartbeatStaleTrialCallback`), so the kill
costs one trial, not the study. A journal file has no heartbeat: there only one process runs a study, and
the RUNNING trials an interrupted run left are failed and retried the same way when the stage reopens it.
A trial that raises (Ctrl-C, a bug) is failed and retried the same way, and the exception goes on.

A trial's seed is that of its slot's original number (`trial_index`), so a retried trial repeats what
the killed one would have done, and one process in a fresh study runs trial k with seed k as before.
The weights of each complete trial are stored in the study itself (`save_trial_model`), so the stage can
load the best network whichever machine trained it; so is every finished trial's record (its values, epochs
and time: `record_trial`), from which the stage logs each trial to MLflow once, wherever it ran.
"""

from __future__ import annotations

import base64
import io
import json
import os
import socket
import threading
import time
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from pipeline.calib.params import check_storage
from pipeline.core.errors import FtcalError

ENV_STORAGE = "FTCAL_OPTUNA_STORAGE"
JOURNAL_FILE = "optuna.journal"
MAX_RETRY = 3  # retries of one slot killed mid-trial before it is given up
SLOT = "ftcal.slot"  # user attribute of every enqueued slot (inherited by its retries)
WORKER = "ftcal.worker"  # user attribute of a trial: host:pid of the process that ran it
_WEIGHTS, _CONFIG = "ftcal.weights", "ftcal.model"  # trial user attributes of a complete trial's network
_RECORD = "ftcal.record"  # trial user attribute of every finished trial: values, epochs, seconds
_CONNECT_ATTEMPTS = 5  # tries to open a database storage, 0.5 s, 1 s, ... apart


class StudyError(FtcalError):
    """A shared study cannot go on (database unreachable, study absent, no slot left)."""


def storage_url(configured: str | None) -> str | None:
    """The RDB URL of the studies: ``$FTCAL_OPTUNA_STORAGE``, else `configured` (``train.storage``), else
    None (a journal file). ``postgresql://`` is mapped to the psycopg (3) driver.

    Raises:
        ConfigError: the URL is not a postgresql, sqlite or mysql SQLAlchemy URL.
    """
    env = os.environ.get(ENV_STORAGE, "").strip()
    url = env or (configured.strip() if isinstance(configured, str) else configured)
    if not url:
        return None
    where = ENV_STORAGE if env else "train.storage"
    check_storage(url, where)
    if url.startswith("postgresql://") or url.startswith("postgres://"):
        url = "postgresql+psycopg://" + url.split("://", 1)[1]
    return url


def redact(url: str) -> str:
    """`url` without its password, for messages."""
    head, sep, rest = url.partition("://")
    if "@" not in rest:
        return url
    cred, host = rest.rsplit("@", 1)
    return f"{head}{sep}{cred.split(':', 1)[0]}:***@{host}"


def open_storage(url: str | None, studies_dir: Path, heartbeat: int) -> Any:
    """The storage of a group's studies: the journal under `studies_dir`, or the database at `url` with a
    heartbeat every `heartbeat` s (stale after 2 * heartbeat s, then retried up to MAX_RETRY times)."""
    import optuna
    from optuna.storages import JournalStorage, RDBStorage, RetryHeartbeatStaleTrialCallback
    from optuna.storages.journal import JournalFileBackend

    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    if url is None:
        studies_dir.mkdir(parents=True, exist_ok=True)
        return JournalStorage(JournalFileBackend(str(studies_dir / JOURNAL_FILE)))
    # Processes starting together on an empty database race to create Optuna's tables: the losers
    # fail on a duplicate key and find the tables there on a retry (as they find a server still starting).
    for attempt in range(_CONNECT_ATTEMPTS):
        try:
            return RDBStorage(
                url,
                engine_kwargs={"pool_pre_ping": True, "pool_size": 1, "max_overflow": 2},
                heartbeat_interval=heartbeat,
                grace_period=2 * heartbeat,
                heartbeat_stale_trial_callback=RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY),
            )
        except Exception as exc:  # sqlalchemy/psycopg errors: unreachable server, bad credentials, a race
            if attempt + 1 == _CONNECT_ATTEMPTS:
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                raise StudyError(f"Optuna storage {redact(url)}: cannot connect: {first}") from None
            time.sleep(0.5 * (attempt + 1))
    raise AssertionError("unreachable")


def _is_shared(storage: Any) -> bool:
    from optuna.storages._heartbeat import is_heartbeat_enabled

    return is_heartbeat_enabled(storage)


def _release_stale(study: Any) -> None:
    """Fail (and re-enqueue) trials no process runs any more: stale heartbeats; on a journal, every
    RUNNING trial (only one process runs a journal study, and it has none running when it calls this)."""
    import optuna
    from optuna.trial import TrialState

    storage = study._storage
    if _is_shared(storage):
        optuna.storages.fail_stale_trials(study)
        return
    for t in study.get_trials(deepcopy=True, states=(TrialState.RUNNING,)):
        storage.set_trial_state_values(t._trial_id, TrialState.FAIL)
        _retry(study, storage.get_trial(t._trial_id))


def _retry(study: Any, failed: Any) -> None:
    """Re-enqueue a failed slot with its params (at most MAX_RETRY times per original slot)."""
    import optuna

    optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY)(study, failed)


def open_study(storage: Any, name: str, pruner: Any, n_trials: int, first: Mapping[str, Any]) -> Any:
    """Create or load study `name` and enqueue the slots it lacks to reach `n_trials` (the stage's side).

    `first` is the params of the first slot of a new study (the group's own values).
    """
    import optuna
    from optuna.trial import TrialState

    try:
        study = optuna.create_study(study_name=name, storage=storage, direction="minimize", pruner=pruner)
        study.enqueue_trial(dict(first), user_attrs={SLOT: True})
    except optuna.exceptions.DuplicatedStudyError:
        study = optuna.load_study(study_name=name, storage=storage, pruner=pruner)
    _release_stale(study)
    live = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING, TrialState.WAITING)
    for _ in range(n_trials - len(study.get_trials(deepcopy=False, states=live))):
        study.enqueue_trial({}, user_attrs={SLOT: True})
    return study


def join_study(storage: Any, name: str, pruner: Any, wait: float, poll: float = 1.0) -> Any:
    """Load study `name`, waiting up to `wait` s for a stage to create it (a worker's side)."""
    import optuna

    deadline = time.monotonic() + wait
    while True:
        try:
            return optuna.load_study(study_name=name, storage=storage, pruner=pruner)
        except KeyError:
            if time.monotonic() > deadline:
                raise StudyError(
                    f"no Optuna study {name} appeared in {wait:.0f} s: run the stage (dvc repro) with the "
                    "same storage, params and data"
                ) from None
            time.sleep(poll)


def finished_trials(study: Any) -> list[Any]:
    """The complete and pruned trials of `study`, by number."""
    from optuna.trial import TrialState

    done = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.PRUNED))
    return sorted(done, key=lambda t: t.number)


def trial_index(trial: Any) -> int:
    """The number of the slot a trial runs: its own, or for a retry that of the trial it repeats."""
    attrs = getattr(trial, "system_attrs", None)  # a FrozenTrial's; a live Trial's are in the storage
    if attrs is None:
        attrs = trial.storage.get_trial_system_attrs(trial._trial_id)
    return int(attrs.get("failed_trial", trial.number))


def _claim(study: Any) -> Any | None:
    """Atomically take the WAITING slot of lowest index (a retry before later slots: as one process
    would have run them), RUNNING from now on; or None."""
    import optuna
    from optuna.trial import TrialState

    storage = study._storage
    waiting = study.get_trials(deepcopy=False, states=(TrialState.WAITING,))
    for t in sorted(waiting, key=lambda t: (trial_index(t), t.number)):
        try:
            if storage.set_trial_state_values(t._trial_id, state=TrialState.RUNNING):
                return storage.get_trial(t._trial_id)
        except optuna.exceptions.UpdateFinishedTrialError:
            continue
    return None


class _Heartbeat:
    """Record a trial's heartbeat every `interval` s in a daemon thread while the block runs."""

    def __init__(self, storage: Any, trial_id: int, interval: int | None) -> None:
        self.storage, self.trial_id, self.interval = storage, trial_id, interval
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _beat(self) -> None:
        while not self._stop.wait(self.interval):
            self.storage.record_heartbeat(self.trial_id)

    def __enter__(self) -> _Heartbeat:
        if self.interval is not None:
            self.storage.record_heartbeat(self.trial_id)
            self._thread = threading.Thread(target=self._beat, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


def _run_one(study: Any, frozen: Any, objective: Callable[[Any], float], sampler: Any) -> None:
    """Run one claimed slot with `sampler`; record COMPLETE, PRUNED or FAIL (then retry and re-raise)."""
    import optuna
    from optuna.trial import TrialState

    storage = study._storage
    study.sampler = sampler
    trial = optuna.Trial(study, frozen._trial_id)
    trial.set_user_attr(WORKER, f"{socket.gethostname()}:{os.getpid()}")
    interval = storage.get_heartbeat_interval() if _is_shared(storage) else None
    with _Heartbeat(storage, frozen._trial_id, interval):
        try:
            value = objective(trial)
        except optuna.TrialPruned:
            study.tell(trial, state=TrialState.PRUNED)
            return
        except BaseException:  # interrupted or a bug: the slot goes back to the queue, then stop
            study.tell(trial, state=TrialState.FAIL)
            _retry(study, storage.get_trial(frozen._trial_id))
            raise
    study.tell(trial, value)


def run_trials(
    study: Any,
    objective: Callable[[Any], float],
    n_trials: int,
    sampler_for: Callable[[int], Any],
    poll: float = 0.5,
    on_trial: Callable[[int], None] | None = None,
) -> int:
    """Run slots of `study` until it holds `n_trials` complete or pruned trials; return how many ran here.

    `sampler_for(index)` gives the sampler of slot `index` (see `trial_index`). Waits (polling every
    `poll` s) while other processes run the last slots, and takes over a slot whose process died.
    `on_trial(finished)` is called after each trial this process ran.

    Raises:
        StudyError: no slot is waiting or running but the study is short of `n_trials` (slots given up).
    """
    from optuna.trial import TrialState

    ran = 0
    while True:
        if _is_shared(study._storage):
            _release_stale(study)
        done = len(finished_trials(study))
        if done >= n_trials:
            return ran
        frozen = _claim(study)
        if frozen is None:
            pending = study.get_trials(deepcopy=False, states=(TrialState.RUNNING, TrialState.WAITING))
            if not pending and len(finished_trials(study)) < n_trials:  # (the last may finish meanwhile)
                raise StudyError(
                    f"Optuna study {study.study_name} has {done} of {n_trials} trials and no slot left "
                    f"(slots failed more than {MAX_RETRY} times): rerun the stage to enqueue new ones"
                )
            time.sleep(poll)
            continue
        _run_one(study, frozen, objective, sampler_for(trial_index(frozen)))
        ran += 1
        if on_trial is not None:
            on_trial(len(finished_trials(study)))


def run_worker(
    storage: Any,
    name: str,
    pruner: Any,
    objective: Callable[[Any], float],
    n_trials: int,
    sampler_for: Callable[[int], Any],
    wait: float,
) -> int:
    """A worker's loop: join study `name` (waiting up to `wait` s for it), run slots until it holds
    `n_trials` finished trials counted over every process; return how many this process ran."""
    study = join_study(storage, name, pruner, wait)
    return run_trials(study, objective, n_trials, sampler_for)


# --- a trial's record and network, kept in the study ----------------------------------------------


def record_trial(
    trial: Any, values: Mapping[str, Any], history: list[dict[str, float]], seconds: float
) -> None:
    """Store what a finished (complete or pruned) trial did: its values, per-epoch history, wall time (s)."""
    record = {"values": dict(values), "history": history, "seconds": seconds}
    trial.set_user_attr(_RECORD, json.dumps(record, sort_keys=True))


def trial_record(trial: Any) -> dict[str, Any]:
    """The record `record_trial` stored for a finished trial (FrozenTrial); empty values if none."""
    raw = trial.user_attrs.get(_RECORD)
    return json.loads(raw) if raw else {"values": {}, "history": [], "seconds": float("nan")}


def save_trial_model(trial: Any, model: Any, info: Mapping[str, Any]) -> None:
    """Store a trial's network (architecture, `info`, weights as base64 of a tensors-only torch.save)."""
    from dataclasses import asdict

    import torch

    buffer = io.BytesIO()
    torch.save(model.state_dict(), buffer)
    config = {"net": asdict(model.config), "n_sensors": model.n_sensors, **dict(info)}
    trial.set_user_attr(_CONFIG, json.dumps(config, sort_keys=True))
    trial.set_user_attr(_WEIGHTS, base64.b64encode(buffer.getvalue()).decode("ascii"))


def load_trial_model(trial: Any) -> tuple[Any, dict[str, Any]]:
    """The network stored by `save_trial_model` (eval mode) and its config; StudyError if absent."""
    import torch

    from pipeline.calib.models import GroupNet, NetConfig

    try:
        config = json.loads(trial.user_attrs[_CONFIG])
        net = config["net"]
        model = GroupNet(
            NetConfig(n_inputs=net["n_inputs"], hidden=net["hidden"], activations=tuple(net["activations"])),
            n_sensors=int(config["n_sensors"]),
        )
        state = torch.load(
            io.BytesIO(base64.b64decode(trial.user_attrs[_WEIGHTS])), map_location="cpu", weights_only=True
        )
        model.load_state_dict(state)
    except (KeyError, ValueError, TypeError, RuntimeError) as exc:
        raise StudyError(f"trial {trial.number} of the Optuna study holds no usable network: {exc}") from None
    return model.eval(), config
