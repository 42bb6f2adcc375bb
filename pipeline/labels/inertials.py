"""The robot's inertial parameters identified from the FT sensors, jointly with a model of each sensor.

Every label is the wrench the URDF predicts; a real robot's URDF is off (CAD masses, cables, covers), and
the labels carry its errors. The readings on exact-label samples tell them apart from the sensor's own
distortion. For the links' inertial parameters ``pi`` (10 per link, `pipeline.physics.regressor`), the
reading of sensor s on an exact sample is modelled as

    reading_s - label_s = Y_s (pi - pi_urdf) + W_s phi(label_s, T_s, plays_s) + noise

``Y_s`` the reading regressor (`ReadingRegressor`): the label's change with the parameters; ``phi`` the
sensor model per output axis (`features`): the wrench (gain, coupling and the torque's lever), its
temperature, a constant (the offset), the wrench times the temperature (the gain's drift), the own axis'
quadratic term, and the play operators' states of the reading (its hysteresis, as the training's play
model). The model is fed the label, not the reading: a map fitted on the reading would shrink the masses and
itself together. Known loads are part of the labels they come with: their wrench is known exactly, which
fixes the scale a link's mass and a sensor's gain share on gravity alone.

Every unknown has a Gaussian prior (`link_prior`, `feature_prior`: the URDF's parameters, a factory
calibration's error), the data a weight per sample (`IdentifyParams.weight`: the samples of a log are
strongly correlated, so each counts for much less than an independent one); the estimate is the posterior
mean, its covariance the posterior's. Where the data say little, the estimate stays at the URDF's value.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.core.play import play_features, play_memory
from pipeline.labels.table import experiment_gravity
from pipeline.logs import schema as S
from pipeline.logs.tables import read_table_metadata
from pipeline.physics.dynamics import ContactCase
from pipeline.physics.regressor import PARAMS, ReadingRegressor, entries, skew, sym
from pipeline.physics.robot import RobotModel

UNITS = np.r_[np.full(3, 20.0), np.full(3, 4.0)]  # N, Nm: the features' unit per axis
BASE_FEATURES = 15  # per output axis: wrench (6), temperature, 1, wrench x temperature (6), quadratic; plays
# the sensor models: their columns among the first BASE_FEATURES, and whether the plays join them
SENSOR_MODELS = {
    "offset": ([7], False),
    "affine": ([*range(6), 7], False),
    "hysteresis": ([7], True),
    "full": (list(range(BASE_FEATURES)), True),
}
TORQUE_SD = 0.05  # Nm: a torque residual weighs as a force residual of 1 N over this
# prior sd per feature block, x the output axis' unit: gain/coupling, lever, temperature, gain drift,
# quadratic, play; the constant (offset) is free. Wide: 2.5 x a factory calibration's usual error (gain 3 %,
# coupling 2 %, lever 1 cm), so a sensor distorted twice as much is still the sensor's and not a mass (with
# the usual errors as the sds, labels against truth on the distortion variant of benchmarks/variant.py grew
# from 0.06 to 0.30 on l_arm_ft and from 0.06 to 0.13 on the feet; with these they stay within 0.02)
PRIOR_SD = {
    "gain": 0.075,
    "coupling": 0.05,
    "lever": 0.025,
    "t": 0.625,
    "zt": 0.025,
    "quad": 0.125,
    "play": 0.2,
}
MASS_SD, COM_SD_M = 0.10, 0.02  # prior sd of a link's mass (x its mass) and centre of mass (m)
REGRESSOR_BATCH = 500  # samples per call of the reading regressor


def features(wrench: np.ndarray, temperature: np.ndarray, plays: np.ndarray, axis: int) -> np.ndarray:
    """(N, BASE_FEATURES + K) sensor-model features of output `axis` from wrench (N, 6) N/Nm, temperature
    (N,) degC, plays (N, 6, K) (the play operators' states z in [-1, 1] of the reading)."""
    z, t = wrench / UNITS, (temperature - 30.0) / 10.0
    own = z[:, axis] * np.abs(z[:, axis]) / 20.0
    return np.column_stack([z, t, np.ones(len(z)), z * t[:, None], own, plays[:, axis, :]])


def feature_prior(axis: int, plays: int) -> np.ndarray:
    """(BASE_FEATURES + plays,) prior precision of output `axis`' feature coefficients (residual units)."""
    u = UNITS[axis]
    sd = np.empty(BASE_FEATURES + plays)
    for j in range(6):
        if (axis < 3) == (j < 3):
            sd[j] = (PRIOR_SD["gain"] if j == axis else PRIOR_SD["coupling"]) * u
        else:
            sd[j] = PRIOR_SD["lever"] * UNITS[0] if axis >= 3 else PRIOR_SD["coupling"] * UNITS[3]
    sd[6], sd[7], sd[8:14] = PRIOR_SD["t"] * u, 1e4, PRIOR_SD["zt"] * u
    sd[14], sd[15:] = PRIOR_SD["quad"] * u, PRIOR_SD["play"] * u
    return 1.0 / sd**2


def sensor_columns(model: str, n_features: int) -> list[int]:
    """The feature columns of sensor model `model` (`SENSOR_MODELS`) among `n_features`."""
    static, plays = SENSOR_MODELS[model]
    return [*static, *range(BASE_FEATURES, n_features)] if plays else static


FREE = 4  # per link: the mass and the first moment; the rotational inertia about the centre of mass stays


def link_basis(pi: np.ndarray) -> np.ndarray:
    """(10 L, 4 L) the directions of each link's mass and first moment ``h = m c`` (kg, kg m) with its
    rotational inertia about the centre of mass held: the inertia about the link frame's origin,
    ``I_o = I_c + S(h)^T S(h) / m``, follows to first order. The slow motions of calibration logs barely
    excite the rotational inertia, and holding it keeps every identified link physical where the URDF's is.
    `pi` (10 L,): the links' parameters in Pinocchio's order (`pipeline.physics.regressor`)."""
    links = pi.reshape(-1, PARAMS)
    out = np.zeros((len(pi), FREE * len(links)))
    for k, p in enumerate(links):
        m, h = p[0], p[1:4]
        sh = skew(h)
        block = out[PARAMS * k : PARAMS * (k + 1), FREE * k : FREE * (k + 1)]
        block[0, 0] = 1.0
        block[4:, 0] = entries(-sh.T @ sh / m**2)
        for a in range(3):
            se = skew(np.eye(3)[a])
            block[1 + a, 1 + a] = 1.0
            block[4:, 1 + a] = entries((se.T @ sh + sh.T @ se) / m)
    return out


def with_change(pi: np.ndarray, change: np.ndarray) -> np.ndarray:
    """(10 L,) the links' parameters `pi` (10 L,) with their masses and first moments changed by `change`
    (4 L,, `link_basis`) and each link's rotational inertia about its centre of mass kept exactly: the same
    first-order change as ``pi + link_basis(pi) @ change``, physical wherever `pi` is and the mass stays
    positive."""
    out = np.array(pi, dtype=float).reshape(-1, PARAMS)
    for k, p in enumerate(out):
        m, h = p[0], p[1:4]
        sh = skew(h)
        i_c = sym(p[4:]) - sh.T @ sh / m
        m2, h2 = m + change[FREE * k], h + change[FREE * k + 1 : FREE * (k + 1)]
        sh2 = skew(h2)
        out[k] = np.r_[m2, h2, entries(i_c + sh2.T @ sh2 / m2)] if m2 > 0 else np.r_[m2, h2, p[4:]]
    return out.reshape(-1)


def link_prior(pi: np.ndarray) -> np.ndarray:
    """(4 L,) prior precision of each link's mass and first moment (`link_basis`) around the URDF's `pi`
    (10 L,): sd MASS_SD of the mass, COM_SD_M of the centre of mass."""
    out = []
    for p in pi.reshape(-1, PARAMS):
        m, c = p[0], p[1:4] / p[0]
        first = np.sqrt((MASS_SD * m * c) ** 2 + (m * COM_SD_M) ** 2)
        out.append(1.0 / np.r_[MASS_SD * m, first] ** 2)
    return np.concatenate(out)


def prior_precision(pi: np.ndarray, cols: list[int], n_plays: int, n_sensors: int) -> np.ndarray:
    """(4 L + S 6 len(cols),) the prior precision of every unknown in `normal_equations`' order: the links'
    masses and first moments around the URDF's `pi` (10 L,), then per sensor and axis the coefficients of
    the features `cols` (with `n_plays` play operators)."""
    sensor = np.concatenate([feature_prior(a, n_plays)[cols] for a in range(6)])
    return np.r_[link_prior(pi), np.tile(sensor, n_sensors)]


@dataclass(frozen=True)
class Sources:
    """Where one log's tables are: the smoothed (joint states), the labelled, and for simulated logs the
    ingested folder holding ``<log>.truth.parquet`` (None: no truth)."""

    smoothed: Path
    labelled: Path
    ingested: Path | None = None


class ExactSamples:
    """One labelled log's exact samples (every `step`-th): readings, labels, temperatures, the play states
    of the reading, and the reading regressor ``Y`` (n, S, 6, B) of the parameter directions `basis`
    (10 L, B), or of every parameter of `links` (B = 10 L) for None. ``sw`` (n, S): the sample is exact for
    the sensor. `reading`: S.FT (the raw reading) or a column kind of the truth table (S.TRUE, S.ORACLE)."""

    def __init__(
        self,
        src: Sources,
        stem: str,
        robot: RobotModel,
        links: list[str],
        *,
        gravity: float,
        step: int,
        widths: np.ndarray,
        basis: np.ndarray | None = None,
        reading: str = S.FT,
    ) -> None:
        table = src.labelled / f"{stem}{S.PARQUET_SUFFIX}"
        lab = pd.read_parquet(table)
        sm = pd.read_parquet(src.smoothed / f"{stem}{S.PARQUET_SUFFIX}")
        self.experiment = read_table_metadata(table).get("ftcal.experiment") or {}
        grav = experiment_gravity(table, self.experiment, gravity)
        q, dq, ddq = (sm[S.joint_cols(k, robot.joint_names)].to_numpy() for k in (S.QS, S.DQS, S.DDQS))
        self.sensors = list(robot.sensors)
        sw = np.column_stack([lab[S.switch_col(s)].to_numpy() for s in self.sensors]).astype(bool)
        rows = np.flatnonzero(sw.any(1) & np.isfinite(q).all(1) & np.isfinite(ddq).all(1))[::step]
        self.sw = sw[rows]
        truth = None
        if src.ingested is not None and (src.ingested / f"{stem}.truth{S.PARQUET_SUFFIX}").is_file():
            truth = pd.read_parquet(src.ingested / f"{stem}.truth{S.PARQUET_SUFFIX}").set_index(S.STAMP)
            truth = truth.reindex(lab[S.STAMP].to_numpy())

        def stack(frame: pd.DataFrame, kind: str, at: np.ndarray | slice = rows) -> np.ndarray:
            return np.stack([frame[S.wrench_cols(kind, s)].to_numpy()[at] for s in self.sensors], 1)

        self.label = stack(lab, S.EXPECTED)
        self.true = stack(truth, S.TRUE) if truth is not None else None
        if reading != S.FT and truth is None:
            raise ValueError(f"{stem}: reading {reading!r} needs the log's truth table")
        whole = stack(lab if reading == S.FT else truth, reading, slice(None))  # (N, S, 6)
        self.raw = whole[rows]
        self.temp = np.stack([lab[S.temperature_col(s)].to_numpy()[rows] for s in self.sensors], 1)
        self.plays = np.zeros((len(rows), len(self.sensors), 6, len(widths)))  # (n, S, 6, K)
        if len(widths):  # the play states of the reading over the whole log in time order, as the training's
            memory = play_memory(whole, widths)
            for k in range(len(self.sensors)):
                z = play_features(whole[:, k], memory[:, k], widths)[rows]  # (n, 6 K): column 6 j + axis
                self.plays[:, k] = z.reshape(len(rows), len(widths), 6).transpose(0, 2, 1)
        size = PARAMS * len(links) if basis is None else basis.shape[1]
        self.Y = np.zeros((len(rows), len(self.sensors), 6, size))
        contacts, fixed = lab[S.CONTACTS].to_numpy()[rows], lab[S.FIXED_LINK].to_numpy()[rows]
        for key in sorted(set(zip(contacts, fixed, strict=True))):
            at = np.flatnonzero((contacts == key[0]) & (fixed == key[1]))
            reg = ReadingRegressor(robot, ContactCase.make(key[0].split(","), key[1], grav), links)
            for a in range(0, len(at), REGRESSOR_BATCH):
                r = at[a : a + REGRESSOR_BATCH]
                y = reg(q[rows[r]], dq[rows[r]], ddq[rows[r]])
                self.Y[r] = y if basis is None else y @ basis

    @property
    def known_loads(self) -> bool:
        """Whether the experiment hangs known loads on the robot (their wrench is part of the labels)."""
        return self.experiment.get("loads", "") not in ("", "[]")


def normal_equations(log: ExactSamples, cols: list[int]) -> tuple[np.ndarray, np.ndarray, float, int]:
    """(K, K), (K,), b'b, n: the log's weighted normal equations of the forward model, K = B + S 6 len(cols)
    (the parameter changes, then per sensor and axis the coefficients of the features `cols`), the weighted
    sum of its squared targets and their number (what its residual's variance needs)."""
    n_s, n_y, f = len(log.sensors), log.Y.shape[3], len(cols)
    h, g = np.zeros((n_y + n_s * 6 * f,) * 2), np.zeros(n_y + n_s * 6 * f)
    bb, count = 0.0, 0
    for k in range(n_s):
        use = log.sw[:, k] & np.isfinite(log.raw[:, k]).all(1) & np.isfinite(log.temp[:, k])
        if not use.any():
            continue
        for a in range(6):
            w2 = 1.0 if a < 3 else 1.0 / TORQUE_SD**2
            idx = np.r_[np.arange(n_y), n_y + (k * 6 + a) * f + np.arange(f)]
            phi = features(log.label[use, k], log.temp[use, k], log.plays[use, k], a)[:, cols]
            x = np.column_stack([log.Y[use, k, a], phi])
            b = log.raw[use, k, a] - log.label[use, k, a]
            h[np.ix_(idx, idx)] += w2 * x.T @ x
            g[idx] += w2 * x.T @ b
            bb, count = bb + w2 * float(b @ b), count + len(b)
    return h, g, bb, count


@dataclass(frozen=True)
class Posterior:
    """The identification's posterior: ``delta`` (P,) the parameters' change from the URDF's, ``cov``
    (P, P) its covariance, ``loo`` (logs, P) the leave-one-log-out estimates, ``prior_sd`` (P,)."""

    delta: np.ndarray
    cov: np.ndarray
    loo: np.ndarray
    prior_sd: np.ndarray


Equations = tuple[np.ndarray, np.ndarray, float, int]  # one log's `normal_equations`


def log_weights(eqs: list[Equations], prior: np.ndarray, weight: float) -> np.ndarray:
    """(logs,) each log's sample weight: `weight` x the median of the logs' residual variances over its own,
    from a first solve with `weight` everywhere. A log the model fits worse (walking: accelerations the
    smoothing lags behind the steps, a systematic error) weighs less, instead of pulling the masses."""
    h = sum(e[0] for e in eqs)
    theta = np.linalg.solve(weight * h + np.diag(prior), weight * sum(e[1] for e in eqs))
    var = np.array([max(e[2] - 2 * theta @ e[1] + theta @ e[0] @ theta, 1e-12) / max(e[3], 1) for e in eqs])
    return weight * np.median(var) / var


def solve(
    eqs: list[Equations],
    prior: np.ndarray,
    n_p: int,
    weights: np.ndarray,
    pinned: np.ndarray | None = None,
) -> Posterior:
    """The posterior of the first `n_p` unknowns (the parameters' changes), from per-log normal equations
    `eqs` (`normal_equations`), the prior precision `prior` (K,) of every unknown and each log's sample
    weight `weights` (logs,). `pinned` (n_p,) bool: the parameters held at the URDF's values (their prior
    made stiff)."""
    prior = np.array(prior, dtype=float)
    if pinned is not None:
        prior[:n_p][pinned] = 1e12 * np.maximum(prior[:n_p][pinned], 1.0)
    h = sum(w * e[0] for w, e in zip(weights, eqs, strict=True))
    g = sum(w * e[1] for w, e in zip(weights, eqs, strict=True))
    cov = np.linalg.inv(h + np.diag(prior))
    loo = [
        np.linalg.solve(h - w * e[0] + np.diag(prior), g - w * e[1])
        for w, e in zip(weights, eqs, strict=True)
    ]
    return Posterior(
        delta=(cov @ g)[:n_p],
        cov=cov[:n_p, :n_p],
        loo=np.array([x[:n_p] for x in loo]).reshape(len(eqs), n_p),
        prior_sd=1.0 / np.sqrt(prior[:n_p]),
    )


__all__ = [
    "BASE_FEATURES",
    "SENSOR_MODELS",
    "ExactSamples",
    "Posterior",
    "Sources",
    "feature_prior",
    "features",
    "FREE",
    "link_basis",
    "link_prior",
    "log_weights",
    "with_change",
    "normal_equations",
    "prior_precision",
    "sensor_columns",
    "solve",
]
