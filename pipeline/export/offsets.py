"""A re-zeroing's offsets beside an export: ``offsets.json``, what the graphs' ``offsets`` input takes.

A re-zeroing (`ftcal rezero`, `pipeline.deploy.rezero`) estimates per sensor the change of its raw
reading's offset since the calibration was trained: delta (6,) N and Nm, sensor frame, such that the
calibration run on ``raw - delta`` matches the exact labels of a still stretch. It belongs in front of
the calibration (on the raw reading), not after it: the calibration is nonlinear. The file lives beside
the export's ``manifest.json`` and says which export it belongs to (the sha256 of that manifest), when,
from which log and stretch, how still the robot was, and per sensor what the stretch could determine:

    {"format": "ftcal-offsets", "version": 1, "manifest_sha256": ..., "robot": ..., "created": ...,
     "logs": [{"path", "sha256"}], "stretches": [{log, t0, t1, joint, joint_rad_s, gyro_rad_s, ...}],
     "sensors": {"<sensor>": {"offset": [6], "estimate": [6], "std": [6], "floor": [6],
                              "threshold": [6], "applied": [6 reasons], "status": "all" | "sums" | "none",
                              "determined": [6], "equations": [...], "pose_spread": [6] | null,
                              "serial": ...}}, "pose_dependence": {...}, "significance": {...}, ...}

``offset`` is subtracted from the sensor's raw wrench (fx fy fz N, tx ty tz Nm) before the calibration:
the ``estimate`` shrunk towards zero where it is not significant (`pipeline.deploy.shrink`); ``std`` the
estimate's uncertainty from the stretch's noise (1 sigma, N and Nm; the prior's along what the stretch
leaves open), ``floor`` the labels' model error for the stretch's pose carried to the offsets (1 sigma),
``threshold`` the shrinkage's per axis, ``applied`` per axis what was applied and why not;
``pose_spread`` the spread of the estimates over the log's still poses where it has several (a systematic
part the noise does not show). A robot's loop reads the file at start-up and binds
`input_vector` of its graph to the graph's ``offsets``
input (`pipeline.export.graph`); `ftcal calibrate` and the deployment tests do the same.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import DataError

FILE = "offsets.json"
FORMAT, VERSION = "ftcal-offsets", 1
WRENCH_FIELDS = tuple(f"wrench.{k}.{a}" for k in ("force", "torque") for a in "xyz")  # manifest `field`s


@dataclass(frozen=True)
class Offsets:
    """Per sensor the raw-side offset change (6,) N / Nm, and the document it came from (None: built in
    memory, e.g. by the deployment tests)."""

    values: dict[str, np.ndarray] = field(default_factory=dict)
    record: dict[str, Any] | None = None

    def __bool__(self) -> bool:
        return bool(self.values)

    def input_vector(self, entry: Mapping[str, Any]) -> np.ndarray | None:
        """(1, K) the graph's ``offsets`` input for a manifest graph entry (its ``inputs``: sensor and
        field of each column): each sensor's offset on its wrench columns, zero elsewhere; None if no
        sensor of the graph has one."""
        vector = np.zeros((1, len(entry["inputs"])))
        for column in entry["inputs"]:
            value = self.values.get(column["sensor"])
            if value is not None and column["field"] in WRENCH_FIELDS:
                vector[0, column["index"]] = value[WRENCH_FIELDS.index(column["field"])]
        return vector if vector.any() else None


def document(
    values: Mapping[str, np.ndarray],
    sensors: Mapping[str, Mapping[str, Any]],
    manifest_sha256: str,
    **about: Any,
) -> dict[str, Any]:
    """The content of offsets.json: `sensors` (sensor -> its entry without ``offset``: std, determined,
    serial...), the offsets `values`, the export's manifest hash, and `about` (robot, created, log,
    stretch, still, poses...)."""
    entries = {s: {"offset": [float(v) for v in values[s]], **dict(sensors.get(s, {}))} for s in values}
    return {
        "format": FORMAT,
        "version": VERSION,
        "manifest_sha256": manifest_sha256,
        **about,
        "sensors": entries,
    }


def read_offsets(file: Path, manifest_sha256: str, sensors: list[str]) -> Offsets:
    """The offsets of `file` for the export whose manifest.json has `manifest_sha256` and models
    `sensors`. Raises DataError naming the file if it is not an offsets file, another export's, or names
    a sensor the export does not model."""
    from pipeline.core.io import read_json

    doc = read_json(file, "an offsets file")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or not isinstance(doc.get("sensors"), dict):
        raise DataError(f"{file}: not an ftcal offsets file (format {FORMAT!r})")
    if doc.get("manifest_sha256") != manifest_sha256:
        raise DataError(
            f"{file}: re-zeroed for another export (its manifest.json has changed since): re-zero again "
            "(`ftcal rezero`) or remove the file"
        )
    values = {}
    for sensor, entry in doc["sensors"].items():
        if sensor not in sensors:
            raise DataError(f"{file}: sensors.{sensor}: not a sensor of the export ({', '.join(sensors)})")
        value = np.asarray(entry.get("offset") if isinstance(entry, dict) else None, dtype=np.float64)
        if value.shape != (6,) or not np.isfinite(value).all():
            raise DataError(f"{file}: sensors.{sensor}.offset must be 6 finite numbers (N, Nm)")
        values[sensor] = value
    return Offsets(values, doc)


def summary(offsets: Offsets) -> str:
    """One line on what a calibration's offsets are: when and from which log they were estimated."""
    if not offsets:
        return "offsets: none (the calibration as delivered)"
    record = offsets.record or {}
    logs = ", ".join(str(log.get("path")) for log in record.get("logs") or []) or "?"
    return f"offsets of {len(offsets.values)} sensor(s), re-zeroed {record.get('created', '?')} from {logs}"
