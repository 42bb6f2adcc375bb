"""An independent least-squares calibration of a recorded run, the reference ftcal's `affine_ls` must meet.

What a lab's own script does, written without ftcal's smoothing, labelling or fitting: joint velocities and
accelerations from a plain Savitzky-Golay filter (0.21 s, order 3) on the encoder positions, a joint whose
readings span at most `STILL_DEG` over the whole log held still (its mean, zero velocity and acceleration),
the expected wrench from iDynTree (`tests.idyntree_ref`), and a plain affine least-squares map from the raw
wrench to it, fitted on the training logs and scored on the test logs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.signal import savgol_filter

from pipeline.logs import schema as S
from tests.idyntree_ref import IDynTreeFT

GRAVITY = np.array([0.0, 0.0, -9.80665])
WINDOW_S, ORDER = 0.21, 3
STILL_DEG = 0.1  # iCub 2.x encoders count 0.088 deg: a joint spanning one step is at rest


@dataclass
class Reference:
    """Per test sample (rows of the test logs where ftcal's switch is 1): the independent label (M, 6), the
    raw wrench (M, 6), the independent map's prediction (M, 6), and the samples' (log, stamp_ns)."""

    label: np.ndarray
    raw: np.ndarray
    predicted: np.ndarray
    keys: pd.MultiIndex


def _window(dt: float) -> int:
    """The SG window, samples (odd), of WINDOW_S at a step of dt s."""
    return int(round(WINDOW_S / dt)) | 1


def _kinematics(q: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w = _window(dt)
    q = np.where(np.isfinite(q), q, 0.0)  # joints the log lacks: a label with its switch on needs none
    dq = savgol_filter(q, w, ORDER, deriv=1, delta=dt, axis=0)
    ddq = savgol_filter(q, w, ORDER, deriv=2, delta=dt, axis=0)
    still = np.ptp(q, axis=0) <= np.radians(STILL_DEG)
    q[:, still], dq[:, still], ddq[:, still] = q[:, still].mean(axis=0), 0.0, 0.0
    return q, dq, ddq


def reference(
    project: Path, urdf: str, joints: list[str], sensor: str, contact: str, test_logs: set[str]
) -> Reference:
    """The independent calibration of `sensor` from `project`'s ingested tables (``data/ingested``), on the
    samples of ftcal's labelled tables (``data/labelled``) whose switch is 1 and wrench ok, away from each
    log's ends by half a window; `contact` is the fixed link (the pole's root_link, a stance sole)."""
    oracle = IDynTreeFT(urdf, joints)
    parts: dict[bool, list[tuple[np.ndarray, np.ndarray, pd.MultiIndex]]] = {True: [], False: []}
    for table in sorted((project / "data" / "labelled").glob("*.parquet")):
        labelled = pd.read_parquet(table, columns=[S.STAMP, S.switch_col(sensor)])
        ingested = pd.read_parquet(project / "data" / "ingested" / table.name).set_index(S.STAMP)
        stamps = ingested.index.to_numpy()
        dt = float(np.median(np.diff(stamps))) / 1e9
        q, dq, ddq = _kinematics(ingested[S.joint_cols(S.Q, joints)].to_numpy(), dt)
        half = _window(dt) // 2
        on = labelled[S.switch_col(sensor)].to_numpy() == 1
        at = np.searchsorted(stamps, labelled[S.STAMP].to_numpy()[on])
        ok = (
            ingested[S.ok_col(S.WRENCH_STREAM, sensor)].to_numpy()[at]
            & (at >= half)
            & (at < len(stamps) - half)
        )
        at = at[ok]
        label = oracle.expected(q[at], dq[at], ddq[at], [contact], contact, GRAVITY)[sensor]
        raw = ingested[S.wrench_cols(S.FT, sensor)].to_numpy()[at]
        keys = pd.MultiIndex.from_arrays([[table.stem] * len(at), stamps[at]], names=["log", S.STAMP])
        parts[table.stem in test_logs].append((raw, label, keys))

    def stack(test: bool) -> tuple[np.ndarray, np.ndarray, pd.MultiIndex]:
        raw, label, keys = zip(*parts[test], strict=True)
        return np.concatenate(raw), np.concatenate(label), keys[0].append(list(keys[1:]))

    (raw_tr, label_tr, _), (raw_te, label_te, keys) = stack(False), stack(True)
    design = np.column_stack([raw_tr, np.ones(len(raw_tr))])
    coefficients = np.linalg.lstsq(design, label_tr, rcond=None)[0]
    return Reference(label_te, raw_te, np.column_stack([raw_te, np.ones(len(raw_te))]) @ coefficients, keys)


def rmse(error: np.ndarray) -> float:
    """Pooled RMSE over the samples and the 6 axes (N and Nm), as ftcal's headline."""
    return float(np.sqrt(np.mean(np.square(error))))
