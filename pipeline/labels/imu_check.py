"""The FT boards' IMU checked against the kinematics: which axis map its accelerometer and gyroscope follow.

The robot model says what a board's accelerometer reads: the proper acceleration of the sensor frame, minus
gravity plus the frame's own acceleration, in the sensor frame (`pipeline.physics.imu`: from the smoothed
joint kinematics and the link fixed in the world, as the labels; the simulator's boards read in that frame).
On quasi-static stretches of a log (the board turning slower than ``still_gyro_rad_s`` by the kinematics
and by its gyroscope, its frame accelerating less than ``still_acc_m_s2``, for ``still_min_s`` or more, one
contact set, outside guard bands) gravity dominates that reading, and the tenth of g the motion may add is
in the prediction (an error of a fifth of it, an elastic joint or a clock offset, stays below 0.2 m/s^2).
Each of the 48 signed permutations (`pipeline.logs.imu_axes`) is fitted there: its residual RMS per axis,
the worst 5 % of samples left out (vibration bursts, impacts). A map is identified when it fits within
``max_rms_m_s2`` and every other one leaves at least twice that, over gravity directions ``min_spread_deg``
apart in the sensor frame (a single posture leaves a rotation about gravity free). The best general
rotation's angle from the map is kept as a sanity figure (a degree or two for a board mounted as the map).

The gyroscope (the same chip) is fitted alike against the frame's angular velocity wherever the kinematics
turn the board faster than ``gyro_min_rad_s``, about axes ``min_spread_deg`` apart (``gyro_max_rms_rad_s``).
The board's map is the accelerometer's; where it has no quasi-static stretch or too few postures, the
gyroscope's alone; where both identify one they must agree (``ingest.imu_axes`` maps both alike). The
identity passes; another map fails, named in the sensor frame (composed with what ``ingest.imu_axes``
already applied) with the params key that fixes it; neither identified: "not checked", with the reasons.

Default thresholds (``label.imu_check``) against ``simulate.imu``: an accelerometer's bias is up to 0.2
m/s^2 per axis and its noise 0.05 m/s^2, so a correct board leaves up to ~0.2 m/s^2 RMS per axis (0.06-0.17
on the default data): 0.5 fits, while a wrong map misses by a share of g wherever gravity turns by tens of
degrees in the sensor frame. A gyroscope's bias is up to 0.01 rad/s, its noise 0.005 rad/s (0.006-0.011
measured): 0.05 fits, where a wrong map misses by a share of the 0.2 rad/s and more the board turns at.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.labels.contacts import Contacts
from pipeline.labels.imu_params import ImuCheckParams
from pipeline.logs import schema as S
from pipeline.logs.imu_axes import (
    FAILED,
    IDENTITY,
    NOT_CHECKED,
    PASSED,
    SIGNED_PERMUTATIONS,
    AxisMap,
    axis_text,
    compose,
    matrix,
)
from pipeline.physics.dynamics import ContactCase
from pipeline.physics.imu import SensorMotion, sensor_motion
from pipeline.physics.robot import RobotModel

EVAL_HZ = 25.0  # the check reads at most this many samples a second (the kinematics cost ~70 us a sample;
# a stretch lasts a second or more)
TRIM = 0.05  # share of the worst residuals left out of a fit's RMS
MAX_SPREAD_SAMPLES = 256  # directions compared pairwise for the spread (evenly spaced)


# --- fits ----------------------------------------------------------------------------------------


def fit_maps(predicted: np.ndarray, measured: np.ndarray) -> list[tuple[AxisMap, float]]:
    """Every signed permutation with its residual RMS per axis (worst `TRIM` left out), best first.

    predicted, measured: (N, 3) sensor-frame prediction and board reading; a map M predicts ``M p``.
    """
    out = []
    for axes in SIGNED_PERMUTATIONS:
        err = np.sum((measured - predicted @ matrix(axes).T) ** 2, axis=1)
        keep = max(1, int(math.ceil(len(err) * (1.0 - TRIM))))
        out.append((axes, math.sqrt(float(np.mean(np.partition(err, keep - 1)[:keep])) / 3.0)))
    return sorted(out, key=lambda item: item[1])


def spread_deg(vectors: np.ndarray) -> float:
    """The largest angle between the lines of two of the (N, 3) vectors (evenly spaced ones of many), deg,
    in [0, 90]: a map that keeps one line keeps its two directions, so a vector and its opposite (a joint
    swinging back) identify no more than one of them."""
    if len(vectors) < 2:
        return 0.0
    pick = vectors[np.unique(np.linspace(0, len(vectors) - 1, MAX_SPREAD_SAMPLES).round().astype(int))]
    unit = pick / np.linalg.norm(pick, axis=1, keepdims=True)
    return math.degrees(math.acos(float(np.clip(np.abs(unit @ unit.T).min(), 0.0, 1.0))))


def rotation_from_map_deg(predicted: np.ndarray, measured: np.ndarray, axes: AxisMap) -> float:
    """The angle (deg) between the best-fitting orthogonal matrix of the handedness of `axes` (least
    squares, Kabsch) and the map itself: a few degrees for a board mounted as the map says."""
    u, _, vt = np.linalg.svd(measured.T @ predicted)
    m = matrix(axes)
    d = np.sign(np.linalg.det(m)) * np.sign(np.linalg.det(u @ vt))
    q = u @ np.diag([1.0, 1.0, d]) @ vt
    return math.degrees(math.acos(float(np.clip((np.trace(m.T @ q) - 1.0) / 2.0, -1.0, 1.0))))


def stretches(
    time_s: np.ndarray, group: np.ndarray, slow: np.ndarray, step_s: float, min_s: float
) -> np.ndarray:
    """(N,) bool: the `slow` samples in runs of one `group` (contact case), without a time gap over 1.5
    `step_s`, spanning at least `min_s` (s; a sample counts `step_s`)."""
    out = np.zeros(len(slow), dtype=bool)
    if not len(slow):
        return out
    brk = np.r_[True, (group[1:] != group[:-1]) | (np.diff(time_s) > 1.5 * step_s) | ~slow[1:] | ~slow[:-1]]
    starts = np.flatnonzero(brk)
    for a, b in zip(starts, np.r_[starts[1:], len(slow)], strict=True):
        if slow[a] and time_s[b - 1] - time_s[a] + step_s >= min_s - 1e-9:
            out[a:b] = True
    return out


@dataclass
class MapFit:
    """One IMU vector fitted over the signed permutations: the identified map, or why none is.

    samples: read; seconds: their time, s; spread_deg: the largest angle between two predicted directions;
    fits: every map with its residual RMS per axis, best first ([] where not fitted).
    """

    samples: int
    seconds: float
    spread_deg: float
    fits: list[tuple[AxisMap, float]]
    axes: AxisMap | None
    reason: str | None

    def rms(self, axes: AxisMap) -> float | None:
        """The residual RMS of `axes` (None before a fit)."""
        return next((r for a, r in self.fits if a == axes), None)

    def record(self, unit: str) -> dict[str, Any]:
        """JSON: samples, seconds, spread, the identified map (or the reason), the RMS of the best map, the
        next one and the identity (`unit`: m_s2 or rad_s)."""
        out: dict[str, Any] = {
            "samples": self.samples,
            "seconds": self.seconds,
            "spread_deg": self.spread_deg,
        }
        out["identified"], out["reason"] = (list(self.axes) if self.axes else None), self.reason
        if self.fits:
            out["best"] = list(self.fits[0][0])
            for key, axes in (("", self.fits[0][0]), ("_next", self.fits[1][0]), ("_identity", IDENTITY)):
                out[f"rms{key}_{unit}"] = self.rms(axes)
        return out


def identify(
    predicted: np.ndarray,
    measured: np.ndarray,
    seconds: float,
    limits: tuple[float, float],
    what: str,
    unit: str,
) -> MapFit:
    """The signed permutation that maps `predicted` (N, 3) onto `measured` (N, 3), over `seconds`, if one
    fits within ``limits[0]`` (per axis, `unit`) and no other within twice it, over directions of `what`
    that span at least ``limits[1]`` deg."""
    max_rms, min_spread = limits
    spread = spread_deg(predicted)
    if spread < min_spread:
        reason = f"{what} stays within {spread:.0f} deg in the sensor frame (at least {min_spread:g} needed)"
        return MapFit(len(predicted), seconds, spread, [], None, reason)
    fits = fit_maps(predicted, measured)
    (best, rms), (other, other_rms) = fits[0], fits[1]
    reason = None
    if rms > max_rms:
        reason = (
            f"no axis map fits: the best, {axis_text(best)}, leaves {rms:.2g} {unit} (more than {max_rms:g})"
        )
    elif other_rms < 2 * max_rms:
        reason = (
            f"two axis maps fit: {axis_text(best)} ({rms:.2g} {unit}), {axis_text(other)} ({other_rms:.2g})"
        )
    return MapFit(len(predicted), seconds, spread, fits, None if reason else best, reason)


@dataclass
class Evaluated:
    """The samples of a log the check reads (every `stride`-th usable one): rows (M,) into the table, their
    times (M,) s, contact case (M,) int, and each sensor frame's motion there (`SensorMotion`, M rows)."""

    rows: np.ndarray
    time_s: np.ndarray
    case: np.ndarray
    step_s: float  # s between two evaluated samples of a run
    motion: dict[str, SensorMotion]


