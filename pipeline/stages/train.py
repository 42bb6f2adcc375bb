"""Stage `train@<group>`: baselines and neural networks for one sensor group (thesis chapter 5).

``ftcal train GROUP LABELLED_DIR OUT_DIR`` reads the labelled tables (`pipeline.logs.schema`, "Labelled
table"), splits them by whole logs, fits the baselines, trains the 7- and 13-input networks with an
Optuna search, scores every model and writes ``OUT_DIR``:

- ``metrics.json``: per model (raw, affine, poly1-4, nn7, nn13), validation and test errors against the
  labels (MSE/MAE/RMSE global, force, torque, per axis; per sensor and, for a foot, of the sum in the sole
  frame), and ``best_on_validation``: the model with the lowest validation error, the one to deploy.
- ``nn7.json`` + ``nn7.pt``, ``nn13.json`` + ``nn13.pt``: the best networks (`calib.models.load_model`
  rebuilds them from the JSON and a weights-only state dict; normalisation constants are in the weights).
- ``baselines.json``: the fitted affine and polynomial coefficients.
- ``predictions.parquet``: the test samples, ``log``, ``stamp_ns``, ``time_s``, the group's labels and
  switches, and ``pred.<model>.<sensor or pair>.<axis>`` for every model (for `evaluate`).

Split: logs whose ``ftcal.experiment`` metadata says ``role: test`` are the test set; ``train.val_logs``
training logs are held out as validation, whole logs, chosen by a seeded draw that takes at most one log
per experiment kind (type, foot, part) and never a kind's last training log (the same for every group).
Models are fitted on the remaining training logs only; validation chooses epochs, Optuna trials and the
model to deploy.

Samples: a sample is used when every input stream of the group's sensors is ok (wrench, temperature, IMU:
the same samples for every model); training keeps those with at least one switch set (the others
contribute nothing to the loss). Errors are computed where the label is exact: a sensor's where its switch
is 1, a foot's sum where ``sw.<pair>`` is 1. ``rmse_labelled`` pools the squared errors of all of a group's
exact labels (sensor parts and sum) and decides validation; ``rmse`` is the headline (the sensor's, or the
foot's sum, as the thesis reports).

Optuna: one study per network size, stored in a journal file under ``--studies`` and named after a hash
of everything that determines its result (group params except n_trials, seed, threads, validation logs,
data, this code): a rerun after an interruption resumes it, a rerun with more trials extends it. Trial k
is seeded from (seed, group, inputs, k) and its sampler is a TPE sampler seeded the same way, so the
search is reproducible whether or not it was resumed. The first trial is the group's own params (the
thesis's defaults); a MedianPruner stops trials whose validation error lags. Every trial is a nested
MLflow run of the stage's run; the best networks are logged with `mlflow.pytorch.log_model` in MLflow's
``pt2`` format (`torch.export`, loadable without unpickling) and registered as ``ftcal-<group>-<7|13>``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import time
import warnings
import zlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from pipeline.calib.models import (
    ACTIVATIONS,
    INPUT_SIZES,
    NORMALISATIONS,
    WRENCH,
    GroupNet,
    LinearBaseline,
    NetConfig,
    fit_linear_baseline,
    normalisation_constants,
    save_model,
    switched_loss,
    wrench_errors,
)
from pipeline.core.config import Params, load_params, repo_root, stage_section
from pipeline.core.errors import ConfigError, DataError
from pipeline.logs import schema as S

STAGE = "train"
STUDIES_DIR = ".optuna"  # default --studies parent, at the repo root (git-ignored)
PRED, LOG, prediction_cols = S.PRED, S.LOG, S.prediction_cols  # the predictions table's columns
RAW, AFFINE = "raw", "affine"
ROLE_TRAIN, ROLE_TEST = "train", "test"
SPLITS = ("train", "val", "test")
_PACKAGE = Path(__file__).resolve().parents[1]
# their bytes are part of a study's identity
_SOURCE_FILES = ("stages/train.py", "calib/models.py")


def nn_name(n_inputs: int) -> str:
    return f"nn{n_inputs}"


def poly_name(order: int) -> str:
    return f"poly{order}"


# --- params --------------------------------------------------------------------------------------

# Keys an Optuna search may vary (their type), and which group params are integers.
SEARCHABLE = {
    "lr": float,
    "weight_decay": float,
    "hidden": int,
    "batch_size": int,
    "epochs": int,
    "normalisation": str,
    "lambda_front": float,
    "lambda_rear": float,
    "lambda_sum": float,
}


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


@dataclass(frozen=True)
class GroupParams:
    """One group's training params: `train.defaults` updated by `train.groups.<name>` (see params.yaml)."""

    name: str  # group name (the key under train.groups)
    sensor: str | None  # a single FT sensor ...
    pair: str | None  # ... or a foot pair of robot.foot_pairs
    inputs: tuple[int, ...]  # network sizes trained: 7 and/or 13
    hidden: int  # neurons per hidden layer
    activations: tuple[str, ...]  # one per hidden layer
    normalisation: str  # max | standard
    batch_size: int  # samples per Adam step
    epochs: int  # passes over the training samples
    lr: float  # Adam learning rate
    weight_decay: float  # Adam weight decay
    lambda_expected: float  # single sensor: lambda of eq. 5.4
    lambda_front: float  # foot: lambdas of eqs. 5.6-5.7
    lambda_rear: float
    lambda_sum: float
    n_trials: int  # Optuna trials per network (the first: these params)
    search: Mapping[str, Any]  # key -> [choices] or {low, high, log}
    tpe_startup_trials: int  # random trials before TPE
    prune_startup_trials: int  # MedianPruner: complete trials before pruning
    prune_warmup_epochs: int  # MedianPruner: epochs never pruned
    poly_orders: tuple[int, ...]  # polynomial baselines
    ridge: float  # ridge penalty per sample (standardised features)

    def __post_init__(self) -> None:
        key = f"train.groups.{self.name}"
        if (self.sensor is None) == (self.pair is None):
            raise ConfigError(f"{key} must have exactly one of 'sensor' or 'pair'")
        for attr in ("sensor", "pair"):
            value = getattr(self, attr)
            if value is not None and (not isinstance(value, str) or not value.strip()):
                raise ConfigError(f"{key}.{attr} must be a non-empty string, got {value!r}")
        inputs = self.inputs
        if not isinstance(inputs, list | tuple) or not inputs or any(i not in INPUT_SIZES for i in inputs):
            raise ConfigError(f"{key}.inputs must be a non-empty list of {INPUT_SIZES}, got {inputs!r}")
        object.__setattr__(self, "inputs", tuple(sorted(set(inputs))))
        acts = self.activations
        if not isinstance(acts, list | tuple) or not acts or any(a not in ACTIVATIONS for a in acts):
            raise ConfigError(
                f"{key}.activations must be a non-empty list of {sorted(ACTIVATIONS)}, got {acts!r}"
            )
        object.__setattr__(self, "activations", tuple(acts))
        for attr, low in (
            ("hidden", 1),
            ("batch_size", 1),
            ("epochs", 1),
            ("n_trials", 1),
            ("tpe_startup_trials", 0),
            ("prune_startup_trials", 0),
            ("prune_warmup_epochs", 0),
        ):
            value = getattr(self, attr)
            if not _is_int(value) or value < low:
                raise ConfigError(f"{key}.{attr} must be an integer >= {low}, got {value!r}")
        if self.normalisation not in NORMALISATIONS:
            raise ConfigError(
                f"{key}.normalisation must be one of {NORMALISATIONS}, got {self.normalisation!r}"
            )
        if not _is_number(self.lr) or self.lr <= 0:
            raise ConfigError(f"{key}.lr must be a positive number, got {self.lr!r}")
        for attr in ("weight_decay", "lambda_expected", "lambda_front", "lambda_rear", "lambda_sum", "ridge"):
            value = getattr(self, attr)
            if not _is_number(value) or value < 0:
                raise ConfigError(f"{key}.{attr} must be a number >= 0, got {value!r}")
            object.__setattr__(self, attr, float(value))
        object.__setattr__(self, "lr", float(self.lr))
        orders = self.poly_orders
        if not isinstance(orders, list | tuple) or any(not _is_int(o) or not 1 <= o <= 4 for o in orders):
            raise ConfigError(f"{key}.poly_orders must be a list of integers in [1, 4], got {orders!r}")
        object.__setattr__(self, "poly_orders", tuple(sorted(set(orders))))
        self._check_search(key)

    def _check_search(self, key: str) -> None:
        if not isinstance(self.search, Mapping):
            raise ConfigError(f"{key}.search must be a mapping, got {self.search!r}")
        for name, spec in self.search.items():
            where = f"{key}.search.{name}"
            if name not in SEARCHABLE:
                raise ConfigError(f"unknown key {where} (searchable: {', '.join(sorted(SEARCHABLE))})")
            default = getattr(self, name)
            kind = SEARCHABLE[name]
            if isinstance(spec, list):
                if not spec or len(set(map(str, spec))) != len(spec):
                    raise ConfigError(f"{where} must be a non-empty list of distinct choices, got {spec!r}")
                for choice in spec:  # each choice must be a valid value of the param
                    try:
                        replace(self, **{name: choice}, search={})
                    except ConfigError:
                        raise ConfigError(f"{where}: invalid choice {choice!r}") from None
                if default not in spec:
                    raise ConfigError(f"{where} must include the group's own value {default!r}, got {spec!r}")
            elif isinstance(spec, Mapping):
                if set(spec) - {"low", "high", "log"} or not {"low", "high"} <= set(spec) or kind is str:
                    raise ConfigError(
                        f"{where} must be a list of choices or {{low, high, log}}, got {spec!r}"
                    )
                low, high = spec["low"], spec["high"]
                ok = _is_int if kind is int else _is_number
                if not (ok(low) and ok(high)) or not low < high or (spec.get("log") and low <= 0):
                    raise ConfigError(f"{where} needs low < high ({kind.__name__}, > 0 if log), got {spec!r}")
                if not low <= default <= high:
                    raise ConfigError(f"{where} must contain the group's own value {default!r}, got {spec!r}")
            else:
                raise ConfigError(f"{where} must be a list of choices or {{low, high, log}}, got {spec!r}")

    @property
    def label(self) -> str:
        """The sensor or pair name the group trains."""
        return self.sensor if self.sensor is not None else str(self.pair)

    def hyperparameters(self) -> dict[str, Any]:
        """The searchable values of these params."""
        return {k: getattr(self, k) for k in SEARCHABLE}


