"""A copy of an MCAP log with messages added, every original record kept byte for byte.

`LogAugmenter` streams the input file: the bytes of its data section (header, schemas, channels,
metadata, attachments, chunks and their message indexes, messages outside chunks) are copied unchanged,
and after any region of it (`LogReader.iter_regions`: an original chunk, or a block of a file without chunk
indexes) a new chunk of added messages can be inserted. The new channels (and their schema if the input
has no standard one of that type) are written after the first region. At the end it writes a new DataEnd
(CRC 0: not computed) and, for an indexed input, a summary: the original schemas, channels,
chunk/metadata/attachment indexes with their offsets moved by the inserted bytes, plus the new ones;
statistics with the added counts. An input without chunk indexes gets no summary, as it had none usable
(an index of the added chunks alone would hide the original messages from readers that trust it): readers
scan it as they scanned the input. So every original message keeps its channel, sequence, log and publish
times and bytes, and readers see the added messages with the others. Memory is one chunk.

Written to ``<out>.part`` and renamed on `close`; `abort` (or an exception in the ``with`` block) deletes it.
"""

from __future__ import annotations

import bisect
import os
import struct
import zlib
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from pipeline.core.errors import DataError
from pipeline.logs.cdr import MAGIC, SCHEMAS, STANDARD_LAYOUTS, schema_layout
from pipeline.logs.mcap_chunks import message_index_records
from pipeline.logs.mcap_read import LogReader

_FOOTER = 1 + 8 + 20  # opcode, length, summary_start, summary_offset_start, crc
_DATA_END = 1 + 8 + 4  # opcode, length, data_section_crc
_COPY_BLOCK = 8 * 2**20


