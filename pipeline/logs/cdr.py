"""ROS 2 messages in CDR: the message types ftcal reads and writes, their schemas and byte layouts.

Supported message types (standard ROS 2 definitions, `SCHEMAS`): sensor_msgs/msg/JointState,
geometry_msgs/msg/WrenchStamped, sensor_msgs/msg/Imu, sensor_msgs/msg/Temperature, std_msgs/msg/String.

Conventions: times are int64 nanoseconds. ``header.stamp`` (sec, nanosec) <-> ``stamp_ns``; the MCAP
log time is the recorder's receive time; the MCAP publish time is written equal to the stamp (for
std_msgs/String, which has no header, the stamp is the publish time). Wrenches are (N, 6)
``[fx fy fz tx ty tz]`` in N and Nm; quaternions (N, 4) ``[x y z w]``.

CDR (XCDR1, little endian, as ROS 2 writes it): a 4-byte encapsulation header ``00 01 00 00``, then
every primitive aligned to its own size counted from the end of that header; a string is a uint32
length that counts the terminating NUL, the bytes and the NUL; a sequence is a uint32 count followed
by its elements (no alignment padding when it is empty).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pipeline.core.errors import DataError

MAGIC = b"\x89MCAP0\r\n"  # first and last bytes of every MCAP file

# --- message types and their schemas ------------------------------------------------------------

JOINT_STATE = "sensor_msgs/msg/JointState"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
IMU = "sensor_msgs/msg/Imu"
TEMPERATURE = "sensor_msgs/msg/Temperature"
STRING = "std_msgs/msg/String"
MESSAGE_TYPES = (JOINT_STATE, WRENCH_STAMPED, IMU, TEMPERATURE, STRING)

_SEPARATOR = "=" * 80
# Standard ROS 2 (Humble..Jazzy) definitions, comments dropped. Dependencies are concatenated after the
# top-level definition as rosbag2 does ("=" * 80, "MSG: pkg/Name", definition), which is the form
# mcap_ros2 parses; builtin_interfaces/Time is included so that `sec` decodes as int32 everywhere.
_DEFINITIONS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/Wrench": "Vector3 force\nVector3 torque",
    WRENCH_STAMPED: "std_msgs/Header header\nWrench wrench",
    IMU: (
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance"
    ),
    TEMPERATURE: "std_msgs/Header header\nfloat64 temperature\nfloat64 variance",
    JOINT_STATE: (
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort"
    ),
    STRING: "string data",
}
_DEPENDENCIES = {
    WRENCH_STAMPED: (
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "geometry_msgs/Wrench",
        "geometry_msgs/Vector3",
    ),
    IMU: ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Quaternion", "geometry_msgs/Vector3"),
    TEMPERATURE: ("std_msgs/Header", "builtin_interfaces/Time"),
    JOINT_STATE: ("std_msgs/Header", "builtin_interfaces/Time"),
    STRING: (),
}


def _schema_text(msgtype: str) -> str:
    parts = [_DEFINITIONS[msgtype]]
    for dep in _DEPENDENCIES[msgtype]:
        parts.append(f"{_SEPARATOR}\nMSG: {dep}\n{_DEFINITIONS[dep]}")
    return "\n".join(parts) + "\n"


SCHEMAS: dict[str, str] = {t: _schema_text(t) for t in MESSAGE_TYPES}
"""Message type -> concatenated ros2msg schema text, as written into every log."""

_PRIMITIVES = {
    "bool",
    "byte",
    "char",
    "float32",
    "float64",
    "int8",
    "uint8",
    "int16",
    "uint16",
    "int32",
    "uint32",
    "int64",
    "uint64",
    "string",
    "wstring",
}
_BUILTIN_TIME = [("int32", "sec"), ("uint32", "nanosec")]


def _type_key(name: str, package: str) -> str:
    """'pkg/msg/Name', 'pkg/Name' or 'Name' (in `package`) -> 'pkg/Name'."""
    parts = name.split("/")
    return f"{package}/{parts[0]}" if len(parts) == 1 else f"{parts[0]}/{parts[-1]}"


def schema_layout(name: str, text: str) -> tuple[tuple[str, str], ...] | None:
    """The flattened field list of a ros2msg schema: ((dotted field path, primitive type[suffix]), ...).

    Comments, constants and default values are ignored, so two schemas with the same layout compare
    equal whatever their formatting. Returns None if a nested type is not defined in `text`.
    """
    blocks: dict[str, list[tuple[str, str]]] = {}
    current = _type_key(name, "")
    for part in re.split(r"^={3,}\s*$", text, flags=re.MULTILINE):
        fields: list[tuple[str, str]] = []
        for raw in part.splitlines():
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            header = re.match(r"^MSG:\s*(\S+)$", line)
            if header:
                current = _type_key(header.group(1), "")
                continue
            tokens = line.split()
            if len(tokens) < 2 or "=" in tokens[1] or (len(tokens) > 2 and tokens[2].startswith("=")):
                continue  # malformed line or constant
            fields.append((tokens[0], tokens[1]))
        if fields or current not in blocks:
            blocks[current] = fields
    blocks.setdefault("builtin_interfaces/Time", _BUILTIN_TIME)
    blocks.setdefault("builtin_interfaces/Duration", _BUILTIN_TIME)

    def flatten(key: str, prefix: str, depth: int) -> list[tuple[str, str]] | None:
        if key not in blocks or depth > 16:
            return None
        out: list[tuple[str, str]] = []
        package = key.split("/")[0]
        for ftype, fname in blocks[key]:
            match = re.match(r"^([^\[]+)(\[.*\])?$", ftype)
            if match is None:
                return None
            base, suffix = match.group(1), match.group(2) or ""
            if base in _PRIMITIVES or base.startswith(("string<", "wstring<")):
                out.append((prefix + fname, base + suffix))
            elif suffix:
                out.append((prefix + fname, _type_key(base, package) + suffix))  # array of messages
            else:
                nested = flatten(_type_key(base, package), f"{prefix}{fname}.", depth + 1)
                if nested is None:
                    return None
                out.extend(nested)
        return out

    result = flatten(_type_key(name, ""), "", 0)
    return tuple(result) if result is not None else None


STANDARD_LAYOUTS = {t: schema_layout(t, SCHEMAS[t]) for t in MESSAGE_TYPES}

# --- CDR layouts of fixed-shape messages ---------------------------------------------------------

# One MCAP Message record header: opcode, record length, channel id, sequence, log time, publish time.
RECORD_HEADER = np.dtype(
    [
        ("op", "u1"),
        ("len", "<u8"),
        ("channel", "<u2"),
        ("sequence", "<u4"),
        ("log_time", "<u8"),
        ("publish_time", "<u8"),
    ]
)
RECORD_HEADER_SIZE = RECORD_HEADER.itemsize  # 31 bytes
# The first 16 CDR bytes of every message with a std_msgs/Header.
CDR_HEAD = np.dtype(
    [
        ("rep0", "u1"),
        ("rep1", "u1"),
        ("options", "<u2"),
        ("sec", "<i4"),
        ("nanosec", "<u4"),
        ("frame_len", "<u4"),
    ]
)


class CdrTemplate:
    """Builds the CDR bytes of one message with placeholders ('slots') for the per-message values.

    The slots' offsets give a numpy structured dtype that reads or writes those values for a whole
    batch of messages that share everything else (frame_id, joint names, array lengths).
    """

    def __init__(self) -> None:
        self.buf = bytearray(b"\x00\x01\x00\x00")  # CDR_LE, options 0
        self.slots: list[tuple[str, str, tuple[int, ...], int]] = []

    def _align(self, size: int) -> None:
        self.buf += bytes(-(len(self.buf) - 4) % size)

    def uint32(self, value: int) -> None:
        self._align(4)
        self.buf += struct.pack("<I", value)

    def string(self, value: bytes, length: int | None = None) -> None:
        """A CDR string; `length` (counting the NUL) overrides len(value) + 1 for layouts only."""
        n = len(value) + 1 if length is None else length
        self.uint32(n)
        self.buf += value.ljust(n, b"\x00")[:n]

    def slot(self, name: str, base: str, shape: tuple[int, ...] = ()) -> None:
        count = int(np.prod(shape)) if shape else 1
        if count == 0:
            return
        size = np.dtype(base).itemsize
        self._align(size)
        self.slots.append((name, base, shape, len(self.buf)))
        self.buf += bytes(size * count)

    def header(self, frame_id: bytes, frame_len: int | None = None) -> None:
        self.slot("sec", "<i4")
        self.slot("nanosec", "<u4")
        self.string(frame_id, frame_len)

    def dtype(self, prefix: int = 0, extra: Sequence[tuple[str, Any, int]] = ()) -> np.dtype:
        """Structured dtype of the slots (offsets shifted by `prefix`), itemsize prefix + message size."""
        names, formats, offsets = [], [], []
        for name, fmt, off in extra:
            names.append(name)
            formats.append(fmt)
            offsets.append(off)
        for name, base, shape, off in self.slots:
            names.append(name)
            formats.append((base, shape) if shape else base)
            offsets.append(prefix + off)
        return np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": prefix + len(self.buf)}
        )


def _body(template: CdrTemplate, msgtype: str) -> None:
    """The slots after the header of the fixed-layout types."""
    if msgtype == WRENCH_STAMPED:
        template.slot("wrench", "<f8", (6,))
    elif msgtype == IMU:
        for name, n in (
            ("orientation", 4),
            ("orientation_covariance", 9),
            ("angular_velocity", 3),
            ("angular_velocity_covariance", 9),
            ("linear_acceleration", 3),
            ("linear_acceleration_covariance", 9),
        ):
            template.slot(name, "<f8", (n,))
    elif msgtype == TEMPERATURE:
        template.slot("temperature", "<f8")
        template.slot("variance", "<f8")
    else:
        raise ValueError(f"not a fixed-layout type: {msgtype}")


def fixed_template(msgtype: str, frame_id: bytes, frame_len: int | None = None) -> CdrTemplate:
    template = CdrTemplate()
    template.header(frame_id, frame_len)
    _body(template, msgtype)
    return template


def joint_state_template(
    frame_id: bytes, names: Sequence[bytes], n_pos: int, n_vel: int, n_eff: int, frame_len: int | None = None
) -> CdrTemplate:
    template = CdrTemplate()
    template.header(frame_id, frame_len)
    template.uint32(len(names))
    for name in names:
        template.string(name)
    for slot, n in (("position", n_pos), ("velocity", n_vel), ("effort", n_eff)):
        template.uint32(n)
        template.slot(slot, "<f8", (n,))
    return template


def split_stamps(stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """int64 ns -> (sec int32, nanosec uint32) as in builtin_interfaces/Time (nanosec in [0, 1e9))."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    sec = np.floor_divide(stamps, 1_000_000_000)
    return sec.astype(np.int32), (stamps - sec * 1_000_000_000).astype(np.uint32)


