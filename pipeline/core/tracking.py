"""MLflow plumbing shared by every stage: one run per stage execution, tagged with DVC stage and git state.

By default runs go to ``sqlite:///<repo root>/mlflow.db`` whatever the working directory, so that
``mlflow ui --backend-store-uri sqlite:///mlflow.db`` run from the repo root shows them; set
``MLFLOW_TRACKING_URI`` to log elsewhere (a server, another database).
"""

from __future__ import annotations

import logging
import os
import subprocess
import warnings
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pipeline.core.config import repo_root

EXPERIMENT = "ftcal"
TRACKING_DB = "mlflow.db"
ARTIFACTS_DIR = "mlartifacts"  # beside a sqlite store (MLflow's default would be ./mlruns of the cwd)

# MLflow's limits (mlflow.utils.validation): parameter values and keys longer than these are rejected.
MAX_PARAM_VALUE_LENGTH = 6000
MAX_PARAM_KEY_LENGTH = 250
_TRUNCATION_MARK = "..."

# Loggers that print INFO lines (schema migrations, store creation) on every run.
_NOISY_LOGGERS = ("alembic", "mlflow", "sqlalchemy", "git")


def tracking_uri() -> str:
    """The MLflow tracking URI: ``$MLFLOW_TRACKING_URI`` if set, else the repo root's ``mlflow.db``."""
    env = os.environ.get("MLFLOW_TRACKING_URI", "").strip()
    if env:
        return env
    return f"sqlite:///{(repo_root() / TRACKING_DB).resolve().as_posix()}"


def flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """Flatten nested mappings to dotted keys with string values, as MLflow params.

    ``{"robot": {"gravity": 9.8, "foot_pairs": {"l_foot": {"front": "a"}}}}`` becomes
    ``{"robot.gravity": "9.8", "robot.foot_pairs.l_foot.front": "a"}``. Lists and other values are
    stringified whole; an empty mapping becomes ``"{}"``. Values longer than MLflow's limit are truncated.
    """
    out: dict[str, str] = {}
    for key, value in d.items():
        name = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, Mapping) and value:
            out.update(flatten(value, name))
        else:
            out[name] = _truncate(_to_str(value), MAX_PARAM_VALUE_LENGTH)
    return out


def _to_str(value: Any) -> str:
    if isinstance(value, Mapping):
        return "{}"
    if value is None:
        return "null"  # as in params.yaml, so a run's params read like the file
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _truncate(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[: limit - len(_TRUNCATION_MARK)] + _TRUNCATION_MARK


def _git(root: Path, *args: str) -> str | None:
    """Output of a git command in `root`, or None if git is missing or fails (e.g. no commit yet)."""
    try:
        result = subprocess.run(
            ["git", *args], cwd=root, capture_output=True, text=True, timeout=10, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return result.stdout.strip() if result.returncode == 0 else None


def git_state(root: Path | None = None) -> tuple[str, str]:
    """(commit sha or ``"unknown"``, ``"true"``/``"false"``/``"unknown"`` for uncommitted changes)."""
    root = root if root is not None else repo_root()
    commit = _git(root, "rev-parse", "--verify", "--quiet", "HEAD") or "unknown"
    status = _git(root, "status", "--porcelain")
    if status is None:
        return commit, "unknown"
    # Ignored files (stage outputs) do not show; without a commit everything is uncommitted.
    return commit, "true" if (status or commit == "unknown") else "false"


def quiet_mlflow() -> None:
    """Keep MLflow's and its database layer's INFO logs and store warnings off the terminal."""
    for name in _NOISY_LOGGERS:
        logging.getLogger(name).setLevel(logging.WARNING)
    # MLflow 3 warns that the file store is deprecated; we use sqlite, but some paths still warn.
    warnings.filterwarnings("ignore", category=FutureWarning, module=r"mlflow(\.|$)")


def _artifact_location(uri: str) -> str | None:
    """For a sqlite store, keep artifacts beside the database instead of in the cwd's ./mlruns."""
    prefix = "sqlite:///"
    if not uri.startswith(prefix) or uri.endswith(":memory:"):
        return None
    return (Path(uri[len(prefix) :]).resolve().parent / ARTIFACTS_DIR).as_uri()


@contextmanager
def stage_run(
    stage: str, params: Mapping[str, Any] | None = None, experiment: str = EXPERIMENT
) -> Iterator[Any]:
    """Run the block inside one MLflow run named after the DVC stage; yield the active run.

    Tags: ``step`` (`stage`: the step, named as its stage would be), ``dvc.stage`` (``$DVC_STAGE``, the DVC
    stage running the step, else `stage`), ``git.commit`` and ``mlflow.source.git.commit`` (sha or
    ``unknown``), ``git.dirty`` (``true``/``false``). `params` are logged flattened with dotted keys.
    If the block raises, the run ends FAILED (KILLED for Ctrl-C) and the exception propagates.
    """
    import mlflow  # deferred: importing mlflow takes seconds, and most of the CLI does not need it

    quiet_mlflow()  # after the import, which configures mlflow's logger at INFO

    uri = tracking_uri()
    mlflow.set_tracking_uri(uri)
    client = mlflow.MlflowClient(uri)
    found = client.get_experiment_by_name(experiment)
    experiment_id = (
        found.experiment_id
        if found is not None
        else client.create_experiment(experiment, artifact_location=_artifact_location(uri))
    )
    commit, dirty = git_state()
    tags = {
        "step": stage,
        # the DVC stage running this step (one stage may run several: `ftcal A + B`); the step outside DVC
        "dvc.stage": os.environ.get("DVC_STAGE") or stage,
        "git.commit": commit,
        "git.dirty": dirty,
        "mlflow.source.git.commit": commit,
    }
    run = mlflow.start_run(experiment_id=experiment_id, run_name=stage, tags=tags)
    try:
        if params:
            flat = flatten(params)
            too_long = [k for k in flat if len(k) > MAX_PARAM_KEY_LENGTH]
            if too_long:
                raise ValueError(f"MLflow param key longer than {MAX_PARAM_KEY_LENGTH} chars: {too_long[0]}")
            mlflow.log_params(flat)
        yield run
    except KeyboardInterrupt:
        mlflow.end_run(status="KILLED")
        raise
    except BaseException:
        mlflow.end_run(status="FAILED")
        raise
    else:
        mlflow.end_run(status="FINISHED")