def evaluated_samples(
    robot: RobotModel,
    contacts: Contacts,
    kinematics: tuple[np.ndarray, np.ndarray, np.ndarray],
    ok: np.ndarray,
    gravity_fixed: np.ndarray,
    time_s: np.ndarray,
) -> Evaluated:
    """Every sensor frame's motion on the samples the check reads: kinematics ok, a contact set, outside
    guard bands, at most `EVAL_HZ` a second. kinematics: (q, dq, ddq), each (N, n_joints)."""
    n = len(time_s)
    dt = float(np.median(np.diff(time_s))) if n > 1 else 1.0 / EVAL_HZ
    stride = max(1, int(round(1.0 / (EVAL_HZ * dt))))
    usable = ok & (contacts.index >= 0) & ~contacts.guard & (np.arange(n) % stride == 0)
    rows = np.flatnonzero(usable)
    keys = sorted({(int(i), str(f)) for i, f in zip(contacts.index[rows], contacts.fixed[rows], strict=True)})
    case = np.full(len(rows), -1)
    motion = {s: SensorMotion(*(np.full((len(rows), 3), np.nan) for _ in range(3))) for s in robot.sensors}
    for k, (set_id, fixed) in enumerate(keys):
        part = (contacts.index[rows] == set_id) & (contacts.fixed[rows] == fixed)
        case[part] = k
        contact_case = ContactCase.make(contacts.sets[set_id], fixed, gravity_fixed)
        q, dq, ddq = (x[rows[part]] for x in kinematics)
        for s, m in sensor_motion(robot, q, dq, ddq, contact_case).items():
            for name in ("rest", "motion", "angular"):
                getattr(motion[s], name)[part] = getattr(m, name)
    return Evaluated(rows, time_s[rows], case, stride * dt, motion)


