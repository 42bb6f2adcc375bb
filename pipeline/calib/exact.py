"""Which sensors of a group can be calibrated: exact labels on the training logs, and why not.

A sensor is calibrated from its exact labels (``sw.<sensor>`` 1 where its wrench is ok), or through an exact
cut-set sum it takes part in (``sw.<cut>`` 1, every member's wrench ok). A recording may give a sensor
neither: its joint streams are absent (an arm without its ``stateExt:o``, :mod:`pipeline.labels.joints`),
or its contacts never make it exact. Such a sensor is left out of its group, named with the reason (the
streams it lacks, from the labelled tables' ``ftcal.label`` metadata ``exact``), and the group's other
sensors train; a group with none left is not calibrated at all: train, evaluate, export and the
deployment tests then write a record saying so (`NOT_CALIBRATED` in their JSON) and nothing else.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from pipeline.core.errors import DataError
from pipeline.logs import schema as S

NOT_CALIBRATED = "not_calibrated"  # key of the JSON records of a group nothing could be calibrated for
LEFT_OUT = "left_out"  # key of the sensors of a group left out of its calibration: sensor -> reason
NOT_CALIBRATED_TEXT = "not calibrated"  # what the metrics and the stages' lines say of such a group


class NotCalibrated(DataError):
    """No sensor of a group has an exact label to train on; `reason` says why (per sensor if they differ)."""

    def __init__(self, group: str, reason: str, left_out: Mapping[str, str]):
        super().__init__(f"{group}: not calibrated: {reason}")
        self.group, self.reason, self.left_out = group, reason, dict(left_out)


@dataclass(frozen=True)
class Usable:
    """Exact samples per sensor (its own labels) and per cut set (``label`` -> members) on training logs."""

    own: dict[str, int]
    cuts: dict[str, int]
    lacks: dict[str, list[str]]  # sensor -> streams (or joints) its labels lacked on those logs
    wrench: dict[str, int]  # samples where the sensor's wrench is ok


def count_exact(paths: Sequence[Path], sensors: Sequence[str], cuts: Mapping[str, Sequence[str]]) -> Usable:
    """Count the exact labels of `sensors` and of the cut sets `cuts` (label -> member sensors) in the
    labelled tables `paths`, reading only their switch and wrench-ok columns and their metadata."""
    own, readings = dict.fromkeys(sensors, 0), dict.fromkeys(sensors, 0)
    sums = dict.fromkeys(cuts, 0)
    lacks: dict[str, set[str]] = {s: set() for s in sensors}
    for path in paths:
        schema = pq.read_schema(path)
        wanted = [S.switch_col(s) for s in sensors] + [S.ok_col(S.WRENCH_STREAM, s) for s in sensors]
        wanted += [S.switch_col(c) for c in cuts]
        table = pq.read_table(path, columns=[c for c in dict.fromkeys(wanted) if c in schema.names])

        def col(name: str, table: Any = table) -> np.ndarray:
            return table.column(name).to_numpy(zero_copy_only=False).astype(bool)

        wrench = {s: col(S.ok_col(S.WRENCH_STREAM, s)) for s in sensors}
        for s in sensors:
            own[s] += int((col(S.switch_col(s)) & wrench[s]).sum())
            readings[s] += int(wrench[s].sum())
        for c, members in cuts.items():
            if S.switch_col(c) in table.column_names:
                on = col(S.switch_col(c))
                sums[c] += int(np.logical_and.reduce([on, *(wrench[m] for m in members)]).sum())
        exact = (S.read_metadata(schema, S.META_LABEL) or {}).get("exact") or {}
        for s in sensors:
            lacks[s].update((exact.get(s) or {}).get("lacks") or ())
    return Usable(own, sums, {s: sorted(v) for s, v in lacks.items()}, readings)


def reason(sensor: str, usable: Usable) -> str:
    """Why `sensor` has no exact label: the streams it lacks, else its contacts."""
    lacks = usable.lacks.get(sensor) or []
    if lacks:
        return f"no exact label (lacks {', '.join(lacks)})"
    if not usable.wrench.get(sensor):
        return f"no exact label (no wrench: {S.ok_col(S.WRENCH_STREAM, sensor)} is false on every sample)"
    return "no exact label (one side of its cut always touches, or its wrench is not ok there)"


def calibrable(
    group: str, sensors: Sequence[str], cuts: Mapping[str, Sequence[str]], paths: Sequence[Path]
) -> tuple[list[str], dict[str, str]]:
    """(the sensors that can be calibrated, sensor -> reason for the others) from the training tables.

    Raises:
        NotCalibrated: none can.
    """
    usable = count_exact(paths, sensors, cuts)
    through_sums = {m for c, members in cuts.items() if usable.cuts[c] for m in members}
    kept = [s for s in sensors if usable.own[s] or s in through_sums]
    left_out = {s: reason(s, usable) for s in sensors if s not in kept}
    if not kept:
        raise NotCalibrated(group, _group_reason(left_out, usable), left_out)
    return kept, left_out


def _group_reason(left_out: Mapping[str, str], usable: Usable) -> str:
    """One reason for a group none of whose sensors can be calibrated: theirs if they share it, else
    ``no exact label (l_leg_ft lacks a; r_leg_ft lacks a, b)``, else each sensor's."""
    reasons = list(dict.fromkeys(left_out.values()))
    if len(reasons) == 1:
        return reasons[0]
    if all(usable.lacks.get(s) for s in left_out):
        each = "; ".join(f"{s} lacks {', '.join(usable.lacks[s])}" for s in left_out)
        return f"no exact label ({each})"
    return "; ".join(f"{s}: {r}" for s, r in left_out.items())


def not_calibrated_record(group: str, sensors: Sequence[str], error: NotCalibrated) -> dict[str, Any]:
    """The JSON record of a group that is not calibrated (train's metrics.json, evaluate's report)."""
    return {"group": group, "sensors": list(sensors), NOT_CALIBRATED: error.reason, LEFT_OUT: error.left_out}


def not_calibrated(record: Mapping[str, Any]) -> str | None:
    """The reason a record (metrics.json, report.json, manifest.json, result.json) gives for its group not
    being calibrated, None for a calibrated group."""
    value = record.get(NOT_CALIBRATED)
    return None if value is None else str(value)


def left_out_text(left_out: Mapping[str, str]) -> str:
    """``l_leg_ft: no exact label (lacks left_leg/stateExt:o); ...`` ('' where none is left out)."""
    return "; ".join(f"{s}: {r}" for s, r in left_out.items())


__all__ = [
    "LEFT_OUT",
    "NOT_CALIBRATED",
    "NOT_CALIBRATED_TEXT",
    "NotCalibrated",
    "calibrable",
    "count_exact",
    "left_out_text",
    "not_calibrated",
    "not_calibrated_record",
]
