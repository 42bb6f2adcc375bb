"""Stage `label`: contacts, exact-label switches and expected wrenches of every FT sensor (thesis 4.2, 5.4).

Per log (a smoothed table): the contact set of every sample, either as the experiment declares it (a
constant set in the ``experiment`` metadata) or detected from the raw foot-sensor normal forces; the link
fixed in the world (a sole of a foot in contact, or root_link on the pole as declared) with gravity in its
frame; then, from the smoothed joint kinematics and the URDF (`pipeline.physics.dynamics`), every sensor's
expected wrench and switch and each foot pair's sum in its sole frame.

Contact detection, per foot: the foot's normal force is the sum of its two sensors' raw readings mapped to
the sole frame (minus sign: the floor pushes up). Raw readings carry offsets, so the force is measured
from the foot's zero level, the median of its lowest readings (the foot in the air). A foot touches when
that force rises above ``contact_on`` x robot weight and stops when it falls below ``contact_off`` x robot
weight (hysteresis); a touching foot touches with both parts. Around every change of the contact set a
guard band of +- ``guard_s`` holds every switch at 0: the labels of either set are not trusted there.

Output ``data/labelled/<log>.parquet`` (schema in :mod:`pipeline.logs.schema`) and, in the MLflow run, a
per-log summary: fraction of exact labels per sensor and pair, contact phases, and for simulated logs the
contact agreement with the true contact set and the label error against the true wrenches.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.core.config import Params, load_params, repo_root, resolve_urdf, stage_section
from pipeline.core.errors import ConfigError, DataError
from pipeline.logs import schema as S
from pipeline.physics.dynamics import ContactCase, expected_wrenches
from pipeline.physics.robot import FootPair, RobotModel, load_robot

STAGE = "label"


@dataclass(frozen=True)
class LabelParams:
    """Section `label` of params.yaml (see the comments there)."""

    contact_on: float  # fraction of robot weight: a foot's normal force above this -> touching
    contact_off: float  # fraction of robot weight: below this -> not touching
    guard_s: float  # s: half-width of the guard band around every contact change
    zero_quantile: float  # the foot's zero level is the median of its readings below this quantile

    def __post_init__(self) -> None:
        for name in ("contact_on", "contact_off", "guard_s", "zero_quantile"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"label.{name} must be a number, got {v!r}")
            object.__setattr__(self, name, float(v))
        if not 0.0 < self.contact_off < self.contact_on < 1.0:
            raise ConfigError(
                f"label.contact_off and label.contact_on must satisfy 0 < contact_off < contact_on < 1 "
                f"(fractions of the robot weight), got {self.contact_off} and {self.contact_on}"
            )
        if not 0.0 <= self.guard_s <= 1.0:
            raise ConfigError(f"label.guard_s must be in [0, 1] s, got {self.guard_s}")
        if not 0.01 <= self.zero_quantile <= 0.5:
            raise ConfigError(f"label.zero_quantile must be in [0.01, 0.5], got {self.zero_quantile}")


# --- pure functions ------------------------------------------------------------------------------


def foot_normal_force(robot: RobotModel, pair: FootPair, raw: dict[str, np.ndarray]) -> np.ndarray:
    """(N,) force the floor would need to push the foot up with, N, from the raw readings (N, 6) of its
    two sensors: minus the z component (sole frame) of what the rest of the robot exerts on the foot.
    Offsets and the foot's own weight remain in it (see `zero_level`)."""
    total = np.zeros(len(next(iter(raw.values()))))
    for sensor, sole_x in ((pair.front, pair.sole_X_front), (pair.rear, pair.sole_X_rear)):
        sign = 1.0 if robot.sensors[sensor].direction == "parent_to_child" else -1.0  # -> rest on foot
        total += sign * (raw[sensor] @ sole_x.T)[:, 2]
    return -total


def zero_level(normal: np.ndarray, quantile: float) -> float:
    """The reading of a foot in the air: the median of its readings below the `quantile` quantile."""
    finite = normal[np.isfinite(normal)]
    if finite.size == 0:
        return math.nan
    low = finite[finite <= np.quantile(finite, quantile)]
    return float(np.median(low))


