"""Error measures of calibrated wrenches (thesis tables 5.1-5.3), numpy only: train and evaluate score with
the same function, and evaluate does not need torch for it."""

from __future__ import annotations

import math

import numpy as np

WRENCH = 6  # fx, fy, fz [N], tx, ty, tz [Nm]
N_FORCE = 3
AXES = ("fx", "fy", "fz", "tx", "ty", "tz")


def wrench_errors(pred: np.ndarray, label: np.ndarray) -> dict[str, float]:
    """MSE, MAE and RMSE of predictions (N, 6) against labels (N, 6), N and Nm (thesis tables 5.1-5.3).

    Keys: ``<mse|mae|rmse>`` (global: all 6 components pooled, mixed units as in the thesis),
    ``<...>_force``, ``<...>_torque`` and ``<...>_<axis>``, plus ``samples``. NaN if N = 0.
    """
    err = np.asarray(pred, dtype=np.float64) - np.asarray(label, dtype=np.float64)
    out: dict[str, float] = {"samples": float(len(err))}
    parts = {"": slice(None), "_force": slice(0, N_FORCE), "_torque": slice(N_FORCE, WRENCH)}
    parts.update({f"_{axis}": slice(a, a + 1) for a, axis in enumerate(AXES)})
    for suffix, sl in parts.items():
        e = err[:, sl]
        mse = float(np.mean(e**2)) if e.size else math.nan
        out[f"mse{suffix}"] = mse
        out[f"mae{suffix}"] = float(np.mean(np.abs(e))) if e.size else math.nan
        out[f"rmse{suffix}"] = math.sqrt(mse) if e.size else math.nan
    return out
