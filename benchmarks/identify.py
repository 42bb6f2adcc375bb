"""What the training logs can tell about the robot's inertial parameters, against the simulator's truth.

Every label is the wrench the URDF predicts, so it carries the URDF's mass and centre-of-mass errors. Run in
a pipeline directory after `dvc repro` on simulated logs (it reads params.yaml, data/smoothed, data/labelled
and the truth tables data/ingested/*.truth.parquet). Per sensor, on its exact-label samples of every log,
the labels' error against the true wrench (RMSE, 6 axes pooled, N and Nm):

1. ``urdf``: the labels as the label stage made them;
2. ``true inertials``: the same labels recomputed with the simulated robot's true inertial parameters,
   ``label + Y (pi_true - pi_urdf)`` (``Y`` the reading regressor, `pipeline.physics.regressor`): what the
   estimated joint velocities and accelerations alone leave, the floor of any identification;
3. ``identified``: the labels recomputed with identified parameters, ``label + Y delta``.

The identification: every massive link's 10 inertial parameters (prior: the URDF's, sd 10 % of the mass,
2 cm of centre of mass, and the inertia to match), jointly with a model of each sensor, from the training
logs' exact samples (cut sets are not used). The forward model of a reading is

    reading - label = Y_s delta + W_s phi(label, T) + noise

where ``phi`` is the sensor model (``--sensor``): ``offset`` (a constant: the sensor known but for its
offset), ``affine`` (its gain, coupling and lever too: the confounds of a mass's scale and a centre of
mass), ``hysteresis`` (the offset and the play operators' states of the reading, as the training's play
model), ``full`` (all of these, temperature, the temperature's gain and the own-axis quadratic), each
coefficient with a Gaussian prior (`PRIOR_SD`). The model is fed the label, not the
reading: a map fitted on the reading would shrink the masses and itself together. ``--reading true`` puts
the simulator's true wrench in place of the raw reading (what the experiments identify with a perfect
sensor), ``--reading oracle`` the exact static inverse of the simulated sensor applied to it (hysteresis
and noise left). The play operators' widths are the training's (`train.defaults.play_widths_n`, `_nm`).
Per part (the links between FT joints), the mass: URDF, identified, posterior sd, leave-one-log-out
(jackknife) sd, true.

    python benchmarks/identify.py --run .
    python benchmarks/identify.py --run . --reading true --sensor offset

The last line counts the parts of at least 1 kg whose mass is identified within 1 % of the truth.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.calib.params import TrainParams  # noqa: E402
from pipeline.core.config import Params, load_params, repo_root, resolve_urdf, stage_section  # noqa: E402
from pipeline.core.play import play_features, play_memory  # noqa: E402
from pipeline.labels.table import experiment_gravity  # noqa: E402
from pipeline.logs import schema as S  # noqa: E402
from pipeline.logs.tables import read_table_metadata  # noqa: E402
from pipeline.physics.cuts import components  # noqa: E402
from pipeline.physics.dynamics import ContactCase  # noqa: E402
from pipeline.physics.regressor import PARAMS, ReadingRegressor, link_params  # noqa: E402
from pipeline.physics.robot import RobotModel, load_robot  # noqa: E402
from pipeline.sim.params import simulate_params  # noqa: E402
from pipeline.sim.world import build_world  # noqa: E402

UNITS = np.r_[np.full(3, 20.0), np.full(3, 4.0)]  # N, Nm: the features' unit per axis
BASE_FEATURES = 15  # per output axis: wrench (6), temperature, 1, wrench x temperature (6), quadratic; plays
# the sensor models: their columns among the first BASE_FEATURES, and whether the plays join them
SENSOR_MODELS = {
    "offset": ([7], False),
    "affine": ([*range(6), 7], False),
    "hysteresis": ([7], True),
    "full": (list(range(BASE_FEATURES)), True),
}
# what stands for the reading: the raw wrench, the true one, or the exact static inverse of the simulated
# sensor applied to the raw one (the reading without its static distortion: hysteresis and noise left)
READINGS = {"raw": S.FT, "true": S.TRUE, "oracle": S.ORACLE}
TORQUE_SD = 0.05  # Nm: a torque residual weighs as a force residual of 1 N over this
# prior sd per feature block, x the output axis' unit: gain/coupling, lever, temperature, gain drift,
# quadratic, play; the constant (offset) is free
PRIOR_SD = {"gain": 0.03, "coupling": 0.02, "lever": 0.01, "t": 0.25, "zt": 0.01, "quad": 0.05, "play": 0.2}
MASS_SD, COM_SD_M = 0.10, 0.02  # prior sd of a link's mass (x its mass) and centre of mass (m)


def features(wrench: np.ndarray, temperature: np.ndarray, plays: np.ndarray, axis: int) -> np.ndarray:
    """(N, BASE_FEATURES + K) sensor-model features of output `axis` from wrench (N, 6) N/Nm, temperature
    (N,) degC, plays (N, 6, K) (the play operators' states z in [-1, 1] of the reading, as the training's
    play model)."""
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


def link_prior(pi: np.ndarray) -> np.ndarray:
    """(10 L,) prior precision of the links' parameters `pi` (10 L,) around the URDF's."""
    out = []
    for p in pi.reshape(-1, PARAMS):
        m, c = p[0], p[1:4] / p[0]
        first = np.sqrt((MASS_SD * m * c) ** 2 + (m * COM_SD_M) ** 2)
        inertia = 0.2 * np.abs(p[4:]).max() + 2 * m * COM_SD_M * (np.linalg.norm(c) + COM_SD_M)
        out.append(1.0 / np.r_[MASS_SD * m, first, np.full(6, inertia)] ** 2)
    return np.concatenate(out)


class Log:
    """One labelled log's exact samples (every `step`-th), their readings, labels, truth and regressors."""

    def __init__(
        self,
        dirs: dict[str, Path],
        stem: str,
        robot: RobotModel,
        links: list[str],
        basis: np.ndarray | None,
        gravity: float,
        step: int,
        widths: np.ndarray,
        reading: str = S.FT,
    ) -> None:
        """`dirs`: the smoothed, labelled and ingested tables; ``self.Y`` (n, S, 6, B) the readings of the
        parameter directions `basis` (10 L, B), or of every parameter (B = 10 L) for None; `reading`: the
        column kind in place of the raw reading (S.FT, else one of the truth table's)."""
        table = dirs["labelled"] / f"{stem}.parquet"
        lab = pd.read_parquet(table)
        sm = pd.read_parquet(dirs["smoothed"] / f"{stem}.parquet")
        truth = pd.read_parquet(dirs["ingested"] / f"{stem}.truth.parquet").set_index(S.STAMP)
        truth = truth.reindex(lab[S.STAMP].to_numpy())
        grav = experiment_gravity(table, read_table_metadata(table).get("ftcal.experiment") or {}, gravity)
        q, dq, ddq = (sm[S.joint_cols(k, robot.joint_names)].to_numpy() for k in (S.QS, S.DQS, S.DDQS))
        self.sensors = list(robot.sensors)
        sw = np.column_stack([lab[S.switch_col(s)].to_numpy() for s in self.sensors]).astype(bool)
        rows = np.flatnonzero(sw.any(1) & np.isfinite(q).all(1) & np.isfinite(ddq).all(1))[::step]
        self.sw = sw[rows]

        def stack(frame: pd.DataFrame, kind: str, at: np.ndarray | slice = rows) -> np.ndarray:
            return np.stack([frame[S.wrench_cols(kind, s)].to_numpy()[at] for s in self.sensors], 1)

        self.label, self.true = stack(lab, S.EXPECTED), stack(truth, S.TRUE)
        whole = stack(lab if reading == S.FT else truth, reading, slice(None))  # (N, S, 6)
        self.raw = whole[rows]
        self.temp = np.stack([lab[S.temperature_col(s)].to_numpy()[rows] for s in self.sensors], 1)
        self.plays = np.zeros((len(rows), len(self.sensors), 6, len(widths)))  # (n, S, 6, K)
        if len(widths):  # the training's play states of the reading, over the whole log in time order
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
            for a in range(0, len(at), 500):
                r = at[a : a + 500]
                y = reg(q[rows[r]], dq[rows[r]], ddq[rows[r]])
                self.Y[r] = y if basis is None else y @ basis


