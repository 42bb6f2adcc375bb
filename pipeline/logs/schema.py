"""Column names, units and Parquet schemas of the tables the stages exchange (the one place they are spelled).

Tables are wide: one row per joint-state sample (the time base of a log), one column per quantity.
Column names are ``<quantity>.<name>[.<axis>]``; build them with the functions below, never by hand.

Ingested table ``data/ingested/<log>.parquet`` (units in brackets):

- ``stamp_ns`` [ns, int64]: joint-state header stamp, the time base; strictly increasing.
- ``time_s`` [s]: ``stamp_ns`` minus the first stamp of the log.
- ``q.<joint>`` [rad or m], ``dq_enc.<joint>`` [rad/s or m/s], ``tau_enc.<joint>`` [Nm or N]:
  encoder positions, encoder velocities (noisy) and efforts from sensor_msgs/JointState, in
  ``RobotModel.joint_names`` order (NaN where the log has no velocity/effort).
- ``ft.<sensor>.<fx|fy|fz|tx|ty|tz>`` [N, Nm]: raw wrench in the sensor frame.
- ``acc.<sensor>.<x|y|z>`` [m/s^2]: FT-board accelerometer (proper acceleration).
- ``gyr.<sensor>.<x|y|z>`` [rad/s]: FT-board gyroscope.
- ``temp.<sensor>`` [degC]: FT-board temperature.
- ``ok.<stream>.<sensor>`` [bool]: the stream's values at this sample are trustworthy: the two source
  messages around it are at most the stream's max gap apart (or one has exactly this stamp).
  Streams: ``wrench``, ``imu``, ``temperature``. Where ``ok`` is False the values are NaN.
  Joint positions are finite: joint-state messages without finite positions are dropped (the time base
  then has a gap, as for a lost message), except the joints a recording declares absent (a dataDumper
  board without its ``data.log``), NaN on every sample.

Truth table ``data/ingested/<log>.truth.parquet`` (simulated logs only; same rows as the ingested table):
``stamp_ns``, ``time_s``, ``true.<sensor>.<axis>``, ``distorted.<sensor>.<axis>``,
``oracle.<sensor>.<axis>`` [N, Nm] with their ``ok.<kind>.<sensor>`` flags, and ``contacts`` [string,
comma-separated links touching the environment; null before the first message].

Smoothed table ``data/smoothed/<log>.parquet``: every column of the ingested table plus
``qs.<joint>`` [rad], ``dqs.<joint>`` [rad/s], ``ddqs.<joint>`` [rad/s^2] (Savitzky-Golay),
``ok.kinematics.<joint>`` [bool] (False where that joint's position is absent or NaN, within half a
window of the ends of its smoothed segments, or in a segment too short to smooth: its smoothed values
are not usable there; the other joints' are unaffected) and ``ok.kinematics`` [bool] (every joint's).

Labelled table ``data/labelled/<log>.parquet`` (same rows as the smoothed table; training input):
``stamp_ns``, ``time_s``; the model inputs ``ft.<sensor>.<axis>``, ``temp.<sensor>``,
``acc.<sensor>.<x|y|z>``, ``gyr.<sensor>.<x|y|z>`` with their ``ok.<stream>.<sensor>`` flags; and the labels:

- ``exp.<sensor>.<axis>`` [N, Nm]: expected wrench of the sensor, in its frame and measure direction
  (iDynTree semantics); NaN where ``sw.<sensor>`` is 0.
- ``sw.<sensor>`` [uint8]: exact-label switch (thesis eqs. 5.5, 5.11): 1 iff one side of the sensor's
  cut touches nothing, the sample lies outside every guard band and its kinematics are ok.
- ``exp.<pair>.<axis>`` [N, Nm]: a foot pair's summed wrench (front + rear mapped by ``sole_X_sensor``)
  in its sole frame; NaN where ``sw.<pair>`` is 0.
- ``sw.<pair>`` [uint8]: 1 iff the contacts lie all on that foot or all off it (the graph-cut rule;
  the thesis's eq. 5.12 switch of the sum loss is ``sw.<pair> * (1 - sw.<front> * sw.<rear>)``).
- ``contacts`` [string]: the contact set used (declared or detected); ``fixed_link`` [string]: the link
  fixed in the world; ``guard`` [bool]: inside a guard band around a contact change.

- ``exp.<cut>.<axis>`` [N, Nm]: a cut set's signed sum ``sum_s sign_s frame_X_s f_s`` of its sensors'
  expected readings in the cut set's common frame (a URDF link; moment about its origin), see
  :mod:`pipeline.physics.cuts`; ``<cut>`` is :func:`cut_set_name` (its sensors joined by ``+``, URDF order).
  NaN where ``sw.<cut>`` is 0. A cut set equal to a foot pair is labelled only under the pair's name.
- ``sw.<cut>`` [uint8]: 1 iff the part the set isolates touches nothing or is alone in touching, outside
  guard bands, kinematics ok (exact even where no member's own switch is 1, e.g. the leg sensors in
  double support).
- ``pose.<cut>.<sensor>.<r00..r22|px|py|pz>`` [1, m]: for the members whose transform to the common
  frame depends on the joints, the pose of the sensor frame in the common frame per sample (rotation
  row-major, then position); the wrench transform is ``[[R, 0], [p^ R, R]]`` (force first). NaN where
  the kinematics are not ok.

Its metadata ``ftcal.label`` (JSON) holds the cut sets (``cut_sets.<cut>``: sensors, frame, signs, the
label name, the isolated part's links, and per member either its constant 6x6 ``X`` or its pose columns),
the foot pairs with their constant 6x6 wrench transforms
(``pairs.<pair>.sole_X_front`` / ``sole_X_rear``, row-major, force first), the contact-detection
settings and the per-log summary.

Parquet key-value metadata: ``ftcal.experiment`` (JSON of the MCAP ``experiment`` record),
``ftcal.ingest`` (JSON: source file, topics found with types, message counts, rates, warnings),
``ftcal.smooth`` (JSON, smoothed tables), ``ftcal.schema`` (the table kind and schema version).
Every field also carries its unit in its Arrow field metadata (key ``unit``).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import pyarrow as pa

SCHEMA_VERSION = 1

# --- time base ---
STAMP = "stamp_ns"  # int64 ns, joint-state header stamp
TIME = "time_s"  # float64 s since the first sample

WRENCH_AXES = ("fx", "fy", "fz", "tx", "ty", "tz")  # N, N, N, Nm, Nm, Nm
VECTOR_AXES = ("x", "y", "z")
CONTACTS = "contacts"

# Quantity prefixes (first component of a column name) and their units.
Q, DQ_ENC, TAU_ENC = "q", "dq_enc", "tau_enc"
FT, ACC, GYR, TEMP = "ft", "acc", "gyr", "temp"
TRUE, DISTORTED, ORACLE = "true", "distorted", "oracle"
EXTERNAL = "external"  # simulated truth: the part of the true wrench due to external pushes and loads
EXPECTED, SWITCH = "exp", "sw"  # labelled tables: expected wrench and its exact-label switch
FIXED_LINK, GUARD = "fixed_link", "guard"
POSE = "pose"  # labelled tables: pose.<cut>.<sensor>.<axis>, sensor pose in a cut set's common frame
CUT_JOIN = "+"  # cut-set names: sensor names joined by this
POSE_AXES = ("r00", "r01", "r02", "r10", "r11", "r12", "r20", "r21", "r22", "px", "py", "pz")  # 1, m
PRED = "pred"  # predictions tables: pred.<model>.<sensor or pair>.<axis> [N, Nm]
LOG = "log"  # predictions tables: the log (labelled table stem) of the sample
QS, DQS, DDQS = "qs", "dqs", "ddqs"
OK = "ok"

# ok.<stream> names
JOINTS_STREAM = "joints"
KINEMATICS_STREAM = "kinematics"
WRENCH_STREAM, IMU_STREAM, TEMPERATURE_STREAM = "wrench", "imu", "temperature"

_UNITS = {
    STAMP: "ns",
    TIME: "s",
    Q: "rad",
    DQ_ENC: "rad/s",
    TAU_ENC: "Nm",
    ACC: "m/s^2",
    GYR: "rad/s",
    TEMP: "degC",
    QS: "rad",
    DQS: "rad/s",
    DDQS: "rad/s^2",
    OK: "",
    CONTACTS: "",
}
_WRENCH_UNITS = {"fx": "N", "fy": "N", "fz": "N", "tx": "Nm", "ty": "Nm", "tz": "Nm"}

# Parquet key-value metadata keys.
META_EXPERIMENT = b"ftcal.experiment"
META_INGEST = b"ftcal.ingest"
META_SMOOTH = b"ftcal.smooth"
META_SCHEMA = b"ftcal.schema"
META_LABEL = b"ftcal.label"
META_SOURCE = b"ftcal.source"  # ingested tables: the log's file, its topics and its reader's metadata records

KIND_INGESTED, KIND_TRUTH, KIND_SMOOTHED, KIND_LABELLED = "ingested", "truth", "smoothed", "labelled"
TRUTH_SUFFIX = ".truth"  # <log>.truth.parquet
PARQUET_SUFFIX = ".parquet"
# the note left in a simulation's output folder (and a deployment day's tables) when nothing was simulated:
# its first line says why (recorded logs only)
NOT_SIMULATED = "not_simulated.txt"


# --- column names ---


def joint_col(quantity: str, joint: str) -> str:
    """``<quantity>.<joint>``, quantity one of Q, DQ_ENC, TAU_ENC, QS, DQS, DDQS."""
    return f"{quantity}.{joint}"


def joint_cols(quantity: str, joints: Iterable[str]) -> list[str]:
    return [joint_col(quantity, j) for j in joints]


def wrench_cols(quantity: str, sensor: str) -> list[str]:
    """The 6 columns ``<quantity>.<sensor>.<fx..tz>``, quantity one of FT, TRUE, DISTORTED, ORACLE,
    EXTERNAL, EXPECTED, PRED."""
    return [f"{quantity}.{sensor}.{axis}" for axis in WRENCH_AXES]


def vector_cols(quantity: str, sensor: str) -> list[str]:
    """The 3 columns ``<quantity>.<sensor>.<x|y|z>``, quantity ACC or GYR."""
    return [f"{quantity}.{sensor}.{axis}" for axis in VECTOR_AXES]


def prediction_cols(model: str, name: str) -> list[str]:
    """The 6 columns ``pred.<model>.<sensor or pair>.<axis>`` of a model's predicted wrench [N, Nm]."""
    return wrench_cols(f"{PRED}.{model}", name)


