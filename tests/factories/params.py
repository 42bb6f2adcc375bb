"""params.yaml files for the stage tests: the repository's params.yaml with small train, ingest and
evaluate sections (tiny networks, few trials, the synthetic groups)."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml

from tests.factories.labelled import LEG, PAIR

ROOT = Path(__file__).resolve().parents[2]

TRAIN_PARAMS = {
    "val_logs": 1,
    "folds": 2,
    "storage": None,
    "heartbeat": 10,
    "selection_margin": 0.1,
    "defaults": {
        "inputs": [7, 13],
        "hidden": 16,
        "activations": ["leaky_relu", "relu"],
        "normalisation": "max",
        "batch_size": 128,
        "epochs": 3,
        "lr": 0.01,
        "average_epochs": 1.0,
        "weight_decay": 0.0,
        "lambda_expected": 1.0,
        "lambda_front": 1.0,
        "lambda_rear": 1.0,
        "lambda_sum": 1.0,
        "lambda_cut": 1.0,
        "lambda_prior": 0.1,
        "lambda_push": 0.1,
        "push_force_n": 20.0,
        "push_lever_m": 0.2,
        "free_lever": True,
        "residual_slope": 0.05,
        "n_trials": 3,
        "search": {"lr": {"low": 0.001, "high": 0.03, "log": True}, "hidden": [16, 32]},
        "tpe_startup_trials": 1,
        "prune_startup_trials": 1,
        "prune_warmup_epochs": 1,
        "prune_margin": 0.1,
        "poly_orders": [1, 2],
        "ridge": 1.0e-6,
        "play_width_fractions": [0.05, 0.2],
        "arx_time_constants_s": [0.5, 5.0],
        "window_time_constants_s": [0.05, 0.5],
        "window_hidden": 8,
        "window_activations": ["relu"],
        "window_epochs": 2,
        "window_lr": 0.003,
        "window_batch_size": 128,
    },
    "groups": {LEG: {"sensor": LEG}, PAIR: {"pair": PAIR, "normalisation": "standard"}},
}


def repo_params() -> dict[str, Any]:
    """The repository's params.yaml as every stage reads it: over pipeline/defaults.yaml (a new copy)."""
    from pipeline.core.defaults import resolve

    return resolve(yaml.safe_load((ROOT / "params.yaml").read_text()))[0]


def _write(tmp_path: Path, data: dict[str, Any], sort_keys: bool = False) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=sort_keys))
    return path


def write_params(tmp_path: Path, train: dict[str, Any] | None = None, **defaults: Any) -> Path:
    """The repo's params.yaml with a small `train` section (and `defaults` overrides)."""
    data = repo_params()
    data["train"] = copy.deepcopy(train or TRAIN_PARAMS)
    data["train"]["defaults"].update(defaults)
    return _write(tmp_path, data)


def write_ingest_params(tmp_path: Path, **ingest_values: object) -> Path:
    """The repo's params.yaml with `ingest_values` in its `ingest` section."""
    data = repo_params()
    data["ingest"].update(ingest_values)
    return _write(tmp_path, data, sort_keys=True)


def write_evaluate_params(tmp_path: Path, **evaluate: Any) -> Path:
    """The repo's params.yaml with two train groups (the leg sensor, the r_foot pair), `evaluate` values in
    its `evaluate` section and a 2 s zoom."""
    data = repo_params()
    data["train"] = copy.deepcopy(data["train"])
    data["train"]["groups"] = {LEG: {"sensor": LEG}, PAIR: {"pair": PAIR}}
    data["evaluate"].update(evaluate, zoom_s=2.0)
    return _write(tmp_path, data)