def join_stamps(sec: np.ndarray, nanosec: np.ndarray) -> np.ndarray:
    """(sec, nanosec) -> int64 ns."""
    return np.asarray(sec, dtype=np.int64) * 1_000_000_000 + np.asarray(nanosec, dtype=np.int64)


def parse_joint_state_layout(data: bytes) -> tuple[int, list[str], tuple[int, int, int]] | None:
    """(frame_id length field, joint names, (n position, n velocity, n effort)) of one CDR JointState.

    None if the bytes do not hold a complete little-endian JointState.
    """
    try:
        if data[1] != 1:
            return None
        pos = 4

        def align(p: int, n: int) -> int:
            return p + (-(p - 4) % n)

        def u32(p: int) -> tuple[int, int]:
            p = align(p, 4)
            return struct.unpack_from("<I", data, p)[0], p + 4

        pos += 8  # stamp
        frame_len, pos = u32(pos)
        pos += frame_len
        count, pos = u32(pos)
        if count > len(data):
            return None
        names = []
        for _ in range(count):
            n, pos = u32(pos)
            if pos + n > len(data):
                return None
            names.append(data[pos : pos + max(n - 1, 0)].decode("utf-8"))
            pos += n
        counts = []
        for _ in range(3):
            n, pos = u32(pos)
            if n:
                pos = align(pos, 8) + 8 * n
            counts.append(n)
        if pos > len(data):
            return None
        return frame_len, names, (counts[0], counts[1], counts[2])
    except (struct.error, IndexError, UnicodeDecodeError):
        return None


