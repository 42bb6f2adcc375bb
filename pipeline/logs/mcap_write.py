"""`LogWriter`: ROS 2 MCAP logs written from whole batches of messages, atomically.

A batch of fixed-layout messages (every message of a batch has the same frame_id, joint names and array
lengths) is encoded as one numpy structured array whose rows are complete MCAP Message records (record
header + CDR payload, `pipeline.logs.cdr`); `pipeline.logs.mcap_chunks` writes the container (zstd
chunks, message indexes, summary, CRCs), so that no per-message Python call is needed.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from pipeline.logs.cdr import (
    IMU,
    JOINT_STATE,
    MAGIC,
    SCHEMAS,
    STRING,
    TEMPERATURE,
    WRENCH_STAMPED,
    CdrTemplate,
    fixed_records,
    fixed_template,
    joint_state_template,
)
from pipeline.logs.mcap_chunks import ChunkSink, Pending, write_record

# --- writer --------------------------------------------------------------------------------------

_PROFILE = "ros2"
_LIBRARY = "ftcal.rosmsg"
_CHUNK_SIZE = 4 * 2**20  # uncompressed bytes per chunk: big enough that per-chunk costs vanish
_MAX_BUFFERED_MESSAGES = 200_000
_MAX_BUFFERED_BYTES = 256 * 2**20


class LogWriter:
    """Writes one ROS 2 MCAP log atomically: to '<path>.part' then renamed on successful close;
    on an exception inside the `with` block the partial file is deleted. Channels/schemas are registered
    on first use of a topic. Schemas are the standard ROS 2 msg definitions (ros2msg encoding, with the
    dependent definitions concatenated the way mcap_ros2 expects) so that mcap_ros2's standard decoder
    decodes every message. Compression zstd, chunked.

    Batch calls are buffered; `flush()` (also called when the buffer exceeds ~200k messages, and on
    close) writes the buffered messages sorted by log time (ties in a deterministic order). Nothing is
    validated (tests write bad logs on purpose: non-monotonic, duplicated or NaN values).
    """

    def __init__(
        self,
        path: str | Path,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        *,
        chunk_size: int = _CHUNK_SIZE,
        compression_level: int = 1,
    ):
        import zstandard

        self.path = Path(path)
        self.part_path = self.path.with_name(self.path.name + ".part")
        compressor = zstandard.ZstdCompressor(level=compression_level)
        self._schemas: dict[str, int] = {}  # message type -> schema id
        self._schema_records: list[Any] = []
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, message type)
        self._channel_records: list[Any] = []
        self._sequence: dict[int, int] = {}
        self._pending: list[Pending] = []
        self._pending_messages = 0
        self._pending_bytes = 0
        self._metadata_indexes: list[Any] = []
        self._closed = False
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.part_path, "wb")  # noqa: SIM115 (closed in close()/abort())
        self._sink = ChunkSink(self._file, compressor, chunk_size)
        try:
            from mcap.records import Header

            self._file.write(MAGIC)
            write_record(self._file, Header(profile=_PROFILE, library=_LIBRARY))
            for name, data in (metadata or {}).items():
                self._add_metadata(name, data)
        except BaseException:
            self.abort()
            raise

    # -- context manager --

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # -- public batch API --

    def joint_states(
        self,
        topic: str,
        stamps_ns: np.ndarray,
        names: Sequence[str],
        position: np.ndarray,
        velocity: np.ndarray,
        effort: np.ndarray | None = None,
        log_times_ns: np.ndarray | None = None,
        frame_id: str = "",
    ) -> None:
        """sensor_msgs/JointState: position (N, J) rad, velocity (N, J) rad/s, effort (N, J) or None."""
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        n = len(stamps)
        arrays = [
            np.asarray(a, dtype=np.float64).reshape(n, -1) if a is not None else np.empty((n, 0))
            for a in (position, velocity, effort)
        ]
        template = joint_state_template(
            frame_id.encode(), [s.encode() for s in names], *(a.shape[1] for a in arrays)
        )
        self._add_fixed(
            topic,
            JOINT_STATE,
            template,
            stamps,
            log_times_ns,
            dict(zip(("position", "velocity", "effort"), arrays, strict=True)),
        )

    def wrenches(
        self,
        topic: str,
        stamps_ns: np.ndarray,
        frame_id: str,
        wrench: np.ndarray,
        log_times_ns: np.ndarray | None = None,
    ) -> None:
        """geometry_msgs/WrenchStamped: wrench (N, 6) [fx fy fz tx ty tz], N and Nm."""
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        self._add_fixed(
            topic,
            WRENCH_STAMPED,
            fixed_template(WRENCH_STAMPED, frame_id.encode()),
            stamps,
            log_times_ns,
            {"wrench": np.asarray(wrench, dtype=np.float64).reshape(len(stamps), 6)},
        )

    def imus(
        self,
        topic: str,
        stamps_ns: np.ndarray,
        frame_id: str,
        linear_acceleration: np.ndarray,
        angular_velocity: np.ndarray,
        log_times_ns: np.ndarray | None = None,
    ) -> None:
        """sensor_msgs/Imu: linear_acceleration (N, 3) m/s^2, angular_velocity (N, 3) rad/s.

        Orientation unknown: orientation = (0, 0, 0, 1) with orientation_covariance[0] = -1 (REP 145);
        the other covariances are 0 ("unknown").
        """
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        n = len(stamps)
        orientation_cov = np.zeros(9)
        orientation_cov[0] = -1.0
        self._add_fixed(
            topic,
            IMU,
            fixed_template(IMU, frame_id.encode()),
            stamps,
            log_times_ns,
            {
                "orientation": np.array([0.0, 0.0, 0.0, 1.0]),
                "orientation_covariance": orientation_cov,
                "linear_acceleration": np.asarray(linear_acceleration, dtype=np.float64).reshape(n, 3),
                "angular_velocity": np.asarray(angular_velocity, dtype=np.float64).reshape(n, 3),
            },
        )

    def temperatures(
        self,
        topic: str,
        stamps_ns: np.ndarray,
        frame_id: str,
        temperature: np.ndarray,
        log_times_ns: np.ndarray | None = None,
    ) -> None:
        """sensor_msgs/Temperature: temperature (N,) deg C; variance 0 (unknown)."""
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        self._add_fixed(
            topic,
            TEMPERATURE,
            fixed_template(TEMPERATURE, frame_id.encode()),
            stamps,
            log_times_ns,
            {"temperature": np.asarray(temperature, dtype=np.float64).reshape(len(stamps))},
        )

    def strings(
        self, topic: str, stamps_ns: np.ndarray, values: Sequence[str], log_times_ns: np.ndarray | None = None
    ) -> None:
        """std_msgs/String (no header: the stamp is written as the MCAP publish time)."""
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        log_times = stamps if log_times_ns is None else np.asarray(log_times_ns, dtype=np.int64).reshape(-1)
        channel = self._channel(topic, STRING)
        if len(values) != len(stamps):
            raise ValueError(f"{topic}: {len(values)} values for {len(stamps)} stamps")
        sequence = self._next_sequence(channel, len(stamps))
        header = struct.Struct("<BQHIQQ")
        parts = []
        for value, seq, log_time, stamp in zip(
            values, sequence.tolist(), log_times.tolist(), stamps.tolist(), strict=True
        ):
            data = value.encode()
            cdr = b"\x00\x01\x00\x00" + struct.pack("<I", len(data) + 1) + data + b"\x00"
            parts.append(
                header.pack(
                    0x05,
                    22 + len(cdr),
                    channel,
                    seq,
                    log_time & 0xFFFFFFFFFFFFFFFF,
                    stamp & 0xFFFFFFFFFFFFFFFF,
                )
                + cdr
            )
        offsets = np.zeros(len(parts) + 1, dtype=np.int64)
        np.cumsum([len(p) for p in parts], out=offsets[1:])
        records = np.frombuffer(b"".join(parts), dtype=np.uint8)
        self._push(Pending(records, 0, log_times, channel, offsets))

    def flush(self) -> None:
        """Write everything buffered so far, sorted by log time, as complete chunks."""
        if not self._pending:
            return
        pending, self._pending = self._pending, []
        self._pending_messages = self._pending_bytes = 0
        self._sink.write(pending)

    def close(self) -> None:
        """Flush, write the summary and footer, and rename '<path>.part' to '<path>'."""
        if self._closed:
            return
        try:
            self.flush()
            self._sink.finish(self._schema_records, self._channel_records, self._metadata_indexes)
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self.part_path, self.path)
            self._closed = True
        except BaseException:
            self.abort()
            raise

    def abort(self) -> None:
        """Discard the log: close and delete '<path>.part'."""
        self._closed = True
        self._pending = []
        try:
            self._file.close()
        finally:
            self.part_path.unlink(missing_ok=True)

    # -- internals --

    def _add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        from mcap.records import Metadata, MetadataIndex

        record = Metadata(name=name, metadata={str(k): str(v) for k, v in data.items()})
        start = self._file.tell()
        write_record(self._file, record)
        self._metadata_indexes.append(
            MetadataIndex(offset=start, length=self._file.tell() - start, name=name)
        )

    def _channel(self, topic: str, msgtype: str) -> int:
        from mcap.records import Channel, Schema

        known = self._channels.get(topic)
        if known is not None:
            if known[1] != msgtype:
                raise ValueError(f"{topic} is registered as {known[1]}, cannot write {msgtype}")
            return known[0]
        if msgtype not in self._schemas:
            schema = Schema(
                id=len(self._schemas) + 1, name=msgtype, encoding="ros2msg", data=SCHEMAS[msgtype].encode()
            )
            self._schemas[msgtype] = schema.id
            self._schema_records.append(schema)
            write_record(self._file, schema)
        channel = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding="cdr",
            schema_id=self._schemas[msgtype],
            metadata={},
        )
        self._channels[topic] = (channel.id, msgtype)
        self._channel_records.append(channel)
        write_record(self._file, channel)
        return channel.id

    def _next_sequence(self, channel: int, n: int) -> np.ndarray:
        first = self._sequence.get(channel, 0)
        self._sequence[channel] = first + n
        return (np.arange(first, first + n, dtype=np.int64) & 0xFFFFFFFF).astype(np.uint32)

    def _add_fixed(
        self,
        topic: str,
        msgtype: str,
        template: CdrTemplate,
        stamps: np.ndarray,
        log_times_ns: np.ndarray | None,
        values: Mapping[str, np.ndarray],
    ) -> None:
        n = len(stamps)
        log_times = stamps if log_times_ns is None else np.asarray(log_times_ns, dtype=np.int64).reshape(-1)
        if len(log_times) != n:
            raise ValueError(f"{topic}: {len(log_times)} log times for {n} stamps")
        channel = self._channel(topic, msgtype)
        sequence = self._next_sequence(channel, n)
        raw = fixed_records(template, channel, sequence, log_times, stamps, stamps, values)
        size = raw.shape[1]
        self._push(Pending(raw.reshape(-1), size, log_times, channel))

    def _push(self, pending: Pending) -> None:
        if len(pending.log_time) == 0:
            return
        self._pending.append(pending)
        self._pending_messages += len(pending.log_time)
        self._pending_bytes += len(pending.records)
        if self._pending_messages > _MAX_BUFFERED_MESSAGES or self._pending_bytes > _MAX_BUFFERED_BYTES:
            self.flush()
