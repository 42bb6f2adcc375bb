"""Labelled tables (schema "Labelled table") of a leg sensor and a foot pair, and the pair's transforms.

Used by the train, evaluate and export tests: one writer of labelled tables, with the r_foot pair's
metadata; TRANSFORMS are the pair's sole_X_front and sole_X_rear.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.logs import schema as S
from pipeline.physics.cuts import map_wrenches


def wrench_transform(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    """6x6 sole_X_sensor for a sensor frame at `position` with orientation `rotation` in the sole frame."""
    px, py, pz = position
    skew = np.array([[0, -pz, py], [pz, 0, -px], [-py, px, 0]])
    out = np.zeros((6, 6))
    out[:3, :3] = rotation
    out[3:, 3:] = rotation
    out[3:, :3] = skew @ rotation
    return out


def rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# (2, 6, 6): the r_foot pair's sole_X_front and sole_X_rear (positions in m)
TRANSFORMS = np.stack(
    [
        wrench_transform(rot_z(0.3), np.array([0.06, 0.01, 0.02])),
        wrench_transform(rot_z(-0.2), np.array([-0.05, -0.01, 0.02])),
    ]
)
LEG, FRONT, REAR, PAIR = "r_leg_ft", "r_foot_front_ft", "r_foot_rear_ft", "r_foot"
SENSORS = (LEG, FRONT, REAR)
SHANK = S.cut_set_name(SENSORS)  # cut set: the leg with its foot's two sensors, exact at every sample
SHANK_SIGNS = {LEG: 1.0, FRONT: -1.0, REAR: -1.0}
SHANK_P = np.array([0.02, -0.01, -0.4])  # m: the leg sensor's position in the sole frame
SCALE = np.array([60.0, 60.0, 200.0, 4.0, 4.0, 1.5])  # N, N, N, Nm, Nm, Nm: amplitude of the true wrenches
# Which labels each synthetic experiment type has: (leg, parts, pair) as functions of the phase u in [0, 1).
# every model a group trains on these tables with the tests' train params (poly orders 1 and 2, networks of 7
# and 13 inputs, play, arx and the windowed network), the raw wrench apart
TRAINED = ("offset", "affine", "poly1", "poly2", "play", "arx", "nn7", "nn13", "win")
SWITCHES = {
    "pole": lambda u: (np.ones_like(u), np.ones_like(u), np.ones_like(u)),  # the foot touches nothing
    "balancing": lambda u: (np.ones_like(u), np.zeros_like(u), np.ones_like(u)),  # whole foot on the floor
    # swing (parts exact), single support (sum exact), double support (nothing exact)
    "walking": lambda u: ((u % 0.5) < 0.4, (u % 0.5) < 0.2, (u % 0.5) < 0.4),
}


def _distortion(sensor: str) -> dict[str, np.ndarray]:
    """The hidden distortion of a sensor, the same in every log: raw = M w + b + d (T - 25) + q w_z^2."""
    rng = np.random.default_rng(list(SENSORS).index(sensor) + 100)
    return {
        "gain": np.eye(6) + 0.03 * rng.normal(size=(6, 6)),
        "offset": rng.uniform(20, 40, 6) * np.r_[1, 1, 1, 0.1, 0.1, 0.1] * rng.choice([-1, 1], 6),
        "drift": rng.normal(size=6) * np.r_[0.5, 0.5, 0.5, 0.02, 0.02, 0.02],
        "quadratic": rng.normal(size=6) * 1e-4,
    }


def write_labelled_log(path: Path, kind: str, role: str, n: int, seed: int, bad_rows: int = 3) -> None:
    """A labelled table (schema "Labelled table"): the three sensors, the r_foot pair and its transforms."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    u = np.arange(n) / n
    cols: dict[str, Any] = {
        S.STAMP: (1_700_000_000_000_000_000 + np.arange(n) * 10_000_000).astype(np.int64),
        S.TIME: t,
    }
    truth = {}
    for s, sensor in enumerate(SENSORS):
        phase = rng.uniform(0, 2 * np.pi, (3, 6))
        freq = rng.uniform(0.05, 0.8, (3, 6))
        w = sum(np.sin(2 * np.pi * freq[k] * t[:, None] + phase[k]) for k in range(3)) * SCALE / 2
        temp = 30 + 4 * np.sin(2 * np.pi * 0.01 * t + seed + s) + rng.uniform(-2, 2)
        d = _distortion(sensor)
        raw = (
            w @ d["gain"].T + d["offset"] + np.outer(temp - 25, d["drift"]) + d["quadratic"] * w[:, [2]] ** 2
        )
        raw += rng.normal(size=raw.shape) * 0.05
        ok = np.ones(n, dtype=bool)
        ok[rng.choice(n, bad_rows, replace=False)] = False  # lost messages: NaN values, flag False
        raw[~ok] = np.nan
        for c, v in zip(S.wrench_cols(S.FT, sensor), raw.T, strict=True):
            cols[c] = v
        cols[S.temperature_col(sensor)] = temp
        for c, v in zip(
            S.vector_cols(S.ACC, sensor) + S.vector_cols(S.GYR, sensor), rng.normal(size=(6, n)), strict=True
        ):
            cols[c] = v
        cols[S.ok_col(S.WRENCH_STREAM, sensor)] = ok
        cols[S.ok_col(S.IMU_STREAM, sensor)] = np.ones(n, dtype=bool)
        cols[S.ok_col(S.TEMPERATURE_STREAM, sensor)] = np.ones(n, dtype=bool)
        truth[sensor] = w
    sw_leg, sw_parts, sw_pair = (np.asarray(a, dtype=bool) for a in SWITCHES[kind](u))
    total = truth[FRONT] @ TRANSFORMS[0].T + truth[REAR] @ TRANSFORMS[1].T
    for name, w, sw in (
        (LEG, truth[LEG], sw_leg),
        (FRONT, truth[FRONT], sw_parts),
        (REAR, truth[REAR], sw_parts),
        (PAIR, total, sw_pair),
    ):
        for c, v in zip(S.wrench_cols(S.EXPECTED, name), np.where(sw[:, None], w, np.nan).T, strict=True):
            cols[c] = v
        cols[S.switch_col(name)] = sw.astype(np.uint8)
    # the shank cut set: leg + foot parts in the sole frame, the leg's pose turning with an ankle angle
    angle = 0.3 * np.sin(2 * np.pi * 0.2 * t)
    rot = np.zeros((n, 3, 3))
    rot[:, 0, 0] = rot[:, 1, 1] = np.cos(angle)
    rot[:, 0, 1], rot[:, 1, 0], rot[:, 2, 2] = -np.sin(angle), np.sin(angle), 1.0
    poses = np.concatenate([rot.reshape(n, 9), np.tile(SHANK_P, (n, 1))], axis=1)
    shank = SHANK_SIGNS[LEG] * map_wrenches(poses, truth[LEG]) - total
    for c, v in zip(S.cut_pose_cols(SHANK, LEG), poses.T, strict=True):
        cols[c] = v
    for c, v in zip(S.wrench_cols(S.EXPECTED, SHANK), shank.T, strict=True):
        cols[c] = v
    cols[S.switch_col(SHANK)] = np.ones(n, dtype=np.uint8)
    cols[S.CONTACTS] = np.full(n, "r_foot_front,r_foot_rear", dtype=object)
    cols[S.FIXED_LINK] = np.full(n, "r_sole", dtype=object)
    cols[S.GUARD] = np.zeros(n, dtype=bool)
    meta = labelled_metadata(kind, role, path.stem)
    write_table(path, cols, S.KIND_LABELLED, meta)


