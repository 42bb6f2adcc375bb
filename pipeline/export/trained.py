"""The one adapter between the train stage's output directory and the export: what a graph needs.

`read_group(models/<group>, name)` reads one model of a group (a network ``nn<k>``, a polynomial
``poly<n>``, the ``affine`` baseline, the ``play`` and ``arx`` models, the windowed network ``win``, or
``raw``: its family's kind in `pipeline.calib.registry` says which form) and returns a `GroupModel`: per
sensor, the plain arrays of the model (float64) in one of four forms, and the project's own predictor for
the reference check. Nothing
else of `pipeline.calib` or `pipeline.stages.train` is used by the export (but the registry), so a change of
their file formats or classes is adapted here only.

Every model of this project is *separable*: sensor s's calibrated wrench depends on sensor s's inputs only
(a foot pair's two networks are side by side; the baselines' W_s act per sensor). Each part below is
therefore one sensor's map, inputs in the order of `pipeline.calib.models` (raw wrench fx..tz N/Nm,
temperature degC, [accelerometer m/s^2, gyroscope rad/s]), output its calibrated wrench (6, N/Nm, sensor
frame). A model with memory (``play``, ``arx``, ``win``) maps a sensor's inputs and its own state (the play
operators' and filters' outputs of its previous sample) to its wrench and next state; its reference takes
rows that are consecutive samples of one log, the state starting afresh at the first
(`pipeline.core.lowpass.memory_of`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.calib.registry import (
    AFFINE,
    IDENTITY,
    LINEAR,
    NETWORK,
    NN,
    RAW,
    WINDOW,
    family_of,
    kind_of,
    patterns,
)
from pipeline.core.errors import DataError

WRENCH = 6
METRICS_FILE = "metrics.json"
BASELINES_FILE = "baselines.json"
WINDOW_SUFFIX = ".json"  # a windowed network's file: models/<group>/<name>.json (win.json)
PREDICTIONS_FILE = "predictions.parquet"


@dataclass(frozen=True)
class Dense:
    """``y = act(W x + b)``: weight (out, in), bias (out,); activation None (linear), relu, leaky_relu
    (negative slope `alpha`), tanh or elu (`alpha`)."""

    weight: np.ndarray
    bias: np.ndarray
    activation: str | None = None
    alpha: float = 0.0


@dataclass(frozen=True)
class NetworkPart:
    """``f = x[:6] + affine_weight @ x[:k] + affine_bias + out_scale * mlp((x - in_offset) / in_scale)``;
    x (n_inputs,), constants float64 (the affine map the network corrects, `pipeline.calib.models`; k = 7,
    or 6 for a group without temperature)."""

    in_offset: np.ndarray  # (n_inputs,)
    in_scale: np.ndarray  # (n_inputs,)
    out_scale: np.ndarray  # (6,) N / Nm
    layers: tuple[Dense, ...]
    affine_weight: np.ndarray  # (6, k)
    affine_bias: np.ndarray  # (6,) N / Nm


@dataclass(frozen=True)
class LinearPart:
    """``f = x[:6] + weights @ phi((x[:k] - offset) / scale)``, phi the monomials of `powers` (P, k);
    k = 7 (wrench, temperature), or 6 (the wrench alone); with play `widths` (K, 6), phi continues with the
    play states of the raw wrench (`pipeline.core.play.play_features`: column 6 k + a, width k, axis a), with
    `time_constants` (J,) with its departures from its low-pass filters at `period`
    (`pipeline.core.lowpass.lowpass_features`: column 6 j + a)."""

    offset: np.ndarray  # (k,)
    scale: np.ndarray  # (k,)
    powers: np.ndarray  # (P, k) int exponents, constant monomial first
    weights: np.ndarray  # (6, P [+ 6 K] [+ 6 J])
    widths: np.ndarray | None = None  # (K, 6) N / Nm: the play operators (None: none)
    time_constants: np.ndarray | None = None  # (J,) s: the filters (None: none)
    period: float | None = None  # s: the sample period the filters run at

    @property
    def state_size(self) -> int:
        """Values of state this part carries from sample to sample (6 K play outputs and 6 J filter outputs;
        0 memoryless)."""
        play = 0 if self.widths is None else int(self.widths.size)
        return play + (0 if self.time_constants is None else WRENCH * len(self.time_constants))


@dataclass(frozen=True)
class IdentityPart:
    """``f = x[:6]``: the raw wrench (the robot's primary calibration)."""


@dataclass(frozen=True)
class WindowPart:
    """``f = play(x, state) + out_scale * mlp((z - in_offset) / in_scale)``, z = [x[:6], the outputs after
    the sample of the play part's J filters (6 J: filter after filter, each the 6 axes fx..tz N/Nm), x[6:k]]
    (F = 6 (J + 1) + k - 6 columns; k = 7 with temperature degC, 6 without): the windowed network
    (`pipeline.calib.window`). `play` is the play model's part with the filters among its operators, their
    weights zero; its state is the part's whole state."""

    play: LinearPart  # the play model's part, with the windows' filters (time_constants, period)
    in_offset: np.ndarray  # (F,)
    in_scale: np.ndarray  # (F,)
    out_scale: np.ndarray  # (6,) N / Nm
    layers: tuple[Dense, ...]

    @property
    def state_size(self) -> int:
        """Values of state this part carries: its play operators' and filters' outputs."""
        return self.play.state_size


Part = NetworkPart | LinearPart | IdentityPart | WindowPart


@dataclass
class GroupModel:
    """One model of one sensor group, ready to become a graph.

    `reference(x)` is the project's own computation in float64: x (N, S * n_inputs) -> (N, S * 6), the
    columns of `input_columns` in, of `output_columns` out.
    """

    group: str
    name: str  # nn7, nn13, affine, poly<n>, play, arx, win, raw
    family: str  # its family's key in `pipeline.calib.registry` (raw, affine, poly, play, arx, nn, win)
    sensors: tuple[str, ...]
    n_inputs: int  # per sensor: 6, 7 or 13
    parts: tuple[Part, ...]  # one per sensor
    input_columns: list[str]
    output_columns: list[str]
    reference: Callable[[np.ndarray], np.ndarray] = field(repr=False)
    info: dict[str, Any] = field(default_factory=dict)  # hyperparameters, training logs, ...

    @property
    def kind(self) -> str:
        """Its family's kind (`pipeline.calib.registry`): identity, linear, network or window."""
        return str(kind_of(self.name))

    @property
    def memory(self) -> bool:
        """Whether a sensor's output depends on its earlier samples (a state carried between calls)."""
        return any(getattr(p, "state_size", 0) for p in self.parts)


def input_columns(sensor: str, n_inputs: int) -> list[str]:
    """Column names of one sensor's inputs (labelled-table names), in the models' order."""
    from pipeline.calib.data import input_cols

    return input_cols(sensor, n_inputs)


def output_columns(sensor: str) -> list[str]:
    """Column names of one sensor's calibrated wrench, fx..tz (labelled-table names of the raw wrench)."""
    from pipeline.logs import schema as S

    return S.wrench_cols(S.FT, sensor)


def prediction_columns(name: str, sensor: str) -> list[str]:
    """Columns of `name`'s predictions of `sensor` in the group's predictions table."""
    from pipeline.logs import schema as S

    return S.prediction_cols(name, sensor)


def read_metrics(model_dir: Path) -> dict[str, Any]:
    """The group's ``metrics.json`` (validation/test errors, best_on_validation, sensors)."""
    from pipeline.core.io import read_json

    path = model_dir / METRICS_FILE
    metrics = read_json(path, "a metrics file", f"not found (is {model_dir} a train@<group> output?)")
    if not isinstance(metrics, dict) or not isinstance(metrics.get("sensors"), list):
        raise DataError(f"{path}: no 'sensors' list (not a train@<group> metrics file)")
    return metrics


def _network(model_dir: Path, name: str, group: str, sensors: tuple[str, ...]) -> GroupModel:
    import torch
    from torch import nn

    from pipeline.calib.models import load_model

    model, config = load_model(model_dir / name)
    n_inputs = int(model.config.n_inputs)
    if tuple(config.get("sensors", sensors)) != sensors:
        raise DataError(
            f"{model_dir / name}.json: sensors {config.get('sensors')} differ from metrics.json's"
        )
    parts = []
    for net in model.nets:
        layers: list[Dense] = []
        for module in net.mlp:
            if isinstance(module, nn.Linear):
                w = module.weight.detach().double().numpy().copy()
                layers.append(Dense(w, module.bias.detach().double().numpy().copy()))
                continue
            kinds = {nn.ReLU: ("relu", 0.0), nn.Tanh: ("tanh", 0.0)}
            if isinstance(module, nn.LeakyReLU):
                kind = ("leaky_relu", float(module.negative_slope))
            elif isinstance(module, nn.ELU):
                kind = ("elu", float(module.alpha))
            elif type(module) in kinds:
                kind = kinds[type(module)]
            else:
                raise DataError(f"{model_dir / name}: layer {type(module).__name__} cannot be exported")
            last = layers[-1]
            layers[-1] = Dense(last.weight, last.bias, kind[0], kind[1])
        parts.append(
            NetworkPart(
                net.in_offset.double().numpy().copy(),
                net.in_scale.double().numpy().copy(),
                net.out_scale.double().numpy().copy(),
                tuple(layers),
                net.affine_weight.double().numpy().copy(),
                net.affine_bias.double().numpy().copy(),
            )
        )
    reference_model = model.double().eval()

    def reference(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return reference_model(torch.tensor(np.asarray(x, dtype=np.float64))).numpy()

    info = {k: config[k] for k in ("hyperparameters", "study", "trial") if k in config}
    return GroupModel(
        group,
        name,
        NN,
        sensors,
        n_inputs,
        tuple(parts),
        [c for s in sensors for c in input_columns(s, n_inputs)],
        [c for s in sensors for c in output_columns(s)],
        reference,
        info,
    )


def _linear(model_dir: Path, name: str, group: str, sensors: tuple[str, ...]) -> GroupModel:
    from pipeline.calib.linear import LinearBaseline

    path = model_dir / BASELINES_FILE
    try:
        baseline = LinearBaseline.from_dict(json.loads(path.read_text(encoding="utf-8"))[name])
    except FileNotFoundError:
        raise DataError(f"{path}: not found") from None
    except KeyError as exc:
        raise DataError(f"{path}: no entry {exc} (models: {name} was not trained?)") from None
    except (OSError, ValueError, TypeError) as exc:
        raise DataError(f"{path}: not a baselines file: {exc}") from None
    n_sensors, width = len(sensors), baseline.offset.shape[-1]  # width: 7, or 6 without temperature
    if (
        baseline.weights.shape[0] != n_sensors
        or baseline.offset.shape != (n_sensors, width)
        or width not in (6, 7)
    ):
        raise DataError(f"{path}: {name} has {baseline.weights.shape[0]} sensors, metrics.json {n_sensors}")
    order = int(baseline.powers.sum(axis=1).max(initial=0))
    info: dict[str, Any] = {"order": order, "monomials": len(baseline.powers)}
    if baseline.widths is not None:
        info["play_widths"] = baseline.widths.tolist()
    if baseline.time_constants is not None:
        info["time_constants_s"], info["period_s"] = baseline.time_constants.tolist(), baseline.period
    return _log_model(group, name, sensors, width, _linear_parts(baseline), baseline, info)


def _log_model(
    group: str,
    name: str,
    sensors: tuple[str, ...],
    width: int,
    parts: tuple[Part, ...],
    model: Any,
    info: dict,
) -> GroupModel:
    """The `GroupModel` of a linear or windowed model whose reference is `model.predict_log` (a
    `pipeline.calib.linear.LinearBaseline` or `pipeline.calib.window.WindowModel`) on rows that are
    consecutive samples of one log, `width` inputs per sensor."""
    n_sensors = len(sensors)

    def reference(x: np.ndarray) -> np.ndarray:  # rows: consecutive samples of one log (with memory)
        x = np.asarray(x, dtype=np.float64).reshape(len(x), n_sensors, width)
        return model.predict_log(x).reshape(len(x), n_sensors * WRENCH)

    return GroupModel(
        group,
        name,
        str(family_of(name).key),
        sensors,
        width,
        parts,
        [c for s in sensors for c in input_columns(s, width)],
        [c for s in sensors for c in output_columns(s)],
        reference,
        info,
    )


def _linear_parts(b: Any) -> tuple[LinearPart, ...]:
    """Per sensor, the `LinearPart` of a `pipeline.calib.linear.LinearBaseline` `b`."""
    return tuple(
        LinearPart(b.offset[s], b.scale[s], b.powers, b.weights[s], b.widths, b.time_constants, b.period)
        for s in range(b.weights.shape[0])
    )


ACTIVATIONS = (None, "relu", "leaky_relu", "tanh", "elu")  # what a graph computes (`pipeline.export.graph`)


def _window(model_dir: Path, name: str, group: str, sensors: tuple[str, ...]) -> GroupModel:
    """The windowed network of ``<name>.json`` (`pipeline.calib.window.WindowModel.to_dict`)."""
    from pipeline.calib.window import read_window

    path = model_dir / f"{name}{WINDOW_SUFFIX}"
    model = read_window(path)
    base, n_sensors = model.base, len(sensors)
    width = base.offset.shape[-1]  # 7, or 6 without temperature
    taus = np.asarray(model.time_constants, dtype=np.float64)
    if (why := _window_fault(model, n_sensors)) is not None:
        raise DataError(f"{path}: {why}")
    filters = np.zeros((*base.weights.shape[:2], WRENCH * len(taus)))  # the play model reads none of them
    with_filters = replace(
        base,
        weights=np.concatenate([base.weights, filters], axis=2),
        time_constants=taus,
        period=model.period,
    )
    parts = tuple(
        WindowPart(
            play,
            net.in_offset,
            net.in_scale,
            net.out_scale,
            tuple(Dense(y.weight, y.bias, y.activation, float(y.alpha)) for y in net.layers),
        )
        for play, net in zip(_linear_parts(with_filters), model.nets, strict=True)
    )

    info: dict[str, Any] = {
        "time_constants_s": taus.tolist(),
        "period_s": float(model.period),
        "play_widths": base.widths.tolist(),
        "layers": [[int(y.weight.shape[0]), y.activation] for y in model.nets[0].layers],
    }
    return _log_model(group, name, sensors, width, parts, model, info)


def _window_fault(model: Any, n_sensors: int) -> str | None:
    """What makes a `pipeline.calib.window.WindowModel` of a group of `n_sensors` unexportable, else None."""
    base, taus = model.base, np.asarray(model.time_constants)
    if base.weights.shape[0] != n_sensors or len(model.nets) != n_sensors:
        return f"{base.weights.shape[0]} play sensors, {len(model.nets)} networks; metrics.json {n_sensors}"
    if base.widths is None or base.time_constants is not None or base.offset.shape[-1] not in (6, 7):
        return "its base is not a play model"
    if not len(taus) or not np.all((taus > 0) & np.isfinite(taus)):
        return f"time constants {taus.tolist()} s are not positive"
    if not 0 < model.period < math.inf:
        return f"sample period {model.period} s"
    n_features = WRENCH * (len(taus) + 1) + base.offset.shape[-1] - WRENCH
    for net in model.nets:
        width = n_features
        for y in net.layers:
            if y.weight.ndim != 2 or y.weight.shape[1] != width or y.bias.shape != (y.weight.shape[0],):
                return f"a network's layers do not chain from its {n_features} inputs"
            if y.activation not in ACTIVATIONS:
                return f"activation {y.activation!r} cannot be exported"
            width = y.weight.shape[0]
        shapes = (net.in_offset.shape, net.in_scale.shape, net.out_scale.shape)
        if width != WRENCH or shapes != ((n_features,), (n_features,), (WRENCH,)):
            return f"a network is not {n_features} inputs to {WRENCH} outputs"
    return None


def _raw(group: str, sensors: tuple[str, ...], width: int = 7) -> GroupModel:
    """The raw wrench, on the inputs of the group's baselines (`width`: 7, or 6 without temperature)."""
    n = len(sensors)

    def reference(x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=np.float64).reshape(len(x), n, width)[:, :, :WRENCH].reshape(len(x), -1)

    return GroupModel(
        group,
        RAW,
        RAW,
        sensors,
        width,
        tuple(IdentityPart() for _ in sensors),
        [c for s in sensors for c in input_columns(s, width)],
        [c for s in sensors for c in output_columns(s)],
        reference,
    )


def read_group(model_dir: str | Path, name: str, group: str | None = None) -> GroupModel:
    """Model `name` of the group trained into `model_dir` (see the module docstring).

    Raises:
        DataError: the directory is not a train output, the model is not in it, or its files are unusable.
    """
    model_dir = Path(model_dir)
    metrics = read_metrics(model_dir)
    group = group or str(metrics.get("group") or model_dir.name)
    sensors = tuple(str(s) for s in metrics["sensors"])
    kind = kind_of(name)
    if kind == IDENTITY:
        model = _raw(group, sensors, _baseline_width(model_dir))
    elif kind == NETWORK:
        model = _network(model_dir, name, group, sensors)
    elif kind == LINEAR:
        model = _linear(model_dir, name, group, sensors)
    elif kind == WINDOW:
        model = _window(model_dir, name, group, sensors)
    else:
        raise DataError(f"{model_dir}: unknown model {name!r} ({', '.join(patterns())})")
    model.info.update(provenance(metrics, name))
    return model


def _baseline_width(model_dir: Path) -> int:
    """The inputs per sensor of a group's baselines: 7 (wrench, temperature), or 6 where it has none."""
    try:
        entry = json.loads((model_dir / BASELINES_FILE).read_text(encoding="utf-8")).get(AFFINE) or {}
        return int(np.shape(entry.get("offset", [[0] * 7]))[-1])
    except (OSError, ValueError):
        return 7


def provenance(metrics: Mapping[str, Any], name: str) -> dict[str, Any]:
    """What the manifest says of a model's training: logs, sample counts, its test errors (N, Nm)."""

    def finite(v: Any) -> Any:
        return v if not isinstance(v, float) or math.isfinite(v) else None

    test = (metrics.get("test") or {}).get(name) or {}
    headline = str(metrics.get("headline") or "")
    keep = {k: finite(test.get(k)) for k in ("rmse", "rmse_labelled", "rmse_force", "rmse_torque")}
    per = {
        s: {k: finite(v) for k, v in (test.get(s) or {}).items() if k.startswith("rmse") or k == "samples"}
        for s in [*metrics["sensors"], headline]
    }
    return {
        "best_on_validation": metrics.get("best_on_validation"),
        "headline": headline,
        "logs": metrics.get("logs"),
        "samples": metrics.get("samples"),
        "test_metrics": {**keep, **{k: v for k, v in per.items() if v}},
        "mlflow_run": metrics.get("mlflow_run"),
    }
