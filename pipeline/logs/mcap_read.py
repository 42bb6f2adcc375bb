"""`LogReader`: the messages of a ROS 2 MCAP log, chunk by chunk, decoded into `Batch`es.

Indexed files (a summary with chunk indexes, as every complete recording has) are read through the chunk
and message indexes: only the chunks holding wanted channels are decompressed. Files whose optional
summary, chunk index or statistics are missing (a streaming recorder that died before its summary,
writers without chunking) are read by scanning the data section (`pipeline.logs.mcap_scan`).
"""

from __future__ import annotations

import io
import struct
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import DataError
from pipeline.logs.cdr import MAGIC, RECORD_HEADER, RECORD_HEADER_SIZE
from pipeline.logs.decode import Batch, ChannelDecoder, as_struct, gather_rows
from pipeline.logs.mcap_scan import (
    ScannedSummary,
    decompress_chunk,
    message_offsets,
    scan_blocks,
    summarise_block,
)


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a log: its message type (schema name), channels and message count."""

    topic: str
    msgtype: str
    message_count: int
    channel_ids: tuple[int, ...] = field(default=())


class LogReader:
    """Reads the messages of a ROS 2 MCAP log chunk by chunk, decoded into `Batch`es.

    Needs a complete file (header magic, data, footer). With chunk indexes and statistics in the summary,
    chunks are read through their message indexes (or walked when a writer did not index them);
    otherwise the data section is scanned (`pipeline.logs.mcap_scan`). CRCs are checked. Every problem
    is a `DataError` naming the file.
    """

    def __init__(self, path: str | Path, *, validate_crcs: bool = True):
        self.path = Path(path)
        self.validate_crcs = validate_crcs
        try:
            self._file = open(self.path, "rb")  # noqa: SIM115 (closed in close())
        except OSError as exc:
            raise DataError(f"{self.path}: cannot open: {exc.strerror or exc}") from None
        try:
            self._open()
        except BaseException:
            self._file.close()
            raise

    def _error(self, problem: str) -> DataError:
        return DataError(f"{self.path}: {problem}")

    def _open(self) -> None:
        from mcap.exceptions import McapError
        from mcap.reader import SeekingReader

        f = self._file
        f.seek(0, io.SEEK_END)
        self.size_bytes = f.tell()
        if self.size_bytes == 0:
            raise self._error("empty file")
        f.seek(0)
        if f.read(len(MAGIC)) != MAGIC:
            raise self._error("not an MCAP file (bad magic bytes at the start)")
        if self.size_bytes < 2 * len(MAGIC) + 29:
            raise self._error("truncated MCAP file (no footer: the recording was interrupted?)")
        f.seek(-len(MAGIC), io.SEEK_END)
        if f.read(len(MAGIC)) != MAGIC:
            raise self._error(
                "truncated MCAP file (no footer: the recording was interrupted or the copy "
                "is incomplete; `mcap recover` can salvage the complete chunks)"
            )
        f.seek(0)
        try:
            reader = SeekingReader(f, validate_crcs=self.validate_crcs)
            summary = reader.get_summary()
            self.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except (McapError, struct.error, ValueError, EOFError) as exc:
            raise self._error(f"corrupted MCAP summary or metadata: {type(exc).__name__}: {exc}") from None
        # The fast path needs chunk indexes; counts need statistics. Without them, scan the data section.
        self.indexed = summary is not None and bool(summary.chunk_indexes)
        if self.indexed and summary.statistics is not None:
            schemas, channels = summary.schemas, summary.channels
            counts = dict(summary.statistics.channel_message_counts)
        else:
            scanned = ScannedSummary()
            for _offset, _consumed, block in scan_blocks(
                f, self.size_bytes, str(self.path), self.validate_crcs
            ):
                summarise_block(block, scanned)
            schemas, channels, counts = scanned.schemas, scanned.channels, scanned.counts
            self.metadata = {**scanned.metadata, **self.metadata}
        self._summary = summary
        self._schemas, self._channels = schemas, channels
        self.topics = _topics(schemas, channels, counts)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> LogReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def message_count(self) -> int:
        return sum(t.message_count for t in self.topics.values())

    def iter_chunks(
        self,
        topics: Iterable[str] | None = None,
        *,
        fast: bool = True,
        progress: Callable[[int], None] | None = None,
    ) -> Iterator[list[Batch]]:
        """Yield, chunk by chunk in file order, the decoded batches of the wanted topics (default all).

        `fast=False` decodes every message with the standard mcap_ros2 decoder. `progress(n)` is called
        with the number of file bytes consumed after each chunk.
        """
        decoders = self._decoders(set(self.topics) if topics is None else set(topics), fast)
        if not self.indexed:
            for _offset, consumed, batches in self._scanned_blocks(decoders):
                yield batches
                if progress is not None:
                    progress(consumed)
            return
        for index, batches in self._indexed_chunks(decoders):
            if batches is not None:
                yield batches
            if progress is not None:
                progress(index.chunk_length + index.message_index_length)

    @property
    def schemas(self) -> dict[int, Any]:
        """Schema id -> mcap.records.Schema (from the summary, or the scan of a file without one)."""
        return dict(self._schemas)

    @property
    def channels(self) -> dict[int, Any]:
        """Channel id -> mcap.records.Channel (from the summary, or the scan of a file without one)."""
        return dict(self._channels)

    @property
    def summary(self) -> Any:
        """The file's summary (mcap.reader Summary: schemas, channels, statistics, chunk indexes), or None."""
        return self._summary

    def iter_regions(
        self, topics: Iterable[str], *, fast: bool = True
    ) -> Iterator[tuple[int | None, list[Batch]]]:
        """Yield the data section in file order as regions: (the file offset where the region ends, the
        batches of `topics` in it); the last region's end is None (the end of the data section).

        A region of an indexed file is a chunk with its message indexes; without chunk indexes, a block of
        the scan (`pipeline.logs.mcap_scan`) up to the next block, so that whatever follows a chunk (its
        message indexes) stays with it. Bytes may be inserted at each region's end (`LogAugmenter`).
        """
        decoders = self._decoders(set(topics), fast)
        if self.indexed:
            for index, batches in self._indexed_chunks(decoders):
                yield (
                    index.chunk_start_offset + index.chunk_length + index.message_index_length,
                    batches or [],
                )
            return
        previous: list[Batch] | None = None
        for offset, _consumed, batches in self._scanned_blocks(decoders):
            if previous is not None:
                yield offset, previous
            previous = batches
        yield None, previous or []

    def _scanned_blocks(
        self, decoders: Mapping[int, ChannelDecoder]
    ) -> Iterator[tuple[int, int, list[Batch]]]:
        """(file offset, file bytes consumed, batches) of each block of a scan of the data section."""
        blocks = scan_blocks(self._file, self.size_bytes, str(self.path), self.validate_crcs)
        for ordinal, (offset, consumed, data) in enumerate(blocks):
            offsets = message_offsets(data, decoders.__contains__)
            yield offset, consumed, self._decode(data, offsets, ordinal, decoders, f"data at byte {offset}")

    def _indexed_chunks(
        self, decoders: Mapping[int, ChannelDecoder]
    ) -> Iterator[tuple[Any, list[Batch] | None]]:
        """(index, batches) of every chunk in file order; batches None when no wanted channel is in it."""
        chunk_indexes = sorted(self._summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
        for ordinal, index in enumerate(chunk_indexes):
            if index.message_index_offsets and not any(c in decoders for c in index.message_index_offsets):
                yield index, None
            else:
                yield index, self._read_chunk(index, ordinal, decoders)

    def _decoders(self, wanted: set[str], fast: bool) -> dict[int, ChannelDecoder]:
        decoders: dict[int, ChannelDecoder] = {}
        for cid, channel in self._channels.items():
            if channel.topic in wanted:
                schema = self._schemas.get(channel.schema_id)
                decoders[cid] = ChannelDecoder(
                    channel.topic, schema.name if schema else "", schema, channel.message_encoding, fast
                )
        return decoders

    def _read_chunk(self, index: Any, ordinal: int, decoders: Mapping[int, ChannelDecoder]) -> list[Batch]:
        where = f"chunk at byte {index.chunk_start_offset}"
        f = self._file
        f.seek(index.chunk_start_offset)
        record = f.read(index.chunk_length + index.message_index_length)
        if len(record) < index.chunk_length + index.message_index_length:
            raise self._error(f"truncated MCAP file ({where} ends after the end of the file)")
        data = decompress_chunk(record, str(self.path), where, self.validate_crcs)
        offsets = self._message_offsets(record[index.chunk_length :], index, data, decoders)
        return self._decode(data, offsets, ordinal, decoders, where)

    def _decode(
        self,
        data: bytes,
        offsets_by_channel: Mapping[int, np.ndarray],
        ordinal: int,
        decoders: Mapping[int, ChannelDecoder],
        where: str,
    ) -> list[Batch]:
        """Decode the Message records at the given offsets of a block of records (a chunk)."""
        buf = np.frombuffer(data, dtype=np.uint8)
        batches: list[Batch] = []
        for cid, offs in offsets_by_channel.items():
            if len(offs) and (offs[0] < 0 or offs[-1] + RECORD_HEADER_SIZE > len(buf)):
                raise self._error(f"corrupted {where} (message index points outside the chunk)")
            head = as_struct(gather_rows(buf, offs, RECORD_HEADER_SIZE), RECORD_HEADER)
            bad = (
                (head["op"] != 0x05)
                | (head["channel"] != cid)
                | (offs + 9 + head["len"] > len(buf))
                | (head["len"] < 22)
            )
            if bad.any():
                raise self._error(f"corrupted {where} (message index points outside a message record)")
            sizes = head["len"].astype(np.int64) - 22
            order = (np.int64(ordinal) << 32) + offs
            try:
                batches.extend(
                    decoders[cid].decode(
                        buf,
                        offs + RECORD_HEADER_SIZE,
                        sizes,
                        head["log_time"].astype(np.int64),
                        head["publish_time"].astype(np.int64),
                        order,
                    )
                )
            except DataError as exc:
                raise self._error(str(exc)) from None
        return batches

    def _message_offsets(
        self,
        indexes: bytes,
        index: Any,
        data: bytes,
        decoders: Mapping[int, ChannelDecoder],
    ) -> dict[int, np.ndarray]:
        """Offsets in the chunk of the wanted channels' Message records, each in file order."""
        out: dict[int, np.ndarray] = {}
        if index.message_index_offsets:
            base = index.chunk_start_offset + index.chunk_length
            for cid, absolute in index.message_index_offsets.items():
                if cid not in decoders:
                    continue
                pos = absolute - base
                try:
                    op, _length, channel, nbytes = struct.unpack_from("<BQHI", indexes, pos)
                except struct.error:
                    raise self._error(
                        f"corrupted message index of chunk at byte {index.chunk_start_offset}"
                    ) from None
                entries = np.frombuffer(indexes, dtype="<u8", count=nbytes // 8, offset=pos + 15)
                if op != 0x07 or channel != cid or len(entries) * 8 != nbytes:
                    raise self._error(f"corrupted message index of chunk at byte {index.chunk_start_offset}")
                offsets = np.sort(entries[1::2].astype(np.int64))
                if len(offsets):
                    out[cid] = offsets
            return out
        return message_offsets(data, decoders.__contains__)  # no message index: walk the records

    def read(self, topics: Iterable[str] | None = None, *, fast: bool = True) -> dict[str, list[Batch]]:
        """All batches of the wanted topics, per topic (whole log in memory: for tests and small logs)."""
        out: dict[str, list[Batch]] = {}
        for batches in self.iter_chunks(topics, fast=fast):
            for batch in batches:
                out.setdefault(batch.topic, []).append(batch)
        return out


def _topics(
    schemas: Mapping[int, Any], channels: Mapping[int, Any], counts: Mapping[int, int]
) -> dict[str, TopicInfo]:
    """Topics of a log from its schemas, channels and per-channel message counts (by topic name)."""
    topics: dict[str, TopicInfo] = {}
    for cid, channel in sorted(channels.items()):
        schema = schemas.get(channel.schema_id)
        msgtype = schema.name if schema is not None else ""
        known = topics.get(channel.topic)
        count = int(counts.get(cid, 0))
        if known is None:
            topics[channel.topic] = TopicInfo(channel.topic, msgtype, count, (cid,))
        else:
            types = msgtype if msgtype == known.msgtype else f"{known.msgtype}|{msgtype}"
            topics[channel.topic] = TopicInfo(
                channel.topic, types, known.message_count + count, (*known.channel_ids, cid)
            )
    return topics


def concat_batches(batches: Sequence[Batch]) -> dict[str, np.ndarray]:
    """Concatenate batches of one topic with equal field shapes into arrays, in file order.

    Returns log_time_ns, publish_time_ns, stamp_ns, order and every field (JointState batches must
    share their joint names; see `Batch.names`).
    """
    if not batches:
        return {}
    keys = ("log_time_ns", "publish_time_ns", "stamp_ns", "order")
    out = {key: np.concatenate([getattr(b, key) for b in batches]) for key in keys}
    for name in batches[0].fields:
        out[name] = np.concatenate([b.fields[name] for b in batches])
    perm = np.argsort(out["order"], kind="stable")
    return {key: value[perm] for key, value in out.items()}
