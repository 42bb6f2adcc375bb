"""Decoding the CDR messages of one MCAP channel in batches: numpy where the layout is known.

`ChannelDecoder` decodes every message of a channel found in one chunk at once by gathering rows of a
known layout (`pipeline.logs.cdr` templates). Messages whose layout the fast path does not know
(big-endian CDR, non-standard schema, variable frame ids, ...) go through the standard `mcap_ros2` decoder.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.core.errors import DataError
from pipeline.logs.cdr import (
    CDR_HEAD,
    JOINT_STATE,
    SCHEMAS,
    STANDARD_LAYOUTS,
    STRING,
    fixed_template,
    from_ros,
    join_stamps,
    joint_state_template,
    parse_joint_state_layout,
    schema_layout,
)
from pipeline.logs.idl import idl_layout

# --- decoded batches --------------------------------------------------------------------------------------


@dataclass
class Batch:
    """Decoded messages of one topic from one chunk, all with the same layout.

    `fields` per type (float64 unless said otherwise; K messages):
    JointState: position (K, J), velocity (K, Jv), effort (K, Je) with `names` (J joint names);
    WrenchStamped: wrench (K, 6); Imu: orientation (K, 4) xyzw, orientation_covariance (K, 9),
    angular_velocity (K, 3), angular_velocity_covariance (K, 9), linear_acceleration (K, 3),
    linear_acceleration_covariance (K, 9); Temperature: temperature (K,), variance (K,);
    every type with a header: frame_id (K,) object; String: data (K,) object.
    """

    topic: str
    msgtype: str
    log_time_ns: np.ndarray  # (K,) int64, the recorder's receive time
    publish_time_ns: np.ndarray  # (K,) int64
    stamp_ns: np.ndarray  # (K,) int64: header.stamp; the publish time for types without header
    order: np.ndarray  # (K,) int64: position in the file (sorts messages in file order)
    fields: dict[str, np.ndarray]
    names: tuple[str, ...] | None = None  # JointState only
    fast: bool = True  # decoded by the vectorised path (False: by the standard mcap_ros2 decoder)

    def __len__(self) -> int:
        return len(self.log_time_ns)


def gather_rows(buf: np.ndarray, offsets: np.ndarray, width: int) -> np.ndarray:
    """(K, width) uint8: bytes [offset, offset + width) of `buf` (1-D uint8) for each of `offsets` (K,).

    Rows of a sliding-window view are copied whole (memcpy per row), ~5-15x faster than an element-wise
    fancy index with a (K, width) index array. The view is made directly on the buffer (~0.1 ms less a call
    than `numpy.lib.stride_tricks.sliding_window_view`, called ~50 times per chunk); an offset
    past ``len(buf) - width`` raises IndexError.
    """
    if width == 0:
        return np.empty((len(offsets), 0), dtype=np.uint8)
    buf = np.ascontiguousarray(buf, dtype=np.uint8)
    if width > len(buf):
        raise ValueError(f"rows of {width} bytes asked of a buffer of {len(buf)} bytes")
    windows = np.ndarray((len(buf) - width + 1, width), dtype=np.uint8, buffer=buf, strides=(1, 1))
    return windows[offsets]


def as_struct(rows: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """(K, itemsize) uint8 rows -> (K,) structured view."""
    return np.ascontiguousarray(rows).view(dtype).reshape(len(rows))


def _has_standard_layout(msgtype: str, schema: Any) -> bool:
    """Whether a ros2msg or ros2idl schema has the field layout of the standard type `msgtype`."""
    if schema is None or msgtype not in STANDARD_LAYOUTS:
        return False
    text = schema.data.decode("utf-8", "replace")
    if schema.encoding == "ros2msg":
        return schema_layout(schema.name, text) == STANDARD_LAYOUTS[msgtype]
    if schema.encoding == "ros2idl":
        return idl_layout(schema.name, text) == STANDARD_LAYOUTS[msgtype]
    return False


class ChannelDecoder:
    """Decodes the messages of one channel: vectorised where the layout is known, else mcap_ros2."""

    MAX_TEMPLATES = 16  # JointState layouts tried per chunk before the rest goes to the fallback
    MAX_FRAME_LEN = 4096

    def __init__(self, topic: str, msgtype: str, schema: Any, message_encoding: str, fast: bool):
        self.topic = topic
        self.msgtype = msgtype
        self.schema = schema
        self.encoding = getattr(schema, "encoding", "")
        standard = message_encoding == "cdr" and _has_standard_layout(msgtype, schema)
        if standard and self.encoding == "ros2idl":  # same CDR bytes: decode it as the .msg definition
            from mcap.records import Schema

            self.schema = Schema(
                id=schema.id, name=msgtype, encoding="ros2msg", data=SCHEMAS[msgtype].encode()
            )
        self.fast = fast and standard
        self.message_encoding = message_encoding
        self._standard: Callable[[bytes], Any] | None = None
        self._layouts: dict[int, np.dtype] = {}

    # -- entry --

    def decode(
        self,
        buf: np.ndarray,
        offsets: np.ndarray,
        sizes: np.ndarray,
        log_time: np.ndarray,
        publish_time: np.ndarray,
        order: np.ndarray,
    ) -> list[Batch]:
        """Decode K messages whose CDR data are buf[offsets[k] : offsets[k] + sizes[k]]."""
        batches: list[Batch] = []
        rest = np.arange(len(offsets))
        if self.fast:
            if self.msgtype == STRING:
                found, rest = self._strings(buf, offsets, sizes, rest)
            elif self.msgtype == JOINT_STATE:
                found, rest = self._joint_states(buf, offsets, sizes, rest)
            else:
                found, rest = self._fixed(buf, offsets, sizes, rest)
            for idx, stamp, fields, names in found:
                batches.append(
                    Batch(
                        self.topic,
                        self.msgtype,
                        log_time[idx],
                        publish_time[idx],
                        publish_time[idx] if stamp is None else stamp,
                        order[idx],
                        fields,
                        names,
                    )
                )
        if len(rest):
            batches.extend(self._fallback(buf, offsets, sizes, log_time, publish_time, order, rest))
        return batches

    # -- vectorised paths --

    def _head(
        self, buf: np.ndarray, offsets: np.ndarray, sizes: np.ndarray, idx: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(rows with a little-endian CDR header of >= 16 bytes, their CDR_HEAD values)."""
        idx = idx[sizes[idx] >= 16]
        head = as_struct(gather_rows(buf, offsets[idx], 16), CDR_HEAD)
        ok = (head["rep0"] == 0) & (head["rep1"] == 1) & (head["frame_len"] <= self.MAX_FRAME_LEN)
        return idx[ok], head[ok]

    def _frame_ids(self, rows: np.ndarray, frame_len: int) -> np.ndarray | None:
        """frame_id per row (object array) from the CDR rows, or None if not valid UTF-8."""
        n = len(rows)
        raw = rows[:, 16 : 16 + max(frame_len - 1, 0)]
        try:
            if raw.shape[1] == 0:
                return np.full(n, "", dtype=object)
            if (raw == raw[0]).all():
                return np.full(n, bytes(raw[0]).decode("utf-8"), dtype=object)
            return np.array([bytes(r).decode("utf-8") for r in raw], dtype=object)
        except UnicodeDecodeError:
            return None

    def _fixed(self, buf: np.ndarray, offsets: np.ndarray, sizes: np.ndarray, rest: np.ndarray):
        found = []
        good, head = self._head(buf, offsets, sizes, rest)
        handled = np.zeros(len(offsets), dtype=bool)
        for frame_len in np.unique(head["frame_len"]).tolist():
            dtype = self._layouts.get(frame_len)
            if dtype is None:
                dtype = fixed_template(self.msgtype, b"", frame_len).dtype()
                self._layouts[frame_len] = dtype
            idx = good[(head["frame_len"] == frame_len) & (sizes[good] >= dtype.itemsize)]
            if not len(idx):
                continue
            rows = gather_rows(buf, offsets[idx], dtype.itemsize)
            frame_ids = self._frame_ids(rows, frame_len)
            if frame_ids is None:
                continue
            values = as_struct(rows, dtype)
            fields = {
                name: values[name].astype(np.float64)
                for name in dtype.names
                if name not in ("sec", "nanosec")
            }
            fields["frame_id"] = frame_ids
            found.append((idx, join_stamps(values["sec"], values["nanosec"]), fields, None))
            handled[idx] = True
        return found, rest[~handled[rest]]

    def _joint_states(self, buf: np.ndarray, offsets: np.ndarray, sizes: np.ndarray, rest: np.ndarray):
        found = []
        good, _ = self._head(buf, offsets, sizes, rest)
        handled = np.zeros(len(offsets), dtype=bool)
        todo = good
        for _ in range(self.MAX_TEMPLATES):
            if not len(todo):
                break
            first = int(todo[0])
            data = buf[offsets[first] : offsets[first] + sizes[first]].tobytes()
            parsed = parse_joint_state_layout(data)
            if parsed is None:
                todo = todo[1:]
                continue
            frame_len, names, counts = parsed
            template = joint_state_template(b"", [n.encode() for n in names], *counts, frame_len=frame_len)
            dtype = template.dtype()
            width = dtype.itemsize
            static = np.ones(width, dtype=bool)  # bytes shared by every message of this layout
            for name in dtype.names:
                sub, off = dtype.fields[name][:2]
                static[off : off + sub.itemsize] = False
            static[:4] = False  # encapsulation options may differ
            candidates = todo[sizes[todo] >= width]
            rows = gather_rows(buf, offsets[candidates], width)
            reference = np.frombuffer(data[:width], dtype=np.uint8)
            match = (rows[:, static] == reference[static]).all(axis=1)
            idx = candidates[match]
            frame_ids = self._frame_ids(rows[match], frame_len)
            if frame_ids is None:
                todo = todo[todo != first]
                continue
            values = as_struct(rows[match], dtype)
            fields = {
                key: (
                    values[key].reshape(len(idx), -1).astype(np.float64)
                    if key in dtype.names
                    else np.empty((len(idx), 0))
                )
                for key, _n in zip(("position", "velocity", "effort"), counts, strict=True)
            }
            fields["frame_id"] = frame_ids
            found.append((idx, join_stamps(values["sec"], values["nanosec"]), fields, tuple(names)))
            handled[idx] = True
            todo = todo[~handled[todo]]
        return found, rest[~handled[rest]]

    def _strings(self, buf: np.ndarray, offsets: np.ndarray, sizes: np.ndarray, rest: np.ndarray):
        idx = rest[sizes[rest] >= 8]
        head = gather_rows(buf, offsets[idx], 8)
        length = head[:, 4:8].copy().view("<u4").reshape(-1).astype(np.int64)
        ok = (head[:, 0] == 0) & (head[:, 1] == 1) & (length <= sizes[idx] - 8)
        idx, length = idx[ok], length[ok]
        values = np.empty(len(idx), dtype=object)
        raw = buf.data
        try:
            for k, (off, n) in enumerate(zip(offsets[idx].tolist(), length.tolist(), strict=True)):
                values[k] = bytes(raw[off + 8 : off + 7 + n]).decode("utf-8") if n > 1 else ""
        except UnicodeDecodeError:
            return [], rest
        handled = np.zeros(len(offsets), dtype=bool)
        handled[idx] = True
        return [(idx, None, {"data": values}, None)], rest[~handled[rest]]

    # -- standard decoder --

    def _fallback(
        self,
        buf: np.ndarray,
        offsets: np.ndarray,
        sizes: np.ndarray,
        log_time: np.ndarray,
        publish_time: np.ndarray,
        order: np.ndarray,
        rest: np.ndarray,
    ) -> list[Batch]:
        if self._standard is None:
            from mcap_ros2.decoder import DecoderFactory

            decoder = DecoderFactory().decoder_for(self.message_encoding, self.schema)
            if decoder is None:
                raise DataError(
                    f"topic {self.topic}: cannot decode {self.message_encoding!r} messages of schema "
                    f"{getattr(self.schema, 'name', None)!r} in {self.encoding!r} encoding"
                    + (
                        " (its layout is not the standard one of this type)"
                        if self.encoding == "ros2idl"
                        else ""
                    )
                )
            self._standard = decoder
        groups: dict[Any, list[tuple[int, int, dict[str, Any]]]] = {}
        raw = buf.data
        for k in rest.tolist():
            off, n = int(offsets[k]), int(sizes[k])
            try:
                msg = self._standard(bytes(raw[off : off + n]))
                stamp, values, names = from_ros(self.msgtype, msg)
            except DataError:
                raise
            except Exception as exc:  # noqa: BLE001 (any decoding failure is a data problem)
                raise DataError(
                    f"topic {self.topic}: message {k} cannot be decoded as {self.msgtype}: "
                    f"{type(exc).__name__}: {exc}"
                ) from None
            shape = tuple((key, np.shape(v)) for key, v in values.items() if key != "frame_id")
            groups.setdefault((names, shape), []).append((k, stamp, values))
        batches = []
        for (names, _), items in groups.items():
            idx = np.array([k for k, _, _ in items], dtype=np.int64)
            stamps = np.array([publish_time[k] if s is None else s for k, s, _ in items], dtype=np.int64)
            fields: dict[str, np.ndarray] = {}
            for key in items[0][2]:
                if key in ("frame_id", "data"):
                    fields[key] = np.array([v[key] for _, _, v in items] + [None], dtype=object)[:-1]
                else:
                    fields[key] = np.array([v[key] for _, _, v in items], dtype=np.float64).reshape(
                        len(items), *np.shape(items[0][2][key])
                    )
            batches.append(
                Batch(
                    self.topic,
                    self.msgtype,
                    log_time[idx],
                    publish_time[idx],
                    stamps,
                    order[idx],
                    fields,
                    names,
                    fast=False,
                )
            )
        return batches