def _norm(x: np.ndarray) -> np.ndarray:
    return np.linalg.norm(x, axis=1)


def fit_accelerometer(
    ev: Evaluated, m: SensorMotion, acc: np.ndarray, gyr: np.ndarray, ok: np.ndarray, cfg: ImuCheckParams
) -> tuple[MapFit, np.ndarray]:
    """(the accelerometer's fit on the quasi-static stretches, their (M,) mask) over the evaluated samples:
    `acc`, `gyr` (M, 3) the board's readings there, `ok` (M,) usable."""
    g, a = cfg.still_gyro_rad_s, cfg.still_acc_m_s2
    slow = (
        ok & (_norm(m.angular) <= g) & (_norm(np.where(ok[:, None], gyr, 0.0)) <= g) & (_norm(m.motion) <= a)
    )
    still = stretches(ev.time_s, ev.case, slow, ev.step_s, cfg.still_min_s)
    seconds = float(still.sum() * ev.step_s)
    if not still.any():
        why = f"no quasi-static stretch of {cfg.still_min_s:g} s (below {g:g} rad/s and {a:g} m/s^2)"
        return MapFit(0, 0.0, 0.0, [], None, why), still
    limits = (cfg.max_rms_m_s2, cfg.min_spread_deg)
    return identify(m.proper[still], acc[still], seconds, limits, "gravity", "m/s^2"), still


