"""Params of the train stage: `train.defaults` and `train.groups.<name>` resolved and validated.

Light on purpose (no torch): params.yaml is validated section by section when it is loaded, whichever
stage runs, so a typo under `train:` surfaces at once.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

from pipeline.calib.pushes import PushPrior
from pipeline.calib.registry import complexity
from pipeline.core.errors import ConfigError
from pipeline.core.play import distinct_positive

INPUT_SIZES = (6, 7, 13)  # raw wrench (+ temperature (+ accelerometer + gyroscope))
NORMALISATIONS = ("max", "standard")
ACTIVATION_NAMES = ("relu", "leaky_relu", "tanh", "elu")
# recorded logs: the plain least-squares affine map (no virtual pushes), the in-situ reference any lab can
# compute, scored beside the models (never a candidate to deploy)
LS_AFFINE = "affine_ls"
STORAGE_SCHEMES = ("postgresql", "sqlite", "mysql")  # SQLAlchemy dialects Optuna's RDB storage supports


def baseline_inputs(inputs: Sequence[int]) -> int:
    """Inputs of a group's affine and polynomial baselines: the wrench alone (6) where the group trains a
    wrench-only network (a log without temperature), else wrench and temperature (7)."""
    return 6 if 6 in inputs else 7


def select_simplest(errors: Mapping[str, float], margin: float) -> str:
    """The model to deploy from validation errors {model: rmse}: walking from the simplest model to the
    most complex, a model replaces the current choice only if its error is below (1 - margin) times the
    current choice's (NaN errors never win). `errors` must not be empty."""
    return select_by_folds({m: [e] for m, e in errors.items()}, margin)


def fold_spread(values: Sequence[float]) -> float:
    """Spread of per-fold values: their standard deviation (ddof 0; with two folds, half their distance)."""
    if len(values) < 2:
        return 0.0
    mean = sum(values) / len(values)
    return math.sqrt(sum((v - mean) ** 2 for v in values) / len(values))


def beats(simple: Sequence[float], complex_: Sequence[float], margin: float) -> bool:
    """Whether a more complex model with per-fold errors `complex_` replaces a simpler one (`simple`):
    its mean error is below (1 - margin) times the simpler one's, and the mean of the per-fold
    improvements exceeds their spread (with two folds: better on both). NaN never wins."""
    if not all(math.isfinite(v) for v in complex_):
        return False
    if not all(math.isfinite(v) for v in simple):
        return True
    gain = [x - y for x, y in zip(simple, complex_, strict=True)]
    mean_a, mean_b, mean_gain = (sum(v) / len(v) for v in (simple, complex_, gain))
    return mean_b < (1.0 - margin) * mean_a and mean_gain > fold_spread(gain)


def select_by_folds(scores: Mapping[str, Sequence[float]], margin: float) -> str:
    """The model to deploy from per-fold validation errors {model: [rmse per fold]}: walking from the
    simplest model to the most complex, a model replaces the current choice only if it `beats` it.
    `scores` must not be empty."""
    won = [step["model"] for step in selection_steps(scores, margin) if step["won"]]
    return won[-1] if won else min(scores, key=complexity)


