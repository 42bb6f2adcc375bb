"""Which inertial parameters the training logs identify, and the robot model the labels may use instead of
the URDF's.

The estimate is `pipeline.labels.inertials`' posterior over every massive link's parameters. A part of the
robot (the links between FT joints, `pipeline.physics.cuts.components`) is *identified* where the data
shrink its mass's posterior sd to at most ``label.identify.shrink`` times the prior's. A part whose mass the
data do not pin down is *re-estimated* where they reject the URDF's values: the posterior's change of the
part's masses and first moments, in its own covariance (a chi-square statistic, conservative: the posterior
covariance is wider than the change's own spread), is beyond the chi-square quantile of
``label.identify.reject_p`` for as many degrees of freedom; its estimate, however uncertain, is then nearer
the robot than the URDF's. The links of the other parts are held at the URDF's values and the posterior is
solved again. The robot model is refused, and the labels keep the URDF's parameters, when:

- no training log hangs a known load on the robot: on gravity alone a link's mass and a sensor's gain scale
  the readings alike, so no data tell them apart;
- the data identify no part (too few postures or motions);
- an identified link is not physical: a mass not positive, or an inertia at the centre of mass that is not
  positive semidefinite or violates the triangle inequality (`pipeline.physics.urdf.checked_inertial`).

Per sensor the labels' change (RMS over the exact samples, 6 axes pooled, N and Nm) and, for simulated logs,
the labels' error against the true wrench with the URDF's and with the identified parameters.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import DataError
from pipeline.labels.imu_params import IdentifyParams
from pipeline.labels.inertials import (
    BASE_FEATURES,
    FREE,
    ExactSamples,
    Sources,
    link_basis,
    log_weights,
    normal_equations,
    prior_precision,
    sensor_columns,
    solve,
    with_change,
)
from pipeline.logs import schema as S
from pipeline.logs.tables import read_table_metadata
from pipeline.physics.cuts import components
from pipeline.physics.regressor import PARAMS, link_params, skew, sym
from pipeline.physics.robot import LinkInertial, RobotModel
from pipeline.physics.urdf import RobotModelError, checked_inertial

SENSOR_MODEL = "full"  # the sensor model identified jointly (`pipeline.labels.inertials.SENSOR_MODELS`)


@dataclass(frozen=True)
class Part:
    """One part's mass (kg): the URDF's, the identified one with its posterior and leave-one-log-out
    (jackknife) sd, the prior's sd; whether the data identify it; the truth of a simulated robot; the
    chi-square statistic of its parameters' change (`dof` masses and first moments) and whether it rejects
    the URDF's values (the part re-estimated)."""

    name: str  # its heaviest link
    links: tuple[str, ...]
    mass_urdf: float
    mass: float
    sd: float
    jackknife: float
    prior_sd: float
    identified: bool
    mass_true: float | None = None
    chi2: float = 0.0
    dof: int = 0
    rejected: bool = False

    @property
    def freed(self) -> bool:
        """Whether the labels use the data's estimate of this part (identified or re-estimated)."""
        return self.identified or self.rejected

    @property
    def state(self) -> str:
        """One phrase: identified, re-estimated (and why) or the URDF's (`part_state`)."""
        return part_state(self.__dict__)


def part_state(part: Mapping[str, Any]) -> str:
    """A part's state in one phrase, from its fields (a `Part`'s, or their JSON in identification.json)."""
    if part["identified"]:
        return "identified"
    if part.get("rejected"):
        return f"re-estimated (the data reject the URDF's: chi2 {part['chi2']:.0f} on {part['dof']})"
    return "not identified (URDF's)"


