"""MCAP records without the summary's help: chunk decompression, record walks, the data-section scan.

The MCAP spec makes the summary section, the chunk and message indexes and the statistics optional: a
streaming recorder that died before writing its summary, or a writer with chunking or indexing turned
off, leaves a file whose data section alone holds every schema, channel, message and metadata record.
`scan_blocks` reads that data section front to back and yields it as blocks of records (a decompressed
chunk, or a run of records written outside chunks) that the reader decodes as it decodes a chunk.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, BinaryIO

import numpy as np

from pipeline.core.errors import DataError

OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_ATTACHMENT, OP_METADATA, OP_DATA_END = 0x09, 0x0C, 0x0F
_LOOSE_BLOCK_BYTES = 4 * 2**20  # records outside chunks are decoded in blocks of about this size


def decompress_chunk(record: bytes, file: str, where: str, validate_crcs: bool) -> bytes:
    """The uncompressed records of a Chunk record (`record` starts at its opcode).

    Raises DataError ("<file>: corrupted <where> (problem)", e.g. where = "chunk at byte N").
    """
    try:
        op, _length, _t0, _t1, usize, crc, clen = struct.unpack_from("<BQQQQII", record, 0)
        compression = bytes(record[41 : 41 + clen]).decode()
        (dlen,) = struct.unpack_from("<Q", record, 41 + clen)
    except (struct.error, UnicodeDecodeError):
        raise DataError(f"{file}: corrupted {where} (bad chunk header)") from None
    if op != OP_CHUNK:
        raise DataError(f"{file}: corrupted {where} (not a chunk record: opcode {op:#04x})")
    start = 49 + clen
    payload = record[start : start + dlen]
    if len(payload) != dlen:
        raise DataError(f"{file}: corrupted {where} (chunk data length {dlen} exceeds the record)")
    try:
        if compression == "zstd":
            import zstandard

            data = zstandard.ZstdDecompressor().decompress(payload, max_output_size=usize)
        elif compression == "lz4":
            import lz4.frame  # type: ignore[import-not-found]

            data = lz4.frame.decompress(payload)
        elif compression == "":
            data = bytes(payload)
        else:
            raise DataError(f"{file}: {where}: unsupported compression {compression!r}")
    except DataError:
        raise
    except Exception as exc:  # noqa: BLE001 (zstd/lz4 raise their own error types)
        raise DataError(f"{file}: corrupted {where} (cannot decompress: {exc})") from None
    if len(data) != usize:
        raise DataError(f"{file}: corrupted {where} (decompressed {len(data)} bytes, expected {usize})")
    if validate_crcs and crc != 0 and zlib.crc32(data) != crc:
        raise DataError(f"{file}: corrupted {where} (CRC mismatch)")
    return data


def message_offsets(data: bytes, wanted: Callable[[int], bool]) -> dict[int, np.ndarray]:
    """Offsets of the Message records of the wanted channel ids in a block of records, in file order."""
    pos, n = 0, len(data)
    found: dict[int, list[int]] = {}
    unpack = struct.Struct("<BQ").unpack_from
    while pos + 9 <= n:
        op, length = unpack(data, pos)
        if op == OP_MESSAGE and pos + 11 <= n:
            (cid,) = struct.unpack_from("<H", data, pos + 9)
            if wanted(cid):
                found.setdefault(cid, []).append(pos)
        pos += 9 + length
    return {cid: np.array(offs, dtype=np.int64) for cid, offs in found.items()}


@dataclass
class ScannedSummary:
    """What a scan of the data section found: the summary a complete file would have had."""

    schemas: dict[int, Any] = field(default_factory=dict)  # id -> mcap.records.Schema
    channels: dict[int, Any] = field(default_factory=dict)  # id -> mcap.records.Channel
    counts: dict[int, int] = field(default_factory=dict)  # channel id -> messages
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)


def _parse(op: int, body: bytes) -> Any:
    from mcap.data_stream import ReadDataStream
    from mcap.records import Channel, Metadata, Schema

    cls = {OP_SCHEMA: Schema, OP_CHANNEL: Channel, OP_METADATA: Metadata}[op]
    return cls.read(ReadDataStream(io.BytesIO(body)))


def summarise_block(data: bytes, out: ScannedSummary) -> None:
    """Add the schemas, channels, metadata and message counts of a block of records to `out`."""
    pos, n = 0, len(data)
    unpack = struct.Struct("<BQ").unpack_from
    while pos + 9 <= n:
        op, length = unpack(data, pos)
        if op == OP_MESSAGE and pos + 11 <= n:
            (cid,) = struct.unpack_from("<H", data, pos + 9)
            out.counts[cid] = out.counts.get(cid, 0) + 1
        elif op in (OP_SCHEMA, OP_CHANNEL, OP_METADATA):
            record = _parse(op, data[pos + 9 : pos + 9 + length])
            if op == OP_SCHEMA:
                out.schemas[record.id] = record
            elif op == OP_CHANNEL:
                out.channels[record.id] = record
            else:
                out.metadata[record.name] = dict(record.metadata)
        pos += 9 + length


def scan_blocks(f: BinaryIO, size: int, where: str, validate_crcs: bool) -> Iterator[tuple[int, int, bytes]]:
    """Yield (file offset, file bytes consumed, records) for each block of the data section, in order.

    A block is a decompressed chunk, or a run of consecutive records written outside chunks. The scan
    stops at the DataEnd or Footer record; a record that runs past the end of the file is an error.
    """
    f.seek(8)
    loose: list[bytes] = []
    loose_start, loose_bytes = 8, 0
    pos = 8
    while pos + 9 <= size:
        head = f.read(9)
        op, length = struct.unpack("<BQ", head)
        if op in (OP_DATA_END, OP_FOOTER):
            break
        if pos + 9 + length > size:
            raise DataError(
                f"{where}: truncated MCAP file (the record at byte {pos} ends after the end of the file; "
                "the recording was interrupted?)"
            )
        if op == OP_CHUNK:
            if loose:
                yield loose_start, pos - loose_start, b"".join(loose)
                loose, loose_bytes = [], 0
            record = head + f.read(length)
            yield pos, 9 + length, decompress_chunk(record, where, f"chunk at byte {pos}", validate_crcs)
            loose_start = pos + 9 + length
        elif op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_METADATA):
            loose.append(head + f.read(length))
            loose_bytes += 9 + length
            if loose_bytes >= _LOOSE_BLOCK_BYTES:
                yield loose_start, pos + 9 + length - loose_start, b"".join(loose)
                loose, loose_bytes, loose_start = [], 0, pos + 9 + length
        else:  # header, attachments, indexes between chunks: nothing to decode
            f.seek(length, io.SEEK_CUR)
        pos += 9 + length
    if loose:
        yield loose_start, pos - loose_start, b"".join(loose)
