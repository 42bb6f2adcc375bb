"""Re-zeroing a deployed calibration: each sensor's raw-side offset change, from still stretches of logs.

Model. The export's calibration f_s of sensor s maps its raw inputs x (wrench N/Nm, temperature, IMU) to
a wrench. Since training, the reading's offset has moved by delta_s (6,): f_s(x - delta_s) is what the
calibration would report with the offset it was trained with. It is nonlinear, so the change belongs in
front of it, on the raw reading, not after it. Over a still stretch with exact labels:

- a sensor with its own exact label L_s: ``f_s(x_i - delta_s) = L_s,i``;
- a cut set C whose sum is exact (both legs in double support, a foot pair...: docs/labels.md):
  ``sum_{s in C} T_s,i f_s(x_i - delta_s) = L_C,i`` (``T_s = sign_s frame_X_s``, `pipeline.physics.cuts`).

Every such equation over every sample, each axis divided by its noise (the raw readings' std over the
stretch, carried through the T_s for a sum), is solved for the deltas by Gauss-Newton: the Jacobian of
f_s at ``x_i - delta_s`` by central differences of the float64 graph (12 calls per group, all samples
at once; the networks are piecewise linear, so a difference is the derivative), a few iterations, each
step halved until the squared error decreases.

What a stretch determines. A sum constrains the sum of its members' offsets only: standing on both feet
the legs and feet have sums alone, and moving weight from one foot to the other (or from a foot's rear
sensor to its front one) changes none of them. The directions the labels determine are the row space of
the equations with f_s the identity: the structure of the labels, not the networks' slopes (whose small
differences between sensors would pass for information). Every step stays in that space; along the
others the deltas keep the prior's value, zero (the calibration as delivered): of the offsets the labels
allow, the nearest to it in the prior's metric (``prior_force_n``, ``prior_torque_nm`` per axis: the
expected size of a change). Per sensor axis, ``determined`` is the share of the prior's variance the
stretches remove (1: fixed by exact labels; between 0 and 1: through sums); a sensor is re-zeroed in full
(``all``), through sums only (``sums``), or not at all (``none``: no exact label of it or of a sum of it).

Uncertainty: the posterior std per axis (N, Nm), from the residuals' scatter (its variance, and its
autocorrelation: the effective number of independent samples) where determined, the prior's where not.
It counts the readings' noise only; the labels' model error for the stretch's pose (the URDF's masses and
centres of mass) does not average out over its samples: a floor per axis (`pipeline.deploy.shrink`). What
is applied (``offsets``) is the estimate shrunk towards zero where it is not significant against both.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from pipeline.core.errors import DataError
from pipeline.deploy.shrink import LabelError, reasons, shrink, thresholds
from pipeline.export.offsets import Offsets
from pipeline.logs import schema as S

STEP_N = 1e-3  # N / Nm: the central-difference step of the Jacobians
TOLERANCE_N = 1e-6  # N / Nm: Gauss-Newton stops when no delta moves more than this
MAX_ITERATIONS = 30
RANK_TOLERANCE = 1e-6  # singular values below this x the largest: directions the labels do not determine
FULL = 0.999  # an axis whose determined share exceeds this is fixed by the labels


@dataclass(frozen=True)
class Prior:
    """The expected size of an offset change per axis (1 sigma): N on force axes, Nm on torque axes."""

    force_n: float
    torque_nm: float

    def scale(self, n_sensors: int) -> np.ndarray:
        return np.tile(np.repeat([self.force_n, self.torque_nm], 3), n_sensors)


@dataclass
class Equation:
    """An exact label over a stretch: ``sum_m T_m f_m = label`` (N samples); T_m (N, 6, 6) per member."""

    name: str  # the sensor, or the cut set's label
    members: tuple[str, ...]
    label: np.ndarray  # (N, 6) N / Nm
    transforms: dict[str, np.ndarray]  # member -> (N, 6, 6)


@dataclass
class StretchData:
    """What a still stretch gives a re-zeroing: the inputs of every group's graph (group -> slot -> (N, k)),
    its equations, the raw readings' noise per sensor (6,) N / Nm."""

    name: str
    inputs: dict[str, dict[int, np.ndarray]]
    equations: list[Equation]
    noise: dict[str, np.ndarray]
    samples: int