def selection_steps(scores: Mapping[str, Sequence[float]], margin: float) -> list[dict[str, Any]]:
    """The walk of `select_by_folds`, one step per model but the simplest: the choice it was compared with
    (``against``), its ``gain`` (1 - its mean error / that choice's; None if either is not finite), and
    whether it ``won`` (replaced that choice)."""
    ordered = sorted(scores, key=complexity)
    choice, steps = ordered[0], []
    for model in ordered[1:]:
        a, b = (sum(scores[m]) / len(scores[m]) for m in (choice, model))
        gain = 1.0 - b / a if math.isfinite(a) and math.isfinite(b) and a > 0 else None
        won = beats(scores[choice], scores[model], margin)
        steps.append({"model": model, "against": choice, "gain": gain, "won": won})
        choice = model if won else choice
    return steps


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
    pair: str | None  # ... or a foot pair of robot.foot_pairs ...
    sensors: tuple[str, ...] | None  # ... or several sensors coupled by the cut sets among them
    inputs: tuple[int, ...]  # network sizes trained: 6 (wrench), 7 (+ temperature), 13 (+ IMU)
    hidden: int  # neurons per hidden layer
    activations: tuple[str, ...]  # one per hidden layer
    normalisation: str  # max | standard
    batch_size: int  # samples per Adam step
    epochs: int  # passes over the training samples
    lr: float  # Adam learning rate
    weight_decay: float  # Adam weight decay
    average_epochs: float  # horizon of the exponential moving average of the weights, epochs (0: none)
    lambda_expected: float  # single sensor: lambda of eq. 5.4
    lambda_front: float  # foot: lambdas of eqs. 5.6-5.7
    lambda_rear: float
    lambda_sum: float
    lambda_cut: float  # several sensors: lambda of each cut set's sum term
    lambda_prior: float  # pull towards the affine map where a sensor has no exact label of its own
    lambda_push: float  # weight of the virtual pushes' prior (pipeline.calib.pushes)
    push_force_n: float  # their force std, N
    push_lever_m: float  # and lever, m (torque std = force x lever)
    free_lever: bool  # the linear fits leave the sensor's torque reference point to the labels
    residual_slope: float  # networks: the Lipschitz bound of their correction in push units (> 0)
    n_trials: int  # Optuna trials per network (the first: these params)
    search: Mapping[str, Any]  # key -> [choices] or {low, high, log}
    tpe_startup_trials: int  # random trials before TPE
    prune_startup_trials: int  # slots never pruned (pipeline.calib.pruning)
    prune_warmup_epochs: int  # epochs of a trial never pruned
    prune_margin: float  # a trial is pruned when its error exceeds the earlier slots' median by more
    poly_orders: tuple[int, ...]  # polynomial baselines
    ridge: float  # ridge penalty per sample (standardised features)
    play_width_fractions: tuple[float, ...]  # the play model's widths, of each raw axis's training span
    #                                          (pipeline.calib.memory; empty: no play model)
    arx_time_constants_s: tuple[float, ...]  # the arx model's candidate low-pass filters, s (empty: no arx)
    window_time_constants_s: tuple[float, ...]  # the windowed network's windows, s (empty: no such network)
    window_hidden: int  # its neurons per hidden layer
    window_activations: tuple[str, ...]  # its hidden layers' activations, one per layer
    window_epochs: int  # its passes over the training samples
    window_lr: float  # its Adam learning rate
    window_batch_size: int  # its samples per Adam step

    def __post_init__(self) -> None:
        key = f"train.groups.{self.name}"
        if sum(v is not None for v in (self.sensor, self.pair, self.sensors)) != 1:
            raise ConfigError(f"{key} must have exactly one of 'sensor', 'pair' or 'sensors'")
        for attr in ("sensor", "pair"):
            value = getattr(self, attr)
            if value is not None and (not isinstance(value, str) or not value.strip()):
                raise ConfigError(f"{key}.{attr} must be a non-empty string, got {value!r}")
        if self.sensors is not None:
            names = self.sensors
            if (
                not isinstance(names, list | tuple)
                or len(names) < 2
                or any(not isinstance(n, str) or not n.strip() for n in names)
                or len(set(names)) != len(names)
            ):
                raise ConfigError(
                    f"{key}.sensors must be a list of 2 or more distinct sensor names, got {names!r}"
                )
            object.__setattr__(self, "sensors", tuple(names))
        inputs = self.inputs
        if not isinstance(inputs, list | tuple) or not inputs or any(i not in INPUT_SIZES for i in inputs):
            raise ConfigError(f"{key}.inputs must be a non-empty list of {INPUT_SIZES}, got {inputs!r}")
        object.__setattr__(self, "inputs", tuple(sorted(set(inputs))))
        for attr in ("activations", "window_activations"):
            acts = getattr(self, attr)
            if not isinstance(acts, list | tuple) or not acts or any(a not in ACTIVATION_NAMES for a in acts):
                names = list(ACTIVATION_NAMES)
                raise ConfigError(f"{key}.{attr} must be a non-empty list of {names}, got {acts!r}")
            object.__setattr__(self, attr, tuple(acts))
        self._check_integers(key)
        if self.normalisation not in NORMALISATIONS:
            raise ConfigError(
                f"{key}.normalisation must be one of {NORMALISATIONS}, got {self.normalisation!r}"
            )
        for attr in ("lr", "window_lr"):
            if not _is_number(getattr(self, attr)) or getattr(self, attr) <= 0:
                raise ConfigError(f"{key}.{attr} must be a positive number, got {getattr(self, attr)!r}")
        for attr in (
            "weight_decay",
            "average_epochs",
            "lambda_expected",
            "lambda_front",
            "lambda_rear",
            "lambda_sum",
            "lambda_cut",
            "lambda_prior",
            "lambda_push",
            "push_force_n",
            "push_lever_m",
            "prune_margin",
            "ridge",
        ):
            value = getattr(self, attr)
            if not _is_number(value) or value < 0:
                raise ConfigError(f"{key}.{attr} must be a number >= 0, got {value!r}")
            object.__setattr__(self, attr, float(value))
        object.__setattr__(self, "lr", float(self.lr))
        object.__setattr__(self, "window_lr", float(self.window_lr))
        slope = self.residual_slope
        if not _is_number(slope) or not 0 < slope <= 1:
            raise ConfigError(f"{key}.residual_slope must be a number in (0, 1], got {slope!r}")
        object.__setattr__(self, "residual_slope", float(slope))
        if not isinstance(self.free_lever, bool):
            raise ConfigError(f"{key}.free_lever must be true or false, got {self.free_lever!r}")
        orders = self.poly_orders
        if not isinstance(orders, list | tuple) or any(not _is_int(o) or not 1 <= o <= 4 for o in orders):
            raise ConfigError(f"{key}.poly_orders must be a list of integers in [1, 4], got {orders!r}")
        object.__setattr__(self, "poly_orders", tuple(sorted(set(orders))))
        self._check_widths(key)
        self._check_search(key)

    def _check_integers(self, key: str) -> None:
        for attr, low in (
            ("hidden", 1),
            ("batch_size", 1),
            ("epochs", 1),
            ("n_trials", 1),
            ("tpe_startup_trials", 0),
            ("prune_startup_trials", 0),
            ("prune_warmup_epochs", 0),
            ("window_hidden", 1),
            ("window_epochs", 1),
            ("window_batch_size", 1),
        ):
            value = getattr(self, attr)
            if not _is_int(value) or value < low:
                raise ConfigError(f"{key}.{attr} must be an integer >= {low}, got {value!r}")

    def _check_widths(self, key: str) -> None:
        fractions = distinct_positive(self.play_width_fractions, f"{key}.play_width_fractions")
        if any(f > 0.5 for f in fractions):
            raise ConfigError(
                f"{key}.play_width_fractions must lie in (0, 0.5] (a wider operator never saturates on the "
                f"training motion), got {list(fractions)}"
            )
        object.__setattr__(self, "play_width_fractions", fractions)
        taus = distinct_positive(self.arx_time_constants_s, f"{key}.arx_time_constants_s")
        object.__setattr__(self, "arx_time_constants_s", taus)
        taus = distinct_positive(self.window_time_constants_s, f"{key}.window_time_constants_s")
        object.__setattr__(self, "window_time_constants_s", taus)

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
        """The sensor or pair name the group trains (several sensors: the group's name)."""
        if self.sensors is not None:
            return self.name
        return self.sensor if self.sensor is not None else str(self.pair)

    @property
    def push(self) -> PushPrior:
        """The virtual pushes every model of the group is fitted with."""
        return PushPrior(self.lambda_push, self.push_force_n, self.push_lever_m, self.free_lever)

    def windowed(self) -> tuple[float, ...] | None:
        """The windowed network's time constants, s; None: the group trains none (none given, or no play
        model for it to correct)."""
        return (
            self.window_time_constants_s
            if self.window_time_constants_s and self.play_width_fractions
            else None
        )

    def hyperparameters(self) -> dict[str, Any]:
        """The searchable values of these params."""
        return {k: getattr(self, k) for k in SEARCHABLE}


