"""wholeBodyDynamics' own secondary calibration: the affine map as the estimator's configuration groups.

iCub and ergoCub run a linear secondary calibration of each FT sensor without any code of their own: the
``wholeBodyDynamics`` device (robotology whole-body-estimators, ``SixAxisForceTorqueMeasureHelpers.cpp``)
applies, per sensor and cycle, before its low-pass filter,

    w = S w_raw - o + c (T - T_ref)

with ``S`` the 6x6 ``FT_SECONDARY_CALIBRATION`` (36 values, row-major), ``c`` and ``T_ref`` the 7 values of
``FT_TEMPERATURE_COEFFICIENTS`` (6 coefficients, N/degC and Nm/degC, then the reference temperature,
degC), and ``o`` the offset: estimated by its ``calib*`` RPCs (and at start-up unless
``startWithZeroFTSensorOffsets``), or, after its ``usePreEstimatedOffset`` RPC, ``o = -FT_OFFSET`` (6
values: FT_OFFSET is added). Wrenches fx fy fz N, tx ty tz Nm in the URDF sensor frame; a sensor is named
as in the URDF and must be among the device's ``SixAxisForceTorqueSensorsNames``.

ftcal's ``affine`` family (`pipeline.calib.parts.LinearPart` of order 1) is ``w = w_raw + A x + c_0``, x
the raw wrench and the board's temperature: so ``S = I + A[:, :6]``, ``c = A[:, 6]``, ``T_ref`` the
training data's mean temperature (the model's standardisation centre) and ``FT_OFFSET = c_0 + c T_ref``;
a re-zeroing's raw-side offset change delta (`pipeline.export.offsets`, subtracted from ``w_raw``) moves
it to ``FT_OFFSET - S delta``. A group trained without temperature has no temperature group (the device
then needs no temperature sensor). whole-body-estimators v0.11.3 and later do not load
``FT_TEMPERATURE_COEFFICIENTS`` (the group only switches temperature reading on): check the version the
robot runs; docs/deployment.md says what the map costs without it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from pipeline.export.linear import folded
from pipeline.export.trained import GroupModel, LinearPart

FILE = "wholebodydynamics.xml"
KEY = "wholebodydynamics"  # the manifests' entry
SECONDARY, TEMPERATURE, OFFSET = "FT_SECONDARY_CALIBRATION", "FT_TEMPERATURE_COEFFICIENTS", "FT_OFFSET"
WRENCH = 6
AFFINE_NAME = "affine"  # the family whose map the configuration holds


def sensor_terms(part: LinearPart) -> dict[str, Any]:
    """One sensor's configuration values from its affine part: ``secondary_calibration`` (36, row-major),
    ``temperature_coefficients`` (7: c then T_ref; None without temperature) and ``offset`` (6, FT_OFFSET,
    N and Nm)."""
    a, c0, _ = folded(part)
    s = np.eye(WRENCH) + a[:, :WRENCH]
    if a.shape[1] > WRENCH:
        c, t_ref = a[:, WRENCH], float(part.offset[WRENCH])
        temperature = [*map(float, c), t_ref]
        offset = c0 + c * t_ref
    else:
        temperature, offset = None, c0
    return {
        "secondary_calibration": [float(v) for v in s.reshape(-1)],
        "temperature_coefficients": temperature,
        "offset": [float(v) for v in offset],
    }


def group_terms(model: GroupModel) -> dict[str, dict[str, Any]]:
    """Sensor -> `sensor_terms` of a group's affine model (`read_group(..., "affine")`)."""
    return {s: sensor_terms(p) for s, p in zip(model.sensors, model.parts, strict=True)}


def rezeroed(terms: Mapping[str, Any], delta: np.ndarray) -> dict[str, Any]:
    """`terms` with FT_OFFSET moved by a re-zeroing's raw-side offset change delta (6,) N/Nm."""
    s = np.reshape(terms["secondary_calibration"], (WRENCH, WRENCH))
    offset = np.asarray(terms["offset"], dtype=np.float64) - s @ np.asarray(delta, dtype=np.float64)
    return {**terms, "offset": [float(v) for v in offset]}


def _values(values: list[float], per_line: int) -> str:
    rows = [values[k : k + per_line] for k in range(0, len(values), per_line)]
    return "(" + "\n             ,".join(",".join(repr(float(v)) for v in row) for row in rows) + ")"


def fragment(sensors: Mapping[str, Mapping[str, Any]], about: str) -> str:
    """The XML groups a lab pastes into its robot's ``estimators/wholebodydynamics.xml`` for `sensors`
    (sensor -> `sensor_terms`), introduced by the comment `about` (robot, models, how to apply the offset).
    Every number is written with all its digits (Python's shortest round-trip repr)."""
    lines = ["<!-- " + about.replace("--", "-") + " -->"]
    groups = [
        (SECONDARY, "secondary_calibration", WRENCH),
        (TEMPERATURE, "temperature_coefficients", 7),
        (OFFSET, "offset", WRENCH),
    ]
    for group, key, per_line in groups:
        rows = [(s, t[key]) for s, t in sensors.items() if t.get(key) is not None]
        if not rows:
            continue
        lines.append(f'<group name="{group}">')
        lines += [f'    <param name="{s}">{_values(list(v), per_line)}</param>' for s, v in rows]
        lines.append("</group>")
    return "\n".join(lines) + "\n"


def about(robot: str, models: Mapping[str, str]) -> str:
    """The fragment's opening comment: what it is and how the robot takes its offset."""
    deployed = ", ".join(f"{g}: {m}" for g, m in models.items())
    return (
        f"ftcal: wholeBodyDynamics secondary calibration of {robot}, the affine map of every group "
        f"(deployed models: {deployed}). Paste into the robot's estimators/wholebodydynamics.xml. "
        "FT_OFFSET is what the calibration was trained with (and the latest ftcal rezero): the device "
        "uses it after its usePreEstimatedOffset RPC (with startWithZeroFTSensorOffsets true); its calib "
        "RPCs estimate their own."
    )


def fallback_cost(
    tables: Mapping[str, Any], deployed: str, names: list[str] | None = None
) -> dict[str, dict[str, Any]]:
    """Per headline of a group's evaluation tables (``report.json`` ``tables``: name -> reference -> model
    -> errors; `names`, default every name): the affine map's test RMSE beside the deployed model's (pooled,
    N/Nm), against the truth where the logs have it, else the held-out labels. A name without both is left
    out."""
    out = {}
    for headline in tables if names is None else names:
        table = tables.get(headline) or {}
        against = "truth" if table.get("truth") else "labels"
        rows = table.get(against) or {}
        if AFFINE_NAME in rows and deployed in rows:
            out[headline] = {
                "against": against,
                "deployed": deployed,
                "deployed_rmse": float(rows[deployed]["rmse"]),
                "affine_rmse": float(rows[AFFINE_NAME]["rmse"]),
            }
    return out