@dataclass
class Gain:
    """How an equation's label moves the solve: its mean over the stretch (6,) N / Nm, and the gradient's
    change per unit change of it (6, 6 S): a constant label error e shifts the gradient by
    ``design.T @ e``."""

    members: tuple[str, ...]
    label: np.ndarray
    design: np.ndarray


def _transforms(cut: Any, table: pd.DataFrame) -> dict[str, np.ndarray]:
    """Member -> (N, 6, 6) ``sign frame_X_s`` of a cut set on the table's samples (its pose columns)."""
    from pipeline.physics.cuts import pose_wrench_transforms

    out = {}
    for sensor, sign in zip(cut.sensors, cut.signs, strict=True):
        fixed = cut.fixed_X.get(sensor)
        if fixed is not None:
            out[sensor] = np.broadcast_to(sign * fixed, (len(table), 6, 6))
        else:
            poses = table[S.cut_pose_cols(cut.label, sensor)].to_numpy(np.float64)
            out[sensor] = sign * pose_wrench_transforms(poses)
    return out


def equations(table: pd.DataFrame, sensors: Sequence[str], cuts: Sequence[Any]) -> list[Equation]:
    """The exact labels of a stretch (its labelled table's rows) among `sensors`: each sensor's own where
    its switch is 1 on every sample, each cut set (`pipeline.physics.cuts.CutSet`, foot pairs included)
    whose members are all in `sensors` and whose switch is 1 on every sample."""

    def exact(name: str) -> np.ndarray | None:
        if S.switch_col(name) not in table or not table[S.switch_col(name)].to_numpy(bool).all():
            return None
        label = table[S.wrench_cols(S.EXPECTED, name)].to_numpy(np.float64)
        return label if np.isfinite(label).all() else None

    out = []
    for s in sensors:
        if (label := exact(s)) is not None:
            out.append(Equation(s, (s,), label, {s: np.broadcast_to(np.eye(6), (len(table), 6, 6))}))
    for cut in cuts:
        if set(cut.sensors) <= set(sensors) and (label := exact(cut.label)) is not None:
            out.append(Equation(cut.label, tuple(cut.sensors), label, _transforms(cut, table)))
    return out


def stretch_data(
    name: str, table: pd.DataFrame, deployment: Any, sensors: Sequence[str], cuts: Sequence[Any]
) -> StretchData:
    """A stretch's inputs, equations and noise from its labelled table rows. DataError naming the stretch
    if an input of a sensor of `sensors` is missing there."""
    inputs: dict[str, dict[int, np.ndarray]] = {}
    noise = {}
    for group, entry in deployment.groups().items():
        n = len(entry["inputs"]) // len(entry["sensors"])
        for slot, sensor in enumerate(entry["sensors"]):
            if sensor not in sensors:
                continue
            columns = [c["column"] for c in entry["inputs"][slot * n : (slot + 1) * n]]
            missing = [c for c in columns if c not in table]
            x = table[columns].to_numpy(np.float64) if not missing else np.full((len(table), n), np.nan)
            if missing or not np.isfinite(x).all():
                what = missing[0] if missing else next(c for c in columns if not np.isfinite(table[c]).all())
                raise DataError(f"{name}: {what}, an input of {sensor}'s calibration, is missing there")
            inputs.setdefault(group, {})[slot] = x
            noise[sensor] = np.maximum(x[:, :6].std(axis=0), 1e-6)
    return StretchData(name, inputs, equations(table, sensors, cuts), noise, len(table))