_GROUP_KEYS = {f.name for f in fields(GroupParams)} - {"name"}
_DEFAULT_KEYS = _GROUP_KEYS - {"sensor", "pair"}


@dataclass(frozen=True)
class TrainParams:
    """Section `train` of params.yaml (see the comments there)."""

    val_logs: int  # training logs held out as validation
    threads: int  # torch CPU threads
    defaults: Mapping[str, Any]  # every group's params ...
    groups: Mapping[str, Any]  # ... updated per group: name -> {sensor | pair, overrides}

    def __post_init__(self) -> None:
        if not _is_int(self.val_logs) or self.val_logs < 1:
            raise ConfigError(f"train.val_logs must be an integer >= 1, got {self.val_logs!r}")
        if not _is_int(self.threads) or self.threads < 1:
            raise ConfigError(f"train.threads must be an integer >= 1, got {self.threads!r}")
        if not isinstance(self.defaults, Mapping):
            raise ConfigError(f"train.defaults must be a mapping, got {self.defaults!r}")
        unknown = sorted(set(self.defaults) - _DEFAULT_KEYS)
        if unknown:
            raise ConfigError(
                f"unknown key train.defaults.{unknown[0]} (allowed: {', '.join(sorted(_DEFAULT_KEYS))})"
            )
        missing = sorted(_DEFAULT_KEYS - set(self.defaults))
        if missing:
            raise ConfigError(f"missing key train.defaults.{missing[0]}")
        if not isinstance(self.groups, Mapping) or not self.groups:
            raise ConfigError(f"train.groups must be a non-empty mapping, got {self.groups!r}")
        for name in self.groups:
            self.group(name)  # validate every group now

    def group(self, name: str) -> GroupParams:
        """The resolved params of group `name` (ConfigError if there is no such group)."""
        if name not in self.groups:
            raise ConfigError(f"train.groups has no group {name!r} (groups: {', '.join(self.groups)})")
        own = self.groups[name]
        if not isinstance(own, Mapping):
            raise ConfigError(f"train.groups.{name} must be a mapping, got {own!r}")
        unknown = sorted(set(own) - _GROUP_KEYS)
        if unknown:
            raise ConfigError(
                f"unknown key train.groups.{name}.{unknown[0]} (allowed: {', '.join(sorted(_GROUP_KEYS))})"
            )
        merged = {"sensor": None, "pair": None, **self.defaults, **own}
        return GroupParams(name=name, **merged)


