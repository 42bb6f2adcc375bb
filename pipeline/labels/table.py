"""Labelling one smoothed table: expected wrenches, switches, foot-pair and cut-set sums (thesis 4.2, 5.4).

Per log: the contact set of every sample (:mod:`pipeline.labels.contacts`), the link fixed in the world
(a sole of a foot in contact, or root_link on the pole as declared) with gravity in its frame; then,
from the smoothed joint kinematics and the URDF (:mod:`pipeline.physics.dynamics`), every sensor's
expected wrench and switch, each foot pair's sum in its sole frame and each cut set's signed sum in its
common frame (:mod:`pipeline.physics.cuts`), with the per-sample poses the trainer needs to map
predictions into that frame. A label's switch is 1 only where the joints it needs are ok
(:mod:`pipeline.physics.needs`, :mod:`pipeline.labels.joints`): a recording without an arm's joints still
labels the legs. Columns and metadata: :mod:`pipeline.logs.schema`.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa

from pipeline.core.config import LabelParams, display_path
from pipeline.core.errors import DataError, RobotModelError
from pipeline.core.io import write_parquet
from pipeline.labels.contacts import Contacts, declared_contacts, detect_contacts
from pipeline.labels.imu_check import check_log
from pipeline.labels.joints import Lacking, joint_ok_of, joint_streams
from pipeline.logs import schema as S
from pipeline.physics.cuts import CutSet, cut_poses, cut_sums
from pipeline.physics.dynamics import ContactCase, choose_root, expected_wrenches
from pipeline.physics.feet import Foot, foot_of_pair
from pipeline.physics.loads import loads_from_metadata, with_loads
from pipeline.physics.needs import JointNeeds
from pipeline.physics.robot import FootPair, RobotModel


@dataclass
class Labeller:
    """What labelling needs besides a table: the robot, its foot pairs and cut sets, the settings."""

    robot: RobotModel
    pairs: list[FootPair]
    cuts: list[CutSet]
    cfg: LabelParams
    gravity: float  # m/s^2, magnitude
    feet: list[Foot] = field(default_factory=list)  # every foot (one or two sensors); [] = the pairs'
    # RNEA threads per table (pinocchio's OpenMP; None: one per core). 1 where tables are labelled in
    # forked processes: one thread per process, and a child forked after an OpenMP team ran hangs in its own
    threads: int | None = None
    needs: JointNeeds = field(init=False, repr=False)  # the joints each label needs (the tree's, cached)

    def __post_init__(self) -> None:
        if not self.feet:
            self.feet = [foot_of_pair(self.robot, p) for p in self.pairs]
        self.needs = JointNeeds(self.robot, self.pairs, self.cuts)

    @property
    def cut_labels(self) -> list[CutSet]:
        """The cut sets with columns of their own (those equal to a foot pair use the pair's)."""
        return [c for c in self.cuts if c.pair is None]

    @property
    def names(self) -> list[str]:
        """Every label name: sensors, foot pairs, cut sets."""
        return [*self.robot.sensors, *(p.name for p in self.pairs), *(c.label for c in self.cut_labels)]


def label_arrays(
    lab: Labeller,
    contacts: Contacts,
    q: np.ndarray,
    dq: np.ndarray,
    ddq: np.ndarray,
    ok: np.ndarray,
    gravity_fixed: np.ndarray,
    lacking: Lacking | None = None,
) -> dict[str, np.ndarray]:
    """Expected wrenches, switches and poses of every sensor, pair and cut set, as labelled-table columns.

    q, dq, ddq: (N, n_joints) smoothed kinematics; ok: (N, n_joints) where each joint's kinematics are
    usable, or (N,) for every joint. A label's switch is 1 where its contact case makes it exact and the
    joints it needs are ok (the others are set to 0 for the RNEA: they do not change it); `lacking`
    counts the samples lost to joints that are not. gravity_fixed: (3,) gravity in the fixed link frame,
    m/s^2.
    """
    robot, n = lab.robot, q.shape[0]
    joint_ok = ok if ok.ndim == 2 else np.repeat(ok[:, None], q.shape[1], axis=1)
    lacking = Lacking() if lacking is None else lacking
    exp = {name: np.full((n, 6), np.nan) for name in lab.names}
    sw = {name: np.zeros(n, dtype=np.uint8) for name in lab.names}
    reading = {s: np.full((n, 6), np.nan) for s in robot.sensors}
    usable = joint_ok.any(axis=1) & (contacts.index >= 0) & ~contacts.guard
    keys = sorted(
        {(int(i), str(f)) for i, f in zip(contacts.index[usable], contacts.fixed[usable], strict=True)}
    )
    for set_id, fixed in keys:
        rows = np.flatnonzero(usable & (contacts.index == set_id) & (contacts.fixed == fixed))
        case = ContactCase.make(contacts.sets[set_id], fixed, gravity_fixed)
        have = joint_ok[rows]
        kin = [np.where(have, a[rows], 0.0) for a in (q, dq, ddq)]
        out = expected_wrenches(robot, *kin, case, lab.pairs, lab.threads)
        root = choose_root(robot, case)

        def gate(name: str, on: np.ndarray, have: np.ndarray = have, root: str = root) -> np.ndarray:
            return lacking.gate(name, on.astype(bool), have, lab.needs.of_label(name, root))

        for s in robot.sensors:
            sw[s][rows] = on = gate(s, out.switch[s])
            exp[s][rows] = np.where(on[:, None], out.reading[s], np.nan)
            reading[s][rows] = out.reading[s]
        for p in lab.pairs:
            sw[p.name][rows] = on = gate(p.name, out.pair_switch[p.name])
            exp[p.name][rows] = np.where(on[:, None], out.pair_sum[p.name], np.nan)
        for cut in lab.cut_labels:
            sw[cut.label][rows] = gate(cut.label, np.full(len(rows), cut.switch(case.contacts)))
    columns: dict[str, np.ndarray] = {}
    q_ok, cache = np.where(joint_ok, q, 0.0), {}
    for cut in lab.cut_labels:
        poses = cut_poses(robot, cut, q_ok, cache)
        on = sw[cut.label] == 1
        if on.any():
            exp[cut.label][on] = cut_sums(
                cut, {s: reading[s][on] for s in cut.sensors}, {s: p[on] for s, p in poses.items()}
            )
        for sensor, pose in poses.items():
            link = robot.sensors[sensor].child_link
            pose[~joint_ok[:, lab.needs.of_region(cut.frame, frozenset({link}))].all(axis=1)] = np.nan
            for axis, col in enumerate(S.cut_pose_cols(cut.label, sensor)):
                columns[col] = pose[:, axis]
    for name in lab.names:
        for axis, col in enumerate(S.wrench_cols(S.EXPECTED, name)):
            columns[col] = exp[name][:, axis]
        columns[S.switch_col(name)] = sw[name]
    return columns


def cut_set_metadata(cut: CutSet) -> dict[str, Any]:
    """The ``ftcal.label`` entry of a cut set (see :mod:`pipeline.logs.schema`): its label sum is
    ``sum_s signs[s] * X_s f_s`` with ``X_s`` = ``X[s]`` (6x6 row-major, constant) or built per sample
    from ``pose_columns[s]`` (:func:`pipeline.physics.cuts.pose_wrench_transforms`)."""
    return {
        "label": cut.label,
        "sensors": list(cut.sensors),
        "frame": cut.frame,
        "signs": dict(zip(cut.sensors, cut.signs, strict=True)),
        "on_part": cut.on_part,
        "part": sorted(cut.part),
        "X": {s: x.ravel().tolist() for s, x in cut.fixed_X.items()},
        "pose_columns": {s: S.cut_pose_cols(cut.label, s) for s in cut.moving},
    }


# --- per log -------------------------------------------------------------------------------------


@dataclass
class LogSummary:
    """What labelling one log found (logged to MLflow; also in the table's ftcal.label metadata)."""

    log: str
    samples: int
    detected: bool
    exact_fraction: dict[str, float]
    contact_phases: dict[str, dict[str, float]]
    guard_fraction: float
    zero_levels: dict[str, float]
    seconds: float
    truth_agreement: float | None = None  # simulated logs: detected == true contact set, outside guards
    label_rmse: dict[str, dict[str, float]] = field(default_factory=dict)  # vs true wrench, switch 1
    imu_axes: dict[str, dict[str, Any]] = field(default_factory=dict)  # per sensor: its IMU check (imu_check)
    # per label name: exact labels (samples), samples lost to joints not ok (lost), the streams (or joints)
    # missing there (lacks): `pipeline.labels.joints.Lacking.summary`
    exact: dict[str, dict[str, Any]] = field(default_factory=dict)
    # joints declared still (ingest.fixed_joints): per exact sensor, the RMS change of its label (N, Nm,
    # pooled) were they off by FIXED_DELTA_DEG
    fixed_sensitivity: dict[str, float] = field(default_factory=dict)


def contact_strings(contacts: Contacts) -> np.ndarray:
    """(N,) the contact set of every sample, links sorted and comma-joined ('' where none)."""
    names = [",".join(sorted(s)) for s in contacts.sets]
    return np.array([names[i] if i >= 0 else "" for i in contacts.index], dtype=object)


def _phases(time_s: np.ndarray, contacts: Contacts) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    if time_s.size == 0:
        return out
    dt = float(np.median(np.diff(time_s))) if time_s.size > 1 else 0.0
    starts = np.flatnonzero(np.r_[True, contacts.index[1:] != contacts.index[:-1]])
    ends = np.r_[starts[1:], contacts.index.size]
    for a, b in zip(starts, ends, strict=True):
        i = contacts.index[a]
        key = ",".join(sorted(contacts.sets[i])) if i >= 0 else "(none)"
        entry = out.setdefault(key, {"segments": 0, "total_s": 0.0})
        entry["segments"] += 1
        entry["total_s"] += float(time_s[b - 1] - time_s[a]) + dt
    for entry in out.values():
        entry["mean_s"] = entry["total_s"] / entry["segments"]
    return out


def _true_labels(lab: Labeller, truth: pd.DataFrame, labels: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """True value of every label name the truth table allows: sensors, pair sums, cut-set sums (mapped
    with the labels' own per-sample poses)."""
    true: dict[str, np.ndarray] = {}
    for s in lab.robot.sensors:
        if set(S.wrench_cols(S.TRUE, s)) <= set(truth.columns):
            true[s] = truth[S.wrench_cols(S.TRUE, s)].to_numpy()
    for p in lab.pairs:
        if p.front in true and p.rear in true:
            true[p.name] = true[p.front] @ p.sole_X_front.T + true[p.rear] @ p.sole_X_rear.T
    for cut in lab.cut_labels:
        if all(s in true for s in cut.sensors):
            poses = {
                s: np.column_stack([labels[c] for c in S.cut_pose_cols(cut.label, s)]) for s in cut.moving
            }
            true[cut.label] = cut_sums(cut, true, poses)
    return true


def _truth_checks(
    truth_path: Path, stamps: np.ndarray, lab: Labeller, contacts: Contacts, labels: dict[str, np.ndarray]
) -> tuple[float | None, dict]:
    """Contact agreement and label error against a simulated log's truth table."""
    truth = pd.read_parquet(truth_path).set_index(S.STAMP).reindex(stamps)
    agreement = None
    if S.CONTACTS in truth:
        true_sets = truth[S.CONTACTS].fillna("").to_numpy()
        valid = ~contacts.guard & (true_sets != "")
        ours = contact_strings(contacts)
        agreement = float(np.mean(ours[valid] == true_sets[valid])) if valid.any() else None
    rmse: dict[str, dict[str, float]] = {}
    for name, value in _true_labels(lab, truth, labels).items():
        on = labels[S.switch_col(name)] == 1
        err = np.column_stack([labels[c] for c in S.wrench_cols(S.EXPECTED, name)])[on] - value[on]
        err = err[np.isfinite(err).all(axis=1)]
        if err.size:
            rmse[name] = {
                "force": float(np.sqrt(np.mean(err[:, :3] ** 2))),
                "torque": float(np.sqrt(np.mean(err[:, 3:] ** 2))),
                "samples": int(err.shape[0]),
            }
    return agreement, rmse


def _read_smoothed(src: Path, robot: RobotModel) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The smoothed table and its ftcal metadata; DataError if unreadable or missing columns."""
    from pipeline.logs.tables import read_table_metadata

    try:
        table = pd.read_parquet(src)
        meta = read_table_metadata(src)
    except (OSError, pa.ArrowException, ValueError) as exc:
        raise DataError(f"{src}: cannot read the smoothed table: {exc}") from None
    missing_joints = [j for j in robot.joint_names if S.joint_col(S.QS, j) not in table]
    if missing_joints:
        raise DataError(
            f"{src}: no smoothed kinematics for joints {', '.join(missing_joints[:5])} "
            "(run the smooth stage, with the same URDF)"
        )
    missing = [s for s in robot.sensors if S.wrench_cols(S.FT, s)[0] not in table]
    if missing:
        raise DataError(f"{src}: no raw wrench columns for sensors {', '.join(missing)}")
    return table, meta


def experiment_gravity(src: Path, experiment: dict[str, str], gravity: float) -> np.ndarray:
    """(3,) gravity in the fixed link frame (m/s^2): the experiment's, else (0, 0, -gravity)."""
    text = experiment.get("gravity", "")
    try:
        value = np.array([float(v) for v in text.split()]) if text else None
    except ValueError:
        raise DataError(f"{src}: experiment metadata gravity {text!r} is not three numbers") from None
    return value if value is not None and value.shape == (3,) else np.array([0.0, 0.0, -gravity])


def _passthrough(table: pd.DataFrame, robot: RobotModel) -> dict[str, np.ndarray]:
    """The time base and every model input of the smoothed table, with their ok flags."""
    out = {S.STAMP: table[S.STAMP].to_numpy(), S.TIME: table[S.TIME].to_numpy()}
    streams = (S.WRENCH_STREAM, S.IMU_STREAM, S.TEMPERATURE_STREAM)
    for s in robot.sensors:
        cols = [*S.wrench_cols(S.FT, s), *S.vector_cols(S.ACC, s), *S.vector_cols(S.GYR, s)]
        cols += [S.temperature_col(s), *(S.ok_col(stream, s) for stream in streams)]
        for c in cols:
            out[c] = table[c].to_numpy()
    return out


def _label_metadata(lab: Labeller) -> dict[str, Any]:
    return {
        "pairs": {
            p.name: {
                "front": p.front,
                "rear": p.rear,
                "sole": p.sole,
                "sole_X_front": p.sole_X_front.ravel().tolist(),
                "sole_X_rear": p.sole_X_rear.ravel().tolist(),
            }
            for p in lab.pairs
        },
        "feet": {
            f.name: {"sole": f.sole, "sensors": list(f.sensors), "links": sorted(f.foot_links)}
            for f in lab.feet
        },
        "cut_sets": {c.name: cut_set_metadata(c) for c in lab.cuts},
        "params": asdict(lab.cfg),
        "urdf": display_path(lab.robot.urdf_path),  # relative to the working directory when under it
    }


FIXED_DELTA_DEG = 5.0  # deg: how far off a joint declared still is assumed to be, for its labels' sensitivity


def fixed_sensitivity(
    lab: Labeller,
    contacts: Contacts,
    kin: tuple[np.ndarray, np.ndarray, np.ndarray],
    ok: np.ndarray,
    gravity_fixed: np.ndarray,
    columns: dict[str, np.ndarray],
    fixed: dict[str, float],
) -> dict[str, float]:
    """Per sensor with exact labels: the RMS change of its label (N, Nm, pooled over the 6 axes) when the
    joints declared still (`fixed`: joint -> deg, ingest.fixed_joints) are all FIXED_DELTA_DEG further."""
    if not fixed:
        return {}
    q = kin[0].copy()
    for joint in fixed:
        q[:, lab.robot.joint_names.index(joint)] += np.radians(FIXED_DELTA_DEG)
    moved = label_arrays(lab, contacts, q, kin[1], kin[2], ok, gravity_fixed)
    return {s: float(np.sqrt(np.nanmean(d**2))) for s, d in _changes(lab, columns, moved).items()}


def _changes(lab: Labeller, columns: dict[str, np.ndarray], other: dict[str, np.ndarray]) -> dict[str, Any]:
    """Per sensor with exact labels: (M, 6) its labels in `other` less those of `columns`, where exact."""
    out = {}
    for sensor in lab.robot.sensors:
        on = columns[S.switch_col(sensor)] == 1
        if on.any():
            cols = S.wrench_cols(S.EXPECTED, sensor)
            out[sensor] = np.column_stack([other[c][on] - columns[c][on] for c in cols])
    return out


def inertial_part(
    lab: Labeller,
    contacts: Contacts,
    kin: tuple[np.ndarray, np.ndarray, np.ndarray],
    ok: np.ndarray,
    gravity_fixed: np.ndarray,
    columns: dict[str, np.ndarray],
) -> dict[str, list[float]]:
    """Per sensor with exact labels: the RMS per axis (6,) of its label's inertial part (N, Nm), the label
    less the same pose's label at rest: all that the smoothed velocities and accelerations put in it. Where
    a recording moves slowly it is mostly their noise (a still joint's flicker, a narrow window's
    accelerations), the labels' kinematic noise."""
    q, dq, ddq = kin
    rest = label_arrays(lab, contacts, q, np.zeros_like(dq), np.zeros_like(ddq), ok, gravity_fixed)
    return {s: np.sqrt(np.nanmean(d**2, axis=0)).tolist() for s, d in _changes(lab, columns, rest).items()}


def label_table(src: Path, dst: Path, lab: Labeller, truth_dir: Path | None = None) -> LogSummary:
    """Label one smoothed table into `dst` (written atomically)."""
    start = time.perf_counter()
    table, meta = _read_smoothed(src, lab.robot)
    experiment = meta.get(S.META_EXPERIMENT.decode()) or {}
    # known loads (a mass attached to a hand or foot) are part of the robot for this log's labels
    lab = replace(lab, robot=with_loads(lab.robot, loads_from_metadata(experiment, str(src)), str(src)))
    robot = lab.robot
    n = len(table)
    q, dq, ddq = (table[S.joint_cols(k, robot.joint_names)].to_numpy() for k in (S.QS, S.DQS, S.DDQS))
    ok = joint_ok_of(table, robot.joint_names)
    lacking = Lacking()
    time_s = table[S.TIME].to_numpy()
    try:  # the log's metadata may name links the URDF lacks: the error names the log
        contacts = declared_contacts(robot, experiment, n)
        if contacts is None:
            raw = {s: table[S.wrench_cols(S.FT, s)].to_numpy() for f in lab.feet for s in f.sensors}
            contacts = detect_contacts(robot, lab.feet, raw, time_s, lab.cfg, lab.gravity, str(src))
        gravity_fixed = experiment_gravity(src, experiment, lab.gravity)
        columns = label_arrays(lab, contacts, q, dq, ddq, ok, gravity_fixed, lacking)
        fixed = ((meta.get(S.META_INGEST.decode()) or {}).get("fixed_joints")) or {}
        sensitivity = fixed_sensitivity(lab, contacts, (q, dq, ddq), ok, gravity_fixed, columns, fixed)
        recorded = str(experiment.get("sim", "")).strip().lower() != "true"
        inertial = inertial_part(lab, contacts, (q, dq, ddq), ok, gravity_fixed, columns) if recorded else {}
        every = ok.all(axis=1)  # the IMU check reads every joint's kinematics
        imu = check_log(robot, table, meta, contacts, (q, dq, ddq), every, gravity_fixed, lab.cfg.imu_check)
    except RobotModelError as exc:
        raise DataError(f"{src}: its experiment metadata does not fit the robot: {exc}") from None

    out = _passthrough(table, robot)
    out.update(columns)
    out[S.CONTACTS] = contact_strings(contacts)
    out[S.FIXED_LINK] = contacts.fixed.astype(object)
    out[S.GUARD] = contacts.guard
    summary = LogSummary(
        log=src.stem,
        samples=n,
        detected=contacts.detected,
        exact_fraction={m: float(np.mean(columns[S.switch_col(m)])) if n else 0.0 for m in lab.names},
        contact_phases=_phases(time_s, contacts),
        guard_fraction=float(np.mean(contacts.guard)) if n else 0.0,
        zero_levels=contacts.zero_levels,
        seconds=0.0,
        imu_axes=imu,
        exact=lacking.summary(
            {m: int(columns[S.switch_col(m)].sum()) for m in lab.names},
            robot.joint_names,
            joint_streams(meta),
        ),
        fixed_sensitivity=sensitivity,
    )
    truth_path = truth_dir / f"{src.stem}{S.TRUTH_SUFFIX}{S.PARQUET_SUFFIX}" if truth_dir else None
    if truth_path is not None and truth_path.is_file():
        summary.truth_agreement, summary.label_rmse = _truth_checks(
            truth_path, out[S.STAMP], lab, contacts, columns
        )
    label_meta = {**_label_metadata(lab), "imu_axes": imu, "exact": summary.exact}
    if inertial:  # a recording's labels' kinematic noise, on its page (pipeline.evaluation.residual)
        label_meta["inertial_rms"] = inertial
    if fixed:
        label_meta["fixed_joints"] = {"deg": fixed, "delta_deg": FIXED_DELTA_DEG, "label_rms": sensitivity}
    kv = {S.META_EXPERIMENT: experiment, S.META_LABEL: label_meta}
    for key in (S.META_INGEST, S.META_SMOOTH):
        if key.decode() in meta:
            kv[key] = meta[key.decode()]
    schema = S.arrow_schema(list(out), S.KIND_LABELLED, kv)
    arrow = pa.Table.from_pydict(
        {k: pa.array(v, type=schema.field(k).type) for k, v in out.items()}, schema=schema
    )
    write_parquet(dst, arrow)
    summary.seconds = time.perf_counter() - start
    return summary


__all__ = ["Labeller", "LogSummary", "cut_set_metadata", "label_arrays", "label_table"]
