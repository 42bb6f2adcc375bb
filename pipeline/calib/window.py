"""The windowed network (family ``win``): a Lipschitz-bounded correction of the play model over exponential
windows of the raw wrench.

Per sensor, ``f = play(x, state) + out_scale * mlp((z - in_offset) / in_scale)`` with z the sensor's raw
wrench now, its exponential windows (first-order low-passes of a few time constants, `time_constants`, at
the training logs' sample period: ``y_t = y_{t-1} + alpha (f_t - y_{t-1})``, `pipeline.core.lowpass`; each a
weighted average of the reading's past over about its time constant) and, where the group has one, its
temperature now (degC): z = [f_t, y_1,t, ..., y_J,t, T_t], F = 6 (J + 1) [+ 1] columns (fx..tz N/Nm, window
after window). A recurrent network whose recurrence is fixed and linear: its state is the filters' outputs,
carried from sample to sample by the same step as the arx model's, so a graph computes it in the play
operators' Scan (`pipeline.export.window`). The play model (`pipeline.calib.linear`, fitted first, held fixed)
carries the sensor's hysteresis; the network adds what the recent past of the reading says beyond it (a
minor loop's shape, a creep, how fast a load changes). Its memory, what `predict` reads beside x, is the play
outputs then the filters' outputs before the sample (6 K + 6 J columns, `pipeline.core.lowpass.memory_of`),
every column a raw-wrench value on axis column mod 6: a push held on the reading moves all of it.

Faithful by construction, as the memoryless networks (`pipeline.calib.models`): every layer is 1-Lipschitz,
the input divided by the push units of its column (`pipeline.calib.pushes.residual_units`, the same units
for every window) and the output ``slope / sqrt(J + 1)`` times them. A push of size d held on the reading
moves the J + 1 wrench columns by d each (a push-metric step of sqrt(J + 1) d), so the correction moves by
at most ``slope`` d at every scale, 1 N or 40 N; at a push's onset (the present moved, the windows by alpha
d) by about ``slope / sqrt(J + 1)`` d. So the model reports a push with the play model's slope within
`slope`, and its memory cannot stand in for the present reading (`pipeline.calib.fidelity`: onset against
held).

Trained on the exact samples with the networks' switched losses and cut-set terms (`pipeline.calib.training`),
each sample carrying its own windows (so batches may be shuffled: the filters run per log in time order
before any sample is picked), Adam, the epoch best on the validation logs kept (epoch -1: the play model
itself). The filters step once a sample: the model is tied to its training logs' sample period (``period``),
as the arx model is; `ftcal calibrate` refuses another rate.
"""

from __future__ import annotations

import json
import math
import time
from contextlib import nullcontext
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pipeline.calib.data import Group, GroupData, derive_seed, group_errors
from pipeline.calib.linear import LinearBaseline
from pipeline.calib.models import ACTIVATIONS, LipschitzLinear, init_mlp, mlp_layers
from pipeline.calib.params import GroupParams
from pipeline.calib.pushes import PushPrior, residual_units
from pipeline.calib.registry import PLAY, WIN
from pipeline.calib.scores import WRENCH
from pipeline.calib.training import NetSetting, Tensors, WeightAverage, to_tensors, train_epoch
from pipeline.core.errors import DataError
from pipeline.core.lowpass import alphas, memory_of
from pipeline.core.play import memory_step


@dataclass(frozen=True)
class WindowSetting:
    """What one windowed network's training depends on (a group's params)."""

    time_constants: tuple[float, ...]  # s: the exponential windows
    hidden: int
    activations: tuple[str, ...]
    slope: float  # the correction's Lipschitz bound in push units
    net: NetSetting  # the losses' weights, epochs, lr and batch size (no virtual pushes: the bound stands in)

    @classmethod
    def of(cls, gp: GroupParams) -> WindowSetting:
        net = replace(
            NetSetting.of(gp, 7),
            push=PushPrior(0.0, gp.push_force_n, gp.push_lever_m),
            slope=gp.residual_slope,
            epochs=gp.window_epochs,
            lr=gp.window_lr,
            batch_size=gp.window_batch_size,
        )
        hidden, activations = gp.window_hidden, gp.window_activations
        return cls(tuple(gp.window_time_constants_s), hidden, activations, gp.residual_slope, net)


@dataclass
class Layer:
    """``act(weight @ x + bias)``, float64 copies of a trained layer (activation None: linear)."""

    weight: np.ndarray  # (out, in)
    bias: np.ndarray  # (out,)
    activation: str | None
    alpha: float = 0.0  # leaky_relu's negative slope, elu's alpha