# --- data ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Group:
    """What a group trains: its sensors (1, or a foot's front and rear) and, for a foot, the transforms."""

    name: str
    sensors: tuple[str, ...]
    pair: str | None = None
    transforms: np.ndarray | None = None  # (S, 6, 6) sole_X_sensor, row-major, force first

    @property
    def headline(self) -> str:
        """The name whose errors are the group's headline: the sensor, or the foot's sum."""
        return self.pair if self.pair is not None else self.sensors[0]


def input_cols(sensor: str, n_inputs: int = 13) -> list[str]:
    """Input columns of one sensor's network, in the order of `pipeline.calib.models`."""
    cols = [*S.wrench_cols(S.FT, sensor), S.temperature_col(sensor)]
    if n_inputs == 13:
        cols += S.vector_cols(S.ACC, sensor) + S.vector_cols(S.GYR, sensor)
    return cols


def _ok_cols(sensor: str) -> list[str]:
    return [S.ok_col(stream, sensor) for stream in (S.WRENCH_STREAM, S.TEMPERATURE_STREAM, S.IMU_STREAM)]


@dataclass
class GroupData:
    """Samples of a group whose inputs are all ok: arrays over N samples and S sensors.

    x (N, S, 13) raw inputs; labels (N, S, 6) N/Nm, NaN where the switch is 0; switches (N, S) bool;
    sum_label (N, 6) and sum_switch (N,) bool (``sw.<pair>``) for a foot, else None; log (N,) index into
    the log names; stamp (N,) ns; time (N,) s.
    """

    log: np.ndarray
    stamp: np.ndarray
    time: np.ndarray
    x: np.ndarray
    labels: np.ndarray
    switches: np.ndarray
    sum_label: np.ndarray | None = None
    sum_switch: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.log)

    def subset(self, mask: np.ndarray) -> GroupData:
        return GroupData(
            **{
                f.name: (None if getattr(self, f.name) is None else getattr(self, f.name)[mask])
                for f in fields(self)
            }
        )

    @property
    def alpha_sum(self) -> np.ndarray | None:
        """Switch of the sum term, eq. 5.12: sw_pair (1 - prod_s sw_s)."""
        if self.sum_switch is None:
            return None
        return self.sum_switch & ~self.switches.all(axis=1)

    def labelled(self) -> np.ndarray:
        """(N,) bool: samples with at least one term in the loss."""
        mask = self.switches.any(axis=1)
        return mask | self.alpha_sum if self.sum_switch is not None else mask


@dataclass(frozen=True)
class LogInfo:
    name: str  # the table's file name without .parquet
    path: Path
    role: str  # train | test
    kind: str  # experiment type[/foot[/part]], e.g. half_foot/l_foot/front


def find_logs(in_dir: Path) -> list[LogInfo]:
    """The labelled tables of `in_dir` with their role and experiment type, sorted by name."""
    if not in_dir.is_dir():
        raise DataError(f"{in_dir}: labelled directory not found")
    paths = sorted(in_dir.glob(f"*{S.PARQUET_SUFFIX}"))
    if not paths:
        raise DataError(f"{in_dir}: no labelled *.parquet tables")
    logs = []
    for path in paths:
        try:
            schema = pq.read_schema(path)
        except (OSError, pa.ArrowException) as exc:
            raise DataError(f"{path}: cannot read Parquet table: {exc}") from None
        experiment = S.read_metadata(schema, S.META_EXPERIMENT) or {}
        role = str(experiment.get("role", "")).strip()
        if role not in (ROLE_TRAIN, ROLE_TEST):
            raise DataError(
                f"{path}: experiment metadata role must be {ROLE_TRAIN!r} or {ROLE_TEST!r}, got {role!r}"
            )
        # The experiment's kind: its type refined by the supporting foot and part where the metadata has
        # them (balancing on the left foot covers other loads than on the right one).
        kind = "/".join(
            str(experiment[k]) for k in ("type", "foot", "part") if str(experiment.get(k, "")).strip()
        )
        logs.append(LogInfo(path.name[: -len(S.PARQUET_SUFFIX)], path, role, kind))
    return logs


