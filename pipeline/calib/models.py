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

Baselines (`LinearBaseline`): the same switched least-squares objective with a model linear in its
parameters, ``f = f_raw + W phi(x)``, fitted in closed form: ``affine`` (phi = [f, T, 1], least squares,
the in-situ affine calibration with temperature) and ``poly<n>`` (phi = every monomial up to order n of
the 7 standardised inputs, ridge; Mohamed et al. 2023 with na = nb = 0).
"""

from __future__ import annotations

import itertools
import json
import os
import pickle
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pipeline.calib.params import ACTIVATION_NAMES, INPUT_SIZES, NORMALISATIONS
from pipeline.calib.pushes import PushPrior, linear_push_gram
from pipeline.calib.scores import WRENCH
from pipeline.core.errors import DataError

AFFINE_INPUTS = 7  # raw wrench + temperature: the inputs of the affine map and the polynomials (6 where
# a group trains on the wrench alone: `fit_linear_baseline(n_inputs=6)`, the networks' affine map then 6 wide)
ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "leaky_relu": nn.LeakyReLU,
    "tanh": nn.Tanh,
    "elu": nn.ELU,
}
assert tuple(ACTIVATIONS) == ACTIVATION_NAMES  # the params check them without importing torch
MODEL_SUFFIX_CONFIG = ".json"
MODEL_SUFFIX_WEIGHTS = ".pt"
_TINY = 1e-9  # a normalisation scale below this (a constant input) is replaced by 1


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
    scale = np.where(scale > _TINY, scale, 1.0)
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


class SensorNet(nn.Module):
    """Calibration network of one sensor: (B, n_inputs) raw inputs -> (B, 6) calibrated wrench (N, Nm).

    ``f = x[:, :6] + x[:, :7] @ affine_weight.T + affine_bias + out_scale * mlp((x - in_offset) / in_scale)``;
    the constants are buffers (saved in the state dict), set from the training samples with
    `set_constants` and from the affine baseline with `set_affine` (zero: the raw wrench).
    """

    def __init__(self, config: NetConfig) -> None:
        super().__init__()
        self.config = config
        layers: list[nn.Module] = []
        width = config.n_inputs
        linear = LipschitzLinear if config.slope > 0 else nn.Linear
        for name in config.activations:
            layers += [linear(width, config.hidden), ACTIVATIONS[name]()]
            width = config.hidden
        layers.append(linear(width, WRENCH))
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("in_offset", torch.zeros(config.n_inputs))
        self.register_buffer("in_scale", torch.ones(config.n_inputs))
        self.register_buffer("out_scale", torch.ones(WRENCH))
        self.register_buffer("affine_weight", torch.zeros(WRENCH, min(config.n_inputs, AFFINE_INPUTS)))
        self.register_buffer("affine_bias", torch.zeros(WRENCH))

    def reset_parameters(self) -> None:
        """xavier_uniform weights, zero biases (thesis 5.5.1), from the current torch RNG state; the output
        layer's weights zero too, so that the network starts as its affine map."""
        for module in self.mlp:
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
                nn.init.zeros_(module.bias)
        nn.init.zeros_(self.mlp[-1].weight)

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


# --- linear baselines ----------------------------------------------------------------------------


def monomial_powers(n_vars: int, order: int) -> np.ndarray:
    """(P, n_vars) exponents of every monomial of total degree <= order, constant first, by degree."""
    rows = [np.zeros(n_vars, dtype=np.int64)]
    for degree in range(1, order + 1):
        for combo in itertools.combinations_with_replacement(range(n_vars), degree):
            row = np.zeros(n_vars, dtype=np.int64)
            np.add.at(row, list(combo), 1)
            rows.append(row)
    return np.array(rows)