@dataclass
class WindowNet:
    """One sensor's correction: ``out_scale * mlp((z - in_offset) / in_scale)`` (module docstring)."""

    in_offset: np.ndarray  # (F,)
    in_scale: np.ndarray  # (F,)
    out_scale: np.ndarray  # (6,) N / Nm
    layers: list[Layer]

    def __call__(self, z: np.ndarray) -> np.ndarray:
        h = (z - self.in_offset) / self.in_scale
        for layer in self.layers:
            h = h @ layer.weight.T + layer.bias
            if layer.activation == "relu":
                h = np.maximum(h, 0.0)
            elif layer.activation == "leaky_relu":
                h = np.where(h > 0, h, layer.alpha * h)
            elif layer.activation == "tanh":
                h = np.tanh(h)
            elif layer.activation == "elu":
                h = np.where(h > 0, h, layer.alpha * np.expm1(np.minimum(h, 0.0)))
        return h * self.out_scale


@dataclass
class WindowModel:
    """A group's windowed network: the play model `base` and one `WindowNet` per sensor (module docstring)."""

    base: LinearBaseline  # the play model it corrects
    time_constants: np.ndarray  # (J,) s: its exponential windows
    period: float  # s: its training logs' sample period (the filters step once a sample)
    nets: list[WindowNet]
    name: str = WIN

    memory = True

    @property
    def play_columns(self) -> int:
        """The memory's play columns (6 K), before the filters'."""
        return int(self.base.widths.size)

    def inputs(self, x: np.ndarray, previous: np.ndarray) -> np.ndarray:
        """(N, F) one sensor's network inputs from its raw inputs x (N, >= 6 or 7) and its filters' outputs
        before each sample (N, 6 J; NaN: a fresh start): the windows after the sample (module docstring)."""
        k = self.base.offset.shape[1]  # 7 with temperature, 6 without
        gains = np.repeat(alphas(self.time_constants, self.period), WRENCH)
        tiled = np.tile(x[:, :WRENCH], len(self.time_constants))
        return np.concatenate([x[:, :WRENCH], memory_step(previous, tiled, np.inf, gains), x[:, WRENCH:k]], 1)

    def predict(self, x: np.ndarray, memory: np.ndarray | None = None) -> np.ndarray:
        """(N, S, 6) calibrated wrenches from raw inputs x (N, S, >= 7) and the memory before each sample
        (N, S, 6 K + 6 J: the play outputs, then the filters')."""
        if memory is None:
            raise ValueError(f"{self.name}: a model with memory needs its play and filter outputs")
        k = self.play_columns
        out = self.base.predict(x, memory[:, :, :k])
        for s, net in enumerate(self.nets):
            out[:, s] += net(self.inputs(x[:, s], memory[:, s, k:]))
        return out

    def memory_of(self, x: np.ndarray, period: float | None = None) -> np.ndarray:
        """(N, S, 6 K + 6 J) the memory of one log's samples x (N, S, >= 6) in time order, `period` s apart
        (None: the training logs'), from a fresh state."""
        return memory_of(x, self.base.widths, self.time_constants, period or self.period)

    def predict_log(self, x: np.ndarray, period: float | None = None) -> np.ndarray:
        """(N, S, 6) calibrated wrenches of one log's samples x (N, S, >= 7) in time order, `period` s apart
        (None: the training logs'), the memory starting afresh at its first sample."""
        return self.predict(x, self.memory_of(x, period))

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "model": (
                "f = base(x) + out_scale * mlp((z - in_offset) / in_scale), z = [x[:6], y_j per time "
                "constant j (y = y before + alpha_j (x[:6] - y before), alpha_j = 1 - exp(-period / "
                "time_constants[j]), y starts at x[:6]), x[6:k]], k = len(base offset); base: the play model "
                "(baselines.json's form); layers: act(weight @ h + bias)"
            ),
            "base": self.base.to_dict(),
            "time_constants": [float(v) for v in self.time_constants],
            "period": float(self.period),
            "nets": [
                {
                    "in_offset": n.in_offset.tolist(),
                    "in_scale": n.in_scale.tolist(),
                    "out_scale": n.out_scale.tolist(),
                    "layers": [
                        {
                            "weight": y.weight.tolist(),
                            "bias": y.bias.tolist(),
                            "activation": y.activation,
                            "alpha": y.alpha,
                        }
                        for y in n.layers
                    ],  # fmt: skip
                }
                for n in self.nets
            ],
        }

    @classmethod
    def from_dict(cls, entry: dict[str, Any]) -> WindowModel:
        """Inverse of `to_dict` (KeyError, ValueError or TypeError if `entry` is not one)."""

        def array(v: Any) -> np.ndarray:
            return np.asarray(v, dtype=np.float64)

        def layers(n: dict[str, Any]) -> list[Layer]:
            return [
                Layer(array(y["weight"]), array(y["bias"]), y["activation"], float(y["alpha"])) for y in n
            ]

        nets = [
            WindowNet(array(n["in_offset"]), array(n["in_scale"]), array(n["out_scale"]), layers(n["layers"]))
            for n in entry["nets"]
        ]
        taus = np.asarray(entry["time_constants"], dtype=np.float64).reshape(-1)
        return cls(
            LinearBaseline.from_dict(entry["base"]), taus, float(entry["period"]), nets, str(entry["name"])
        )