def resolve_group(gp: GroupParams, params: Params, logs: Sequence[LogInfo]) -> Group:
    """The sensors (and transforms) of a group, checked against robot.foot_pairs and the tables."""
    first = pq.read_schema(logs[0].path)
    names = set(first.names)
    key = f"train.groups.{gp.name}"
    if gp.sensor is not None:
        if S.wrench_cols(S.FT, gp.sensor)[0] not in names:
            have = ", ".join(S.sensors_of(first.names)) or "none"
            raise ConfigError(
                f"{key}.sensor: {gp.sensor!r} is not an FT sensor of the labelled tables (have: {have})"
            )
        return Group(gp.name, (gp.sensor,))
    pairs = {p.name: p for p in params.robot.foot_pairs}
    if gp.pair not in pairs:
        raise ConfigError(
            f"{key}.pair: {gp.pair!r} is not in robot.foot_pairs (have: {', '.join(pairs) or 'none'})"
        )
    pair = pairs[gp.pair]
    transforms = None
    for log in logs:
        meta = S.read_metadata(pq.read_schema(log.path), S.META_LABEL) or {}
        entry = (meta.get("pairs") or {}).get(pair.name)
        try:
            t = np.array([entry["sole_X_front"], entry["sole_X_rear"]], dtype=np.float64).reshape(2, 6, 6)
        except (TypeError, KeyError, ValueError):
            raise DataError(
                f"{log.path}: metadata ftcal.label has no 6x6 pairs.{pair.name}.sole_X_front/rear"
            ) from None
        if transforms is not None and not np.allclose(t, transforms, rtol=1e-9, atol=1e-12):
            raise DataError(f"{log.path}: pairs.{pair.name} transforms differ from {logs[0].name}'s")
        transforms = t
    return Group(gp.name, pair.sensors, pair.name, transforms)


def _read_log(log: LogInfo, group: Group, index: int) -> GroupData:
    wanted = [S.STAMP, S.TIME]
    for sensor in group.sensors:
        wanted += input_cols(sensor) + _ok_cols(sensor) + S.wrench_cols(S.EXPECTED, sensor)
        wanted.append(S.switch_col(sensor))
    if group.pair is not None:
        wanted += S.wrench_cols(S.EXPECTED, group.pair) + [S.switch_col(group.pair)]
    try:
        table = pq.read_table(log.path, columns=wanted)
    except (OSError, pa.ArrowException) as exc:
        names = set(pq.read_schema(log.path).names)
        missing = [c for c in wanted if c not in names]
        detail = f"missing column {missing[0]}" if missing else str(exc)
        raise DataError(f"{log.path}: not a labelled table for {group.name}: {detail}") from None

    def col(name: str) -> np.ndarray:
        return table.column(name).to_numpy(zero_copy_only=False)

    def block(names: Sequence[str]) -> np.ndarray:
        return (
            np.column_stack([col(c).astype(np.float64) for c in names])
            if table.num_rows
            else np.empty((0, len(names)))
        )

    n = table.num_rows
    ok = np.ones(n, dtype=bool)
    x, labels, switches = [], [], []
    for sensor in group.sensors:
        for c in _ok_cols(sensor):
            ok &= col(c).astype(bool)
        x.append(block(input_cols(sensor)))
        labels.append(block(S.wrench_cols(S.EXPECTED, sensor)))
        switches.append(col(S.switch_col(sensor)).astype(bool))
    data = GroupData(
        log=np.full(n, index, dtype=np.int64),
        stamp=col(S.STAMP).astype(np.int64),
        time=col(S.TIME).astype(np.float64),
        x=np.stack(x, axis=1),
        labels=np.stack(labels, axis=1),
        switches=np.stack(switches, axis=1),
    )
    if group.pair is not None:
        data.sum_label = block(S.wrench_cols(S.EXPECTED, group.pair))
        data.sum_switch = col(S.switch_col(group.pair)).astype(bool)
    ok &= np.isfinite(data.x).all(axis=(1, 2))
    data = data.subset(ok)
    for s, sensor in enumerate(group.sensors):
        if not np.isfinite(data.labels[data.switches[:, s], s]).all():
            raise DataError(
                f"{log.path}: {S.EXPECTED}.{sensor} is not finite where {S.switch_col(sensor)} is 1"
            )
    if data.sum_switch is not None and not np.isfinite(data.sum_label[data.sum_switch]).all():
        raise DataError(
            f"{log.path}: {S.EXPECTED}.{group.pair} is not finite where {S.switch_col(group.pair)} is 1"
        )
    return data


def concat(parts: Sequence[GroupData]) -> GroupData:
    first = parts[0]
    return GroupData(
        **{
            f.name: (
                None
                if getattr(first, f.name) is None
                else np.concatenate([getattr(p, f.name) for p in parts])
            )
            for f in fields(GroupData)
        }
    )


def derive_seed(seed: int, *parts: str | int) -> int:
    """A 32-bit seed from the master seed and names/numbers (stable across runs and platforms)."""
    words = [seed] + [zlib.crc32(p.encode()) if isinstance(p, str) else int(p) for p in parts]
    return int(np.random.SeedSequence(words).generate_state(1)[0])


def split_logs(logs: Sequence[LogInfo], val_logs: int, seed: int) -> dict[str, list[str]]:
    """Whole-log split: test = role test; validation = `val_logs` training logs; train = the rest.

    Validation takes at most one log per experiment kind (type, supporting foot and part), never a
    kind's only training log, drawn with a generator seeded from `seed` (kinds in a seeded order, then a
    seeded log of each): every kind of experiment stays in the training set.

    Raises:
        DataError: no training or no test logs, or too few training logs for a validation set.
    """
    train = [log for log in logs if log.role == ROLE_TRAIN]
    test = [log.name for log in logs if log.role == ROLE_TEST]
    if not train:
        raise DataError("no training logs (role 'train' in the experiment metadata)")
    if not test:
        raise DataError("no test logs (role 'test' in the experiment metadata)")
    rng = np.random.default_rng(derive_seed(seed, "validation"))
    by_kind: dict[str, list[str]] = {}
    for log in train:
        by_kind.setdefault(log.kind, []).append(log.name)
    candidates = sorted(k for k, names in by_kind.items() if len(names) >= 2)
    order = [candidates[i] for i in rng.permutation(len(candidates))]
    val = [sorted(by_kind[k])[int(rng.integers(len(by_kind[k])))] for k in order[:val_logs]]
    if not val:
        raise DataError(
            f"cannot hold out a validation log: no experiment kind has 2 or more training logs "
            f"(training logs: {', '.join(log.name for log in train)})"
        )
    return {
        "train": sorted(n.name for n in train if n.name not in val),
        "val": sorted(val),
        "test": sorted(test),
    }


