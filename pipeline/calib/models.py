"""Calibration models of one sensor group: neural networks, the thesis's switched losses, linear baselines.

A *sensor group* is what is trained together (thesis chapter 5): one FT sensor (a leg or an arm), or the
front and rear sensors of one foot, coupled by the sum of their wrenches in the sole frame. Everything
here works on arrays of shape (N, S, ...) with S = 1 or 2 sensors; nothing reads files or params.

Inputs of one sensor, in this order (thesis 5.3): raw wrench f (6: fx, fy, fz N; tx, ty, tz Nm, the
primary calibration's output) [6 inputs: a board without thermometer]; temperature T (degC) [7 inputs];
then FT-board accelerometer (3, m/s^2) and gyroscope (3, rad/s) [13 inputs]. Output: the calibrated
wrench (6, N and Nm, sensor frame).

Networks (`SensorNet`): the thesis's MLP, hidden layers of `hidden` neurons with one activation each
(default LeakyReLU then ReLU), xavier_uniform weights, a linear output layer, as the correction of a map
the physics justifies:

- The network learns a correction on top of the fitted affine map,
  ``f_cal = f_raw + A [f_raw, T] + b + c(x)``, with ``A`` (6, 7) and ``b`` (6,) the group's affine baseline
  (a buffer, fitted before the network, faithful by its virtual pushes: `pipeline.calib.pushes`). The
  output layer starts at zero, so the untrained network *is* the affine map, and where the training data
  say nothing (a leg in double support) it stays close to it instead of extrapolating from ReLU pieces.
- The correction ``c`` is Lipschitz with bound `slope` (``train.defaults.residual_slope``) in push units
  (`pipeline.calib.pushes.residual_units`: a push's force on force axes, force x lever on torque axes; a
  degree on the temperature; 10 m/s^2 and 2.5 rad/s on the IMU): its inputs are divided by those units
  (after subtracting their training mean, ``standard``, or not, ``max``), its output is ``slope`` times
  them, and every layer is 1-Lipschitz (`LipschitzLinear`: the weight divided by its spectral norm where
  that exceeds 1; the activations are 1-Lipschitz). So a change ``d`` of the raw wrench changes the
  correction by at most ``slope * |d|`` (push metric), at every scale: a push of 1 N and one of 40 N are
  reported with the affine map's slope within ``slope``, and the IMU can stand in for at most ``slope`` x
  20 N per 10 m/s^2 of the wrench. What the affine map misses and such a correction can hold is what the
  physics of a strain-gauge sensor gives (gains drifting with temperature, a nonlinearity of a few % at full
  scale); what it cannot is a projection of the reading onto the relation the training motions follow,
  which answers a small push otherwise than a large one (a memoryless model that beats the sensor's noise
  floor that way is reading a prior over the robot's motions, not the sensor). After training the layers
  are baked into plain linear layers (`SensorNet.bake`): the saved and exported network is an ordinary MLP.

Losses: `pipeline.calib.losses` (the thesis's switched losses, eqs. 5.4-5.12).

Baselines: `pipeline.calib.linear` (the affine map the networks correct, and the polynomials).
"""

from __future__ import annotations

import json
import os
import pickle
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pipeline.calib.linear import AFFINE_INPUTS, TINY_SCALE
from pipeline.calib.params import ACTIVATION_NAMES, INPUT_SIZES, NORMALISATIONS
from pipeline.calib.scores import WRENCH
from pipeline.core.errors import DataError

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "leaky_relu": nn.LeakyReLU,
    "tanh": nn.Tanh,
    "elu": nn.ELU,
}
assert tuple(ACTIVATIONS) == ACTIVATION_NAMES  # the params check them without importing torch
MODEL_SUFFIX_CONFIG = ".json"
MODEL_SUFFIX_WEIGHTS = ".pt"


# --- normalisation -------------------------------------------------------------------------------