def fit_gyroscope(
    ev: Evaluated, m: SensorMotion, gyr: np.ndarray, ok: np.ndarray, cfg: ImuCheckParams
) -> MapFit:
    """The gyroscope's fit wherever the kinematics turn the board faster than ``gyro_min_rad_s``."""
    turning = ok & (_norm(m.angular) >= cfg.gyro_min_rad_s)
    seconds = float(turning.sum() * ev.step_s)
    if seconds < cfg.still_min_s:
        why = f"the board turns faster than {cfg.gyro_min_rad_s:g} rad/s for {seconds:.1f} s only"
        return MapFit(int(turning.sum()), seconds, 0.0, [], None, why)
    limits = (cfg.gyro_max_rms_rad_s, cfg.min_spread_deg)
    return identify(m.angular[turning], gyr[turning], seconds, limits, "the rotation axis", "rad/s")


def check_sensor(
    ev: Evaluated,
    sensor: str,
    imu: tuple[np.ndarray, np.ndarray, np.ndarray],
    cfg: ImuCheckParams,
    applied: AxisMap | None = None,
) -> dict[str, Any]:
    """The check of one sensor on a log's evaluated samples: its record (`verdict`).

    imu: (accelerometer (N, 3) m/s^2, gyroscope (N, 3) rad/s, ok (N,) bool), the table's whole columns;
    applied: the map ``ingest.imu_axes`` applied to this log's board (None: none).
    """
    acc, gyr, ok = (x[ev.rows] for x in imu)
    m = ev.motion[sensor]
    ok = ok.astype(bool) & np.isfinite(np.c_[acc, gyr, m.rest]).all(axis=1)
    if not ok.any():
        nothing = MapFit(0, 0.0, 0.0, [], None, "no IMU sample with usable kinematics")
        return verdict(sensor, nothing, nothing, applied)
    acc_fit, still = fit_accelerometer(ev, m, acc, gyr, ok, cfg)
    out = verdict(sensor, acc_fit, fit_gyroscope(ev, m, gyr, ok, cfg), applied)
    if acc_fit.fits:  # the sanity figure: how far the best general rotation (or mirror) lies from the map
        out["accelerometer"]["rotation_deg"] = rotation_from_map_deg(
            m.proper[still], acc[still], acc_fit.fits[0][0]
        )
    return out


def _evidence(acc: MapFit, gyro: MapFit) -> str:
    """What identified the map, e.g. ``accelerometer: residual 0.14 m/s^2 over 3.6 s quasi-static, the
    identity's 9.3; gyroscope: ...`` (or why the accelerometer could not)."""
    parts = []
    for fit, what, unit in ((acc, "accelerometer", "m/s^2 over"), (gyro, "gyroscope", "rad/s over")):
        if fit.axes is not None:
            during = "quasi-static" if fit is acc else "turning"
            other = f"the next map's {fit.fits[1][1]:.2g}"
            if fit.axes != IDENTITY:
                other = f"the identity's {fit.rms(IDENTITY):.2g}"
            parts.append(
                f"{what}: residual {fit.rms(fit.axes):.2g} {unit} {fit.seconds:.1f} s {during}, {other}"
            )
    if acc.axes is None:
        parts.append(f"accelerometer not checked: {acc.reason}")
    return "; ".join(parts)