@dataclass
class SensorStats:
    """Sufficient statistics of one sensor's labels over exact samples (P parameters): ``yty`` (P, P) sum
    of Y^T Y over samples and axes, for simulated logs ``yte`` (P,) sum of Y^T (label - true) and ``ete``
    the sum of squared label errors; ``n`` the number of values (samples x 6)."""

    yty: np.ndarray
    yte: np.ndarray
    ete: float = 0.0
    n: int = 0
    n_true: int = 0

    def add(self, y: np.ndarray, err: np.ndarray | None) -> None:
        """Add samples: y (n, 6, P) the regressor rows, err (n, 6) label - true wrench (None: no truth; with
        truth only its finite samples are added)."""
        if err is not None:
            ok = np.isfinite(err).all(1)
            y, e = y[ok], err[ok].reshape(-1)
            self.yte += y.reshape(-1, y.shape[2]).T @ e
            self.ete += float(e @ e)
            self.n_true += len(e)
        flat = y.reshape(-1, y.shape[2])
        self.yty += flat.T @ flat
        self.n += flat.shape[0]

    def change(self, delta: np.ndarray) -> float:
        """RMS of the labels' change ``Y delta``, N and Nm pooled."""
        return float(np.sqrt(max(delta @ self.yty @ delta, 0.0) / max(self.n, 1)))

    def error(self, delta: np.ndarray) -> float | None:
        """RMS of (label + Y delta - true) on the samples with truth; None without truth (with truth, ``yty``
        is over the same samples)."""
        if not self.n_true:
            return None
        sq = self.ete + 2 * delta @ self.yte + delta @ self.yty @ delta
        return float(np.sqrt(max(sq, 0.0) / self.n_true))


@dataclass
class Identification:
    """The identification's outcome (module docstring). ``pi`` (10 L,): the parameters the labels use if
    the model is accepted (``status == "identified"``), the URDF's elsewhere; ``reason``: why not."""

    links: list[str]
    pi_urdf: np.ndarray
    pi: np.ndarray
    status: str
    reason: str
    parts: list[Part]
    sensors: dict[str, dict[str, float | None]]
    logs: list[str]
    known_load_logs: list[str]
    samples: int
    link_sd: np.ndarray = field(default_factory=lambda: np.zeros(0))
    criteria: dict[str, float] = field(default_factory=dict)  # label.identify's shrink and reject_p

    @property
    def accepted(self) -> bool:
        return self.status == "identified"

    def inertials(self) -> dict[str, LinkInertial]:
        """The identified links' inertial parameters (link frame, about the centre of mass), for the URDF."""
        out = {}
        for k, link in enumerate(self.links):
            p = self.pi[PARAMS * k : PARAMS * (k + 1)]
            if np.array_equal(p, self.pi_urdf[PARAMS * k : PARAMS * (k + 1)]):
                continue
            out[link] = to_inertial(p)
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the parts, the sensors, the decision)."""
        return {
            "status": self.status,
            "reason": self.reason,
            "logs": self.logs,
            "known_load_logs": self.known_load_logs,
            "exact_samples": self.samples,
            "criteria": self.criteria,
            "parts": [p.__dict__ | {"links": list(p.links)} for p in self.parts],
            "sensors": self.sensors,
        }


def to_inertial(p: np.ndarray) -> LinkInertial:
    """A link's 10 parameters (Pinocchio's order, about the link frame's origin) as mass, centre of mass and
    inertia about it (no check: `checked_inertial` checks)."""
    m = float(p[0])
    c = p[1:4] / m if m != 0 else np.zeros(3)
    s = skew(c)
    return LinkInertial(mass=m, com=c, inertia=sym(p[4:]) - m * s.T @ s)


def training_stems(labelled: Path) -> list[str]:
    """The training logs among `labelled`'s tables (experiment metadata role ``train``), by name."""
    out = []
    for path in sorted(labelled.glob(f"*{S.PARQUET_SUFFIX}")):
        experiment = read_table_metadata(path).get("ftcal.experiment") or {}
        if str(experiment.get("role", "")).strip() == "train":
            out.append(path.name[: -len(S.PARQUET_SUFFIX)])
    return out


def _parts(robot: RobotModel, links: list[str]) -> list[tuple[str, list[int]]]:
    """(heaviest link, link indices) of every part with mass."""
    out = []
    for part in components(robot, {ft.joint for ft in robot.sensors.values()}):
        idx = [k for k, lk in enumerate(links) if lk in part]
        if idx:
            out.append((max((links[k] for k in idx), key=lambda lk: robot.links[lk].mass), idx))
    return out