def normal_equations(log: Log, cols: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(K, K), (K,): the log's weighted normal equations of the forward model, K = 10 L + S 6 len(cols)
    (the link parameters' changes, then per sensor and axis the coefficients of the features `cols`)."""
    n_s, n_y, f = len(log.sensors), log.Y.shape[3], len(cols)
    h, g = np.zeros((n_y + n_s * 6 * f,) * 2), np.zeros(n_y + n_s * 6 * f)
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
    return h, g


def rmse(errors: list[np.ndarray]) -> float:
    e = np.concatenate(errors) if errors else np.zeros((0, 6))
    return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


def parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, default=Path("."), help="a pipeline directory after dvc repro")
    ap.add_argument("--params", type=Path, help="default: RUN/params.yaml")
    for name in ("smoothed", "labelled", "ingested"):
        ap.add_argument(f"--{name}", type=Path, help=f"default: RUN/data/{name}")
    ap.add_argument("--sensor", choices=list(SENSOR_MODELS), default="full", help="the sensor model")
    ap.add_argument("--reading", choices=list(READINGS), default="raw", help="what stands for the reading")
    ap.add_argument("--step", type=int, default=10, help="every step-th exact sample")
    ap.add_argument("--weight", type=float, default=0.1, help="data weight (correlated samples)")
    ap.add_argument("--quick", action="store_true", help="a run of seconds (every 200th sample)")
    return ap.parse_args()


def report_parts(
    robot: RobotModel,
    links: list[str],
    pi_urdf: np.ndarray,
    truth_delta: np.ndarray,
    delta: np.ndarray,
    cov: np.ndarray,
    loo: np.ndarray,
) -> None:
    """Per part (links between FT joints): its mass as the URDF, the identification (its posterior and
    jackknife sd from the leave-one-log-out estimates `loo` (logs, 10 L)) and the truth say; the count of
    parts of at least 1 kg identified within 1 % last."""
    print("\npart (heaviest link)   URDF kg   identified kg   posterior sd   jackknife sd    true kg")
    close = heavy = 0
    for part in components(robot, {ft.joint for ft in robot.sensors.values()}):
        sel = np.zeros(len(pi_urdf))
        sel[[PARAMS * k for k, lk in enumerate(links) if lk in part]] = 1.0
        if not sel.any():
            continue
        m_urdf, m_true, m_id = sel @ pi_urdf, sel @ (pi_urdf + truth_delta), sel @ (pi_urdf + delta)
        sd, parts_loo = np.sqrt(sel @ cov[: len(sel), : len(sel)] @ sel), loo @ sel
        jack = np.sqrt((len(loo) - 1) / len(loo) * ((parts_loo - parts_loo.mean()) ** 2).sum())
        name = max((lk for lk in links if lk in part), key=lambda lk: robot.links[lk].mass)
        print(f"{name:>20} {m_urdf:9.3f} {m_id:15.3f} {sd:14.3f} {jack:14.3f} {m_true:10.3f}")
        if m_urdf >= 1.0:
            heavy += 1
            close += abs(m_id - m_true) <= 0.01 * m_true
    print(f"parts of at least 1 kg identified within 1 % of the truth: {close} of {heavy}")


def identify(
    dirs: dict[str, Path],
    stems: list[str],
    robot: RobotModel,
    links: list[str],
    params: Params,
    args: argparse.Namespace,
    widths: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The identified parameter changes (10 L,), the posterior covariance of all unknowns and the
    leave-one-log-out estimates (logs, 10 L), from the training logs among `stems`."""
    cols = sensor_columns(args.sensor, BASE_FEATURES + len(widths))
    eqs = []
    for stem in (s for s in stems if s.endswith("_train")):
        log = Log(
            dirs, stem, robot, links, None, params.robot.gravity, args.step, widths, READINGS[args.reading]
        )
        eqs.append(normal_equations(log, cols))
        print(f"{stem}: {len(log.sw)} exact samples", flush=True)
    n_p = PARAMS * len(links)
    prec = np.r_[
        link_prior(link_params(robot, links)),
        np.tile(np.concatenate([feature_prior(a, len(widths))[cols] for a in range(6)]), len(robot.sensors)),
    ]
    h, g = sum(e[0] for e in eqs), sum(e[1] for e in eqs)
    cov = np.linalg.inv(args.weight * h + np.diag(prec))
    loo = [
        np.linalg.solve(args.weight * (h - e[0]) + np.diag(prec), args.weight * (g - e[1]))[:n_p] for e in eqs
    ]
    return (cov @ (args.weight * g))[:n_p], cov, np.array(loo)


def print_label_errors(
    dirs: dict[str, Path],
    stems: list[str],
    robot: RobotModel,
    links: list[str],
    basis: np.ndarray,
    params: Params,
    args: argparse.Namespace,
) -> None:
    """Per sensor, the labels' RMSE against truth on every log's exact samples: as labelled, and with the
    parameter changes of `basis` (10 L, 2: the truth's, the identified)."""
    print("\nlabels against truth on exact samples, every log (RMSE, 6 axes pooled, N and Nm)")
    print(f"{'sensor':>18} {'urdf':>8} {'true inertials':>15} {'identified':>11}")
    errs: dict[tuple[str, str], list[np.ndarray]] = {}
    for stem in stems:
        log = Log(dirs, stem, robot, links, basis, params.robot.gravity, args.step, np.zeros((0, 6)))
        for k, s in enumerate(robot.sensors):
            on = log.sw[:, k] & np.isfinite(log.true[:, k]).all(1)
            base = log.label[on, k] - log.true[on, k]
            for name, e in (
                ("urdf", base),
                ("true", base + log.Y[on, k, :, 0]),
                ("ident", base + log.Y[on, k, :, 1]),
            ):
                errs.setdefault((s, name), []).append(e)
    for s in robot.sensors:
        urdf, true, ident = (rmse(errs[s, name]) for name in ("urdf", "true", "ident"))
        print(f"{s:>18} {urdf:8.3f} {true:15.3f} {ident:11.3f}")


def main() -> None:
    args = parse()
    args.step = 200 if args.quick else args.step
    params = load_params(args.params or args.run / "params.yaml")
    dirs = {n: getattr(args, n) or args.run / "data" / n for n in ("smoothed", "labelled", "ingested")}
    stems = sorted(p.stem for p in dirs["labelled"].glob("*.parquet"))
    missing = [s for s in stems if not (dirs["ingested"] / f"{s}.truth.parquet").is_file()]
    if not stems or missing:
        what = (
            f"{dirs['labelled']}: no labelled table"
            if not stems
            else (f"{dirs['ingested']}: no <log>.truth.parquet for {len(missing)} of {len(stems)} logs")
        )
        sys.exit(f"identify: {what} (it needs simulated logs after dvc repro)")
    robot = load_robot(resolve_urdf(params.robot.urdf, repo_root()))
    truth_robot = build_world(params, simulate_params(params)).truth_robot
    links = [lk for lk, i in robot.links.items() if i is not None and i.mass > 0]
    pi_urdf = link_params(robot, links)
    truth_delta = link_params(truth_robot, links) - pi_urdf
    train_params = stage_section(params, "train", TrainParams)  # the play widths, as the training's
    widths = np.array(train_params.group(next(iter(train_params.groups))).play_widths() or np.zeros((0, 6)))
    delta, cov, loo = identify(dirs, stems, robot, links, params, args, widths)
    print_label_errors(dirs, stems, robot, links, np.column_stack([truth_delta, delta]), params, args)
    report_parts(robot, links, pi_urdf, truth_delta, delta, cov, loo)


if __name__ == "__main__":
    main()