def hysteresis(force: np.ndarray, on: float, off: float) -> np.ndarray:
    """(N,) bool: True from where `force` rises above `on` until it falls below `off` (N; NaN keeps state).
    Starts from the side of the first finite sample."""
    state = np.zeros(force.shape[0], dtype=bool)
    finite = np.flatnonzero(np.isfinite(force))
    current = bool(finite.size and force[finite[0]] > 0.5 * (on + off))
    for k, value in enumerate(force):
        if value > on:
            current = True
        elif value < off:
            current = False
        state[k] = current
    return state


def guard_band(time_s: np.ndarray, changed: np.ndarray, guard_s: float) -> np.ndarray:
    """(N,) bool: samples within `guard_s` of a change; a change at sample k happens halfway between
    samples k-1 and k (`changed[k]` True)."""
    events = 0.5 * (time_s[1:] + time_s[:-1])[changed[1:]]
    if events.size == 0 or guard_s <= 0:
        return np.zeros(time_s.shape[0], dtype=bool)
    idx = np.searchsorted(events, time_s)
    before = np.abs(time_s - events[np.clip(idx - 1, 0, events.size - 1)])
    after = np.abs(events[np.clip(idx, 0, events.size - 1)] - time_s)
    return np.minimum(before, after) < guard_s


@dataclass
class Contacts:
    """Contact sets of a log. sets: the distinct sets; index: (N,) per sample, -1 where no foot touches;
    fixed: (N,) the fixed link per sample ('' where none); guard: (N,) in a guard band; detected: whether
    the contacts were detected (else declared); zero_levels: per foot pair, N."""

    sets: list[frozenset[str]]
    index: np.ndarray
    fixed: np.ndarray
    guard: np.ndarray
    detected: bool
    zero_levels: dict[str, float] = field(default_factory=dict)


def declared_contacts(robot: RobotModel, experiment: dict[str, str], n: int) -> Contacts | None:
    """The experiment's constant contact set, if its metadata declares one."""
    names = [c for c in experiment.get("contacts", "").split(",") if c]
    if not names:
        return None
    for name in names:
        robot.check_link(name, "contact link")
    contacts = frozenset(names)
    fixed = experiment.get("fixed_link") or ""
    if not fixed:
        fixed = sorted(contacts)[0]
    robot.check_link(fixed, "fixed link")
    return Contacts(
        [contacts],
        np.zeros(n, dtype=int),
        np.full(n, fixed, dtype=object),
        np.zeros(n, dtype=bool),
        detected=False,
    )


def detect_contacts(
    robot: RobotModel,
    pairs: list[FootPair],
    raw: dict[str, np.ndarray],
    time_s: np.ndarray,
    cfg: LabelParams,
    gravity: float,
    source: str,
) -> Contacts:
    """Foot contacts from the raw foot-sensor normal forces (see the module docstring)."""
    weight = robot.total_mass() * gravity
    n = time_s.shape[0]
    touching, levels = {}, {}
    for pair in pairs:
        normal = foot_normal_force(robot, pair, raw)
        level = zero_level(normal, cfg.zero_quantile)
        spread = np.nanquantile(normal, 0.95) - np.nanquantile(normal, 0.05) if np.isfinite(level) else 0.0
        if not spread > 2 * cfg.contact_on * weight:
            raise DataError(
                f"{source}: cannot detect the contacts of {pair.name}: its normal force never changes by "
                f"{2 * cfg.contact_on:.0%} of the robot's weight (the foot never lifts or never lands); "
                "declare the contacts in the log's experiment metadata"
            )
        levels[pair.name] = level
        touching[pair.name] = hysteresis(normal - level, cfg.contact_on * weight, cfg.contact_off * weight)
    links = {p.name: robot.sensors[p.front].child_link for p in pairs}
    rear = {p.name: robot.sensors[p.rear].child_link for p in pairs}
    labels = np.array(
        [",".join(p.name for p in pairs if touching[p.name][k]) for k in range(n)], dtype=object
    )
    keys, index = np.unique(labels, return_inverse=True)
    sets = [
        frozenset(c for name in key.split(",") if name for c in (links[name], rear[name])) for key in keys
    ]
    index = np.where(labels == "", -1, index)
    # fixed link: a sole of a touching foot, kept while that foot touches (both soles are still in double
    # support; the choice only picks the frame of the computation)
    sole = {p.name: p.sole for p in pairs}
    fixed = np.full(n, "", dtype=object)
    current = ""
    for k in range(n):
        on = [p.name for p in pairs if touching[p.name][k]]
        if current not in on:
            current = on[0] if on else ""
        fixed[k] = sole[current] if current else ""
    changed = np.r_[False, index[1:] != index[:-1]]
    return Contacts(sets, index, fixed, guard_band(time_s, changed, cfg.guard_s), True, levels)