def switch_col(name: str) -> str:
    """``sw.<sensor or pair>``: exact-label switch (uint8) in labelled tables."""
    return f"{SWITCH}.{name}"


def cut_set_name(sensors: Iterable[str]) -> str:
    """``<sensor>+<sensor>+...``: the name of a cut set (its sensors in URDF order), used as ``<cut>`` in
    ``exp.<cut>.<axis>`` (:func:`wrench_cols` with EXPECTED) and ``sw.<cut>`` (:func:`switch_col`)."""
    return CUT_JOIN.join(sensors)


def cut_sum_cols(cut: str) -> list[str]:
    """The 6 columns ``exp.<cut>.<axis>`` [N, Nm] of a cut set's expected signed sum, common frame."""
    return wrench_cols(EXPECTED, cut)


def cut_switch_col(cut: str) -> str:
    """``sw.<cut>`` [uint8]: the cut set's exact-label switch."""
    return switch_col(cut)


def cut_pose_cols(cut: str, sensor: str) -> list[str]:
    """The 12 columns ``pose.<cut>.<sensor>.<r00..r22|px|py|pz>``: pose of the sensor frame in the cut
    set's common frame (rotation row-major [1], position [m])."""
    return [f"{POSE}.{cut}.{sensor}.{axis}" for axis in POSE_AXES]