def load_group_data(group: Group, logs: Sequence[LogInfo]) -> GroupData:
    return concat([_read_log(log, group, i) for i, log in enumerate(logs)])


# --- errors --------------------------------------------------------------------------------------


def group_errors(group: Group, data: GroupData, pred: np.ndarray) -> dict[str, Any]:
    """Errors of predictions (N, S, 6) against the exact labels of `data` (see the module docstring)."""
    out: dict[str, Any] = {}
    squares = []
    for s, sensor in enumerate(group.sensors):
        m = data.switches[:, s]
        out[sensor] = wrench_errors(pred[m, s], data.labels[m, s])
        squares.append(((pred[m, s] - data.labels[m, s]) ** 2).ravel())
    if group.pair is not None:
        m = data.sum_switch
        total = np.einsum("sij,nsj->ni", group.transforms, pred[m])
        out[group.pair] = wrench_errors(total, data.sum_label[m])
        squares.append(((total - data.sum_label[m]) ** 2).ravel())
    pooled = np.concatenate(squares)
    out["rmse_labelled"] = math.sqrt(float(pooled.mean())) if pooled.size else math.nan
    out["rmse"] = out[group.headline]["rmse"]
    return out


# --- networks ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NetSetting:
    """Everything one network training depends on (a group's params with one trial's values)."""

    n_inputs: int
    hidden: int
    activations: tuple[str, ...]
    normalisation: str
    batch_size: int
    epochs: int
    lr: float
    weight_decay: float
    lambdas: tuple[float, ...]  # per sensor
    lambda_sum: float

    @classmethod
    def of(cls, gp: GroupParams, n_inputs: int, values: Mapping[str, Any] | None = None) -> NetSetting:
        v = {**gp.hyperparameters(), **(values or {})}
        lambdas = (gp.lambda_expected,) if gp.sensor is not None else (v["lambda_front"], v["lambda_rear"])
        return cls(
            n_inputs,
            int(v["hidden"]),
            gp.activations,
            str(v["normalisation"]),
            int(v["batch_size"]),
            int(v["epochs"]),
            float(v["lr"]),
            float(v["weight_decay"]),
            tuple(map(float, lambdas)),
            float(v["lambda_sum"]),
        )


@dataclass
class Tensors:
    x: torch.Tensor  # (N, S * n_inputs) float32
    labels: torch.Tensor  # (N, S, 6)
    switches: torch.Tensor  # (N, S) bool
    sum_label: torch.Tensor | None
    alpha_sum: torch.Tensor | None


def _flat_inputs(data: GroupData, n_inputs: int) -> np.ndarray:
    return data.x[:, :, :n_inputs].reshape(len(data), -1)


def to_tensors(data: GroupData, n_inputs: int) -> Tensors:
    f32 = torch.float32
    return Tensors(
        x=torch.as_tensor(_flat_inputs(data, n_inputs), dtype=f32),
        labels=torch.as_tensor(data.labels, dtype=f32),
        switches=torch.as_tensor(data.switches),
        sum_label=None if data.sum_label is None else torch.as_tensor(data.sum_label, dtype=f32),
        alpha_sum=None if data.sum_switch is None else torch.as_tensor(data.alpha_sum),
    )


def predict(model: GroupNet, data: GroupData) -> np.ndarray:
    """(N, S, 6) float64 calibrated wrenches of a network on `data`."""
    with torch.no_grad():
        x = torch.as_tensor(_flat_inputs(data, model.config.n_inputs), dtype=torch.float32)
        out = model.eval()(x).numpy().astype(np.float64)
    return out.reshape(len(data), model.n_sensors, WRENCH)


EpochCallback = Callable[[int, float, float], None]  # (epoch, mean training loss, validation error)


def train_network(
    group: Group,
    train: GroupData,
    val: GroupData,
    setting: NetSetting,
    seed: int,
    on_epoch: EpochCallback | None = None,
) -> tuple[GroupNet, list[dict[str, float]]]:
    """Train one group network with Adam on the switched loss; keep the epoch of lowest validation error.

    `train` holds only samples with at least one term in the loss. Weight init and batch order come from
    `seed`. `on_epoch` may raise (e.g. optuna.TrialPruned) to stop. Returns the model at its best epoch
    (eval mode) and the per-epoch history [{epoch, loss, val_rmse}].
    """
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    n_sensors = len(group.sensors)
    model = GroupNet(NetConfig(setting.n_inputs, setting.hidden, setting.activations), n_sensors)
    model.reset_parameters()
    for s, net in enumerate(model.nets):
        x = train.x[:, s, : setting.n_inputs]
        offset, scale = normalisation_constants(x, setting.normalisation)
        out_scale = normalisation_constants(x[:, :WRENCH], "standard")[1]
        net.set_constants(offset, scale, out_scale)
    t = to_tensors(train, setting.n_inputs)
    lambdas = torch.tensor(setting.lambdas, dtype=torch.float32)
    transforms = None if group.transforms is None else torch.as_tensor(group.transforms, dtype=torch.float32)
    optimiser = torch.optim.Adam(model.parameters(), lr=setting.lr, weight_decay=setting.weight_decay)
    history: list[dict[str, float]] = []
    best_state, best_err = None, math.inf
    n = len(train)
    for epoch in range(setting.epochs):
        model.train()
        order = torch.randperm(n, generator=generator)
        total, batches = 0.0, 0
        for start in range(0, n, setting.batch_size):
            idx = order[start : start + setting.batch_size]
            pred = model(t.x[idx]).view(-1, n_sensors, WRENCH)
            loss, _ = switched_loss(
                pred,
                t.labels[idx],
                t.switches[idx],
                lambdas,
                None if t.sum_label is None else t.sum_label[idx],
                None if t.alpha_sum is None else t.alpha_sum[idx],
                transforms,
                setting.lambda_sum,
            )
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            total += float(loss.detach())
            batches += 1
        err = group_errors(group, val, predict(model, val))["rmse_labelled"]
        err = err if math.isfinite(err) else math.inf  # a diverged network: the worst, not NaN
        history.append({"epoch": epoch, "loss": total / max(batches, 1), "val_rmse": err})
        if err < best_err:
            best_err = err
            best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        if on_epoch is not None:
            on_epoch(epoch, history[-1]["loss"], err)
    if best_state is not None:
        model.load_state_dict(best_state)
    return model.eval(), history