_GROUP_KEYS = {f.name for f in fields(GroupParams)} - {"name"}
_DEFAULT_KEYS = _GROUP_KEYS - {"sensor", "pair", "sensors"}


def check_storage(url: Any, where: str = "train.storage") -> None:
    """Raise ConfigError naming `where` unless `url` is None or a supported database URL."""
    if url is None:
        return
    scheme = url.split("://", 1)[0].split("+", 1)[0] if isinstance(url, str) and "://" in url else None
    if scheme == "postgres":
        scheme = "postgresql"
    if scheme not in STORAGE_SCHEMES:
        raise ConfigError(
            f"{where} must be null (a journal file) or a database URL such as "
            f"postgresql://user:password@host:5432/db, got {url!r}"
        )


@dataclass(frozen=True)
class TrainParams:
    """Section `train` of params.yaml (see the comments there)."""

    val_logs: int  # training logs held out as validation
    folds: int  # cross-validation folds by whole logs (fold 0: the validation logs above)
    storage: str | None  # Optuna studies: None = journal file, else a database URL (calib.studies)
    heartbeat: int  # s between heartbeats of a trial on a database; stale (retried) after twice that
    selection_margin: float  # a more complex model is chosen only if its validation error is this much lower
    defaults: Mapping[str, Any]  # every group's params ...
    groups: Mapping[str, Any]  # ... updated per group: name -> {sensor | pair, overrides}

    def __post_init__(self) -> None:
        if not _is_int(self.val_logs) or self.val_logs < 1:
            raise ConfigError(f"train.val_logs must be an integer >= 1, got {self.val_logs!r}")
        if not _is_int(self.folds) or self.folds < 1:
            raise ConfigError(f"train.folds must be an integer >= 1, got {self.folds!r}")
        check_storage(self.storage)
        if not _is_int(self.heartbeat) or self.heartbeat < 1:
            raise ConfigError(f"train.heartbeat must be an integer >= 1 (s), got {self.heartbeat!r}")
        if not _is_number(self.selection_margin) or not 0 <= self.selection_margin < 1:
            raise ConfigError(
                f"train.selection_margin must be a number in [0, 1), got {self.selection_margin!r}"
            )
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
        merged = {"sensor": None, "pair": None, "sensors": None, **self.defaults, **own}
        return GroupParams(name=name, **merged)