def label_arrays(
    robot: RobotModel,
    pairs: list[FootPair],
    contacts: Contacts,
    q: np.ndarray,
    dq: np.ndarray,
    ddq: np.ndarray,
    ok: np.ndarray,
    gravity_fixed: np.ndarray,
) -> dict[str, np.ndarray]:
    """Expected wrenches and switches of every sensor and pair for one log, as labelled-table columns.

    q, dq, ddq: (N, n_joints) smoothed kinematics; ok: (N,) samples whose kinematics are usable;
    gravity_fixed: (3,) gravity in the fixed link frame, m/s^2.
    """
    n = q.shape[0]
    names = [*robot.sensors, *(p.name for p in pairs)]
    exp = {name: np.full((n, 6), np.nan) for name in names}
    sw = {name: np.zeros(n, dtype=np.uint8) for name in names}
    usable = ok & (contacts.index >= 0) & ~contacts.guard
    keys = sorted(
        {(int(i), str(f)) for i, f in zip(contacts.index[usable], contacts.fixed[usable], strict=True)}
    )
    for set_id, fixed in keys:
        rows = np.flatnonzero(usable & (contacts.index == set_id) & (contacts.fixed == fixed))
        case = ContactCase.make(contacts.sets[set_id], fixed, gravity_fixed)
        out = expected_wrenches(robot, q[rows], dq[rows], ddq[rows], case, pairs)
        for s in robot.sensors:
            exp[s][rows], sw[s][rows] = out.wrench[s], out.switch[s]
        for p in pairs:
            exp[p.name][rows], sw[p.name][rows] = out.pair_sum[p.name], out.pair_switch[p.name]
    columns: dict[str, np.ndarray] = {}
    for name in names:
        for axis, col in zip(range(6), S.wrench_cols(S.EXPECTED, name), strict=True):
            columns[col] = exp[name][:, axis]
        columns[S.switch_col(name)] = sw[name]
    return columns


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


def _truth_checks(
    truth_path: Path,
    table: pd.DataFrame,
    robot: RobotModel,
    pairs: list[FootPair],
    contacts: Contacts,
    labels: dict[str, np.ndarray],
) -> tuple[float | None, dict]:
    """Contact agreement and label error against a simulated log's truth table."""
    truth = pd.read_parquet(truth_path)
    truth = truth.set_index(S.STAMP).reindex(table[S.STAMP].to_numpy())
    outside = ~contacts.guard
    agreement = None
    if S.CONTACTS in truth:
        true_sets = truth[S.CONTACTS].fillna("").to_numpy()
        ours = np.array(
            [",".join(sorted(contacts.sets[i])) if i >= 0 else "" for i in contacts.index], dtype=object
        )
        valid = outside & (true_sets != "")
        agreement = float(np.mean(ours[valid] == true_sets[valid])) if valid.any() else None
    # true wrench per label name: every sensor in the truth table, and each pair's sum in its sole frame
    true: dict[str, np.ndarray] = {}
    for s in robot.sensors:
        if set(S.wrench_cols(S.TRUE, s)) <= set(truth.columns):
            true[s] = truth[S.wrench_cols(S.TRUE, s)].to_numpy()
    for p in pairs:
        if p.front in true and p.rear in true:
            true[p.name] = true[p.front] @ p.sole_X_front.T + true[p.rear] @ p.sole_X_rear.T
    rmse: dict[str, dict[str, float]] = {}
    for name, value in true.items():
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


