"""Linear models of a sensor group: the affine map the networks correct, polynomials of order 1-4, and the
affine map with play operators or low-pass filters of the raw wrench (memory).

Every model here is ``f = f_raw + W phi(x)``, linear in its parameters W, fitted in closed form on the same
switched least-squares objective as the networks (`pipeline.calib.losses`, thesis eqs. 5.4-5.12), with the
virtual pushes' prior (`pipeline.calib.pushes`): ``affine`` (phi = [f, T, 1], least squares,
the in-situ affine calibration with temperature), ``poly<n>`` (phi = every monomial up to order n of
the 7 standardised inputs, ridge; Mohamed et al. 2023 with na = nb = 0) and ``play`` (phi = the affine
features and, per raw wrench axis and play width r, the play operator's state ``z = (f_a - y) / r`` in
[-1, 1], `pipeline.core.play`: a Prandtl-Ishlinskii model of the sensor's hysteresis, least squares) and
``arx`` (phi = the affine features and, per raw wrench axis and time constant tau, the reading's departure
``f_a - y`` from its first-order low-pass y, `pipeline.core.lowpass`: a lagged linear map of the raw wrench's
history, least squares). Output axis a of a model with memory reads the states of raw axis a only.

The play and arx models have memory: a sample's features depend on the operators' outputs y of the sample
before (``memory``, (N, S, M): its first 6 K columns the play outputs, per width k and axis a column
``6 k + a``, its last 6 J the filter outputs, per time constant j and axis a, in the wrench's unit; NaN at a
fresh start, where y starts at the sample's own reading; a group's memory holds both and serves each model).
`pipeline.core.lowpass.memory_of` computes it over one log's samples in time order, each sensor's over the
samples where its wrench is finite (a missing reading neither moves nor resets the operators). A virtual push
moves the present reading with that memory held.
Arrays are (N, S, ...) over N samples and S sensors; wrenches N and Nm.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from pipeline.calib.memory import saturated
from pipeline.calib.pushes import PushPrior, linear_push_gram, push_gram
from pipeline.calib.scores import WRENCH
from pipeline.core.errors import DataError
from pipeline.core.lowpass import alphas, lowpass_features, memory_of
from pipeline.core.play import play_features

AFFINE_INPUTS = 7  # raw wrench + temperature: the inputs of the affine map and the polynomials (6 where
# a group trains on the wrench alone: `fit_linear_baseline(n_inputs=6)`, the networks' affine map then 6 wide)
TINY_SCALE = 1e-9  # a normalisation scale below this (a constant input) is replaced by 1
# the ridge of a memory model's operator columns, per sample, relative to each column's mean square: a
# column must explain more than this fraction of its own energy to earn its weight (`_memory_terms`)
MEMORY_RIDGE = 1e-3


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
    """``f_s = f_raw,s + W_s phi(x_s)`` per sensor s, phi = monomials of the standardised 7 inputs, and
    with play `widths` the play states of the raw wrench after them, with `time_constants` its departures from
    its low-pass filters after those.

    `offset`/`scale` (S, 7) standardise each sensor's inputs; `powers` (P, 7) are the monomial
    exponents (order 1: [1, f, T], the affine model); `weights` (S, 6, P [+ 6 K] [+ 6 J]) the fitted W_s;
    `widths` (K, 6) the play widths per raw axis (N, Nm), `time_constants` (J,) the filters' (s) at `period`
    (s, the training logs' sample period), None for a memoryless model.
    """

    name: str
    offset: np.ndarray
    scale: np.ndarray
    powers: np.ndarray
    weights: np.ndarray
    widths: np.ndarray | None = None
    time_constants: np.ndarray | None = None
    period: float | None = None

    @property
    def memory(self) -> bool:
        """Whether the model reads the operators' outputs of the sample before (its `memory`)."""
        return self.widths is not None or self.time_constants is not None

    @property
    def n_operators(self) -> int:
        """Operators per raw axis: K play widths and J filters."""
        return sum(len(v) for v in (self.widths, self.time_constants) if v is not None)

    def features(self, x: np.ndarray, s: int, memory: np.ndarray | None = None) -> np.ndarray:
        """(N, P [+ 6 K] [+ 6 J]) features of sensor s from its raw inputs x (N, >= 7; >= 6 for a wrench-only
        model) and, with memory, the operators' outputs before each sample (N, M >= 6 K + 6 J: the play
        outputs first, the filters' last; module docstring)."""
        k = self.offset.shape[1]  # 7, or 6 without temperature
        phi = [_monomials((x[:, :k] - self.offset[s]) / self.scale[s], self.powers)]
        if not self.memory:
            return phi[0]
        if memory is None:
            raise ValueError(f"{self.name}: a model with memory needs its operators' outputs before a sample")
        if self.widths is not None:
            phi.append(play_features(x[:, :WRENCH], memory[:, : self.widths.size], self.widths))
        if self.time_constants is not None:
            j = WRENCH * len(self.time_constants)
            gains = alphas(self.time_constants, float(self.period))
            phi.append(lowpass_features(x[:, :WRENCH], memory[:, memory.shape[1] - j :], gains))
        return np.concatenate(phi, axis=1)

    def predict(self, x: np.ndarray, memory: np.ndarray | None = None) -> np.ndarray:
        """(N, S, 6) calibrated wrenches from raw inputs x (N, S, >= 7) (with memory: and the operators'
        outputs before each sample, (N, S, M), `memory_of`)."""
        return np.stack(
            [
                x[:, s, :WRENCH]
                + self.features(x[:, s], s, None if memory is None else memory[:, s]) @ self.weights[s].T
                for s in range(x.shape[1])
            ],
            axis=1,
        )

    def predict_log(self, x: np.ndarray, period: float | None = None) -> np.ndarray:
        """(N, S, 6) calibrated wrenches of one log's samples x (N, S, >= 7) in time order, `period` s apart
        (None: the training logs' period), the memory starting afresh at its first sample (`memory_of`)."""
        return self.predict(x, memory_of(x, self.widths, self.time_constants, period or self.period))

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
        out = {
            "name": self.name,
            "model": "f = f_raw + W phi((x[:k] - offset) / scale), k = len(offset), phi = monomials (powers)",
            "offset": self.offset.tolist(),
            "scale": self.scale.tolist(),
            "powers": self.powers.tolist(),
            "weights": self.weights.tolist(),
        }
        if self.widths is not None:
            out["model"] += (
                ", then per width k and raw axis a the play state z = (f_a - y) / widths[k][a], "
                "y = clip(y before, f_a - widths[k][a], f_a + widths[k][a]) (y starts at f_a)"
            )
            out["widths"] = self.widths.tolist()
        if self.time_constants is not None:
            out["model"] += (
                ", then per time constant j and raw axis a the departure f_a - y, y = y before + alpha_j "
                "(f_a - y before), alpha_j = 1 - exp(-period / time_constants[j]) (y starts at f_a)"
            )
            out["time_constants"] = self.time_constants.tolist()
            out["period"] = self.period
        return out

    @classmethod
    def from_dict(cls, entry: Mapping[str, Any]) -> LinearBaseline:
        """Inverse of `to_dict` (KeyError, ValueError or TypeError if `entry` is not one)."""
        widths, time_constants = entry.get("widths"), entry.get("time_constants")
        return cls(
            str(entry["name"]),
            np.asarray(entry["offset"], dtype=np.float64),
            np.asarray(entry["scale"], dtype=np.float64),
            np.asarray(entry["powers"], dtype=np.int64),
            np.asarray(entry["weights"], dtype=np.float64),
            None if widths is None else np.asarray(widths, dtype=np.float64).reshape(-1, WRENCH),
            None if time_constants is None else np.asarray(time_constants, dtype=np.float64).reshape(-1),
            None if time_constants is None else float(entry["period"]),
        )


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
    widths: np.ndarray | None = None,
    memory: np.ndarray | None = None,
    time_constants: np.ndarray | None = None,
    period: float | None = None,
) -> LinearBaseline:
    """Minimise the switched loss of `switched_loss` over W in closed form (normal equations).

        J(W) = sum_i [sum_s alpha_si lambda_s |r_si - W_s phi_si|^2 + alpha_sum,i lambda_sum
               |r_sum,i - sum_s X_s W_s phi_si|^2] + ridge N sum_s |W_s without its constant column|^2
               + push.weight sum_i sum_s E_delta |W_s (phi(x_si + delta) - phi(x_si))|^2

    with r = label - raw (residuals, so ridge shrinks towards the primary calibration). Sum samples
    couple the sensors of a foot through X_s; the normal equations are then solved jointly. The last
    term is the virtual pushes' prior (`pipeline.calib.pushes`): exact for the affine model, sampled
    (seeded by `seed`) for the polynomials and the play model (a push moves the present reading, the
    memory held).

    Args:
        x: (N, S, >= 7) raw inputs; labels (N, S, 6); switches (N, S) bool; other arrays as in
            `switched_loss` (numpy). `ridge` is per sample, on standardised features.
        n_inputs: the inputs the model reads, 7 (wrench and temperature) or 6 (the wrench alone).
        widths: (K, 6) play widths per raw axis (N, Nm): the play model; time_constants (J,) s: the arx
            model's filters at `period` s; with either `memory` (N, S, M) the operators' outputs before each
            sample (`memory_of` of each sample's log; module docstring); both None: memoryless.

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
    scale = np.where(inputs.std(axis=0) > TINY_SCALE, inputs.std(axis=0), 1.0)
    powers = monomial_powers(n_inputs, order)
    model = LinearBaseline(name, offset, scale, powers, np.zeros(0), widths, time_constants, period)
    p = len(powers) + WRENCH * model.n_operators
    model.weights = np.zeros((n_sensors, WRENCH, p))
    phis = [model.features(x[:, s], s, None if memory is None else memory[:, s]) for s in range(n_sensors)]
    normal, rhs = _normal_equations(phis, x, labels, switches, lambdas)
    if use_sum:
        _add_sum_term(normal, rhs, phis, x, sum_label, alpha_sum.astype(bool), transforms, lambda_sum)
    penalty = np.tile(np.r_[0.0, np.ones(p - 1)], WRENCH * n_sensors) * ridge * n
    allowed = None
    if model.memory:
        penalty, allowed = _memory_terms(phis, switches, len(powers), model, penalty)
    normal[np.diag_indices_from(normal)] += penalty
    if push is not None and push.active:
        rng, k, eye = np.random.default_rng(seed), WRENCH * p, np.eye(WRENCH)
        for s in range(n_sensors):
            features = partial(model.features, s=s)
            if model.memory:
                gram = push_gram(features, x[:, s], push, rng, memory=memory[:, s])
            else:
                gram = linear_push_gram(features, model.powers, model.scale[s], x[:, s], push, rng)
            normal[s * k : (s + 1) * k, s * k : (s + 1) * k] += push.weight * np.kron(eye, gram)
            if push.free_lever:
                _free_lever(normal[s * k : (s + 1) * k, s * k : (s + 1) * k], gram, push.weight, model, s)
    model.weights = _solve_informed(normal, rhs, allowed).reshape(n_sensors, WRENCH, p)
    return model


def _memory_terms(
    phis: Sequence[np.ndarray], switches: np.ndarray, static: int, model: LinearBaseline, penalty: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The penalty (one per unknown, `penalty` the static features') and the allowed unknowns of a model
    with memory: each operator column pays ``MEMORY_RIDGE`` per sample times its mean square over the
    labelled samples (a scale-free ridge: a state the data barely move cannot take a weight that a fresh
    start would multiply), and output axis a reads only its own raw axis's states (`_own_axis`) of the play
    operators the labelled samples saturate (`pipeline.calib.memory.saturated`)."""
    n, p = len(switches), phis[0].shape[1]
    out, allowed = penalty.copy(), []
    for s, phi in enumerate(phis):
        rows = phi[switches[:, s]] if switches[:, s].any() else phi
        states = rows[:, static:]
        usable = np.ones(p - static, dtype=bool)
        if model.widths is not None:
            usable[: model.widths.size] = saturated(states[:, : model.widths.size])
        msq = np.mean(states**2, axis=0) if len(states) else np.zeros(p - static)
        for o in range(WRENCH):
            at = (s * WRENCH + o) * p
            out[at + static : at + p] += MEMORY_RIDGE * n * msq
        own = _own_axis(static, model.n_operators).reshape(WRENCH, p)
        own[:, static:] &= usable
        allowed.append(own.reshape(-1))
    return out, np.concatenate(allowed)


