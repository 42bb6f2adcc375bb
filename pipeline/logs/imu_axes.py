"""The axes of an FT board's IMU in the sensor frame: axis maps, the params that state them, their action.

An axis map names, for each IMU axis x, y, z in turn, the sensor-frame axis it points along with its
sign: ``("-y", "-x", "z")`` says that the board's x axis is the sensor frame's -y, its y axis the sensor
frame's -x and its z axis the sensor frame's z. Its matrix ``M`` (3, 3) has those axes as rows, so that a
vector ``v`` of the sensor frame reads ``M v`` on the board (``board_x = -v_y``: the map read literally),
and a board's reading ``r`` is ``M^T r`` in the sensor frame. The 48 signed permutations include the 24
improper ones (a mirror, e.g. two fields swapped by a driver): the data, not the chip, are checked.

The accelerometer and the gyroscope are one chip: one map holds for both (`ingest.imu_axes` maps both,
`simulate.imu.axes` puts a simulated board's IMU in such axes). Pure Python (params validate without numpy);
the functions on arrays import numpy.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from itertools import permutations, product
from typing import TYPE_CHECKING, Any

from pipeline.core.errors import ConfigError

if TYPE_CHECKING:
    import numpy as np

AxisMap = tuple[str, str, str]  # per IMU axis x, y, z: the signed sensor-frame axis, e.g. ("-y", "-x", "z")
AXES = ("x", "y", "z")
IDENTITY: AxisMap = ("x", "y", "z")
PASSED, FAILED, NOT_CHECKED = "passed", "failed", "not checked"  # a board's check (pipeline.labels.imu_check)


def _signed(sign: int, axis: int) -> str:
    return ("-" if sign < 0 else "") + AXES[axis]


# every signed permutation, the identity first
SIGNED_PERMUTATIONS: tuple[AxisMap, ...] = tuple(
    (_signed(s[0], p[0]), _signed(s[1], p[1]), _signed(s[2], p[2]))  # type: ignore[misc]
    for p in permutations(range(3))
    for s in product((1, -1), repeat=3)
)


def parse_axis_map(value: Any, key: str) -> AxisMap:
    """An axis map from params (a list of three of x, y, z each with an optional sign, every axis once);
    ConfigError naming `key` otherwise."""
    if isinstance(value, str) or not isinstance(value, Sequence) or len(value) != 3:
        raise ConfigError(f"{key} must be a list of three axes such as [-y, -x, z], got {value!r}")
    out = []
    for k, item in enumerate(value):
        text = str(item).strip().replace(" ", "") if isinstance(item, str) else ""
        sign, axis = ("-", text[1:]) if text.startswith("-") else ("", text.removeprefix("+"))
        if axis not in AXES:
            raise ConfigError(f"{key}[{k}] must be one of x, y, z with an optional sign, got {item!r}")
        out.append(sign + axis)
    if sorted(a[-1] for a in out) != list(AXES):
        raise ConfigError(f"{key} must name each of x, y, z once, got {value!r}")
    return tuple(out)  # type: ignore[return-value]


def parse_axis_maps(value: Any, key: str) -> dict[str, AxisMap]:
    """A mapping FT sensor -> axis map from params (None or {} for none); ConfigError naming the key."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ConfigError(f"{key} must be a mapping FT sensor -> [x, y, z axes], got {value!r}")
    out = {}
    for sensor, axes in value.items():
        if not isinstance(sensor, str) or not sensor.strip():
            raise ConfigError(f"{key} keys must be FT sensor names, got {sensor!r}")
        out[sensor] = parse_axis_map(axes, f"{key}.{sensor}")
    return out


def check_sensors(maps: Mapping[str, AxisMap], sensors: Iterable[str], key: str) -> None:
    """ConfigError naming `key`.<sensor> for a mapped sensor that the robot does not have."""
    have = list(sensors)
    for sensor in maps:
        if sensor not in have:
            raise ConfigError(
                f"{key}.{sensor}: no FT sensor of that name in the URDF (have: {', '.join(have)})"
            )


def flagged_boards(records: Mapping[str, Mapping[str, Mapping[str, Any]]]) -> dict[str, str]:
    """Sensor -> one line, for each FT sensor whose IMU check failed in a log: that log's message and the
    logs that failed. `records`: log -> sensor -> the label stage's check (`pipeline.labels.imu_check`,
    ``imu_axes`` of a labelled table's ``ftcal.label`` metadata)."""
    out = {}
    for sensor in sorted({s for by_sensor in records.values() for s in by_sensor}):
        status = {log: dict(by_sensor.get(sensor) or {}) for log, by_sensor in sorted(records.items())}
        failed = {log: r for log, r in status.items() if r.get("status") == FAILED}
        if not failed:
            continue
        checked = sum(r.get("status") in (PASSED, FAILED) for r in status.values())
        maps = sorted({tuple(r.get("axes") or ()) for r in failed.values()})
        names = ", ".join(list(failed)[:3]) + (", ..." if len(failed) > 3 else "")
        differ = f"; the logs find {' or '.join(axis_text(m) for m in maps)}" if len(maps) > 1 else ""  # type: ignore[arg-type]
        first = next(iter(failed.values()))["message"]
        out[sensor] = f"{first} (in {len(failed)} of {checked} checked logs: {names}{differ})"
    return out


def axis_text(axes: AxisMap) -> str:
    """``(x, y, z) = (-y, -x, z)``: how the stage's messages state a map."""
    return f"(x, y, z) = ({', '.join(axes)})"


def matrix(axes: AxisMap) -> np.ndarray:
    """(3, 3) the board's axes in the sensor frame, as rows: ``board = M sensor``."""
    import numpy as np

    out = np.zeros((3, 3))
    for row, name in enumerate(axes):
        out[row, AXES.index(name[-1])] = -1.0 if name.startswith("-") else 1.0
    return out


def axis_map(m: np.ndarray) -> AxisMap:
    """The axis map of a signed permutation matrix (inverse of `matrix`)."""
    import numpy as np

    cols = [int(np.argmax(np.abs(row))) for row in m]
    return tuple(_signed(int(np.sign(m[r, c])), c) for r, c in enumerate(cols))  # type: ignore[return-value]


def compose(outer: AxisMap, inner: AxisMap) -> AxisMap:
    """The map of ``matrix(outer) @ matrix(inner)``: `inner` applied to a vector first."""
    return axis_map(matrix(outer) @ matrix(inner))


def to_board(values: np.ndarray, axes: AxisMap | None) -> np.ndarray:
    """(K, 3j) sensor-frame vectors (j of them side by side, e.g. accelerometer then gyroscope) as a board
    with these axes reads them; unchanged for None."""
    return values if axes is None else _apply(values, matrix(axes))


def to_sensor_frame(values: np.ndarray, axes: AxisMap | None) -> np.ndarray:
    """(K, 3j) a board's readings (j vectors side by side) in the sensor frame (inverse of `to_board`)."""
    return values if axes is None else _apply(values, matrix(axes).T)


def _apply(values: np.ndarray, m: np.ndarray) -> np.ndarray:
    k = values.shape[1] // 3
    return (values.reshape(len(values), k, 3) @ m.T).reshape(values.shape)


__all__ = [
    "AXES",
    "IDENTITY",
    "SIGNED_PERMUTATIONS",
    "FAILED",
    "NOT_CHECKED",
    "PASSED",
    "AxisMap",
    "axis_map",
    "axis_text",
    "check_sensors",
    "compose",
    "flagged_boards",
    "matrix",
    "parse_axis_map",
    "parse_axis_maps",
    "to_board",
    "to_sensor_frame",
]