def label_table(
    src: Path,
    dst: Path,
    robot: RobotModel,
    pairs: list[FootPair],
    cfg: LabelParams,
    gravity: float,
    truth_dir: Path | None = None,
) -> LogSummary:
    """Label one smoothed table into `dst` (written atomically)."""
    from pipeline.logs.tables import read_table_metadata

    start = time.perf_counter()
    try:
        table = pd.read_parquet(src)
        meta = read_table_metadata(src)
    except (OSError, pa.ArrowException, ValueError) as exc:
        raise DataError(f"{src}: cannot read the smoothed table: {exc}") from None
    experiment = meta.get(S.META_EXPERIMENT.decode()) or {}
    missing_joints = [j for j in robot.joint_names if S.joint_col(S.QS, j) not in table]
    if missing_joints:
        raise DataError(
            f"{src}: no smoothed kinematics for joints {', '.join(missing_joints[:5])} "
            "(run the smooth stage, with the same URDF)"
        )
    missing = [s for s in robot.sensors if S.wrench_cols(S.FT, s)[0] not in table]
    if missing:
        raise DataError(f"{src}: no raw wrench columns for sensors {', '.join(missing)}")
    n = len(table)
    q = table[S.joint_cols(S.QS, robot.joint_names)].to_numpy()
    dq = table[S.joint_cols(S.DQS, robot.joint_names)].to_numpy()
    ddq = table[S.joint_cols(S.DDQS, robot.joint_names)].to_numpy()
    ok = table[S.ok_col(S.KINEMATICS_STREAM)].to_numpy(bool) & np.isfinite(np.c_[q, dq, ddq]).all(axis=1)
    time_s = table[S.TIME].to_numpy()
    gravity_text = experiment.get("gravity", "")
    try:
        gravity_fixed = np.array([float(v) for v in gravity_text.split()]) if gravity_text else None
    except ValueError:
        raise DataError(f"{src}: experiment metadata gravity {gravity_text!r} is not three numbers") from None
    if gravity_fixed is None or gravity_fixed.shape != (3,):
        gravity_fixed = np.array([0.0, 0.0, -gravity])

    contacts = declared_contacts(robot, experiment, n)
    if contacts is None:
        raw = {}
        for pair in pairs:
            for s in (pair.front, pair.rear):
                raw[s] = table[S.wrench_cols(S.FT, s)].to_numpy()
        contacts = detect_contacts(robot, pairs, raw, time_s, cfg, gravity, str(src))
    columns = label_arrays(robot, pairs, contacts, q, dq, ddq, ok, gravity_fixed)

    out = {S.STAMP: table[S.STAMP].to_numpy(), S.TIME: time_s}
    for s in robot.sensors:
        for cols in (
            S.wrench_cols(S.FT, s),
            S.vector_cols(S.ACC, s),
            S.vector_cols(S.GYR, s),
            [S.temperature_col(s)],
            [S.ok_col(stream, s) for stream in (S.WRENCH_STREAM, S.IMU_STREAM, S.TEMPERATURE_STREAM)],
        ):
            for c in cols:
                out[c] = table[c].to_numpy()
    out.update(columns)
    out[S.CONTACTS] = np.array(
        [",".join(sorted(contacts.sets[i])) if i >= 0 else "" for i in contacts.index], dtype=object
    )
    out[S.FIXED_LINK] = contacts.fixed.astype(object)
    out[S.GUARD] = contacts.guard

    names = [*robot.sensors, *(p.name for p in pairs)]
    summary = LogSummary(
        log=src.stem,
        samples=n,
        detected=contacts.detected,
        exact_fraction={name: float(np.mean(columns[S.switch_col(name)])) if n else 0.0 for name in names},
        contact_phases=_phases(time_s, contacts),
        guard_fraction=float(np.mean(contacts.guard)) if n else 0.0,
        zero_levels=contacts.zero_levels,
        seconds=0.0,
    )
    truth_path = truth_dir / f"{src.stem}{S.TRUTH_SUFFIX}{S.PARQUET_SUFFIX}" if truth_dir else None
    if truth_path is not None and truth_path.is_file():
        summary.truth_agreement, summary.label_rmse = _truth_checks(
            truth_path, table, robot, pairs, contacts, columns
        )
    label_meta = {
        "pairs": {
            p.name: {
                "front": p.front,
                "rear": p.rear,
                "sole": p.sole,
                "sole_X_front": p.sole_X_front.ravel().tolist(),
                "sole_X_rear": p.sole_X_rear.ravel().tolist(),
            }
            for p in pairs
        },
        "params": asdict(cfg),
        "urdf": str(robot.urdf_path),
    }
    kv = {S.META_EXPERIMENT: experiment, S.META_LABEL: label_meta}
    for key in (S.META_INGEST, S.META_SMOOTH):
        if key.decode() in meta:
            kv[key] = meta[key.decode()]
    schema = S.arrow_schema(list(out), S.KIND_LABELLED, kv)
    arrow = pa.Table.from_pydict(
        {k: pa.array(v, type=schema.field(k).type) for k, v in out.items()}, schema=schema
    )
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    try:
        pq.write_table(arrow, tmp, compression="zstd")
        os.replace(tmp, dst)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    summary.seconds = time.perf_counter() - start
    return summary