def from_ros(msgtype: str, msg: Any) -> tuple[int | None, dict[str, Any], tuple[str, ...] | None]:
    """(stamp ns or None, field values, joint names) of a message decoded by mcap_ros2."""

    def vec(v: Any, names: str = "xyz") -> list[float]:
        return [float(getattr(v, c)) for c in names]

    if msgtype == STRING:
        return None, {"data": str(msg.data)}, None
    stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
    values: dict[str, Any] = {"frame_id": str(msg.header.frame_id)}
    names = None
    if msgtype == WRENCH_STAMPED:
        values["wrench"] = vec(msg.wrench.force) + vec(msg.wrench.torque)
    elif msgtype == IMU:
        values["orientation"] = vec(msg.orientation, "xyzw")
        values["orientation_covariance"] = [float(x) for x in msg.orientation_covariance]
        values["angular_velocity"] = vec(msg.angular_velocity)
        values["angular_velocity_covariance"] = [float(x) for x in msg.angular_velocity_covariance]
        values["linear_acceleration"] = vec(msg.linear_acceleration)
        values["linear_acceleration_covariance"] = [float(x) for x in msg.linear_acceleration_covariance]
    elif msgtype == TEMPERATURE:
        values["temperature"] = float(msg.temperature)
        values["variance"] = float(msg.variance)
    elif msgtype == JOINT_STATE:
        names = tuple(str(n) for n in msg.name)
        for key in ("position", "velocity", "effort"):
            values[key] = [float(x) for x in getattr(msg, key)]
    else:
        raise DataError(f"unsupported message type {msgtype}")
    return stamp, values, names