def verdict(sensor: str, acc: MapFit, gyro: MapFit, applied: AxisMap | None) -> dict[str, Any]:
    """The check's record of one sensor (JSON): ``status`` (passed, failed, not checked) and its one-line
    ``message`` (a ``reason`` where not checked); ``axes``: the board's axes in the sensor frame where
    identified (by the accelerometer on quasi-static stretches, else by the gyroscope alone; where both
    identify one they must agree); ``applied``: what ``ingest.imu_axes`` mapped; ``accelerometer`` and
    ``gyroscope``: their fits (`MapFit.record`)."""
    base = applied or IDENTITY
    out: dict[str, Any] = {"applied": list(applied) if applied else None, "axes": None}
    out["accelerometer"], out["gyroscope"] = acc.record("m_s2"), gyro.record("rad_s")
    found = acc.axes or gyro.axes
    if found is None:
        out["status"] = NOT_CHECKED
        out["reason"] = f"accelerometer: {acc.reason}; gyroscope: {gyro.reason}"
        out["message"] = f"{sensor}: IMU not checked ({out['reason']})"
        return out
    board = compose(base, found)
    out["axes"] = list(board)
    evidence = _evidence(acc, gyro)
    if acc.axes and gyro.axes and acc.axes != gyro.axes:
        out["status"] = FAILED
        out["message"] = (
            f"{sensor}: the IMU's accelerometer axes are {axis_text(board)} of the sensor frame, its "
            f"gyroscope's {axis_text(compose(base, gyro.axes))} ({evidence}): ingest.imu_axes maps both "
            "alike; fix the board or train 7-input networks"
        )
    elif found == IDENTITY:
        out["status"] = PASSED
        out["message"] = f"{sensor}: the IMU's axes are the sensor frame's ({evidence})"
    else:
        fix = f"set ingest.imu_axes: {{{sensor}: [{', '.join(board)}]}}"
        if board == IDENTITY:
            fix = f"remove ingest.imu_axes.{sensor} (the board needs none)"
        out["status"] = FAILED
        out["message"] = (
            f"{sensor}: the IMU's axes are {axis_text(board)} of the sensor frame ({evidence}): {fix}"
        )
    return out


def check_log(
    robot: RobotModel,
    table: Any,
    meta: dict[str, Any],
    contacts: Contacts,
    kinematics: tuple[np.ndarray, np.ndarray, np.ndarray],
    ok: np.ndarray,
    gravity_fixed: np.ndarray,
    cfg: Any,
) -> dict[str, dict[str, Any]]:
    """Every sensor's check on one smoothed table: sensor -> its record (`verdict`), the ``imu_axes`` of the
    labelled table's ``ftcal.label`` metadata.

    table: DataFrame with the ``time_s``, ``acc``, ``gyr`` and ``ok.imu`` columns of `pipeline.logs.schema`;
    meta: its ftcal metadata (``ftcal.ingest`` says which maps ``ingest.imu_axes`` applied); kinematics:
    (q, dq, ddq) smoothed, each (N, n_joints); ok: (N,) samples whose kinematics are usable; gravity_fixed:
    (3,) in the fixed link's frame, m/s^2; cfg: `ImuCheckParams` or its mapping.
    """
    cfg = ImuCheckParams.from_mapping(cfg)
    applied = (meta.get(S.META_INGEST.decode()) or {}).get("imu_axes") or {}
    ev = evaluated_samples(robot, contacts, kinematics, ok, gravity_fixed, table[S.TIME].to_numpy())
    out = {}
    for s in robot.sensors:
        imu = tuple(
            table[c].to_numpy()
            for c in (S.vector_cols(S.ACC, s), S.vector_cols(S.GYR, s), S.ok_col(S.IMU_STREAM, s))
        )
        out[s] = check_sensor(ev, s, imu, cfg, tuple(applied[s]) if applied.get(s) else None)  # type: ignore[arg-type]
    return out
