"""A log's re-zeroing: the still stretch it reads, the solve (`pipeline.deploy.rezero`), pose dependence.

The stretch is a given window (it must be still: `pipeline.deploy.still`) or the first still stretch of
the log, its first ``deploy.rezero.duration_s`` seconds; several logs' stretches are solved together
(standing on the left foot, then on the right: what each leaves open the other may fix). A log held still
in several poses also says whether the offsets depend on the pose: each pose is re-zeroed alone, and the
spread of a sensor's offsets over the poses is compared with its reading's noise (std over the stretch);
above ``pose_limit`` times the noise on an axis, the sensor's calibration is named pose-dependent (its
hysteresis, or a model error the labels carry, differs from pose to pose).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.core.errors import DataError
from pipeline.deploy.params import RezeroParams
from pipeline.deploy.rezero import Prior, Rezero, StretchData, solve, stretch_data
from pipeline.deploy.shrink import LabelError
from pipeline.deploy.still import Motion, StillLimits, Stretch, motion, stretches, window
from pipeline.logs import schema as S


@dataclass
class LogTables:
    """A log's labelled and smoothed tables (same rows) and the motion read from them."""

    name: str
    labelled: pd.DataFrame
    motion: Motion


def limits(cfg: RezeroParams) -> StillLimits:
    return StillLimits(cfg.still_joint_rad_s, cfg.still_gyro_rad_s, cfg.min_s)


def log_tables(name: str, labelled: Any, smoothed: Any, robot: Any, cfg: RezeroParams) -> LogTables:
    """Read a log's tables (paths) and find how it moves."""
    table = pd.read_parquet(labelled)
    joints = S.joint_cols(S.DQS, robot.joint_names)
    smooth = pd.read_parquet(smoothed, columns=[S.STAMP, *(c for c in joints if c in _columns(smoothed))])
    return LogTables(name, table, motion(table, smooth, robot.joint_names, list(robot.sensors), limits(cfg)))


def _columns(path: Any) -> set[str]:
    import pyarrow.parquet as pq

    return set(pq.read_schema(path).names)


def pick(log: LogTables, cfg: RezeroParams, start_s: float | None = None) -> Stretch:
    """The stretch a re-zeroing reads: from `start_s` (s of the log's time) for ``duration_s``, which must
    be still; None: the first still stretch, at most ``duration_s`` of it. DataError (one line) if the
    window moves, or no stretch is still."""
    m = log.motion
    if start_s is not None:
        start, stop = window(m, start_s, cfg.duration_s)
        if stop - start < 2:
            raise DataError(f"{log.name}: no samples in {start_s:g}-{start_s + cfg.duration_s:g} s")
        picked = m.stretch(log.name, start, stop)
        _check_still(picked, m, cfg)
        return picked
    found = [s for s in stretches(m, log.name) if s.seconds >= cfg.min_s]
    if not found:
        fastest = m.stretch(log.name, 0, len(m.time_s))
        raise DataError(
            f"{log.name}: the robot is never still for {cfg.min_s:g} s (deploy.rezero.min_s; joints under "
            f"{cfg.still_joint_rad_s:g} rad/s, FT boards under {cfg.still_gyro_rad_s:g} rad/s; fastest "
            f"joint {fastest.joint} at {fastest.joint_rad_s:.3g} rad/s): nothing to re-zero from"
        )
    first = found[0]
    return m.stretch(log.name, first.start, min(first.stop, window(m, first.t0, cfg.duration_s)[1]))


def _check_still(picked: Stretch, m: Motion, cfg: RezeroParams) -> None:
    where = f"{picked.log}: {picked.t0:.2f}-{picked.t1:.2f} s"
    if picked.joint_rad_s > cfg.still_joint_rad_s:
        raise DataError(
            f"{where}: the robot moved (joint {picked.joint} at {picked.joint_rad_s:.3g} rad/s > "
            f"deploy.rezero.still_joint_rad_s = {cfg.still_joint_rad_s:g}): re-zero from a still stretch"
        )
    if picked.gyro_rad_s is not None and picked.gyro_rad_s > cfg.still_gyro_rad_s:
        raise DataError(
            f"{where}: the robot moved (an FT board turning at {picked.gyro_rad_s:.3g} rad/s > "
            f"deploy.rezero.still_gyro_rad_s = {cfg.still_gyro_rad_s:g}): re-zero from a still stretch"
        )
    if "|" in picked.contacts:
        raise DataError(f"{where}: the contacts change ({picked.contacts}): re-zero from one stance")


def stretch_name(picked: Stretch) -> str:
    return f"{picked.log} {picked.t0:.2f}-{picked.t1:.2f} s (contacts {picked.contacts or 'none'})"


def _data(
    log: LogTables, picked: Stretch, deployment: Any, sensors: Sequence[str], cuts: Sequence[Any]
) -> StretchData:
    rows = log.labelled.iloc[picked.start : picked.stop]
    return stretch_data(stretch_name(picked), rows, deployment, sensors, cuts)