# --- the stage -----------------------------------------------------------------------------------


def run(
    params: Params,
    in_dir: str | Path,
    out_dir: str | Path,
    truth_dir: str | Path | None = None,
    *,
    progress: bool | None = None,
) -> list[LogSummary]:
    """Label every smoothed table of `in_dir` into `out_dir`, in one MLflow run."""
    import mlflow

    from pipeline.core.tracking import stage_run
    from pipeline.logs.smoothing import find_tables

    cfg = stage_section(params, STAGE, LabelParams)
    src, out = Path(in_dir), Path(out_dir)
    if not src.is_dir():
        raise DataError(f"{src}: input directory not found")
    tables = find_tables(src)
    if not tables:
        raise DataError(f"{src}: no smoothed *.parquet tables")
    robot = load_robot(resolve_urdf(params.robot.urdf, repo_root()))
    pairs = [robot.foot_pair(p.name, p.front, p.rear, p.sole) for p in params.robot.foot_pairs]
    show = sys.stderr.isatty() if progress is None else progress
    summaries: list[LogSummary] = []
    start = time.perf_counter()
    with stage_run(STAGE, {"label": asdict(cfg), "robot": asdict(params.robot)}):
        from rich.console import Console
        from rich.progress import Progress

        with Progress(console=Console(stderr=True), transient=True, disable=not show) as bar:
            task = bar.add_task("label", total=len(tables))
            for table in tables:
                summaries.append(
                    label_table(
                        table,
                        out / table.name,
                        robot,
                        pairs,
                        cfg,
                        params.robot.gravity,
                        Path(truth_dir) if truth_dir else None,
                    )
                )
                bar.advance(task)
        seconds = time.perf_counter() - start
        samples = sum(s.samples for s in summaries)
        metrics: dict[str, float] = {
            "logs": len(summaries),
            "samples": samples,
            "seconds": seconds,
            "samples_per_s": samples / seconds if seconds else 0.0,
        }
        for s in summaries:
            metrics[f"{s.log}.guard_fraction"] = s.guard_fraction
            if s.truth_agreement is not None:
                metrics[f"{s.log}.contact_agreement"] = s.truth_agreement
            for name, frac in s.exact_fraction.items():
                metrics[f"{s.log}.exact.{name}"] = frac
            for name, err in s.label_rmse.items():
                metrics[f"{s.log}.label_rmse_force.{name}"] = err["force"]
                metrics[f"{s.log}.label_rmse_torque.{name}"] = err["torque"]
        mlflow.log_metrics(metrics)
        mlflow.log_dict({"logs": [asdict(s) for s in summaries]}, "label_summary.json")
    return summaries


def _cmd(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    summaries = run(params, args.inputs, args.out, args.truth)
    samples = sum(s.samples for s in summaries)
    seconds = sum(s.seconds for s in summaries)
    print(
        f"labelled {len(summaries)} log(s), {samples} samples, {samples / max(seconds, 1e-9):.0f} samples/s, "
        f"into {args.out}"
    )
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal label IN OUT [--truth DIR]`."""
    parser = subparsers.add_parser(
        STAGE, help="contacts, switches and expected wrenches", description=(__doc__ or "").split("\n\n")[0]
    )
    parser.add_argument("inputs", type=Path, metavar="IN", help="directory of smoothed <log>.parquet tables")
    parser.add_argument("out", type=Path, help="output directory for the labelled <log>.parquet tables")
    parser.add_argument(
        "--truth",
        type=Path,
        default=None,
        help="directory of simulated <log>.truth.parquet tables (optional): adds the contact "
        "agreement and label error against truth to the summary",
    )
    parser.add_argument("--params", type=Path, default=None, help="params file (default: repo params.yaml)")
    parser.set_defaults(func=_cmd)


__all__ = ["LabelParams", "detect_contacts", "guard_band", "hysteresis", "label_arrays", "label_table", "run"]