# --- the stage -----------------------------------------------------------------------------------


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


class _Progress:
    """Transient rich bars (trials, epochs) and one line per finished trial, on stderr; or nothing."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self._progress: Any = None

    @contextmanager
    def running(self) -> Iterator[_Progress]:
        if not self.enabled:
            yield self
            return
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        with Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=Console(stderr=True),
            transient=True,
        ) as progress:
            self._progress = progress
            try:
                yield self
            finally:
                self._progress = None

    def task(self, description: str, total: int) -> Any:
        return None if self._progress is None else self._progress.add_task(description, total=total)

    def update(self, task: Any, **kwargs: Any) -> None:
        if task is not None:
            self._progress.update(task, **kwargs)

    def remove(self, task: Any) -> None:
        if task is not None:
            self._progress.remove_task(task)

    def line(self, text: str) -> None:
        if self._progress is not None:
            self._progress.console.print(text, highlight=False)
        elif self.enabled:
            print(text, file=sys.stderr)


def _code_digest() -> str:
    h = hashlib.sha256()
    for name in _SOURCE_FILES:
        h.update((_PACKAGE / name).read_bytes())
    return h.hexdigest()


def _data_digest(*datas: GroupData) -> str:
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
    progress: _Progress,
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
        save_model(trial_dir / f"trial_{trial.number:04d}", model, {"values": values, "seed": trial_seed})
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
    )


def _fmt(values: Mapping[str, Any]) -> str:
    return " ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in values.items())


@dataclass
class TrainResult:
    group: str
    metrics: dict[str, Any]  # as in metrics.json
    seconds: float
    mlflow_run: str  # id of the stage's MLflow run
    files: list[str] = field(default_factory=list)  # written in the output directory


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(obj, indent=1, sort_keys=True, allow_nan=True) + "\n")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _write_predictions(
    path: Path, group: Group, data: GroupData, log_names: Sequence[str], preds: Mapping[str, np.ndarray]
) -> None:
    cols: dict[str, Any] = {
        LOG: pa.array(np.asarray(log_names, dtype=object)[data.log], pa.string()),
        S.STAMP: pa.array(data.stamp, pa.int64()),
        S.TIME: pa.array(data.time, pa.float64()),
    }
    for s, sensor in enumerate(group.sensors):
        for a, c in enumerate(S.wrench_cols(S.EXPECTED, sensor)):
            cols[c] = pa.array(data.labels[:, s, a])
        cols[S.switch_col(sensor)] = pa.array(data.switches[:, s].astype(np.uint8))
    if group.pair is not None:
        for a, c in enumerate(S.wrench_cols(S.EXPECTED, group.pair)):
            cols[c] = pa.array(data.sum_label[:, a])
        cols[S.switch_col(group.pair)] = pa.array(data.sum_switch.astype(np.uint8))
    for model, pred in preds.items():
        for s, sensor in enumerate(group.sensors):
            for a, c in enumerate(prediction_cols(model, sensor)):
                cols[c] = pa.array(pred[:, s, a])
        if group.pair is not None:
            total = np.einsum("sij,nsj->ni", group.transforms, pred)
            for a, c in enumerate(prediction_cols(model, group.pair)):
                cols[c] = pa.array(total[:, a])
    table = pa.table(cols).replace_schema_metadata(
        {b"ftcal.train": json.dumps({"group": group.name, "models": list(preds)}).encode()}
    )
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        pq.write_table(table, tmp, compression="zstd")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _log_trial_run(
    group: str, name: str
) -> Callable[[int, dict[str, Any], list[dict[str, float]], str, float], None]:
    """A callback that records one trial as a nested MLflow run (params, per-epoch metrics, state)."""
    import mlflow
    from mlflow.entities import Metric, Param

    def log(
        index: int, values: dict[str, Any], history: list[dict[str, float]], state: str, seconds: float
    ) -> None:
        client = mlflow.MlflowClient()
        parent = mlflow.active_run()
        run = client.create_run(
            parent.info.experiment_id,
            run_name=f"{group} {name} trial {index + 1}",
            tags={
                "mlflow.parentRunId": parent.info.run_id,
                "group": group,
                "network": name,
                "trial": str(index + 1),
                "state": state,
            },
        )
        now = int(time.time() * 1000)
        metrics = [
            Metric(k, float(h[k]), now, int(h["epoch"])) for h in history for k in ("loss", "val_rmse")
        ]
        metrics.append(Metric("seconds", seconds, now, 0))
        if history:
            metrics.append(Metric("best_val_rmse", min(h["val_rmse"] for h in history), now, 0))
        client.log_batch(
            run.info.run_id, metrics=metrics, params=[Param(k, str(v)) for k, v in values.items()]
        )
        client.set_terminated(run.info.run_id, "FINISHED" if state == "COMPLETE" else "KILLED")

    return log


def _log_network(
    group: Group, name: str, model: GroupNet, example: np.ndarray, info: Mapping[str, Any]
) -> None:
    """Log a network in MLflow's pt2 format (no pickle) with signature and input example; register it."""
    import mlflow
    import mlflow.pytorch
    from mlflow.models import infer_signature

    example = example.astype(np.float32)
    with torch.no_grad():
        output = model(torch.from_numpy(example)).numpy()
    mlflow.pytorch.log_model(
        model,
        name=name,
        signature=infer_signature(example, output),
        input_example=example,
        serialization_format="pt2",
        registered_model_name=f"ftcal-{group.name}-{model.config.n_inputs}",
        pip_requirements=[f"torch=={torch.__version__.split('+')[0]}"],
        metadata=dict(info),
    )


