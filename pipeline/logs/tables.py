"""Ingested tables on disk: streamed atomic Parquet writing, the ftcal metadata, leftover temp files.

An ingested table is written in row groups to a hidden temporary file beside it (`pipeline.core.io`) and
renamed over it only when complete, so the next stage never reads half a table.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.core.io import atomic_path
from pipeline.logs.align import StreamStats

ROW_GROUP_ROWS = 16_384


@dataclass
class LogReport:
    """What ingest did with one log."""

    source: str
    output: str | None = None
    truth_output: str | None = None
    samples: int = 0
    messages: int = 0
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)
    streams: dict[str, StreamStats] = field(default_factory=dict)
    error: str | None = None
    absent: list[str] = field(default_factory=list)  # streams the log does not have (topics, ports)
    not_read: list[str] = field(default_factory=list)  # what the log holds that ingest does not read
    fixed: list[str] = field(default_factory=list)  # joints it lacks, filled from ingest.fixed_joints
    frozen: dict[str, int] = field(default_factory=dict)  # sensor -> samples flagged as frozen
    outputs: list[str] = field(default_factory=list)  # every table written (one per segment)
    kept: int | None = None  # samples written to the tables (the window's, the segments'); None: all


class AtomicParquet:
    """A Parquet file written in row groups to a temp file in the same directory, renamed on commit."""

    def __init__(self, path: Path, arrow_schema: Any):
        self.path = path
        self._atomic = atomic_path(path)  # entered on the first row group, left by commit() or abort()
        self.tmp: Path | None = None
        self.schema = arrow_schema  # pyarrow.Schema
        self._writer: Any = None  # pyarrow.parquet.ParquetWriter
        self._pieces: list[Any] = []
        self._rows = 0
        self.rows_written = 0

    def write(self, columns: Mapping[str, Any]) -> None:
        """Append rows: column name -> (N,) values, in the schema's types."""
        import pyarrow as pa

        table = pa.Table.from_pydict(dict(columns), schema=self.schema)
        self._pieces.append(table)
        self._rows += table.num_rows
        if self._rows >= ROW_GROUP_ROWS:
            self._flush()

    def _open(self) -> None:
        import pyarrow.parquet as pq

        self.tmp = self._atomic.__enter__()
        self._writer = pq.ParquetWriter(self.tmp, self.schema, compression="zstd")

    def _flush(self) -> None:
        import pyarrow as pa

        if not self._pieces:
            return
        if self._writer is None:
            self._open()
        self._writer.write_table(pa.concat_tables(self._pieces), row_group_size=max(self._rows, 1))
        self.rows_written += self._rows
        self._pieces, self._rows = [], 0

    def commit(self, metadata: Mapping[bytes, Any]) -> None:
        """Write the rest, the key-value metadata (JSON values) and the footer; rename over `path`."""
        self._flush()
        if self._writer is None:  # no rows: still a valid, empty table
            self._open()
        self._writer.add_key_value_metadata(
            {
                k.decode(): v if isinstance(v, str) else json.dumps(v, sort_keys=True)
                for k, v in metadata.items()
            }
        )
        self._writer.close()
        self._atomic.__exit__(None, None, None)

    def abort(self) -> None:
        """Close and delete the temporary file (nothing is left at `path`)."""
        if self._writer is not None:
            with contextlib.suppress(Exception):  # the temp file goes anyway
                self._writer.close()
            err = RuntimeError("aborted")
            with contextlib.suppress(RuntimeError):
                self._atomic.__exit__(RuntimeError, err, None)


def read_table_metadata(path: str | Path | Any) -> dict[str, Any]:
    """The ``ftcal.*`` key-value metadata of a Parquet table, JSON-decoded (schema and file footer).

    `path` may also be a table already open as a ``pyarrow.parquet.ParquetFile`` (its footer is not read
    again).
    """
    import pyarrow.parquet as pq

    out: dict[str, Any] = {}
    pf = path if isinstance(path, pq.ParquetFile) else pq.ParquetFile(path)
    meta = pf.metadata.metadata or {}
    schema_meta = pf.schema_arrow.metadata or {}
    for key, value in {**schema_meta, **meta}.items():
        if key.startswith(b"ftcal."):
            out[key.decode()] = json.loads(value)
    return out