def read_window(path: Path) -> WindowModel:
    """The windowed network of a train output's ``win.json``.

    Raises:
        DataError: the file is missing or is not a `WindowModel.to_dict`.
    """
    try:
        return WindowModel.from_dict(json.loads(path.read_text(encoding="utf-8")))
    except FileNotFoundError:
        raise DataError(f"{path}: not found (models: {path.stem} was not trained?)") from None
    except (OSError, ValueError, TypeError, KeyError) as exc:
        raise DataError(f"{path}: not a windowed network: {exc!r}") from None


# --- training ------------------------------------------------------------------------------------


class _SensorWindow(nn.Module):
    """One sensor's correction in torch, Lipschitz layers (module docstring); output layer zero."""

    def __init__(self, n_inputs: int, setting: WindowSetting) -> None:
        super().__init__()
        self.mlp = mlp_layers(n_inputs, setting.hidden, setting.activations)
        init_mlp(self.mlp)
        self.register_buffer("in_offset", torch.zeros(n_inputs))
        self.register_buffer("in_scale", torch.ones(n_inputs))
        self.register_buffer("out_scale", torch.ones(WRENCH))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.out_scale * self.mlp((z - self.in_offset) / self.in_scale)

    def to_numpy(self) -> WindowNet:
        layers: list[Layer] = []
        for module in self.mlp:
            if isinstance(module, LipschitzLinear):
                plain = module.bake()
                layers.append(Layer(_f64(plain.weight), _f64(plain.bias), None))
            elif layers:
                name = next(k for k, v in ACTIVATIONS.items() if isinstance(module, v))
                alpha = float(getattr(module, "negative_slope", getattr(module, "alpha", 0.0)))
                layers[-1] = replace(layers[-1], activation=name, alpha=alpha)
        return WindowNet(_f64(self.in_offset), _f64(self.in_scale), _f64(self.out_scale), layers)


def _f64(t: torch.Tensor) -> np.ndarray:
    return t.detach().numpy().astype(np.float64)


class _GroupWindow(nn.Module):
    """The group's corrections side by side on (B, S F + S 6): every sensor's inputs, then the play model's
    outputs, which it returns corrected (B, S 6)."""

    def __init__(self, n_sensors: int, n_inputs: int, setting: WindowSetting) -> None:
        super().__init__()
        self.n_inputs = n_inputs
        self.nets = nn.ModuleList(_SensorWindow(n_inputs, setting) for _ in range(n_sensors))

    @property
    def n_sensors(self) -> int:
        return len(self.nets)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, f = self.n_sensors, self.n_inputs
        corrections = [net(x[:, s * f : (s + 1) * f]) for s, net in enumerate(self.nets)]
        return x[:, n * f :] + torch.cat(corrections, dim=1)


