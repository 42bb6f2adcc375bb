"""Synthetic sensors of the calibration-family tests, sampled at 100 Hz.

A creeping sensor (the arx and windowed-network tests): its reading overshoots a change of load by CREEP of
it and relaxes to it with time constant TAU, over a gain, an offset and white noise. A free arm (the
virtual-push and lever tests): its true wrench lies on torque = LEVER x force, its raw reading adds white
noise to a slightly distorted copy, and its labels are exact.
"""

from __future__ import annotations

import numpy as np

from pipeline.calib.pushes import PushPrior
from pipeline.core.lowpass import alphas, lowpass_outputs

DT = 0.01  # s, the simulated logs' rate
TAU = 1.5  # s, the creep's time constant
CREEP = np.r_[0.03, -0.02, 0.025, 0.02, 0.03, -0.015]  # overshoot of a load change, fraction of it
NOISE = np.array([0.6, 0.6, 0.6, 0.03, 0.03, 0.03])  # N, Nm: white noise std of both sensors' readings
PUSH = PushPrior(0.1, 20.0, 0.2)  # the virtual pushes the fits are given
LEVER = np.array([0.0, 0.0, 0.15])  # m: the free arm's torque = LEVER x force


def creep_log(seed: int, n: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """(raw inputs (n, 1, 7), true wrench (n, 1, 6)) of one log: steps and ramps of a few 100 N read through
    gain, offset, creep (``c (w - lowpass_TAU(w))``) and white noise."""
    rng = np.random.default_rng(seed)
    scale = np.r_[np.full(3, 150.0), np.full(3, 8.0)]
    levels = rng.uniform(-1, 1, (n // 200 + 1, 6)) * scale
    w = np.repeat(levels, 200, axis=0)[:n]
    w = np.apply_along_axis(lambda c: np.convolve(c, np.ones(20) / 20, mode="same"), 0, w)  # 0.2 s ramps
    lagged = lowpass_outputs(w, np.full(6, alphas(np.array([TAU]), DT)[0]))
    raw = 1.02 * w + np.r_[30.0, -20.0, 25.0, 2.0, -1.0, 1.5] + CREEP * (w - lagged)
    raw += rng.normal(size=raw.shape) * NOISE
    x = np.concatenate([raw, np.full((n, 1), 30.0)], axis=1)
    return x[:, None, :], w[:, None, :]


def on_relation(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(raw inputs (n, 1, 13), exact labels (n, 1, 6)) of a free arm: torque = LEVER x force."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    force = np.stack(
        [15 * np.sin(0.7 * (k + 1) * t) + 5 * np.sin(2.3 * (k + 1) * t + k) for k in range(3)], 1
    )
    true = np.c_[force, np.cross(LEVER, force)]
    distortion = np.eye(6) + rng.uniform(-0.02, 0.02, (6, 6))
    raw = true @ distortion.T + np.r_[25.0, -30, 40, 2, -1, 3] + rng.standard_normal((n, 6)) * NOISE
    x = np.zeros((n, 1, 13))
    x[:, 0, :6], x[:, 0, 6] = raw, 30.0 + 0.1 * rng.standard_normal(n)
    return x, true[:, None, :]