def rezero_logs(
    deployment: Any, picked: Sequence[tuple[LogTables, Stretch]], sensors: Sequence[str], cuts: Sequence[Any],
    cfg: RezeroParams, poses: Sequence[Mapping[str, Any]] = (),
) -> Rezero:  # fmt: skip
    """Solve the offsets of `sensors` from the stretches `picked` together (module docstring); the floor of
    what is applied includes the spread over the still poses of the first of `poses` (`pose_dependence` of
    the logs) that has several."""
    data = [_data(log, s, deployment, sensors, cuts) for log, s in picked]
    spread = pose_spread(poses)
    return solve(deployment, data, sensors, prior(cfg), label_error(cfg), cfg.significance, spread)


def pose_spread(poses: Sequence[Mapping[str, Any]]) -> dict[str, list[float]]:
    """Sensor -> the spread of its offsets over the still poses (N, Nm) of the first log of `poses`
    (`pose_dependence` of each) that has several; none: empty."""
    for log in poses:
        if log["sensors"]:
            return {s: p["spread"] for s, p in log["sensors"].items()}
    return {}


def prior(cfg: RezeroParams) -> Prior:
    return Prior(cfg.prior_force_n, cfg.prior_torque_nm)


def label_error(cfg: RezeroParams) -> LabelError:
    return LabelError(cfg.label_mass_rel, cfg.label_com_m)


def pose_dependence(
    deployment: Any, log: LogTables, sensors: Sequence[str], cuts: Sequence[Any], cfg: RezeroParams
) -> dict[str, Any]:
    """Each still pose of `log` re-zeroed alone; per sensor re-zeroed in full in every pose, the offsets'
    spread over the poses (std, N / Nm per axis), the reading's noise (std over a pose, mean of the poses),
    their worst-axis ratio and whether it exceeds ``pose_limit``. Fewer than two poses: ``poses`` only."""
    poses, results = [], []
    for found in stretches(log.motion, log.name):
        if found.seconds < cfg.min_s:
            continue
        m = log.motion
        picked = m.stretch(log.name, found.start, min(found.stop, window(m, found.t0, cfg.duration_s)[1]))
        data = _data(log, picked, deployment, sensors, cuts)
        if data.equations:
            poses.append((picked, data))
            results.append(solve(deployment, [data], sensors, prior(cfg)))
    out: dict[str, Any] = {"log": log.name, "poses": [[p.t0, p.t1] for p, _ in poses], "sensors": {}}
    if len(results) < 2:
        return out
    for s in sensors:
        if any(r.status(s) != "all" for r in results):
            continue
        spread = np.std([r.estimated[s] for r in results], axis=0, ddof=1)
        noise = np.mean([d.noise[s] for _, d in poses], axis=0)
        ratio = float((spread / noise).max())
        out["sensors"][s] = {
            "offsets": [[float(v) for v in r.estimated[s]] for r in results],
            "spread": spread.tolist(), "noise": noise.tolist(), "ratio": ratio,
            "depends": bool(ratio > cfg.pose_limit),
        }  # fmt: skip
    return out


def record(result: Rezero, picked: Sequence[Stretch], poses: dict[str, Any] | None) -> dict[str, Any]:
    """What a re-zeroing reports (beside its offsets): the stretches and how still, the solve, per sensor
    its status, std and equations, and the pose dependence."""
    return {
        "stretches": [p.record() | {"name": stretch_name(p)} for p in picked],
        "samples": result.samples,
        "iterations": result.iterations,
        "residual_rms": result.residual_rms,
        "status": {s: result.status(s) for s in result.sensors},
        "pose_dependence": poses,
    }


def rezero_day(
    exported: Any, logs: Sequence[Any], sensors: Sequence[str], robot: Any, cuts: Sequence[Any],
    cfg: RezeroParams,
) -> dict[str, Any]:  # fmt: skip
    """A deployment day re-zeroed from its first still seconds: the first still stretch of its logs (in the
    day's order, `pipeline.deploy.prepare.DeployLog`), the export in `exported` as delivered, the group's
    `sensors`. Returns the offsets reached (sensor -> 6 numbers), per sensor its entry, and `record`'s
    fields; or ``{"error": why}`` when the day has no still stretch, or none with an exact label."""
    from pipeline.export.runtime import Deployment

    # the offsets are solved for offline, with the float64 graphs whatever runs the calibration (a float32
    # runtime's rounding would only slow the solver's convergence); the days are then judged through it
    deployment = Deployment.load(exported, offsets=False, runtime="onnxruntime")
    chosen = [s for s in sensors if s in deployment.sensors()]
    for log in logs:
        tables = log_tables(log.name, log.labelled, log.smoothed, robot, cfg)
        try:
            picked = pick(tables, cfg)
        except DataError:
            continue
        poses = pose_dependence(deployment, tables, chosen, cuts, cfg)
        try:
            result = rezero_logs(deployment, [(tables, picked)], chosen, cuts, cfg, [poses])
        except DataError as exc:  # the first still seconds have no exact label of the group's sensors
            return {"error": str(exc)}
        offsets = {s: [float(v) for v in value] for s, value in result.rezeroed().values.items()}
        return {"offsets": offsets, "sensors": result.record(), **record(result, [picked], poses)}
    return {"error": f"no still stretch of {cfg.min_s:g} s or more in the day's logs: not re-zeroed"}