@dataclass
class Rezero:
    """A re-zeroing's result per sensor of `sensors`: the estimated offset change (6,) N / Nm, its posterior
    std from the noise (6,), its floor from the labels' model error (6,), the threshold of its shrinkage and
    the offset applied (subtracted from the raw wrench; `pipeline.deploy.shrink`), the share of each axis the
    labels determine (6,), the equations naming it."""

    sensors: list[str]
    estimated: dict[str, np.ndarray]
    std: dict[str, np.ndarray]
    floor: dict[str, np.ndarray]
    threshold: dict[str, np.ndarray]
    determined: dict[str, np.ndarray]
    involved: dict[str, list[str]]
    residual_rms: dict[str, list[float]] = field(default_factory=dict)  # equation -> (6,) after the fit
    iterations: int = 0
    samples: int = 0

    @property
    def offsets(self) -> dict[str, np.ndarray]:
        """Sensor -> the offset applied (6,) N / Nm: its estimate shrunk where not significant."""
        return {s: shrink(self.estimated[s], self.threshold[s]) for s in self.sensors}

    def status(self, sensor: str) -> str:
        """``all`` (every axis fixed by exact labels), ``sums`` (through cut-set sums only), ``none``."""
        share = self.determined[sensor]
        return "all" if share.min() > FULL else ("none" if not self.involved[sensor] else "sums")

    def rezeroed(self) -> Offsets:
        """The offsets of the sensors this re-zeroing reached (``all`` or ``sums``)."""
        return Offsets({s: v for s, v in self.offsets.items() if self.status(s) != "none"})

    def record(self) -> dict[str, dict[str, Any]]:
        """Sensor -> its JSON-able entry (offset aside): estimate, std, floor, threshold, per axis what was
        applied and why not, determined share, status, equations."""
        applied = self.offsets
        return {
            s: {
                "estimate": [float(v) for v in self.estimated[s]],
                "std": [float(v) for v in self.std[s]],
                "floor": [float(v) for v in self.floor[s]],
                "threshold": [float(v) for v in self.threshold[s]],
                "applied": reasons(self.estimated[s], applied[s], self.threshold[s]),
                "determined": [round(float(v), 4) for v in self.determined[s]],
                "status": self.status(s),
                "equations": self.involved[s],
            }
            for s in self.sensors
        }


