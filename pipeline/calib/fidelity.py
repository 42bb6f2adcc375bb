"""How faithfully a model reports a change of the wrench it did not see in training (no truth needed).

A virtual push along one axis of a sensor's raw reading (the factory map reports it as that change) should
come out of a calibration as about the same change: the factory map's gain and coupling errors are a few
%. Per model and sensor, on a set of samples (their inputs only: no label, no truth), the *slope* of axis a
is the mean of ``(f(x + d e_a) - f(x))_a / d`` with d the virtual push's size on that axis (`PushPrior`:
its force std on force axes, force x lever on torque axes). A model that rebuilds a force from torque
channels or the accelerometer has a slope far from 1 on that axis; a faithful one is within the factory
calibration's few %.

The same at small scale (``scales``): a push of 1, 5 and 20 N (`SCALES_N`; torque axes: that force at the
prior's lever) either way along each axis, the slope ``mean((f(x + d e_a) - f(x - d e_a))_a / 2d)``: a
calibration that snaps small changes of its input to its training relation (a network that learned to
cancel noise) reports a 1 N push with a slope far below 1, while the larger prior size looks faithful.

For a network with the FT board's IMU among its inputs, ``imu_kg`` is the largest mean derivative of a
force output with respect to an accelerometer input (kg): how much of the wrench it reads off the IMU.

A model with memory (the ``play`` family: its state, the play outputs of the sample before, is wrench-valued,
column c on raw axis c mod 6) is pushed twice. Held: the push has been there long enough for the state to
carry it (the state moves with the push; a play operator's state then moves with its input, z unchanged),
so the slopes above are those of its static part, judged as any model's. At its onset (``instant``: the
state held): the slopes of the same pushes the moment they start, where the memory answers too. A sensor's
hysteresis makes its reading of a fresh push larger (smaller) than of a held one by its minor-loop gain g
(h / width: 0.4-0.5 for 0.5 % of full scale spread over widths of 0.2-10 % of it); a memory model undoes that
with a gap g / (1 + g) between its two slopes, what its memory adds to the present wrench, which must stay
below half of it (`pipeline.evaluation.fidelity`, ``evaluate.memory_tolerance``): a memory that stands in
for the present wrench (a play of a width near the noise, cancelling the reading) answers a fresh push with
a slope near 0.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from pipeline.calib.pushes import PushPrior

WRENCH = 6
ACC = slice(7, 10)  # accelerometer columns of a sensor's 13 inputs
SAMPLES = 2000  # samples the slopes are averaged over (evenly spaced)
SCALES_N = (1.0, 5.0, 20.0)  # small-scale virtual pushes, N on force axes (x the prior's lever on torques)
DEFAULT_LEVER_M = 0.2  # lever of the torque pushes when the fit has no push prior, m

Predict = Callable[[np.ndarray], np.ndarray]  # (N, S, 13) raw inputs -> (N, S, 6) calibrated


def model_fidelity(
    predict: Callable[..., np.ndarray],
    x: np.ndarray,
    push: PushPrior,
    n_inputs: int,
    memory: np.ndarray | None = None,
) -> list[dict[str, Any]]:
    """Per sensor (in the group's order): {"slopes": 6 floats, "scales": {"1": 6 floats, ...}, "imu_kg":
    float or None} (module docstring); with `memory` (N, S, 6 K: the state before each sample of x, read by
    ``predict(x, memory)``), those of a held push and ``"instant"``: {"slopes", "scales"} at its onset."""
    pick = np.unique(np.linspace(0, len(x) - 1, min(SAMPLES, len(x))).astype(int)) if len(x) else []
    x = np.asarray(x[pick], dtype=np.float64)
    if not len(x):
        return []
    if memory is None:
        return _slopes(predict, x, push, n_inputs)
    state = np.asarray(memory[pick], dtype=np.float64)
    repeat = state.shape[2] // WRENCH

    def held(z: np.ndarray) -> np.ndarray:  # the state moved by the push z - x on its wrench
        return predict(z, state + np.tile(z[:, :, :WRENCH] - x[:, :, :WRENCH], (1, 1, repeat)))

    out = _slopes(held, x, push, n_inputs)
    for entry, onset in zip(out, _slopes(lambda z: predict(z, state), x, push, n_inputs), strict=True):
        entry["instant"] = {"slopes": onset["slopes"], "scales": onset["scales"]}
    return out


def _slopes(predict: Predict, x: np.ndarray, push: PushPrior, n_inputs: int) -> list[dict[str, Any]]:
    """`model_fidelity` of a memoryless predictor on the picked samples x (N, S, k)."""
    base = predict(x)
    size = np.sqrt(push.variances()) if push.force_n > 0 else np.r_[np.full(3, 20.0), np.full(3, 4.0)]
    out: list[dict[str, Any]] = [{"slopes": [], "imu_kg": None} for _ in range(x.shape[1])]
    for a in range(WRENCH):
        moved = x.copy()
        moved[:, :, a] += size[a]
        change = (predict(moved) - base)[:, :, a] / size[a]
        for s in range(x.shape[1]):
            out[s]["slopes"].append(float(np.mean(change[:, s])))
    lever = push.lever_m if push.force_n > 0 else DEFAULT_LEVER_M
    for s, slopes in enumerate(scale_slopes(predict, x, lever)):
        out[s]["scales"] = slopes
    if n_inputs == 13:
        for j in range(3):
            moved = x.copy()
            moved[:, :, ACC.start + j] += 1.0  # m/s^2
            change = (predict(moved) - base)[:, :, :3]  # N per m/s^2 = kg
            for s in range(x.shape[1]):
                worst = float(np.max(np.abs(change[:, s].mean(axis=0))))
                out[s]["imu_kg"] = max(out[s]["imu_kg"] or 0.0, worst)
    return out


def scale_slopes(predict: Predict, x: np.ndarray, lever_m: float) -> list[dict[str, list[float]]]:
    """Per sensor: scale (N, as text) -> 6 slopes of a push of that size either way along each axis."""
    out: list[dict[str, list[float]]] = [{} for _ in range(x.shape[1])]
    for force in SCALES_N:
        size = np.r_[np.full(3, force), np.full(3, force * lever_m)]
        for a in range(WRENCH):
            up, down = x.copy(), x.copy()
            up[:, :, a] += size[a]
            down[:, :, a] -= size[a]
            change = (predict(up) - predict(down))[:, :, a] / (2 * size[a])
            for s in range(x.shape[1]):
                out[s].setdefault(f"{force:g}", []).append(float(np.mean(change[:, s])))
    return out


def group_fidelity(
    predictors: Mapping[str, tuple[Callable[..., np.ndarray], int]],
    x: np.ndarray,
    sensors: list[str],
    push: PushPrior,
    memory: Mapping[str, np.ndarray] | None = None,
) -> dict[str, dict[str, dict[str, Any]]]:
    """model -> sensor -> `model_fidelity` entry, for `predictors` (model -> (predict, inputs per sensor));
    `memory`: model -> the state before each sample of x of the models with memory."""
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for name, (predict, n_inputs) in predictors.items():
        rows = model_fidelity(predict, x, push, n_inputs, (memory or {}).get(name))
        out[name] = dict(zip(sensors, rows, strict=True))
    return out


def memory_gaps(entry: Mapping[str, Any]) -> list[tuple[str, int, float]]:
    """[(scale as in `entry_slopes`, axis, instant slope - held slope)] of a memory model's sensor entry
    (empty for a memoryless model's)."""
    instant = entry.get("instant")
    if not instant:
        return []
    held = dict(entry_slopes(entry))
    return [
        (scale, a, float(v - held[scale][a]))
        for scale, slopes in entry_slopes(instant)
        if scale in held
        for a, v in enumerate(slopes)
    ]


def worst_gap(entry: Mapping[str, Any]) -> float:
    """Largest |slope - 1| of one sensor's entry, at the prior's size and at every small scale."""
    return max(abs(v - 1.0) for _, slopes in entry_slopes(entry) for v in slopes)


def entry_slopes(entry: Mapping[str, Any]) -> list[tuple[str, list[float]]]:
    """[(scale: "" for the prior's size, else "1 N", ...; its 6 slopes)] of one sensor's entry (an entry
    written before the small scales has the prior's size only)."""
    return [("", list(entry["slopes"]))] + [
        (f"{k} N", list(v)) for k, v in (entry.get("scales") or {}).items()
    ]