def part_table(
    robot: RobotModel,
    links: list[str],
    pi_urdf: np.ndarray,
    post: Any,
    pi_true: np.ndarray | None,
    shrink: float,
    reject_p: float,
) -> list[Part]:
    """Every part's masses (`Part`) from the posterior `post` over the links' masses and first moments
    (`pipeline.labels.inertials.Posterior`); `pi_true`: a simulated robot's true parameters, else None; a
    part is identified where its mass's sd is at most `shrink` x the prior's, re-estimated where the
    chi-square statistic of its parameters' change exceeds the quantile of `reject_p` (module docstring)."""
    from scipy.stats import chi2

    parts = []
    for name, idx in _parts(robot, links):
        own = np.array([FREE * k + j for k in idx for j in range(FREE)])
        change, cov = post.delta[own], post.cov[np.ix_(own, own)]
        stat = float(change @ np.linalg.solve(cov, change))
        sel = np.zeros(FREE * len(links))
        sel[[FREE * k for k in idx]] = 1.0
        mass_urdf = float(sum(pi_urdf[PARAMS * k] for k in idx))
        loo = post.loo @ sel
        jack = np.sqrt((len(loo) - 1) / len(loo) * ((loo - loo.mean()) ** 2).sum()) if len(loo) > 1 else 0.0
        sd, prior_sd = float(np.sqrt(sel @ post.cov @ sel)), float(np.sqrt(sel @ (post.prior_sd**2 * sel)))
        parts.append(
            Part(
                name=name,
                links=tuple(links[k] for k in idx),
                mass_urdf=mass_urdf,
                mass=mass_urdf + float(sel @ post.delta),
                sd=sd,
                jackknife=float(jack),
                prior_sd=prior_sd,
                identified=sd <= shrink * prior_sd,
                mass_true=float(sum(pi_true[PARAMS * k] for k in idx)) if pi_true is not None else None,
                chi2=stat,
                dof=len(own),
                rejected=bool(stat > chi2.isf(reject_p, len(own))),
            )
        )
    return parts


def _physical(links: list[str], pi: np.ndarray, which: list[int]) -> str:
    """'' if every link of `which` is physical, else what is wrong with the first that is not."""
    for k in which:
        inertial = to_inertial(pi[PARAMS * k : PARAMS * (k + 1)])
        if inertial.mass <= 0:
            return f"link {links[k]}: identified mass {inertial.mass:.4g} kg is not positive"
        try:
            checked_inertial(inertial, float(np.linalg.norm(inertial.com)), f"link {links[k]}")
        except RobotModelError as exc:
            return str(exc)
    return ""


def _read_logs(
    src: Sources,
    stems: list[str],
    robot: RobotModel,
    links: list[str],
    gravity: float,
    step: int,
    widths: np.ndarray,
    cols: list[int],
    both: np.ndarray,
    progress: Any,
) -> tuple[list[Any], dict[str, SensorStats], list[str], int]:
    """Per log the normal equations (sensor features `cols`, play widths `widths` (K, 6)) over the first 4 L
    columns of `both` (10 L, B: `link_basis`, and the truth's direction last for a simulated robot); per
    sensor the labels' statistics over all B; the logs with known loads; the number of exact samples."""
    n_p = FREE * len(links)
    stats = {s: SensorStats(np.zeros((both.shape[1],) * 2), np.zeros(both.shape[1])) for s in robot.sensors}
    eqs, loaded, samples = [], [], 0
    for stem in stems:
        log = ExactSamples(src, stem, robot, links, gravity=gravity, step=step, widths=widths, basis=both)
        for k, s in enumerate(log.sensors):
            on = log.sw[:, k]
            stats[s].add(log.Y[on, k], None if log.true is None else log.label[on, k] - log.true[on, k])
        log.Y = log.Y[..., :n_p]
        eqs.append(normal_equations(log, cols))
        loaded += [stem] if log.known_loads else []
        samples += len(log.sw)
        if progress is not None:
            progress(stem)
    return eqs, stats, loaded, samples


