"""Still stretches of a log: where a re-zeroing may read the sensors' offsets.

A re-zeroing compares the calibrated readings with their exact labels over a few seconds, and trusts
them only if the robot stood still: every joint slower than ``still_joint_rad_s`` (the smoothed joint
velocities, rad/s) and, where the FT boards have a gyroscope, every board turning slower than
``still_gyro_rad_s`` (its gyroscope's norm, low-passed: the board speed `pipeline.evaluation.noise`
measures), with one contact set and outside the labeller's guard bands, for at least ``min_s`` seconds.
Moving, the labels lean on the smoothed accelerations and the readings on the sensors' hysteresis; still,
neither matters.

A pose is a still stretch between two motions; a log held in several poses (`poses`) tells whether the
offsets a re-zeroing finds depend on the pose.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.logs import schema as S

LOWPASS_HZ, LOWPASS_ORDER = 2.0, 2  # the gyroscopes' low-pass before their norm (noise and vibration out)
EDGE_S = 0.5  # s left out at the ends of a stretch of contiguous samples (the filter's transients)
MAX_GAP_S = 0.1  # s: a longer gap between samples ends a stretch


@dataclass(frozen=True)
class StillLimits:
    """What counts as still (``deploy.rezero``)."""

    joint_rad_s: float  # every joint slower than this, rad/s (smoothed velocities)
    gyro_rad_s: float  # every FT board slower than this, rad/s (low-passed gyroscope norm)
    min_s: float  # the shortest still stretch, s


@dataclass(frozen=True)
class Stretch:
    """Samples [start, stop) of a log's tables (times t0..t1, s) and how still the robot was there: the
    fastest joint and its speed (rad/s), the fastest FT board's speed (rad/s; None without gyroscopes),
    the contact set."""

    log: str
    start: int
    stop: int
    t0: float
    t1: float
    joint: str
    joint_rad_s: float
    gyro_rad_s: float | None
    contacts: str

    @property
    def seconds(self) -> float:
        return self.t1 - self.t0

    def record(self) -> dict[str, Any]:
        """JSON-able: the stretch and its stillness."""
        return asdict(self) | {"seconds": self.seconds}


@dataclass
class Motion:
    """Per sample of a log: the fastest joint's speed (rad/s) and name, the fastest FT board's speed
    (rad/s, NaN without gyroscopes), and whether the sample is still (`StillLimits`)."""

    time_s: np.ndarray
    joint_speed: np.ndarray
    joint: np.ndarray
    gyro_speed: np.ndarray
    still: np.ndarray
    contacts: np.ndarray

    def stretch(self, log: str, start: int, stop: int) -> Stretch:
        """The stretch [start, stop) and its stillness figures."""
        k = start + int(np.nanargmax(np.where(np.isfinite(self.joint_speed[start:stop]),
                                              self.joint_speed[start:stop], np.inf)))  # fmt: skip
        gyro = self.gyro_speed[start:stop]
        contacts = sorted({str(c) for c in self.contacts[start:stop]})
        return Stretch(
            log, start, stop, float(self.time_s[start]), float(self.time_s[stop - 1]),
            str(self.joint[k]), float(self.joint_speed[k]),
            float(np.nanmax(gyro)) if np.isfinite(gyro).any() else None, " | ".join(contacts),
        )  # fmt: skip


def motion(
    labelled: pd.DataFrame, smoothed: pd.DataFrame, joints: list[str], sensors: list[str], limits: StillLimits
) -> Motion:
    """Joint and board speeds of a log (its labelled and smoothed tables, same rows) and its still samples.

    Joints whose velocity is absent from the whole log are left out; a sample where another joint's is
    missing is not still. Boards: the gyroscopes of `sensors` that the log has. A sample where a reading of
    `sensors` the log has (wrench, temperature) is missing counts as not still: nothing to read there.
    """
    from pipeline.evaluation.noise import board_speed, quasi_static_mask

    stamps = labelled[S.STAMP].to_numpy(np.int64)
    if len(smoothed) != len(labelled) or not np.array_equal(smoothed[S.STAMP].to_numpy(np.int64), stamps):
        raise ValueError("the smoothed and labelled tables of a log must have the same rows")
    cols = [c for c in S.joint_cols(S.DQS, joints) if c in smoothed and smoothed[c].notna().any()]
    dq = np.abs(smoothed[cols].to_numpy(np.float64)) if cols else np.zeros((len(stamps), 1))
    dq = np.where(np.isfinite(dq), dq, np.inf)
    fastest = np.argmax(dq, axis=1)
    speed = dq[np.arange(len(dq)), fastest]
    names = np.array([c.split(".", 1)[1] for c in cols] or ["-"], dtype=object)[fastest]
    gyros = [
        labelled[S.vector_cols(S.GYR, s)].to_numpy(np.float64) for s in sensors if _has_gyro(labelled, s)
    ]
    bad = ~np.isfinite(np.concatenate(gyros, axis=1)).all(axis=1) if gyros else np.zeros(len(stamps), bool)
    segments, fs = _segments(stamps, bad)
    gyro = (
        board_speed(gyros, segments, fs, LOWPASS_HZ, LOWPASS_ORDER)
        if gyros and math.isfinite(fs)
        else np.full(len(stamps), np.nan)
    )
    # one normalised speed: still below 1 (a missing gyroscope value is not a motion, a missing joint is)
    normalised = np.maximum(speed / limits.joint_rad_s, np.nan_to_num(gyro / limits.gyro_rad_s, nan=0.0))
    if gyros:
        normalised[~np.isfinite(gyro)] = np.inf
    readings = [
        c for s in sensors for c in (*S.wrench_cols(S.FT, s), S.temperature_col(s)) if _has(labelled, c)
    ]
    if readings:
        normalised[~np.isfinite(labelled[readings].to_numpy(np.float64)).all(axis=1)] = np.inf
    contacts = labelled[S.CONTACTS].to_numpy(object)
    still = quasi_static_mask(
        normalised, contacts, labelled[S.GUARD].to_numpy(bool), segments, fs, 1.0, limits.min_s,
        EDGE_S if gyros else 0.0,
    )  # fmt: skip
    return Motion(labelled[S.TIME].to_numpy(np.float64), speed, names, gyro, still, contacts)


def _segments(stamps: np.ndarray, bad: np.ndarray) -> tuple[np.ndarray, float]:
    """((N,) ids of the stretches the low-pass filters alone, rate Hz): a stretch ends at a gap longer
    than MAX_GAP_S (a lost sample or two do not matter to a 2 Hz low-pass) and around every sample whose
    gyroscopes are not all finite (`bad`), which alone is a stretch of its own."""
    if len(stamps) < 2:
        return np.zeros(len(stamps), dtype=np.int64), math.nan
    step = np.diff(stamps).astype(np.float64)
    new = (step > MAX_GAP_S * 1e9) | (bad[1:] != bad[:-1]) | bad[1:]
    return np.r_[0, np.cumsum(new)].astype(np.int64), 1e9 / float(np.median(step))


def _has(table: pd.DataFrame, column: str) -> bool:
    """The table has the column, with a value somewhere."""
    return column in table and bool(np.isfinite(table[column].to_numpy(np.float64)).any())


def _has_gyro(table: pd.DataFrame, sensor: str) -> bool:
    return all(_has(table, c) for c in S.vector_cols(S.GYR, sensor))


def stretches(m: Motion, log: str) -> list[Stretch]:
    """The still stretches of a log (`motion`), in time order."""
    edges = np.flatnonzero(np.diff(np.r_[0, m.still.astype(np.int8), 0]))
    return [m.stretch(log, int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def window(m: Motion, start_s: float, duration_s: float) -> tuple[int, int]:
    """Samples [start, stop) of the times [start_s, start_s + duration_s) of a log."""
    start = int(np.searchsorted(m.time_s, start_s, side="left"))
    stop = int(np.searchsorted(m.time_s, start_s + duration_s, side="left"))
    return start, stop