def fixed_records(
    template: CdrTemplate,
    channel: int,
    sequence: np.ndarray,
    log_times: np.ndarray,
    publish_times: np.ndarray,
    stamps: np.ndarray,
    values: Mapping[str, np.ndarray],
) -> np.ndarray:
    """(n, size) uint8: n complete MCAP Message records (record header + CDR) of a fixed-layout type.

    `template` (`fixed_template`) fixes the type and frame_id; times are int64 ns (header.stamp from
    `stamps`); `values` fills the template's slots by name (e.g. ``wrench`` (n, 6)).
    """
    n = len(stamps)
    extra = [
        (name, RECORD_HEADER.fields[name][0], RECORD_HEADER.fields[name][1]) for name in RECORD_HEADER.names
    ]
    dtype = template.dtype(prefix=RECORD_HEADER_SIZE, extra=extra)
    size = dtype.itemsize
    rows = np.empty(n, dtype=dtype)
    raw = rows.view(np.uint8).reshape(n, size)
    raw[:, RECORD_HEADER_SIZE:] = np.frombuffer(bytes(template.buf), dtype=np.uint8)
    rows["op"] = 0x05
    rows["len"] = size - 9
    rows["channel"] = channel
    rows["sequence"] = sequence
    rows["log_time"] = np.asarray(log_times, dtype=np.int64).view(np.uint64)
    rows["publish_time"] = np.asarray(publish_times, dtype=np.int64).view(np.uint64)
    sec, nanosec = split_stamps(np.asarray(stamps, dtype=np.int64))
    rows["sec"] = sec
    rows["nanosec"] = nanosec
    for name, value in values.items():
        if name in dtype.names:
            rows[name] = value
    return raw