def temperature_col(sensor: str) -> str:
    return f"{TEMP}.{sensor}"


def ok_col(stream: str, sensor: str | None = None) -> str:
    """``ok.<stream>`` or ``ok.<stream>.<sensor>``."""
    return f"{OK}.{stream}" if sensor is None else f"{OK}.{stream}.{sensor}"


def unit(column: str) -> str:
    """The unit of a column, from its name."""
    if column in _UNITS:
        return _UNITS[column]
    parts = column.split(".")
    if parts[0] in (FT, TRUE, DISTORTED, ORACLE, EXTERNAL, EXPECTED, PRED):
        return _WRENCH_UNITS.get(parts[-1], "")
    if parts[0] == POSE:
        return "m" if parts[-1].startswith("p") else ""
    return _UNITS.get(parts[0], "")


def ingested_columns(joints: Sequence[str], sensors: Sequence[str]) -> list[str]:
    """The columns of an ingested table, in order."""
    cols = [STAMP, TIME]
    for quantity in (Q, DQ_ENC, TAU_ENC):
        cols += joint_cols(quantity, joints)
    for s in sensors:
        cols += wrench_cols(FT, s) + vector_cols(ACC, s) + vector_cols(GYR, s) + [temperature_col(s)]
        cols += [ok_col(WRENCH_STREAM, s), ok_col(IMU_STREAM, s), ok_col(TEMPERATURE_STREAM, s)]
    return cols


