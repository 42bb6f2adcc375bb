"""Which physical sensor a calibration belongs to: serial numbers recorded at export, checked on every log.

A log names the boards it was recorded with in its experiment record (``serial.<sensor>`` keys,
`pipeline.logs.serials`). At export each sensor's calibration records the serial of its training logs
(they must agree: a calibration learnt from two boards belongs to neither), else ``robot.serials`` of
params.yaml, else none. `ftcal calibrate` and `ftcal rezero` refuse a log whose serial for a modelled
sensor differs from the recorded one, naming both: a board was swapped, and the old one's calibration
must not be applied to it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from pipeline.core.errors import DataError
from pipeline.logs.serials import log_serials


def training_serials(
    experiments: Mapping[str, Mapping[str, object]],
    sensors: Sequence[str],
    declared: Mapping[str, str] | None,
) -> dict[str, str | None]:
    """Sensor -> the serial a calibration belongs to: the one its training logs record (`experiments`:
    log -> experiment record), else `declared` (``robot.serials``), else None. Raises DataError naming two
    logs that record different serials for one sensor."""
    out: dict[str, str | None] = {}
    for sensor in sensors:
        seen: dict[str, str] = {}  # serial -> first log recording it
        for log, experiment in experiments.items():
            serial = log_serials(experiment).get(sensor)
            if serial is not None:
                seen.setdefault(serial, log)
        if len(seen) > 1:
            (a, log_a), (b, log_b) = list(seen.items())[:2]
            raise DataError(
                f"{log_b}: {sensor} is serial {b!r} there but {a!r} in {log_a}: the training logs of one "
                "calibration come from two sensor boards"
            )
        out[sensor] = next(iter(seen), None) or (declared or {}).get(sensor)
    return out


def training_imu_axes(
    ingests: Mapping[str, Mapping[str, object]], sensors: Sequence[str]
) -> dict[str, list[str] | None]:
    """Sensor -> the IMU axis map ingest applied to its board in the training logs (`ingests`: log -> its
    ``ftcal.ingest`` metadata, whose ``imu_axes`` is `ingest.imu_axes`; None: unmapped). Raises DataError
    naming two logs ingested with different maps for one sensor (the board's inputs would differ)."""
    out: dict[str, list[str] | None] = {}
    for sensor in sensors:
        seen: dict[tuple[str, ...] | None, str] = {}
        for log, ingest in ingests.items():
            axes = (ingest.get("imu_axes") or {}).get(sensor)  # type: ignore[union-attr]
            seen.setdefault(tuple(axes) if axes else None, log)
        if len(seen) > 1:
            (a, log_a), (b, log_b) = list(seen.items())[:2]
            raise DataError(
                f"{log_b}: {sensor}'s IMU was ingested with axes {b} there but {a} in {log_a}: set "
                "ingest.imu_axes once for every training log"
            )
        axes = next(iter(seen), None)
        out[sensor] = list(axes) if axes else None
    return out


def check_serials(
    expected: Mapping[str, str | None],
    experiment: Mapping[str, object] | None,
    where: str | Path,
    export: Path,
) -> list[str]:
    """Refuse a log recorded with another board than a calibration's: DataError naming the sensor and both
    serials. `expected`: sensor -> the export's serial (None: not recorded, not checked). Returns warnings
    for the checked sensors whose serial the log does not record."""
    recorded = log_serials(experiment)
    unknown = []
    for sensor, serial in expected.items():
        if serial is None:
            continue
        if sensor not in recorded:
            unknown.append(sensor)
        elif recorded[sensor] != serial:
            raise DataError(
                f"{where}: {sensor} is serial {recorded[sensor]!r} in this log, but the calibration in "
                f"{export} belongs to serial {serial!r} (another board: recalibrate it)"
            )
    if not unknown:
        return []
    return [
        f"{where}: records no serial of {', '.join(unknown)}: cannot check they are the calibrated boards"
    ]
