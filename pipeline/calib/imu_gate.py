"""No 13-input network of a group with an FT board whose IMU is not in the sensor frame.

The label stage checks every board's IMU against the kinematics (`pipeline.labels.imu_check`) and writes
each log's verdict into its table's ``ftcal.label`` metadata (``imu_axes``). A network that reads a board
whose axes are swapped or inverted learns a relation that a deployment with a correct board (or another
log) cannot reproduce, so a group whose board failed in any of its logs trains no 13-input network until
``ingest.imu_axes`` maps that board (ingest, label and train then re-run, and the check passes). This is a
skip with a warning, not an error: the baselines and the 7-input networks are sound, ``dvc repro`` goes on
to evaluate and report them, and the report and ``metrics.json`` (``notes``) say why the network is missing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import pyarrow.parquet as pq

from pipeline.calib.data import Group, LogInfo
from pipeline.calib.params import GroupParams
from pipeline.core.errors import DataError
from pipeline.logs import schema as S
from pipeline.logs.imu_axes import flagged_boards

IMU_INPUTS = 13  # the network size that reads the IMU


def imu_checks(logs: Sequence[LogInfo]) -> dict[str, dict[str, dict]]:
    """log -> sensor -> the label stage's IMU check record (logs labelled without one: none)."""
    out = {}
    for log in logs:
        meta = S.read_metadata(pq.read_schema(log.path), S.META_LABEL) or {}
        out[log.name] = dict(meta.get("imu_axes") or {})
    return out


def refuse_flagged_imu(
    gp: GroupParams, group: Group, logs: Sequence[LogInfo]
) -> tuple[GroupParams, Group, list[str]]:
    """(`gp` and `group` without the 13-input network where a board of the group failed the IMU check in
    one of `logs`, the notes saying so: one line per such sensor, naming the axis map its IMU follows and
    the ``ingest.imu_axes`` entry to set). DataError if the group trains nothing else."""
    if IMU_INPUTS not in gp.inputs:
        return gp, group, []
    flagged = flagged_boards(imu_checks(logs))
    notes = [f"{group.name}: no 13-input network: {flagged[s]}" for s in group.sensors if s in flagged]
    if not notes:
        return gp, group, []
    inputs = tuple(n for n in gp.inputs if n != IMU_INPUTS)
    if not inputs:
        raise DataError(f"{notes[0]}; train.groups.{group.name}.inputs has no other network to train")
    return replace(gp, inputs=inputs), replace(group, n_inputs=max(inputs)), notes


__all__ = ["IMU_INPUTS", "imu_checks", "refuse_flagged_imu"]