def _flat(model: WindowModel, data: GroupData, memory: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(N, S F + S 6) float64: every sensor's network inputs, then the play model's outputs."""
    k = model.play_columns
    z = [model.inputs(data.x[:, s], memory[:, s, k:]) for s in range(data.x.shape[1])]
    return np.concatenate([*z, base.reshape(len(base), -1)], axis=1)


def window_memory(base: LinearBaseline, data: GroupData) -> np.ndarray:
    """(N, S, 6 K + 6 J) the windowed network's memory of `data` (its play columns, then `data.window`)."""
    return np.concatenate([data.memory[:, :, : base.widths.size], data.window], axis=2)


def train_window(
    group: Group, train: GroupData, val: GroupData, base: LinearBaseline, setting: WindowSetting, seed: int
) -> tuple[WindowModel, list[dict[str, float]]]:
    """The windowed network correcting the play model `base`, trained on `train`'s exact samples, the epoch
    best on `val` kept (epoch -1: `base` itself); and its history [{epoch, loss, val_rmse}]."""
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    taus = np.asarray(setting.time_constants, dtype=np.float64)
    units_one = residual_units(setting.net.push.force_n, setting.net.push.lever_m, 7)
    k = base.offset.shape[1]
    units = np.r_[np.tile(units_one[:WRENCH], len(taus) + 1), units_one[WRENCH:k]]
    model = WindowModel(base, taus, float(np.median(train.period)), [])
    memory = window_memory(base, train)
    prior = base.predict(train.x, memory[:, :, : model.play_columns])
    flat = _flat(model, train, memory, prior)
    net = _GroupWindow(train.x.shape[1], len(units), setting)
    per_sensor = flat[:, : net.n_sensors * len(units)].reshape(len(flat), net.n_sensors, -1)
    out_scale = setting.slope / math.sqrt(len(taus) + 1) * units[:WRENCH]
    for s, sensor_net in enumerate(net.nets):
        for name, value in (
            ("in_offset", per_sensor[:, s].mean(0)),
            ("in_scale", units),
            ("out_scale", out_scale),
        ):
            getattr(sensor_net, name).copy_(torch.as_tensor(value, dtype=torch.float32))
    t: Tensors = to_tensors(train, 7, group, prior)
    t.x = torch.as_tensor(flat, dtype=torch.float32)
    val_memory = window_memory(base, val)
    val_flat = torch.as_tensor(
        _flat(model, val, val_memory, base.predict(val.x, val_memory[:, :, : model.play_columns])),
        dtype=torch.float32,
    )

    def val_error() -> float:
        with torch.no_grad():
            pred = net.eval()(val_flat).numpy().astype(np.float64).reshape(len(val), -1, WRENCH)
        err = group_errors(group, val, pred)["rmse_labelled"]
        return err if math.isfinite(err) else math.inf

    lambdas = torch.tensor(setting.net.lambdas, dtype=torch.float32)
    transforms = None if group.transforms is None else torch.as_tensor(group.transforms, dtype=torch.float32)
    optimiser = torch.optim.Adam(net.parameters(), lr=setting.net.lr)
    best_err = val_error()
    best_state = {key: v.detach().clone() for key, v in net.state_dict().items()}
    history = [{"epoch": -1, "loss": math.nan, "val_rmse": best_err}]
    steps = math.ceil(len(train) / setting.net.batch_size)
    average = (
        WeightAverage(net, setting.net.average_epochs * steps) if setting.net.average_epochs > 0 else None
    )
    for epoch in range(setting.net.epochs):
        loss = train_epoch(group, net, t, lambdas, transforms, setting.net, optimiser, generator, average)
        with average.applied() if average is not None else nullcontext():
            err = val_error()
            if err < best_err:
                best_err = err
                best_state = {key: v.detach().clone() for key, v in net.state_dict().items()}
        history.append({"epoch": epoch, "loss": loss, "val_rmse": err})
    net.load_state_dict(best_state)
    model.nets = [sensor_net.to_numpy() for sensor_net in net.nets]
    return model, history


@dataclass
class WindowFit:
    """A group's trained windowed network, its per-epoch history [{epoch, loss, val_rmse}] and seconds."""

    model: WindowModel
    history: list[dict[str, float]]
    seconds: float

    def info(self) -> dict[str, Any]:
        """metrics.json's entry: windows, period, best epoch and history (its seconds are the timings')."""
        best = min(self.history, key=lambda h: h["val_rmse"])
        return {
            "time_constants_s": [float(v) for v in self.model.time_constants],
            "period_s": self.model.period,
            "best_epoch": int(best["epoch"]),
            "val_rmse_labelled": best["val_rmse"],
            "history": self.history,
        }


def fit_windowed(
    gp: GroupParams,
    group: Group,
    train: GroupData,
    val: GroupData,
    baselines: dict[str, LinearBaseline],
    seed: int,
) -> WindowFit | None:
    """The group's windowed network on `train` (best epoch on `val`) over its play model of `baselines`; None
    where the group trains none (`GroupParams.windowed`)."""
    if group.windows is None or PLAY not in baselines:
        return None
    t = time.perf_counter()
    model, history = train_window(
        group, train, val, baselines[PLAY], WindowSetting.of(gp), derive_seed(seed, WIN)
    )
    return WindowFit(model, history, time.perf_counter() - t)