def identify_robot(
    robot: RobotModel,
    src: Sources,
    cfg: IdentifyParams,
    gravity: float,
    truth_robot: RobotModel | None = None,
    progress: Any = None,
) -> Identification:
    """Identify `robot`'s inertial parameters from the training logs of `src.labelled` (module docstring).

    `truth_robot`: the simulated robot's true model (its parameters and the labels' error against the true
    wrench on the page), else None. `progress`: called with each log's name after it is read.

    Raises:
        DataError: no training log among the labelled tables.
    """
    stems = training_stems(src.labelled)
    if not stems:
        raise DataError(f"{src.labelled}: no training log (experiment metadata role 'train') to identify")
    links = [lk for lk, i in robot.links.items() if i is not None and i.mass > 0]
    pi_urdf = link_params(robot, links)
    pi_true = link_params(truth_robot, links) if truth_robot is not None else None
    basis = link_basis(pi_urdf)
    n_p = basis.shape[1]
    # the statistics of the labels' change also carry the truth's direction, as a last column
    both = basis if pi_true is None else np.column_stack([basis, pi_true - pi_urdf])
    widths = np.asarray(cfg.widths(), dtype=float).reshape(-1, 6)
    cols = sensor_columns(SENSOR_MODEL, BASE_FEATURES + len(widths))
    eqs, stats, loaded, samples = _read_logs(
        src, stems, robot, links, gravity, cfg.step, widths, cols, both, progress
    )
    prior = prior_precision(pi_urdf, cols, len(widths), len(robot.sensors))
    weights = log_weights(eqs, prior, cfg.weight)
    free = solve(eqs, prior, n_p, weights)
    parts = part_table(robot, links, pi_urdf, free, pi_true, cfg.shrink, cfg.reject_p)
    held = np.ones(n_p, dtype=bool)
    for part in (p for p in parts if p.freed):
        for k in (links.index(lk) for lk in part.links):
            held[FREE * k : FREE * (k + 1)] = False
    post = solve(eqs, prior, n_p, weights, pinned=held) if (~held).any() else free
    change = np.where(held, 0.0, post.delta)
    pi = with_change(pi_urdf, change)
    parts = [_with_mass(p, links, pi_urdf, change, post) if p.freed else p for p in parts]
    status, reason = "identified", _refusal(bool(loaded), held, cfg, links, pi)
    if reason:
        status, pi = "urdf", pi_urdf.copy()
    extra = [0.0] * (both.shape[1] - n_p)
    ident = np.r_[change, extra]
    truth_dir = np.r_[np.zeros(n_p), 1.0] if pi_true is not None else None
    sensors = {
        s: {
            "label_change": st.change(ident) if status == "identified" else 0.0,
            "error_urdf": st.error(np.zeros(len(ident))),
            "error_identified": st.error(ident),
            "error_true_inertials": st.error(truth_dir) if truth_dir is not None else None,
        }
        for s, st in stats.items()
    }
    return Identification(
        links=links,
        pi_urdf=pi_urdf,
        pi=pi,
        status=status,
        reason=reason,
        parts=parts,
        sensors=sensors,
        logs=stems,
        known_load_logs=loaded,
        samples=samples,
        link_sd=np.sqrt(np.diag(post.cov)),
        criteria={"shrink": cfg.shrink, "reject_p": cfg.reject_p},
    )


def _refusal(loaded: bool, held: np.ndarray, cfg: IdentifyParams, links: list[str], pi: np.ndarray) -> str:
    """Why the identified model is refused ('' if it is not): no known loads, no part freed (`held` (4 L,)
    every parameter held), or a freed link that is not physical (`pi` (10 L,) the identified parameters)."""
    if not loaded:
        return "no training log hangs a known load on the robot: a mass and a sensor's gain scale alike"
    if held.all():
        return (
            f"the data shrink no part's mass sd to {cfg.shrink:g} x the prior's, nor reject any part's URDF "
            "values (too few postures or motions)"
        )
    return _physical(links, pi, [k for k in range(len(links)) if not held[FREE * k]])


def _with_mass(p: Part, links: list[str], pi_urdf: np.ndarray, change: np.ndarray, post: Any) -> Part:
    """`p` with its mass and sd from the solve with the other parts held (`change` (4 L,) its estimate)."""
    sel = np.zeros(len(change))
    sel[[FREE * links.index(lk) for lk in p.links]] = 1.0
    return Part(
        **(
            p.__dict__
            | {"mass": p.mass_urdf + float(sel @ change), "sd": float(np.sqrt(sel @ post.cov @ sel))}
        )
    )


__all__ = [
    "Identification",
    "Part",
    "identify_robot",
    "part_state",
    "part_table",
    "to_inertial",
    "training_stems",
]