TRUTH_KINDS = (TRUE, DISTORTED, ORACLE, EXTERNAL)


def truth_columns(sensors: Sequence[str]) -> list[str]:
    """The columns of a truth table, in order."""
    cols = [STAMP, TIME]
    for s in sensors:
        for kind in TRUTH_KINDS:
            cols += wrench_cols(kind, s) + [ok_col(kind, s)]
    cols.append(CONTACTS)
    return cols


def joint_ok_cols(joints: Iterable[str]) -> list[str]:
    """``ok.kinematics.<joint>`` [bool] per joint: that joint's smoothed kinematics are usable."""
    return [ok_col(KINEMATICS_STREAM, j) for j in joints]


def smoothed_extra_columns(joints: Sequence[str]) -> list[str]:
    """The columns that `smooth` adds to an ingested table."""
    return [
        *joint_cols(QS, joints),
        *joint_cols(DQS, joints),
        *joint_cols(DDQS, joints),
        ok_col(KINEMATICS_STREAM),
        *joint_ok_cols(joints),
    ]


def arrow_type(column: str) -> pa.DataType:
    if column == STAMP:
        return pa.int64()
    if column.startswith(OK + ".") or column == GUARD:
        return pa.bool_()
    if column.startswith(SWITCH + "."):
        return pa.uint8()
    if column in (CONTACTS, FIXED_LINK):
        return pa.string()
    return pa.float64()


def arrow_schema(columns: Sequence[str], kind: str, metadata: Mapping[bytes, Any] | None = None) -> pa.Schema:
    """Arrow schema of a table with these columns: dtypes and units from the names, plus metadata.

    Metadata values that are not bytes are stored as JSON.
    """
    fields = [
        pa.field(c, arrow_type(c), nullable=(c == CONTACTS), metadata={b"unit": unit(c).encode()})
        for c in columns
    ]
    meta = {META_SCHEMA: json.dumps({"kind": kind, "version": SCHEMA_VERSION}).encode()}
    for key, value in (metadata or {}).items():
        meta[key] = value if isinstance(value, bytes) else json.dumps(value, sort_keys=True).encode()
    return pa.schema(fields, metadata=meta)


def read_metadata(schema: pa.Schema, key: bytes) -> Any:
    """A JSON metadata value of a table schema (None if absent)."""
    raw = (schema.metadata or {}).get(key)
    return None if raw is None else json.loads(raw)


def joints_of(columns: Iterable[str], quantity: str = Q) -> list[str]:
    """Joint names of a table, in column order, from its ``<quantity>.<joint>`` columns."""
    prefix = quantity + "."
    return [c[len(prefix) :] for c in columns if c.startswith(prefix)]


def sensors_of(columns: Iterable[str], quantity: str = FT) -> list[str]:
    """FT sensor names of a table, in column order, from its ``<quantity>.<sensor>.fx`` columns."""
    prefix, suffix = quantity + ".", "." + WRENCH_AXES[0]
    return [c[len(prefix) : -len(suffix)] for c in columns if c.startswith(prefix) and c.endswith(suffix)]
