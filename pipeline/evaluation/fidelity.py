"""Trust in a group's calibrations off the training relation: virtual-push fidelity and excitation
(the page shows them with the fallbacks they cause: `pipeline.evaluation.trust`).

- Fidelity (`pipeline.calib.fidelity`, written by train, no truth): each model's per-axis slope under a
  virtual push, at the push prior's size and at 1, 5 and 20 N; a model with a slope farther than
  ``evaluate.fidelity_tolerance`` from 1 on any axis of any sensor at any scale is *unfaithful* and not
  recommended, like a noise-flagged one.
- Excitation (`pipeline.calib.excitation`, written by train): per sensor the directions its training
  labels excite; here also how far the test samples lie outside them (the recommended model's output).
- Passed over: when the model cross-validation prefers is flagged, which one is deployed instead, why, and
  what it costs (mean fold error, and against the truth where there is one).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from pipeline.calib.excitation import OUTSIDE, Excitation
from pipeline.calib.fidelity import entry_slopes, memory_gaps

AXES = ("fx", "fy", "fz", "tx", "ty", "tz")
NEVER_FLAGGED = ("raw", "oracle")  # the factory map and the simulator's exact inverse are references


def unfaithful(
    fidelity: Mapping[str, Mapping[str, Any]], tolerance: float, memory_tolerance: float = math.inf
) -> dict[str, str]:
    """model -> why it is unfaithful ("r_arm_ft fx slope 0.31 at 1 N"), for the models of `fidelity` (model
    -> sensor -> {slopes, scales}) with a slope farther than `tolerance` from 1 at any scale, or (a model with
    memory) whose slope at a push's onset differs from its held one by more than `memory_tolerance`."""
    out = {}
    for model, sensors in fidelity.items():
        gap = max(
            ((abs(d), s, a, d, scale) for s, e in sensors.items() for scale, a, d in memory_gaps(e)),
            default=None,
        )
        if gap is not None and gap[0] > memory_tolerance:
            at = f" at {gap[4]}" if gap[4] else ""
            out[model] = f"{gap[1]} {AXES[gap[2]]} memory adds {gap[3]:+.2f} to the slope of a fresh push{at}"
            continue
        if model in NEVER_FLAGGED:
            continue
        worst = max(
            (
                (abs(v - 1.0), s, a, v, scale)
                for s, e in sensors.items()
                for scale, slopes in entry_slopes(e)
                for a, v in enumerate(slopes)
            ),
            default=None,
        )
        if worst is not None and worst[0] > tolerance:
            at = f" at {worst[4]}" if worst[4] else ""
            out[model] = f"{worst[1]} {AXES[worst[2]]} slope {worst[3]:.2f}{at}"
    return out


def outside_stats(excitation: Mapping[str, Any], wrenches: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """Per sensor with an excitation: percentiles of the outside distance (noise units) of `wrenches`
    (sensor -> (N, 6)) and the share of samples beyond `OUTSIDE`."""
    out = {}
    for sensor, entry in excitation.items():
        w = wrenches.get(sensor)
        if w is None:
            continue
        w = w[np.isfinite(w).all(axis=1)]
        if not len(w):
            continue
        d = Excitation.from_dict(dict(entry)).outside(w)
        out[sensor] = {
            "p50": float(np.percentile(d, 50)),
            "p95": float(np.percentile(d, 95)),
            "max": float(d.max()),
            "share_outside": float(np.mean(d > OUTSIDE)),
        }
    return out