LOGS = [
    ("00_pole", "pole", "train"),
    ("01_pole", "pole", "train"),
    ("02_balancing", "balancing", "train"),
    ("03_walking", "walking", "train"),
    ("04_walking", "walking", "train"),
    ("05_pole", "pole", "test"),
    ("06_walking", "walking", "test"),
]


def write_labelled_logs(out: Path, n: int) -> Path:
    """Every log of `LOGS` as a labelled table of `n` samples in `out` (each log its own seed)."""
    for i, (name, kind, role) in enumerate(LOGS):
        write_labelled_log(out / f"{name}_{role}.parquet", kind, role, n=n, seed=i)
    return out


def labelled_metadata(kind: str, role: str, log: str) -> dict[bytes, Any]:
    """The Parquet metadata of a labelled table: its experiment and the r_foot pair's transforms."""
    return {
        S.META_EXPERIMENT: {"type": kind, "role": role, "log": log, "sim": "true"},  # generated: a simulation
        S.META_LABEL: {
            "pairs": {
                PAIR: {
                    "front": FRONT,
                    "rear": REAR,
                    "sole": "r_sole",
                    "sole_X_front": TRANSFORMS[0].ravel().tolist(),
                    "sole_X_rear": TRANSFORMS[1].ravel().tolist(),
                }
            },
            "cut_sets": {
                S.cut_set_name((FRONT, REAR)): {
                    "label": PAIR,
                    "sensors": [FRONT, REAR],
                    "frame": "r_sole",
                    "signs": {FRONT: 1.0, REAR: 1.0},
                    "X": {FRONT: TRANSFORMS[0].ravel().tolist(), REAR: TRANSFORMS[1].ravel().tolist()},
                    "pose_columns": {},
                },
                SHANK: {
                    "label": SHANK,
                    "sensors": list(SENSORS),
                    "frame": "r_sole",
                    "signs": SHANK_SIGNS,
                    "X": {FRONT: TRANSFORMS[0].ravel().tolist(), REAR: TRANSFORMS[1].ravel().tolist()},
                    "pose_columns": {LEG: S.cut_pose_cols(SHANK, LEG)},
                },
            },
        },
    }


def write_table(path: Path, cols: dict[str, Any], kind: str, meta: dict[bytes, Any]) -> None:
    """A table of the project's schema (`kind`: labelled, truth...) with its ftcal metadata."""
    schema = S.arrow_schema(list(cols), kind, meta)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pydict(cols, schema=schema), path)
