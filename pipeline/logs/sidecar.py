"""Experiment metadata kept beside a recording: the sidecar YAML, and what a record says is absent.

Recordings that carry no experiment record of their own (logger ``.mat`` files, YARP dataDumper runs) get
it from a YAML sidecar beside them: ``<log stem>.yaml`` beside a ``.mat``, ``<run>.yaml`` beside a run
folder. It holds the fields of the MCAP ``experiment`` record (``type``, ``role``, ``robot``,
``contacts``, ``fixed_link``...: scalars, a list of contact links joined with ','), and optionally
``window`` and ``segments`` (`pipeline.logs.segments`), which are stored in the record as JSON strings,
the form an MCAP ``experiment`` record carries them in (``ftcal convert-*`` writes them so).

A reader that knows which of the contract's streams a recording lacks (a dataDumper port folder without
``data.log``) says so in a ``recording`` metadata record (`RECORDING`): ``absent_topics`` (contract topics,
comma-separated), ``absent_joints`` (URDF joints whose positions the recording does not have),
``absent_streams`` (the recording's own names of what is missing, for the ingest summary) and
``absent_joint_streams`` (JSON: each absent stream -> the joints it carries, so that a label lacking a joint
names the recording's stream, e.g. ``left_arm/stateExt:o``), and ``not_read``: what the recording holds that
the contract does not read (a dataDumper run's other ports, e.g. ``right_leg/inertialMTB``, and folders of
ports that never connected), named once in the ingest summary. Ingest then treats those streams as absent
(NaN and flagged) instead of as an error; a converted MCAP keeps the record.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pipeline.core.errors import DataError
from pipeline.logs.segments import SPLIT_KEYS, parse_split, split_to_record

RECORDING = "recording"  # metadata record name: what the recording lacks
ABSENT_TOPICS, ABSENT_JOINTS, ABSENT_STREAMS = "absent_topics", "absent_joints", "absent_streams"
ABSENT_JOINT_STREAMS = "absent_joint_streams"
NOT_READ = "not_read"
ENCODERS, ENCODER_STEPS = "encoders", "steps_rad"  # record: each joint's encoder step on its own board


def read_sidecar(side: Path, log: Path) -> dict[str, str]:
    """The experiment record of `log` from its YAML sidecar `side`: names -> strings, as the MCAP record.

    `window` and `segments` are checked (`pipeline.logs.segments.parse_split`) and stored as JSON.
    Raises DataError naming the file (and the key) if the sidecar is missing or bad.
    """
    import yaml

    if not side.is_file():
        raise DataError(
            f"{log}: missing experiment sidecar {side.name} beside it (YAML with at least `type`, "
            "and `role`, `robot`, `contacts`, `window`, `segments` where known; see docs/recorded-logs.md)"
        )
    try:
        data = yaml.safe_load(side.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise DataError(f"{side}: cannot read the experiment sidecar: {' '.join(str(exc).split())}") from None
    if not isinstance(data, Mapping):
        raise DataError(f"{side}: the experiment sidecar must be a YAML mapping, got {type(data).__name__}")
    out: dict[str, str] = {}
    split: dict[str, Any] = {}
    for key, value in data.items():
        if key in SPLIT_KEYS:
            split[str(key)] = value
            continue
        if isinstance(value, list | tuple) and all(isinstance(v, str) for v in value):
            value = ",".join(value)
        if isinstance(value, bool):
            value = "true" if value else "false"
        if value is None:
            value = ""
        if not isinstance(value, str | int | float):
            raise DataError(f"{side}: experiment key {key!r} must be a scalar, got {value!r}")
        out[str(key)] = str(value)
    if not out.get("type", "").strip():
        raise DataError(
            f"{side}: the experiment sidecar lacks `type` (pole, balancing, half_foot, walking...)"
        )
    window, segments = parse_split(split, str(side))
    out.update(split_to_record(window, segments))
    return out


def declared_absent(metadata: Mapping[str, Mapping[str, str]]) -> dict[str, Any]:
    """What the `recording` record of a log's metadata declares absent: {"topics", "joints", "streams"}
    (lists of names), "joint_streams" (joint -> its stream's name) and "not_read" (names of what the
    recording holds and ingest does not read)."""
    record = metadata.get(RECORDING) or {}

    def names(key: str) -> list[str]:
        return [n for n in str(record.get(key, "")).split(",") if n]

    try:
        by_stream = json.loads(record.get(ABSENT_JOINT_STREAMS) or "{}")
    except ValueError:
        by_stream = {}
    by_stream = by_stream if isinstance(by_stream, dict) else {}
    return {
        "topics": names(ABSENT_TOPICS),
        "joints": names(ABSENT_JOINTS),
        "streams": names(ABSENT_STREAMS),
        "not_read": names(NOT_READ),
        "joint_streams": {str(j): str(s) for s, joints in by_stream.items() for j in joints or ()},
    }


def encoders_record(steps: Mapping[str, float]) -> dict[str, str]:
    """The `encoders` record: joint -> its encoder step (rad) found on its board's own readings, before
    they were interpolated at another board's stamps (which takes them off the lattice)."""
    return {ENCODER_STEPS: json.dumps({str(j): float(v) for j, v in steps.items() if v > 0})}


def declared_steps(metadata: Mapping[str, Any]) -> dict[str, float]:
    """joint -> encoder step (rad) of a log's `encoders` record (`metadata`: its reader's records); {}
    without one."""
    try:
        steps = json.loads((metadata.get(ENCODERS) or {}).get(ENCODER_STEPS) or "{}")
    except (ValueError, AttributeError):
        return {}
    return {str(j): float(v) for j, v in steps.items()} if isinstance(steps, dict) else {}


def absent_record(
    topics: list[str],
    joints: list[str],
    streams: list[str],
    joint_streams: Mapping[str, list[str]] | None = None,
    not_read: list[str] | None = None,
) -> dict[str, str]:
    """The `recording` record declaring these absent (see the module docstring); `joint_streams`: absent
    stream -> the joints it carries; `not_read`: what the recording holds that ingest does not read."""
    record = {
        ABSENT_TOPICS: ",".join(topics),
        ABSENT_JOINTS: ",".join(joints),
        ABSENT_STREAMS: ",".join(streams),
    }
    if joint_streams:
        record[ABSENT_JOINT_STREAMS] = json.dumps({k: list(v) for k, v in joint_streams.items()})
    if not_read:
        record[NOT_READ] = ",".join(not_read)
    return record


_TEMPLATES = {"imu": "ft_imu", "temperature": "ft_temperature", "wrench": "ft_wrench"}


def describe_absent(
    lacking: Mapping[str, list[str]], sensors: list[str], topics: Any
) -> list[tuple[str, str]]:
    """(summary entry, warning) per stream kind (imu, temperature, wrench) that some sensors lack:
    ``imu (all 6 sensors)`` or ``temperature (l_leg_ft, r_leg_ft)``; `topics`: TopicParams."""
    out = []
    for kind, names in lacking.items():
        every = len(names) == len(sensors) and len(names) > 1
        template = _TEMPLATES[kind]
        if every:
            listed, which = getattr(topics, template), f" of all {len(names)} sensors"
        else:
            listed, which = ", ".join(topics.sensor_topic(template, s) for s in names), ""
        entry = f"{kind} ({f'all {len(names)} sensors' if every else ', '.join(names)})"
        out.append((entry, f"no {listed}{which}: its columns are NaN and flagged"))
    return out