def _flatten_metrics(prefix: str, errors: Mapping[str, Any]) -> dict[str, float]:
    out: dict[str, float] = {}
    for k, v in errors.items():
        if isinstance(v, Mapping):
            out.update(_flatten_metrics(f"{prefix}.{k}", v))
        elif isinstance(v, int | float) and math.isfinite(v):
            out[f"{prefix}.{k}"] = float(v)
    return out


@dataclass
class Prepared:
    """A group's data, split by whole logs, ready to fit (see `prepare`)."""

    cfg: TrainParams
    gp: GroupParams
    group: Group
    split: dict[str, list[str]]  # train/val/test -> log names
    log_names: list[str]  # every log, in the order `GroupData.log` indexes
    train: GroupData  # training samples with at least one loss term
    val: GroupData  # every validation sample with ok inputs
    test: GroupData  # every test sample with ok inputs


def prepare(params: Params, group_name: str, in_dir: Path) -> Prepared:
    """Read the group's samples from the labelled tables of `in_dir` and split them (module docstring).

    Raises:
        ConfigError: unknown group, or a group naming a sensor or pair the data does not have.
        DataError: missing directory or tables, no train/test logs, no exact label to train or validate on.
    """
    cfg = stage_section(params, STAGE, TrainParams)
    gp = cfg.group(group_name)
    logs = find_logs(in_dir)
    group = resolve_group(gp, params, logs)
    split = split_logs(logs, cfg.val_logs, params.seed)
    log_names = [log.name for log in logs]
    data = {}
    for k, names in split.items():
        part = load_group_data(group, [logs[log_names.index(n)] for n in names])
        part.log = np.array([log_names.index(n) for n in names])[part.log]  # split-local -> global index
        data[k] = part
    train = data["train"].subset(data["train"].labelled())
    if len(train) == 0:
        names = (*group.sensors, *([group.pair] if group.pair else []))
        switch = " or ".join(S.switch_col(n) for n in names)
        raise DataError(f"{group.name}: no training sample with an exact label ({switch} = 1) in {in_dir}")
    val = data["val"]
    if not (val.switches.any() or (val.sum_switch is not None and val.sum_switch.any())):
        raise DataError(f"{group.name}: the validation logs ({', '.join(split['val'])}) have no exact label")
    return Prepared(cfg, gp, group, split, log_names, train, val, data["test"])


def fit_baselines(gp: GroupParams, group: Group, train: GroupData) -> dict[str, LinearBaseline]:
    """The affine (least squares) and polynomial (ridge) baselines on the switched loss of the networks."""
    args = {
        "x": train.x,
        "labels": train.labels,
        "switches": train.switches,
        "lambdas": NetSetting.of(gp, 7).lambdas,
        "sum_label": train.sum_label,
        "alpha_sum": train.alpha_sum,
        "transforms": group.transforms,
        "lambda_sum": gp.lambda_sum,
    }
    out = {AFFINE: fit_linear_baseline(AFFINE, order=1, ridge=0.0, **args)}
    for order in gp.poly_orders:
        out[poly_name(order)] = fit_linear_baseline(poly_name(order), order=order, ridge=gp.ridge, **args)
    return out


def score(
    prep: Prepared, preds: Mapping[str, Mapping[str, np.ndarray]], nets: Mapping[str, NetResult]
) -> dict[str, Any]:
    """metrics.json: validation and test errors of every model, the model to deploy, the chosen networks."""
    group = prep.group
    metrics: dict[str, Any] = {
        "group": group.name,
        "kind": "sensor" if group.pair is None else "pair",
        "sensors": list(group.sensors),
        "pair": group.pair,
        "headline": group.headline,
        "logs": prep.split,
        "samples": {"train": len(prep.train), "val": len(prep.val), "test": len(prep.test)},
        "selection": "lowest validation rmse_labelled",
    }
    for k, data in (("val", prep.val), ("test", prep.test)):
        metrics[k] = {name: group_errors(group, data, pred) for name, pred in preds[k].items()}
    ranked = sorted(metrics["val"], key=lambda m: metrics["val"][m]["rmse_labelled"])
    metrics["best_on_validation"] = ranked[0]
    metrics["validation_ranking"] = ranked
    metrics["networks"] = {
        name: {
            "trial": r.trial,
            "hyperparameters": asdict(NetSetting.of(prep.gp, r.model.config.n_inputs, r.values)),
            "seed": r.seed,
            "best_epoch": r.best_epoch,
            "val_rmse_labelled": r.val_rmse,
            "study": r.study,
            "trials_run": r.trials_run,
            "trials_reused": r.trials_reused,
            "trials_pruned": r.trials_pruned,
        }
        for name, r in nets.items()
    }
    return metrics


def _network_info(prep: Prepared, r: NetResult, metrics: Mapping[str, Any], name: str) -> dict[str, Any]:
    n_inputs = r.model.config.n_inputs
    sensors = prep.group.sensors
    return {
        "group": prep.group.name,
        "sensors": list(sensors),
        "input_columns": [c for sensor in sensors for c in input_cols(sensor, n_inputs)],
        "output_columns": [c for sensor in sensors for c in S.wrench_cols(S.FT, sensor)],
        "hyperparameters": metrics["networks"][name]["hyperparameters"],
        "study": r.study,
        "trial": r.trial,
    }


def _mlflow_metrics(group: Group, metrics: Mapping[str, Any]) -> dict[str, float]:
    """The headline errors as flat MLflow metric names, e.g. ``test.nn7.r_leg_ft.rmse_force``."""
    flat: dict[str, float] = {}
    for k in ("val", "test"):
        for name, errors in metrics[k].items():
            keep = {"rmse": errors["rmse"], "rmse_labelled": errors["rmse_labelled"]}
            keep.update({s: errors[s] for s in (*group.sensors, group.headline)})
            flat.update(_flatten_metrics(f"{k}.{name}", keep))
    flat.update({f"seconds.{k}": v for k, v in metrics["seconds"].items()})
    return flat