class LogAugmenter:
    """Copies `reader`'s file to `out_path` with added channels and chunks (module docstring)."""

    def __init__(self, reader: LogReader, out_path: str | Path, *, compression_level: int = 1) -> None:
        import zstandard

        self.reader = reader
        self.path = Path(out_path)
        self.part_path = self.path.with_name(self.path.name + ".part")
        self._compressor = zstandard.ZstdCompressor(level=compression_level)
        summary = reader.summary
        # with chunk indexes and statistics the copy gets a summary; without, none (readers scan it)
        self._indexed = reader.indexed and summary.statistics is not None
        self._src = open(reader.path, "rb")  # noqa: SIM115 (closed in close()/abort())
        try:
            self._data_end = self._find_data_end()
        except BaseException:
            self._src.close()
            raise
        self._schemas, self._channels = reader.schemas, reader.channels
        self._new_records: list[Any] = []  # schemas and channels to write before the first chunk
        self._new_chunk_indexes: list[Any] = []
        self._counts: dict[int, int] = {}
        self._sequence: dict[int, int] = {}
        self._pos = 0  # next byte of the input to copy
        self._segments: list[tuple[int, int]] = [(0, 0)]  # (input offset, shift) of each copied segment
        self._shift = 0
        self._started = False
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._out = open(self.part_path, "wb")  # noqa: SIM115

    # -- context manager --

    def __enter__(self) -> LogAugmenter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # -- public --

    def add_channel(self, topic: str, msgtype: str) -> int:
        """Register a new channel (cdr, ros2msg schema of `msgtype`) before the first chunk; its id."""
        from mcap.records import Channel, Schema

        if self._started:
            raise RuntimeError("channels must be added before copying the first chunk")
        if any(c.topic == topic for c in self._channels.values()):
            raise DataError(f"{self.reader.path}: already has topic {topic}")
        # An indexed copy reuses a standard schema of the input (readers take schemas from the summary); a
        # scanned copy gets its own, written with the channel: the input's may first appear after it.
        schema_id = next(
            (
                sid
                for sid, s in sorted(self._schemas.items())
                if self._indexed
                and s.name == msgtype
                and s.encoding == "ros2msg"
                and schema_layout(s.name, s.data.decode("utf-8", "replace")) == STANDARD_LAYOUTS.get(msgtype)
            ),
            None,
        )
        if schema_id is None:
            schema_id = max(self._schemas, default=0) + 1
            schema = Schema(id=schema_id, name=msgtype, encoding="ros2msg", data=SCHEMAS[msgtype].encode())
            self._schemas[schema_id] = schema
            self._new_records.append(schema)
        channel = Channel(
            id=max(self._channels, default=0) + 1,
            topic=topic,
            message_encoding="cdr",
            schema_id=schema_id,
            metadata={},
        )
        self._channels[channel.id] = channel
        self._new_records.append(channel)
        return channel.id

    def next_sequence(self, channel: int, n: int) -> np.ndarray:
        """(n,) uint32 sequence numbers of the next n messages of an added channel."""
        first = self._sequence.get(channel, 0)
        self._sequence[channel] = first + n
        return (np.arange(first, first + n, dtype=np.int64) & 0xFFFFFFFF).astype(np.uint32)

    def copy_through(self, end: int | None) -> None:
        """Copy the input up to byte `end` (a region's end, `LogReader.iter_regions`; None: the end of the
        data section). The added channels and schemas are written after the first region."""
        self._copy(self._data_end if end is None else end)
        if not self._started:
            self._insert(b"".join(_record_bytes(r) for r in self._new_records))
            self._started = True

    def add_chunk(self, parts: Sequence[tuple[int, np.ndarray, np.ndarray]]) -> None:
        """Insert one chunk of added messages: parts of (channel, records (n, size) uint8, log times (n,))."""
        parts = [p for p in parts if len(p[2])]
        if not parts:
            return
        if not self._started:
            raise RuntimeError("add_chunk before the first copy_through")
        self._insert(self._chunk(parts))

    def close(self) -> None:
        """Copy the rest of the data section, write DataEnd, summary and footer; rename to the output path."""
        try:
            self.copy_through(None)
            self._finish()
            self._out.flush()
            os.fsync(self._out.fileno())
            self._out.close()
            self._src.close()
            os.replace(self.part_path, self.path)
        except BaseException:
            self.abort()
            raise

    def abort(self) -> None:
        """Discard the output: close and delete ``<out>.part``."""
        self._src.close()
        try:
            self._out.close()
        finally:
            self.part_path.unlink(missing_ok=True)

    # -- internals --

    def _find_data_end(self) -> int:
        """Offset of the input's DataEnd record (just before the summary section)."""
        f = self._src
        f.seek(-(len(MAGIC) + _FOOTER), os.SEEK_END)
        op, length, summary_start, _, _ = struct.unpack("<BQQQI", f.read(_FOOTER))
        end = summary_start if summary_start else f.seek(-(len(MAGIC) + _FOOTER), os.SEEK_END)
        f.seek(end - _DATA_END)
        op2, length2 = struct.unpack("<BQ", f.read(9))
        if op != 0x02 or length != 20 or op2 != 0x0F or length2 != 4:
            raise DataError(
                f"{self.reader.path}: corrupted MCAP end (no footer or DataEnd record where expected)"
            )
        return end - _DATA_END

    def _copy(self, until: int) -> None:
        """Copy input bytes [self._pos, until) to the output."""
        if until < self._pos:
            raise DataError(f"{self.reader.path}: chunks overlap or are out of order at byte {until}")
        self._src.seek(self._pos)
        remaining = until - self._pos
        while remaining:
            block = self._src.read(min(remaining, _COPY_BLOCK))
            if not block:
                raise DataError(f"{self.reader.path}: truncated MCAP file (ends before byte {until})")
            self._out.write(block)
            remaining -= len(block)
        self._pos = until

    def _insert(self, data: bytes) -> None:
        if data:
            self._out.write(data)
            self._shift += len(data)
            self._segments.append((self._pos, self._shift))

    def _moved(self, offset: int) -> int:
        """New offset of the input byte at `offset`."""
        k = bisect.bisect_right(self._segments, (offset, float("inf"))) - 1
        return offset + self._segments[k][1]

    def _chunk(self, parts: Sequence[tuple[int, np.ndarray, np.ndarray]]) -> bytes:
        """Chunk record + message indexes of the added messages, sorted by log time."""
        from mcap.records import ChunkIndex

        channel = np.concatenate([np.full(len(t), c, dtype=np.int64) for c, _, t in parts])
        log_time = np.concatenate([np.asarray(t, dtype=np.int64) for _, _, t in parts])
        sizes = np.concatenate([np.full(len(t), r.shape[1], dtype=np.int64) for _, r, t in parts])
        order = np.argsort(log_time, kind="stable")
        if len({r.shape[1] for _, r, _ in parts}) == 1:  # one record size (the usual case): one gather
            data = np.concatenate([r for _, r, _ in parts])[order].tobytes()
        else:
            source_start = np.cumsum(np.r_[0, sizes[:-1]])
            source = memoryview(b"".join(np.ascontiguousarray(r).tobytes() for _, r, _ in parts))
            pieces = zip(source_start[order].tolist(), sizes[order].tolist(), strict=True)
            data = b"".join([source[s : s + n] for s, n in pieces])
        offset = np.cumsum(np.r_[0, sizes[order][:-1]])
        channel, log_time = channel[order], log_time[order]
        compressed = self._compressor.compress(data)
        t0, t1 = int(log_time.min()), int(log_time.max())
        body = struct.pack("<QQQI", t0, t1, len(data), zlib.crc32(data))
        body += struct.pack("<I", 4) + b"zstd" + struct.pack("<Q", len(compressed))
        start = self._out.tell()
        out = [struct.pack("<BQ", 0x06, len(body) + len(compressed)), body, compressed]
        chunk_length = 9 + len(body) + len(compressed)
        index_offsets, pos = {}, start + chunk_length
        for cid, record, count in message_index_records(channel, log_time, offset):
            index_offsets[cid] = pos
            pos += len(record)
            out.append(record)
            self._counts[cid] = self._counts.get(cid, 0) + count
        self._new_chunk_indexes.append(
            ChunkIndex(
                message_start_time=t0,
                message_end_time=t1,
                chunk_start_offset=start,
                chunk_length=chunk_length,
                message_index_offsets=index_offsets,
                message_index_length=pos - start - chunk_length,
                compression="zstd",
                compressed_size=len(compressed),
                uncompressed_size=len(data),
            )
        )
        return b"".join(out)

    def _summary_groups(self) -> list[tuple[int, list[Any]]]:
        """(opcode, records) of the summary: original records with moved offsets plus the added ones."""
        from mcap.opcode import Opcode
        from mcap.records import AttachmentIndex, ChunkIndex, MetadataIndex, Statistics

        summary = self.reader.summary
        chunk_indexes = [
            ChunkIndex(
                message_start_time=c.message_start_time,
                message_end_time=c.message_end_time,
                chunk_start_offset=self._moved(c.chunk_start_offset),
                chunk_length=c.chunk_length,
                message_index_offsets={k: self._moved(v) for k, v in c.message_index_offsets.items()},
                message_index_length=c.message_index_length,
                compression=c.compression,
                compressed_size=c.compressed_size,
                uncompressed_size=c.uncompressed_size,
            )
            for c in summary.chunk_indexes
        ]
        chunk_indexes = sorted([*chunk_indexes, *self._new_chunk_indexes], key=lambda c: c.chunk_start_offset)
        old = summary.statistics
        counts = dict(old.channel_message_counts) if old else {}
        for cid, n in self._counts.items():
            counts[cid] = counts.get(cid, 0) + n
        had = bool(old and old.message_count)
        starts = [c.message_start_time for c in self._new_chunk_indexes] + (
            [old.message_start_time] if had else []
        )
        ends = [c.message_end_time for c in self._new_chunk_indexes] + ([old.message_end_time] if had else [])
        statistics = Statistics(
            message_count=(old.message_count if old else 0) + sum(self._counts.values()),
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=old.attachment_count if old else 0,
            metadata_count=old.metadata_count if old else 0,
            chunk_count=len(chunk_indexes),
            message_start_time=min(starts, default=0),
            message_end_time=max(ends, default=0),
            channel_message_counts=dict(sorted(counts.items())),
        )
        attachments = [
            _moved_attachment(a, self._moved(a.offset), AttachmentIndex) for a in summary.attachment_indexes
        ]
        metadata = [MetadataIndex(self._moved(m.offset), m.length, m.name) for m in summary.metadata_indexes]
        return [
            (Opcode.SCHEMA, [self._schemas[k] for k in sorted(self._schemas)]),
            (Opcode.CHANNEL, [self._channels[k] for k in sorted(self._channels)]),
            (Opcode.STATISTICS, [statistics]),
            (Opcode.CHUNK_INDEX, chunk_indexes),
            (Opcode.ATTACHMENT_INDEX, attachments),
            (Opcode.METADATA_INDEX, metadata),
        ]

    def _finish(self) -> None:
        """DataEnd, summary (schemas, channels, statistics, indexes), summary offsets, footer, magic; for
        an input without chunk indexes, DataEnd and a footer without summary, as the input had."""
        from mcap.data_stream import RecordBuilder
        from mcap.opcode import Opcode
        from mcap.records import DataEnd, Footer, SummaryOffset

        self._out.write(_record_bytes(DataEnd(data_section_crc=0)))
        if not self._indexed:
            self._out.write(_record_bytes(Footer(0, 0, 0)))
            self._out.write(MAGIC)
            return
        summary_start = self._out.tell()
        builder = RecordBuilder()
        offsets = []
        for opcode, records in self._summary_groups():
            if not records:
                continue
            first = builder.count
            for record in records:
                record.write(builder)
            offsets.append(SummaryOffset(opcode, summary_start + first, builder.count - first))
        summary_offset_start = summary_start + builder.count
        for offset in offsets:
            offset.write(builder)
        data = builder.end()
        crc = zlib.crc32(data)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
        self._out.write(data)
        self._out.write(_record_bytes(Footer(summary_start, summary_offset_start, crc)))
        self._out.write(MAGIC)


def _record_bytes(record: Any) -> bytes:
    from mcap.data_stream import RecordBuilder

    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def _moved_attachment(a: Any, offset: int, cls: type) -> Any:
    return cls(
        offset=offset,
        length=a.length,
        log_time=a.log_time,
        create_time=a.create_time,
        data_size=a.data_size,
        name=a.name,
        media_type=a.media_type,
    )