def _free_lever(block: np.ndarray, gram: np.ndarray, weight: float, model: LinearBaseline, s: int) -> None:
    """Release the lever from the virtual pushes' penalty of sensor `s` (`block`, its (6 P, 6 P) part of the
    normal matrix, in place): of the correction's torque<-force coefficients T (3, 3), T_oa = W[3 + o, j_a] /
    scale_a with j_a the linear feature of raw force axis a (Nm/N = m), only the symmetric part pays.

    The antisymmetric part is a cross product, ``T f = -d x f``: the sensor's torque reference point moved by
    d (m). A sensor's origin is wherever its gauges and mounting put it (the simulated sensors' `lever_m`,
    up to 8 mm), and the labels see it wherever a force varies; it cannot rebuild a force from a torque nor
    cancel a torque's noise on a limb's relation, so a push is reported exactly once d is right. Penalised,
    it was half learned where the labels' forces vary little (an iCub 2.x foot sensor's sideways forces): a
    push at its sole, 1.2 cm below it, then read 0.2-0.6 of its torque about the vertical axis.
    """
    linear = {int(np.argmax(row)): j + 1 for j, row in enumerate(model.powers[1:]) if row.sum() == 1}
    if not all(a in linear for a in range(3)):
        return
    p = gram.shape[0]
    cols = [linear[a] for a in range(3)]
    scale = model.scale[s][:3]
    # the penalty's weight per coefficient in physical units (h I on T), from the gram's force diagonal
    h = weight * float(np.mean(np.diag(gram)[cols] * scale**2))
    idx = np.array([(3 + o) * p + cols[a] for o in range(3) for a in range(3)])
    swap = np.array([3 * a + o for o in range(3) for a in range(3)])  # (o, a) -> (a, o)
    sym = (np.eye(9) + np.eye(9)[swap]) / 2  # vec(T) -> vec of its symmetric part (a projector)
    d = 1.0 / np.tile(scale, 3)  # T = W / scale
    block[np.ix_(idx, idx)] -= weight * np.kron(np.eye(3), gram[np.ix_(cols, cols)])
    block[np.ix_(idx, idx)] += h * (d[:, None] * sym * d[None, :])