def _outputs(deployment: Any, data: StretchData, deltas: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Sensor -> (N, 6) the calibration's wrench of each stretch sample with the offsets `deltas`."""
    run = deployment.with_offsets(Offsets(dict(deltas)))
    out = {}
    for group, slots in data.inputs.items():
        y = run.predict(group, slots)
        sensors = deployment.groups()[group]["sensors"]
        out.update({sensors[slot]: y[slot] for slot in slots})
    return out


def _jacobians(deployment: Any, data: StretchData, deltas: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Sensor -> (N, 6, 6) d(output)/d(delta) by central differences (every sensor's axis k at once)."""
    out = {s: np.zeros((data.samples, 6, 6)) for s in deltas}
    for k in range(6):
        step = STEP_N * np.eye(6)[k]
        plus = _outputs(deployment, data, {s: d + step for s, d in deltas.items()})
        minus = _outputs(deployment, data, {s: d - step for s, d in deltas.items()})
        for s in deltas:
            out[s][:, :, k] = (plus[s] - minus[s]) / (2.0 * STEP_N)
    return out


def _sigma(eq: Equation, noise: Mapping[str, np.ndarray]) -> np.ndarray:
    """(6,) the noise of an equation's axes: the members' reading noise through their mean transforms."""
    var = sum((eq.transforms[m].mean(axis=0) ** 2) @ noise[m] ** 2 for m in eq.members)
    return np.sqrt(np.maximum(var, 1e-12))


def _rows(
    eq: Equation, data: StretchData, y: Mapping[str, np.ndarray], jac: Mapping[str, np.ndarray] | None,
    index: Mapping[str, int], scale: np.ndarray,
) -> tuple[np.ndarray, np.ndarray | None]:  # fmt: skip
    """(whitened residuals (N, 6), their derivatives (N, 6, 6 S) in prior units) of one equation; `jac`
    None: residuals only; `y` None-like entries are not used then."""
    sigma = _sigma(eq, data.noise)
    predicted = sum(np.einsum("nij,nj->ni", eq.transforms[m], y[m]) for m in eq.members)
    residual = (eq.label - predicted) / sigma
    if jac is None:
        return residual, None
    design = np.zeros((data.samples, 6, len(scale)))
    for m in eq.members:
        cols = slice(6 * index[m], 6 * index[m] + 6)
        design[:, :, cols] = -np.einsum("nij,njk->nik", eq.transforms[m], jac[m])
    return residual, design / sigma[None, :, None] * scale[None, None, :]


def _basis(stretches: Sequence[StretchData], index: Mapping[str, int], scale: np.ndarray) -> np.ndarray:
    """(6 S, r) orthonormal basis, in prior units, of the offset directions the labels determine: the row
    space of the equations with the identity for every calibration (module docstring)."""
    rows = []
    for data in stretches:
        for eq in data.equations:
            identity = {m: np.broadcast_to(-np.eye(6), (data.samples, 6, 6)) for m in eq.members}
            _, design = _rows(eq, data, {m: np.zeros((data.samples, 6)) for m in eq.members}, identity,
                              index, scale)  # fmt: skip
            rows.append(design.mean(axis=0))
    if not rows:
        return np.zeros((len(scale), 0))
    _, sv, vt = np.linalg.svd(np.concatenate(rows), full_matrices=False)
    return vt[: int((sv > RANK_TOLERANCE * sv[0]).sum())].T if sv[0] > 0 else np.zeros((len(scale), 0))


def _system(
    deployment: Any, stretches: Sequence[StretchData], deltas: Mapping[str, np.ndarray],
    index: Mapping[str, int], scale: np.ndarray, derivatives: bool,
) -> tuple[np.ndarray, np.ndarray, float, list[tuple[str, np.ndarray, np.ndarray]], list[Gain]]:  # fmt: skip
    """(normal matrix H (6 S, 6 S), gradient A^T r (6 S,), squared error, per equation (name, whitened
    residuals (N, 6), residuals N / Nm), per equation its `Gain`) at `deltas`; H and the gradient zero and no
    gains without `derivatives`."""
    h, g, cost, out, gains = np.zeros((len(scale),) * 2), np.zeros(len(scale)), 0.0, [], []
    for data in stretches:
        y = _outputs(deployment, data, deltas)
        jac = _jacobians(deployment, data, deltas) if derivatives else None
        for eq in data.equations:
            residual, design = _rows(eq, data, y, jac, index, scale)
            cost += float((residual**2).sum())
            name = f"{data.name}: {eq.name}" if len(stretches) > 1 else eq.name
            out.append((name, residual, residual * _sigma(eq, data.noise)))
            if design is not None:
                h += np.einsum("nik,nil->kl", design, design)
                g += np.einsum("nik,ni->k", design, residual)
                per_label = design.sum(axis=0) / _sigma(eq, data.noise)[:, None]
                gains.append(Gain(eq.members, eq.label.mean(axis=0), per_label))
    return h, g, cost, out, gains


def _posterior_std(
    h: np.ndarray, basis: np.ndarray, residuals: list[np.ndarray], scale: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(6 S,) posterior std, N / Nm: determined directions from the normal matrix scaled by the residuals'
    variance and autocorrelation (effective samples), the others the prior's; and (6 S,) its determined
    part alone (what the estimate's noise is: along the others the estimate stays at zero)."""
    squares = sum(float((r**2).sum()) for r in residuals)  # each (N_i, 6): time series per axis
    variance = max(squares / max(sum(r.size for r in residuals), 1), 1e-12)
    lag = sum(float((r[1:] * r[:-1]).sum()) for r in residuals) / max(squares, 1e-300)
    longest = max((len(r) for r in residuals), default=1)
    inflation = float(np.clip((1 + lag) / max(1 - lag, 1e-9), 1.0, longest))
    reduced = basis.T @ h @ basis / (variance * inflation)
    determined = np.diag(basis @ np.linalg.inv(reduced) @ basis.T)
    cov = determined + np.diag(np.eye(len(scale)) - basis @ basis.T)
    return scale * np.sqrt(np.clip(cov, 0.0, None)), scale * np.sqrt(np.clip(determined, 0.0, None))


def _floor(
    gains: Sequence[Gain], h: np.ndarray, basis: np.ndarray, index: Mapping[str, int], scale: np.ndarray,
    label_error: LabelError,
) -> np.ndarray:  # fmt: skip
    """(6 S,) the offsets' floor, N / Nm (`LabelError.label_floor` of the mean labels). A sensor with exact
    labels of its own: theirs (RMS over them; the calibration's slope taken as one), whatever sums it is also
    in, whose labels' errors are those of their members' (the same links). Through sums only: each sum's
    carried by the solve's linear map from labels to offsets (a constant label error e moves the Gauss-Newton
    solution by ``-B (B^T H B)^-1 B^T design^T e``), the sums independent."""
    solve_map = basis @ np.linalg.inv(basis.T @ h @ basis) @ basis.T
    variance = np.zeros(len(scale))
    for sensor, i in index.items():
        rows = slice(6 * i, 6 * i + 6)
        own = [label_error.label_floor(g.label) ** 2 for g in gains if g.members == (sensor,)]
        if own:
            variance[rows] = np.mean(own, axis=0)
            continue
        for g in (g for g in gains if sensor in g.members):
            k = scale[rows, None] * (solve_map[rows] @ g.design.T)  # (6, 6): offsets per unit label error
            variance[rows] += (k**2) @ label_error.label_floor(g.label) ** 2
    return np.sqrt(variance)


def solve(
    deployment: Any, stretches: Sequence[StretchData], sensors: Sequence[str], prior: Prior,
    label_error: LabelError | None = None, significance: float = 0.0,
    pose_spread: Mapping[str, Sequence[float]] | None = None,
) -> Rezero:  # fmt: skip
    """Each sensor's raw-side offset change from the exact labels of `stretches` (module docstring), and
    what of it is applied: shrunk where within `significance` x its noise and its floor, the labels' error
    of `label_error` (None: none) with the spread of its estimates over a log's still poses where known
    (`pose_spread`: sensor -> (6,) N / Nm), in quadrature (`pipeline.deploy.shrink`; significance 0: every
    estimate applied as it is).

    `deployment`: the export (`pipeline.export.runtime.Deployment`, as delivered: its own offsets are
    not used); `sensors`: the sensors re-zeroed (the equations' other members are not). Raises DataError if
    no stretch has an exact label among them.
    """
    sensors = list(sensors)
    index, scale = {s: i for i, s in enumerate(sensors)}, prior.scale(len(sensors))
    basis = _basis(stretches, index, scale)
    if basis.shape[1] == 0:
        names = ", ".join(d.name for d in stretches)
        raise DataError(f"{names}: no exact label of {', '.join(sensors)} there, nor of a sum of only them")
    deployment = deployment.with_offsets(Offsets())

    def per_sensor(v: np.ndarray) -> dict[str, np.ndarray]:
        return {s: v[6 * i : 6 * i + 6] for s, i in index.items()}

    def deltas(z: np.ndarray) -> dict[str, np.ndarray]:
        return per_sensor(scale * z)

    z, iterations = np.zeros(len(scale)), 0
    while iterations < MAX_ITERATIONS:
        iterations += 1
        h, g, cost, _, _ = _system(deployment, stretches, deltas(z), index, scale, True)
        step = -basis @ np.linalg.solve(basis.T @ h @ basis, basis.T @ g)
        t = 1.0  # halved until the squared error decreases (a network's kink can overshoot a full step)
        while (
            t > 1 / 64 and _system(deployment, stretches, deltas(z + t * step), index, scale, False)[2] > cost
        ):
            t /= 2
        z = z + t * step
        if np.abs(t * step * scale).max() < TOLERANCE_N:
            break
    h, _, _, residuals, gains = _system(deployment, stretches, deltas(z), index, scale, True)
    std, noise = _posterior_std(h, basis, [w for _, w, _ in residuals], scale)
    floor = (
        np.zeros(len(scale)) if label_error is None else _floor(gains, h, basis, index, scale, label_error)
    )
    known = pose_spread or {}
    spread = [np.zeros(6) if known.get(s) is None else np.asarray(known[s], float) for s in sensors]
    floor = np.hypot(floor, np.concatenate(spread))
    threshold = thresholds(noise, floor, significance)
    share = np.diag(basis @ basis.T)
    involved = {
        s: sorted({eq.name for d in stretches for eq in d.equations if s in eq.members}) for s in sensors
    }
    return Rezero(
        sensors, deltas(z), per_sensor(std), per_sensor(floor), per_sensor(threshold), per_sensor(share),
        involved, {name: np.sqrt(np.mean(r**2, axis=0)).tolist() for name, _, r in residuals},
        iterations, sum(d.samples for d in stretches),
    )  # fmt: skip
