"""Atomic file writes and the JSON/CSV/Parquet helpers every stage uses.

A stage never leaves a half-written file for the next stage to read: each writer below writes to a
hidden temporary file in the destination's directory and renames it over the destination (atomic on
POSIX), and removes the temporary file if anything fails or is interrupted.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success rename it to `path`, on failure delete it.

    The temporary name keeps the destination's suffix (``.<stem>.<pid>.tmp<suffix>``) so writers that
    pick a format from the file name (matplotlib, pyarrow) still do the right thing.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield an empty staging directory beside `path`; on success it replaces `path` whole (an older one
    is removed), on failure it is deleted and `path` is left as it was."""
    import shutil

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
        old = path.with_name(f".{path.name}.{os.getpid()}.old")
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_atomic(path: str | Path, write: Callable[[Path], Any]) -> None:
    """Call ``write(tmp)`` and move the file it wrote to `path` (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        write(tmp)


def jsonable(obj: Any) -> Any:
    """`obj` with non-finite floats as None and numpy scalars/arrays as Python values (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if hasattr(obj, "tolist"):  # numpy scalar or array
        return jsonable(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps_json(obj: Any, *, indent: int | None = 1) -> str:
    """Strict JSON text of `obj` (NaN/inf as null), keys in insertion order, newline-terminated."""
    return json.dumps(jsonable(obj), indent=indent, allow_nan=False) + "\n"


def read_json(path: str | Path, what: str, missing: str = "not found") -> Any:
    """The JSON document of `path`. DataError ``<path>: <missing>`` if there is no such file,
    ``<path>: not <what>: <why>`` if it cannot be read or parsed."""
    from pipeline.core.errors import DataError

    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataError(f"{path}: {missing}") from None
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: not {what}: {exc}") from None


def write_json(path: str | Path, obj: Any, *, indent: int | None = 1) -> None:
    """Write `obj` as strict JSON (see :func:`dumps_json`), atomically."""
    write_text(path, dumps_json(obj, indent=indent))


def write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 `text` to `path`, atomically."""
    write_atomic(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def write_csv(path: str | Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Write a CSV with a header row, atomically; None and non-finite floats become empty cells."""

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            for row in rows:
                writer.writerow(
                    ["" if v is None or (isinstance(v, float) and not math.isfinite(v)) else v for v in row]
                )

    write_atomic(path, write)


def write_parquet(path: str | Path, table: Any) -> None:
    """Write a pyarrow Table as zstd-compressed Parquet, atomically."""
    import pyarrow.parquet as pq

    write_atomic(path, lambda tmp: pq.write_table(table, tmp, compression="zstd"))