def _monomials(z: np.ndarray, powers: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """(N, P) products z^powers for z (N, V) and powers (P, V), by repeated multiplication (exact).

    Each product is ``1 * z_0 ... z_0 * z_1 ...`` in ascending variable order, one factor at a time;
    a monomial is computed as the one of its powers less the last factor times that factor (the same
    products, each computed once instead of once per monomial containing it), `chunk` samples at a time.
    """
    z = np.asarray(z, dtype=np.float64)
    plan = _monomial_plan(powers)
    out = np.empty((len(z), len(powers)))
    rows = np.empty((len(plan), min(chunk, len(z))))  # one monomial per row: contiguous products
    for first in range(0, len(z), chunk):
        part = z[first : first + chunk].T
        m = part.shape[1]
        for j, base, v in plan:
            if v < 0:
                rows[j, :m] = 1.0
            else:
                np.multiply(rows[base, :m] if base >= 0 else 1.0, part[v], out=rows[j, :m])
        out[first : first + m] = rows[: len(powers), :m].T
    return out


def _monomial_plan(powers: np.ndarray) -> list[tuple[int, int, int]]:
    """How `_monomials` builds each product: (row, row of the powers less the last factor or -1 for the
    constant 1, that factor's variable or -1 for the constant itself), in an order where every base comes
    first; prefixes that are not among `powers` get rows after them."""
    index = {tuple(int(k) for k in p): j for j, p in enumerate(powers)}
    plan: list[tuple[int, int, int]] = []
    done: set[tuple[int, ...]] = set()

    def build(p: tuple[int, ...]) -> int:
        if p not in index:
            index[p] = len(index)
        if p not in done:
            nonzero = [v for v, k in enumerate(p) if k]
            if not nonzero:
                plan.append((index[p], -1, -1))
            else:
                last = nonzero[-1]
                less = p[:last] + (p[last] - 1,) + p[last + 1 :]
                base = -1 if not any(less) else build(less)
                plan.append((index[p], base, last))
            done.add(p)
        return index[p]

    for p in powers:
        build(tuple(int(k) for k in p))
    return plan


@dataclass
class LinearBaseline:
    """``f_s = f_raw,s + W_s phi(x_s)`` per sensor s, phi = monomials of the standardised 7 inputs.

    `offset`/`scale` (S, 7) standardise each sensor's inputs; `powers` (P, 7) are the monomial
    exponents (order 1: [1, f, T], the affine model); `weights` (S, 6, P) the fitted W_s.
    """

    name: str
    offset: np.ndarray
    scale: np.ndarray
    powers: np.ndarray
    weights: np.ndarray

    def features(self, x: np.ndarray, s: int) -> np.ndarray:
        """(N, P) features of sensor s from its raw inputs x (N, >= 7; >= 6 for a wrench-only model)."""
        k = self.offset.shape[1]  # 7, or 6 without temperature
        return _monomials((x[:, :k] - self.offset[s]) / self.scale[s], self.powers)

    def predict(self, x: np.ndarray) -> np.ndarray:
        """(N, S, 6) calibrated wrenches from raw inputs x (N, S, >= 7)."""
        return np.stack(
            [x[:, s, :WRENCH] + self.features(x[:, s], s) @ self.weights[s].T for s in range(x.shape[1])],
            axis=1,
        )

    def affine_map(self, s: int) -> tuple[np.ndarray, np.ndarray]:
        """Sensor s's model as ``f_raw + weight @ x[:7] + bias``: (weight (6, 7), bias (6,)); order 1 only."""
        k = self.offset.shape[1]
        if len(self.powers) != k + 1 or self.powers.sum(axis=1).max() > 1:
            raise ValueError(f"{self.name}: not an affine model (monomials of order > 1)")
        w = self.weights[s]  # columns: constant, then z_v = (x_v - offset_v) / scale_v in input order
        order = np.argmax(self.powers[1:], axis=1)  # which input each linear column multiplies
        weight = np.zeros((WRENCH, k))
        weight[:, order] = w[:, 1:] / self.scale[s][order]
        bias = w[:, 0] - weight @ self.offset[s]
        return weight, bias

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "model": "f = f_raw + W phi((x[:k] - offset) / scale), k = len(offset), phi = monomials (powers)",
            "offset": self.offset.tolist(),
            "scale": self.scale.tolist(),
            "powers": self.powers.tolist(),
            "weights": self.weights.tolist(),
        }