def train_group(
    params: Params,
    group_name: str,
    in_dir: str | Path,
    out_dir: str | Path,
    studies: str | Path | None = None,
    *,
    progress: bool | None = None,
) -> TrainResult:
    """Run the stage for one group: read, split, fit, search, score, write `out_dir`, log to MLflow."""
    import mlflow

    from pipeline.core.tracking import stage_run

    t0 = time.perf_counter()
    src, out = Path(in_dir), Path(out_dir)
    studies = Path(studies) if studies is not None else repo_root() / STUDIES_DIR / group_name
    prep = prepare(params, group_name, src)
    gp, group = prep.gp, prep.group
    data = {"val": prep.val, "test": prep.test}
    torch.set_num_threads(prep.cfg.threads)
    torch.use_deterministic_algorithms(True)
    ui = _Progress(sys.stderr.isatty() if progress is None else progress)
    identity = {  # everything a study's result depends on, but n_trials (more trials extend a study)
        "group": {k: v for k, v in asdict(gp).items() if k != "n_trials"},
        "seed": params.seed,
        "threads": prep.cfg.threads,
        "split": prep.split,
        "data": _data_digest(prep.train, prep.val),
        "code": _code_digest(),
        "torch": torch.__version__,
    }
    timings: dict[str, float] = {}
    preds: dict[str, dict[str, np.ndarray]] = {k: {RAW: d.x[:, :, :WRENCH].copy()} for k, d in data.items()}
    own = {k: v for k, v in asdict(gp).items() if k != "name"}
    stage_params = {
        "train": {"group": group_name, "val_logs": prep.cfg.val_logs, "threads": prep.cfg.threads, **own},
        "seed": params.seed,
    }
    with stage_run(f"{STAGE}@{group_name}", stage_params) as run, ui.running():
        mlflow.set_tags(
            {
                "group": group_name,
                "in_dir": str(src),
                "out_dir": str(out),
                "val_logs": ",".join(prep.split["val"]),
                "test_logs": ",".join(prep.split["test"]),
            }
        )
        t = time.perf_counter()
        baselines = fit_baselines(gp, group, prep.train)
        for name, model in baselines.items():
            for k, d in data.items():
                preds[k][name] = model.predict(d.x)
        timings["baselines"] = time.perf_counter() - t
        seconds = timings["baselines"]
        ui.line(f"{group.name}: baselines fitted on {len(prep.train)} samples in {seconds:.1f} s")

        nets: dict[str, NetResult] = {}
        for n_inputs in gp.inputs:
            name = nn_name(n_inputs)
            t = time.perf_counter()
            nets[name] = search_network(
                gp,
                group,
                prep.train,
                prep.val,
                n_inputs,
                params.seed,
                studies,
                identity,
                ui,
                _log_trial_run(group.name, name),
            )
            for k, d in data.items():
                preds[k][name] = predict(nets[name].model, d)
            timings[name] = time.perf_counter() - t

        metrics = score(prep, preds, nets)
        out.mkdir(parents=True, exist_ok=True)
        files = ["metrics.json", "baselines.json", "predictions.parquet"]
        example = prep.test.subset(np.arange(min(5, len(prep.test))))
        for name, r in nets.items():
            info = _network_info(prep, r, metrics, name)
            save_model(out / name, r.model, info)
            files += [f"{name}.json", f"{name}.pt"]
            t = time.perf_counter()
            columns = {k: info[k] for k in ("group", "sensors", "input_columns", "output_columns")}
            _log_network(group, name, r.model, _flat_inputs(example, r.model.config.n_inputs), columns)
            timings[f"log_{name}"] = time.perf_counter() - t
        _write_json(out / "baselines.json", {name: b.to_dict() for name, b in baselines.items()})
        _write_predictions(out / "predictions.parquet", group, prep.test, prep.log_names, preds["test"])
        timings["total"] = time.perf_counter() - t0
        metrics["seconds"] = timings
        _write_json(out / "metrics.json", metrics)
        mlflow.log_metrics(_mlflow_metrics(group, metrics))
        mlflow.set_tag("best_on_validation", metrics["best_on_validation"])
        for name in ("metrics.json", "baselines.json"):
            mlflow.log_artifact(str(out / name))
    return TrainResult(group.name, metrics, time.perf_counter() - t0, run.info.run_id, files)


def _cmd(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    result = train_group(params, args.group, args.inputs, args.out, args.studies)
    m = result.metrics
    test = m["test"]
    head = m["headline"]
    summary = ", ".join(f"{name} {test[name]['rmse']:.3g}" for name in test)
    print(
        f"{result.group}: test RMSE of {head} (N, Nm pooled): {summary}; "
        f"lowest validation error: {m['best_on_validation']} ({result.seconds:.0f} s)"
    )
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal train GROUP IN OUT`."""
    parser = subparsers.add_parser(
        STAGE,
        help="baselines and neural networks of one sensor group",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument("group", help="sensor group: a key of train.groups in params.yaml")
    parser.add_argument("inputs", type=Path, metavar="IN", help="directory of labelled <log>.parquet tables")
    parser.add_argument("out", type=Path, help="output directory of the group's models and metrics")
    parser.add_argument(
        "--studies",
        type=Path,
        default=None,
        metavar="DIR",
        help=f"directory of the group's Optuna studies and trial weights (default: {STUDIES_DIR}/GROUP "
        "at the repo root); a rerun with the same inputs resumes from it",
    )
    parser.add_argument(
        "--params",
        type=Path,
        default=None,
        metavar="PATH",
        help="params file (default: params.yaml at the repo root)",
    )
    parser.set_defaults(func=_cmd)