def _own_axis(static: int, n_operators: int) -> np.ndarray:
    """(6 (static + 6 K),) bool, one sensor's unknowns row-major (output axis, feature): every static feature,
    and of the K operators' states (play, filters) only those of the output's own raw axis. A sensor's
    hysteresis is per axis (the simulated sensors': h_a play(v_a), v = C w), so its own axis's states
    model it; another axis's wide operator is near linear in that axis over motions narrower than it and
    would stand in for a static coupling that the virtual pushes (memory held) do not see. Measured on the
    default data with every axis's states allowed: l_foot_front_ft's ty read 0.41 Nm per unit of fx's 90 N
    state, which took 0.25 off its ty slope at the 10-40 N pushes of a later day (Test D failed); with its
    own axis only, every foot sensor passed and the headlines' error against the truth fell (0.776 ->
    0.745 Nm/N pooled, l_foot)."""
    axis = np.tile(np.arange(WRENCH), n_operators)  # the raw axis of each operator's state
    rows = [np.r_[np.ones(static, dtype=bool), axis == o] for o in range(WRENCH)]
    return np.concatenate(rows)


def _normal_equations(
    phis: Sequence[np.ndarray],
    x: np.ndarray,
    labels: np.ndarray,
    switches: np.ndarray,
    lambdas: Sequence[float],
) -> tuple[np.ndarray, np.ndarray]:
    """(normal matrix, right-hand side) of the sensors' own terms of `fit_linear_baseline`, unknowns per
    sensor W_s (6, P) flattened row-major (output axis, feature)."""
    n_sensors, p = len(phis), phis[0].shape[1]
    k = WRENCH * p
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
    return normal, rhs


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


def _solve_informed(normal: np.ndarray, rhs: np.ndarray, allowed: np.ndarray | None = None) -> np.ndarray:
    """The normal equations' solution; unknowns that no sample informs (e.g. a foot sensor with neither
    part nor sum labels), or not `allowed` (bool, one per unknown), stay 0."""
    informed = np.abs(normal).sum(axis=1) > 0
    if allowed is not None:
        informed &= allowed
    solution = np.zeros(len(rhs))
    sub = normal[np.ix_(informed, informed)]
    try:
        solution[informed] = np.linalg.solve(sub, rhs[informed])
    except np.linalg.LinAlgError:
        solution[informed] = np.linalg.lstsq(sub, rhs[informed], rcond=None)[0]
    return solution