def fit_linear_baseline(
    name: str,
    x: np.ndarray,
    labels: np.ndarray,
    switches: np.ndarray,
    order: int,
    ridge: float,
    lambdas: Sequence[float],
    sum_label: np.ndarray | None = None,
    alpha_sum: np.ndarray | None = None,
    transforms: np.ndarray | None = None,
    lambda_sum: float = 1.0,
    n_inputs: int = AFFINE_INPUTS,
    push: PushPrior | None = None,
    seed: int = 0,
) -> LinearBaseline:
    """Minimise the switched loss of `switched_loss` over W in closed form (normal equations).

        J(W) = sum_i [sum_s alpha_si lambda_s |r_si - W_s phi_si|^2 + alpha_sum,i lambda_sum
               |r_sum,i - sum_s X_s W_s phi_si|^2] + ridge N sum_s |W_s without its constant column|^2
               + push.weight sum_i sum_s E_delta |W_s (phi(x_si + delta) - phi(x_si))|^2

    with r = label - raw (residuals, so ridge shrinks towards the primary calibration). Sum samples
    couple the sensors of a foot through X_s; the normal equations are then solved jointly. The last
    term is the virtual pushes' prior (`pipeline.calib.pushes`): exact for the affine model, sampled
    (seeded by `seed`) for the polynomials.

    Args:
        x: (N, S, >= 7) raw inputs; labels (N, S, 6); switches (N, S) bool; other arrays as in
            `switched_loss` (numpy). `ridge` is per sample, on standardised features.
        n_inputs: the inputs the model reads, 7 (wrench and temperature) or 6 (the wrench alone).

    Raises:
        DataError: no sample has a switch set.
    """
    x = np.asarray(x, dtype=np.float64)
    n, n_sensors = x.shape[:2]
    use_sum = sum_label is not None and alpha_sum is not None and transforms is not None and alpha_sum.any()
    if not switches.any() and not use_sum:
        raise DataError(f"{name}: no training sample with an exact label")
    inputs = x[:, :, :n_inputs]
    offset = inputs.mean(axis=0)
    scale = np.where(inputs.std(axis=0) > _TINY, inputs.std(axis=0), 1.0)
    powers = monomial_powers(n_inputs, order)
    model = LinearBaseline(name, offset, scale, powers, np.zeros((n_sensors, WRENCH, len(powers))))
    phis = [model.features(x[:, s], s) for s in range(n_sensors)]
    p = len(powers)
    k = WRENCH * p  # unknowns per sensor: W_s flattened row-major (output axis, feature)
    normal = np.zeros((n_sensors * k, n_sensors * k))
    rhs = np.zeros(n_sensors * k)
    eye = np.eye(WRENCH)
    for s in range(n_sensors):
        rows = switches[:, s]
        if rows.any():
            phi, r = phis[s][rows], (labels[rows, s] - x[rows, s, :WRENCH])
            # row-major vec: W phi = (I6 kron phi^T) vec(W)
            normal[s * k : (s + 1) * k, s * k : (s + 1) * k] += lambdas[s] * np.kron(eye, phi.T @ phi)
            rhs[s * k : (s + 1) * k] += lambdas[s] * (r.T @ phi).reshape(-1)
    if use_sum:
        _add_sum_term(normal, rhs, phis, x, sum_label, alpha_sum.astype(bool), transforms, lambda_sum)
    penalty = np.tile(np.r_[0.0, np.ones(p - 1)], WRENCH * n_sensors) * ridge * n
    normal[np.diag_indices_from(normal)] += penalty
    if push is not None and push.active:
        rng = np.random.default_rng(seed)
        for s in range(n_sensors):
            features = partial(model.features, s=s)
            gram = linear_push_gram(features, model.powers, model.scale[s], x[:, s], push, rng)
            normal[s * k : (s + 1) * k, s * k : (s + 1) * k] += push.weight * np.kron(eye, gram)
    model.weights = _solve_informed(normal, rhs).reshape(n_sensors, WRENCH, p)
    return model


def _add_sum_term(
    normal: np.ndarray,
    rhs: np.ndarray,
    phis: Sequence[np.ndarray],
    x: np.ndarray,
    sum_label: np.ndarray,
    rows: np.ndarray,
    transforms: np.ndarray,
    lambda_sum: float,
) -> None:
    """Add the sum term of `fit_linear_baseline` (samples `rows`) to its normal equations, in place."""
    k = len(rhs) // len(phis)
    r = sum_label[rows] - np.einsum("sij,nsj->ni", transforms, x[rows, :, :WRENCH])
    phis = [phi[rows] for phi in phis]
    for s, phi_s in enumerate(phis):
        # X_s W_s phi = (X_s kron phi^T) vec(W_s)
        rhs[s * k : (s + 1) * k] += lambda_sum * (transforms[s].T @ r.T @ phi_s).reshape(-1)
        for t, phi_t in enumerate(phis):
            block = np.kron(transforms[s].T @ transforms[t], phi_s.T @ phi_t)
            normal[s * k : (s + 1) * k, t * k : (t + 1) * k] += lambda_sum * block


def _solve_informed(normal: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The normal equations' solution; unknowns that no sample informs (e.g. a foot sensor with neither
    part nor sum labels) stay 0."""
    informed = np.abs(normal).sum(axis=1) > 0
    solution = np.zeros(len(rhs))
    sub = normal[np.ix_(informed, informed)]
    try:
        solution[informed] = np.linalg.solve(sub, rhs[informed])
    except np.linalg.LinAlgError:
        solution[informed] = np.linalg.lstsq(sub, rhs[informed], rcond=None)[0]
    return solution
