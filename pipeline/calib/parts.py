"""The forms a model takes on its way to a graph: per sensor, the plain arrays of one model (float64) in one
of four parts the export builds a graph of (`pipeline.export.graph`) and the C calibrator computes
(`pipeline.export.csource`), and a group's model as those parts with its float64 reference.

Every model of this project is *separable*: sensor s's calibrated wrench depends on sensor s's inputs only
(a foot pair's two networks are side by side; the baselines' W_s act per sensor). Each part below is
therefore one sensor's map, inputs in the order of `pipeline.calib.models` (raw wrench fx..tz N/Nm,
temperature degC, [accelerometer m/s^2, gyroscope rad/s]), output its calibrated wrench (6, N/Nm, sensor
frame). A model with memory maps a sensor's inputs and its own state (the play operators' and filters'
outputs of its previous sample) to its wrench and next state; its reference takes rows that are consecutive
samples of one log, the state starting afresh at the first (`pipeline.core.lowpass.memory_of`). A family
(`pipeline.calib.families`) says how its models are read into these forms (its ``read``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.calib.registry import family_of, kind_of

WRENCH = 6
ACTIVATIONS = (None, "relu", "leaky_relu", "tanh", "elu")  # what a graph computes (`pipeline.export.graph`)


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
    family: str  # its family's key (`pipeline.calib.registry`: raw, affine, poly, play, arx, nn, win)
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


def log_model(
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


def linear_parts(b: Any) -> tuple[LinearPart, ...]:
    """Per sensor, the `LinearPart` of a `pipeline.calib.linear.LinearBaseline` `b`."""
    return tuple(
        LinearPart(b.offset[s], b.scale[s], b.powers, b.weights[s], b.widths, b.time_constants, b.period)
        for s in range(b.weights.shape[0])
    )