def normalisation_constants(x: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """(offset, scale), each (F,), such that (x - offset) / scale is normalised; x (N, F) training inputs.

    ``max``: offset 0, scale max |x| per column (thesis 5.5.1). ``standard``: mean and standard deviation.
    A column that is constant (scale 0) gets scale 1, so that it passes through without dividing by 0.
    """
    x = np.asarray(x, dtype=np.float64)
    if kind == "max":
        offset = np.zeros(x.shape[1])
        scale = np.abs(x).max(axis=0) if len(x) else np.ones(x.shape[1])
    elif kind == "standard":
        offset = x.mean(axis=0) if len(x) else np.zeros(x.shape[1])
        scale = x.std(axis=0) if len(x) else np.ones(x.shape[1])
    else:
        raise ValueError(f"normalisation must be one of {NORMALISATIONS}, got {kind!r}")
    scale = np.where(scale > TINY_SCALE, scale, 1.0)
    return offset, scale


# --- networks ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NetConfig:
    """Architecture of the network of one sensor (thesis 5.5.1: 2 hidden layers of 100, LeakyReLU, ReLU)."""

    n_inputs: int  # 7 (wrench + temperature) or 13 (+ accelerometer + gyroscope)
    hidden: int = 100  # neurons per hidden layer; 64-128 is plenty for a 7 -> 6 map
    activations: tuple[str, ...] = ("leaky_relu", "relu")  # one per hidden layer, so len = number of layers
    slope: float = 0.0  # > 0: the correction's Lipschitz bound in push units (`SensorNet`); 0: unbounded

    def __post_init__(self) -> None:
        if self.n_inputs not in INPUT_SIZES:
            raise ValueError(f"n_inputs must be one of {INPUT_SIZES}, got {self.n_inputs!r}")
        if self.hidden < 1:
            raise ValueError(f"hidden must be >= 1, got {self.hidden!r}")
        object.__setattr__(self, "activations", tuple(self.activations))
        for name in self.activations:
            if name not in ACTIVATIONS:
                raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {name!r}")


class LipschitzLinear(nn.Linear):
    """A linear layer whose weight acts divided by its spectral norm where that exceeds 1: a 1-Lipschitz
    map (in the 2-norm). `bake` stores the divided weight, after which the layer is a plain linear one."""

    def effective_weight(self) -> torch.Tensor:
        norm = torch.linalg.matrix_norm(self.weight, ord=2)
        return self.weight / torch.clamp(norm, min=1.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return nn.functional.linear(x, self.effective_weight(), self.bias)

    def bake(self) -> nn.Linear:
        """The plain layer this one acts as in training (the norm's last bits depend on whether autograd
        records it: the weight is computed as a training step computes it)."""
        plain = nn.Linear(self.in_features, self.out_features, dtype=self.weight.dtype)
        with torch.enable_grad():
            weight = self.effective_weight().detach()
        with torch.no_grad():
            plain.weight.copy_(weight)
            plain.bias.copy_(self.bias)
        return plain


def mlp_layers(
    n_inputs: int, hidden: int, activations: tuple[str, ...], linear: type[nn.Linear] = LipschitzLinear
) -> nn.Sequential:
    """The MLP of a network's correction: per activation a `linear` layer of `hidden` neurons and that
    activation, then a linear layer to the 6 wrench components (the memoryless networks' `SensorNet`, the
    windowed networks' `pipeline.calib.window`)."""
    layers: list[nn.Module] = []
    width = n_inputs
    for name in activations:
        layers += [linear(width, hidden), ACTIVATIONS[name]()]
        width = hidden
    layers.append(linear(width, WRENCH))
    return nn.Sequential(*layers)


def init_mlp(mlp: nn.Sequential) -> None:
    """xavier_uniform weights, zero biases (thesis 5.5.1), from the current torch RNG state, and the output
    layer's weights zero: the correction starts at 0."""
    for module in mlp:
        if isinstance(module, nn.Linear):
            nn.init.xavier_uniform_(module.weight)
            nn.init.zeros_(module.bias)
    nn.init.zeros_(mlp[-1].weight)


class SensorNet(nn.Module):
    """Calibration network of one sensor: (B, n_inputs) raw inputs -> (B, 6) calibrated wrench (N, Nm).

    ``f = x[:, :6] + x[:, :7] @ affine_weight.T + affine_bias + out_scale * mlp((x - in_offset) / in_scale)``;
    the constants are buffers (saved in the state dict), set from the training samples with
    `set_constants` and from the affine baseline with `set_affine` (zero: the raw wrench).
    """

    def __init__(self, config: NetConfig) -> None:
        super().__init__()
        self.config = config
        linear = LipschitzLinear if config.slope > 0 else nn.Linear
        self.mlp = mlp_layers(config.n_inputs, config.hidden, config.activations, linear)
        self.register_buffer("in_offset", torch.zeros(config.n_inputs))
        self.register_buffer("in_scale", torch.ones(config.n_inputs))
        self.register_buffer("out_scale", torch.ones(WRENCH))
        self.register_buffer("affine_weight", torch.zeros(WRENCH, min(config.n_inputs, AFFINE_INPUTS)))
        self.register_buffer("affine_bias", torch.zeros(WRENCH))

    def reset_parameters(self) -> None:
        """xavier_uniform weights, zero biases (thesis 5.5.1), from the current torch RNG state; the output
        layer's weights zero too, so that the network starts as its affine map."""
        init_mlp(self.mlp)

    def set_affine(self, weight: np.ndarray, bias: np.ndarray) -> None:
        """The affine map the correction starts from: weight (6, 7) on [f_raw, T] (or (6, 6) on f_raw),
        bias (6,) (N, Nm)."""
        if tuple(np.shape(weight)) != tuple(self.affine_weight.shape):  # a wrench-only affine map
            self.register_buffer(
                "affine_weight", torch.zeros(np.shape(weight), dtype=self.affine_weight.dtype)
            )
        self.affine_weight.copy_(torch.as_tensor(np.asarray(weight), dtype=self.affine_weight.dtype))
        self.affine_bias.copy_(torch.as_tensor(np.asarray(bias), dtype=self.affine_bias.dtype))

    def bake(self) -> None:
        """Replace every Lipschitz layer by the plain layer it acts as (for saving and export)."""
        for k, module in enumerate(self.mlp):
            if isinstance(module, LipschitzLinear):
                self.mlp[k] = module.bake()

    def set_constants(self, in_offset: np.ndarray, in_scale: np.ndarray, out_scale: np.ndarray) -> None:
        for name, value in (("in_offset", in_offset), ("in_scale", in_scale), ("out_scale", out_scale)):
            buffer = getattr(self, name)
            buffer.copy_(torch.as_tensor(np.asarray(value), dtype=buffer.dtype))

    def correction(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 6) what the network adds to its affine map, N and Nm."""
        return self.out_scale * self.mlp((x - self.in_offset) / self.in_scale)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        affine = x[:, : self.affine_weight.shape[1]] @ self.affine_weight.T + self.affine_bias
        return x[:, :WRENCH] + affine + self.correction(x)


class GroupNet(nn.Module):
    """The networks of a sensor group side by side: (B, S * n_inputs) -> (B, S * 6).

    Input columns are sensor 0's inputs then sensor 1's (each in the order of the module docstring);
    output columns are sensor 0's calibrated wrench then sensor 1's.
    """

    def __init__(self, config: NetConfig, n_sensors: int) -> None:
        super().__init__()
        self.config = config
        self.nets = nn.ModuleList(SensorNet(config) for _ in range(n_sensors))

    @property
    def n_sensors(self) -> int:
        return len(self.nets)

    def reset_parameters(self) -> None:
        for net in self.nets:
            net.reset_parameters()

    def bake(self) -> None:
        for net in self.nets:
            net.bake()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = self.config.n_inputs
        return torch.cat([net(x[:, s * n : (s + 1) * n]) for s, net in enumerate(self.nets)], dim=1)

    def correction(self, x: torch.Tensor) -> torch.Tensor:
        """(B, S * 6) what the networks add to their affine maps (`SensorNet.correction`)."""
        n = self.config.n_inputs
        return torch.cat([net.correction(x[:, s * n : (s + 1) * n]) for s, net in enumerate(self.nets)], 1)


def save_model(path: str | Path, model: GroupNet, info: Mapping[str, Any] | None = None) -> None:
    """Write `model` as ``<path>.json`` (architecture + `info`) and ``<path>.pt`` (tensors only).

    The weights file is a ``torch.save`` of the state dict (a dict of tensors), readable with
    ``torch.load(weights_only=True)``: loading never executes code from the file. Written atomically.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    config = {"net": asdict(model.config), "n_sensors": model.n_sensors, **dict(info or {})}
    for suffix, write in (
        (MODEL_SUFFIX_WEIGHTS, lambda p: torch.save(model.state_dict(), p)),
        (MODEL_SUFFIX_CONFIG, lambda p: p.write_text(json.dumps(config, indent=1, sort_keys=True) + "\n")),
    ):
        final = path.with_name(path.name + suffix)
        tmp = final.with_name(f".{final.name}.{os.getpid()}.tmp")
        try:
            write(tmp)
            os.replace(tmp, final)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def load_model(path: str | Path) -> tuple[GroupNet, dict[str, Any]]:
    """Rebuild a model written by `save_model` from ``<path>.json`` and ``<path>.pt`` (weights only).

    Returns the module in eval mode and its JSON config (with the `info` given at saving: input and
    output column names, sensors, ...). Raises DataError naming the file if either file is unusable.
    """
    path = Path(path)
    config_file = path.with_name(path.name + MODEL_SUFFIX_CONFIG)
    weights_file = path.with_name(path.name + MODEL_SUFFIX_WEIGHTS)
    try:
        config = json.loads(config_file.read_text(encoding="utf-8"))
        net = config["net"]
        model = GroupNet(
            NetConfig(n_inputs=net["n_inputs"], hidden=net["hidden"], activations=tuple(net["activations"])),
            n_sensors=int(config["n_sensors"]),
        )
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{config_file}: not a model config: {exc}") from None
    try:
        state = torch.load(weights_file, map_location="cpu", weights_only=True)
        for s, net in enumerate(model.nets):  # the width of the affine map each network corrects (6 or 7)
            shape = state.get(f"nets.{s}.affine_weight", net.affine_weight).shape
            net.register_buffer("affine_weight", torch.zeros(tuple(shape), dtype=net.affine_weight.dtype))
        model.load_state_dict(state)
    except pickle.UnpicklingError:
        raise DataError(
            f"{weights_file}: holds objects other than tensors; refusing to unpickle it (weights only)"
        ) from None
    except (OSError, RuntimeError, KeyError, ValueError) as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(f"{weights_file}: cannot load weights: {first_line}") from None
    return model.eval(), config
