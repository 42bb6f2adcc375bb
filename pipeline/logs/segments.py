"""One recording, several logs: the experiment's useful `window` and its train/test `segments`.

A lab's recording often holds more than one usable stretch, or one stretch that must both train and test
(a single long "yoga" run). Its experiment metadata (sidecar YAML, or the MCAP ``experiment`` record, where
the two keys are JSON strings) may say, in seconds of the ingested table's ``time_s`` (from the log's first
joint-state stamp):

- ``window: [start_s, end_s]``: only the samples with start_s <= time_s < end_s are kept;
- ``segments: [{start_s, end_s, role}, ...]``: each segment becomes its own table ``<log>__seg<k>``
  (k: its position in the list) whose experiment record has that ``role`` (train or test), so that every
  later stage, and the split by whole logs, sees several logs. Samples between segments are dropped.

Segments may not overlap, must lie inside the window when both are given (errors name the key at once),
and must lie inside the recording and hold samples (checked once the log is read). They may be as close as
a lab writes them: smoothing never crosses a table, and the first and last half window of each are not ok
for labelling (`pipeline.logs.smoothing`), so no test sample's kinematics are computed from a training
segment's samples.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.core.errors import DataError
from pipeline.logs import schema as S

WINDOW, SEGMENTS = "window", "segments"
SPLIT_KEYS = (WINDOW, SEGMENTS)
ROLES = ("train", "test")
SEGMENT_KEYS = ("start_s", "end_s", "role")


@dataclass(frozen=True)
class Segment:
    """One stretch of a recording with its role: start_s <= time_s < end_s (s)."""

    index: int  # position in the metadata's list
    start_s: float
    end_s: float
    role: str


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise DataError(f"{where} must be a number of seconds, got {value!r}")
    return float(value)


def _interval(start: Any, end: Any, where: str) -> tuple[float, float]:
    a, b = _number(start, f"{where} start"), _number(end, f"{where} end")
    if not 0 <= a < b:
        raise DataError(f"{where} must satisfy 0 <= start < end (s), got [{a:g}, {b:g}]")
    return a, b


def _decoded(value: Any, where: str) -> Any:
    if isinstance(value, str):  # from an MCAP experiment record: JSON text
        try:
            return json.loads(value)
        except json.JSONDecodeError as exc:
            raise DataError(f"{where} is not valid JSON: {exc}") from None
    return value


def parse_split(data: Mapping[str, Any], where: str) -> tuple[tuple[float, float] | None, list[Segment]]:
    """(window or None, segments sorted by start) from metadata values (YAML lists or JSON strings).

    Raises DataError naming `where` and the key: a malformed window or segment, a role other than train
    or test, overlapping segments, a segment outside the window.
    """
    window = None
    raw_window = _decoded(data.get(WINDOW), f"{where}: {WINDOW}")
    if raw_window not in (None, ""):
        if not isinstance(raw_window, list | tuple) or len(raw_window) != 2:
            raise DataError(f"{where}: {WINDOW} must be [start_s, end_s], got {raw_window!r}")
        window = _interval(*raw_window, f"{where}: {WINDOW}")
    raw = _decoded(data.get(SEGMENTS), f"{where}: {SEGMENTS}")
    if raw in (None, ""):
        return window, []
    if not isinstance(raw, list | tuple) or not raw:
        raise DataError(f"{where}: {SEGMENTS} must be a non-empty list of {{start_s, end_s, role}}")
    segments = []
    for k, item in enumerate(raw):
        key = f"{where}: {SEGMENTS}[{k}]"
        if not isinstance(item, Mapping) or set(item) != set(SEGMENT_KEYS):
            raise DataError(f"{key} must be a mapping with exactly {', '.join(SEGMENT_KEYS)}, got {item!r}")
        if item["role"] not in ROLES:
            raise DataError(f"{key}.role must be one of {', '.join(ROLES)}, got {item['role']!r}")
        a, b = _interval(item["start_s"], item["end_s"], key)
        if window is not None and not (window[0] <= a and b <= window[1]):
            raise DataError(f"{key} [{a:g}, {b:g}] s leaves the {WINDOW} [{window[0]:g}, {window[1]:g}] s")
        segments.append(Segment(k, a, b, str(item["role"])))
    segments.sort(key=lambda s: s.start_s)
    for prev, seg in zip(segments[:-1], segments[1:], strict=True):
        if seg.start_s < prev.end_s:
            raise DataError(
                f"{where}: {SEGMENTS}[{seg.index}] [{seg.start_s:g}, {seg.end_s:g}] s overlaps "
                f"{SEGMENTS}[{prev.index}] [{prev.start_s:g}, {prev.end_s:g}] s"
            )
    return window, segments


def split_to_record(window: tuple[float, float] | None, segments: Sequence[Segment]) -> dict[str, str]:
    """The two keys as an experiment record holds them (JSON strings; absent when not given)."""
    out = {}
    if window is not None:
        out[WINDOW] = json.dumps(list(window))
    if segments:
        ordered = sorted(segments, key=lambda s: s.index)
        items = [{"start_s": s.start_s, "end_s": s.end_s, "role": s.role} for s in ordered]
        out[SEGMENTS] = json.dumps(items)
    return out


def segment_name(log: str, segment: Segment) -> str:
    """Table name of a segment of `log`."""
    return f"{log}__seg{segment.index}"


class SplitTables:
    """The tables one log is written to: the whole log, or one per segment; rows routed by ``time_s``.

    `open_table(name, experiment)` creates a table writer (with ``write``, ``commit``, ``abort`` and
    ``path``: `pipeline.logs.tables.AtomicParquet`) for a table name and its experiment record.
    """

    def __init__(
        self,
        name: str,
        experiment: Mapping[str, str],
        open_table: Callable[[str, dict[str, str]], Any],
        where: str,
    ):
        self.where = where
        self.window, self.segments = parse_split(experiment, f"{where}: experiment")
        base = {k: v for k, v in experiment.items() if k not in SPLIT_KEYS}
        if self.window is not None:
            base[WINDOW] = experiment[WINDOW]
        if not self.segments:
            lo, hi = self.window if self.window is not None else (-math.inf, math.inf)
            self.parts = [(lo, hi, open_table(name, base))]
        else:
            self.parts = [
                (
                    s.start_s,
                    s.end_s,
                    open_table(
                        segment_name(name, s),
                        {
                            **base,
                            "role": s.role,
                            "run": name,
                            "segment": str(s.index),
                            "segment_s": json.dumps([s.start_s, s.end_s]),
                        },
                    ),
                )
                for s in self.segments
            ]
        self.rows = [0] * len(self.parts)
        self.last_time_s = -math.inf  # of the whole log, kept or not

    @property
    def tables(self) -> list[Any]:
        return [t for _, _, t in self.parts]

    def write(self, columns: Mapping[str, Any]) -> None:
        """Route rows (column -> (N,) values, with ``time_s``) to the tables whose stretch holds them."""
        time = np.asarray(columns[S.TIME])
        if len(time):
            self.last_time_s = max(self.last_time_s, float(time[-1]))
        for k, (lo, hi, table) in enumerate(self.parts):
            keep = (time >= lo) & (time < hi)
            if keep.all():
                table.write(columns)
            elif keep.any():
                table.write({c: np.asarray(v)[keep] for c, v in columns.items()})
            self.rows[k] += int(keep.sum())

    def check(self) -> None:
        """After the last row: every stretch inside the log with samples."""
        end = self.last_time_s
        if self.window is not None and not self.rows[0] and not self.segments:
            raise DataError(
                f"{self.where}: the experiment window [{self.window[0]:g}, {self.window[1]:g}] s holds no "
                f"data (the log's samples span 0 to {end:.3f} s)"
            )
        for seg, rows in zip(self.segments, self.rows if self.segments else [], strict=True):
            if seg.end_s > end or not rows:
                raise DataError(
                    f"{self.where}: {SEGMENTS}[{seg.index}] [{seg.start_s:g}, {seg.end_s:g}] s leaves the "
                    f"recording (its samples span 0 to {end:.3f} s)"
                )

    def commit(self, metadata: Mapping[bytes, Any]) -> None:
        for table in self.tables:
            table.commit(metadata)

    def abort(self) -> None:
        for table in self.tables:
            table.abort()
