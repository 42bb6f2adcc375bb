"""Stage `ingest`: MCAP logs -> one aligned Parquet table per log (plus the simulated truth apart).

Every ``*.mcap`` under the source directory is decoded (`pipeline.logs.rosmsg`), and every topic is aligned
on the joint-state header stamps, which are the time base of the log (one row per joint-state sample,
columns in `pipeline.logs.schema`). How the messages of a stream become values at a time-base sample:

- Arrival order is the recorder's (log time, file position). Messages whose stamps go back by less than
  ``ingest.max_reorder_s`` in arrival order are out of order and simply re-sorted by stamp; a larger
  step back is a clock jump and an error. Messages with an already seen stamp are duplicates: the
  first to arrive is kept. Messages with NaN/inf values are dropped (an error beyond
  ``ingest.max_nonfinite_fraction`` of a topic's messages).
- Continuous signals (wrench, IMU, temperature, simulated wrenches) are linearly interpolated between
  the last message at or before the sample and the first after it; the sample is ok when those two
  messages are at most the stream's max gap apart (``ingest.max_gap_s``, ``ingest.max_gap_temperature_s``),
  or one message has exactly its stamp. Otherwise the values are NaN and ``ok.<stream>`` is False:
  too many lost messages, a stream that starts late or stops early; never a silent extrapolation.
- Discrete signals (the simulated contact set) take the latest message at or before the sample.

Logs are streamed chunk by chunk and the table is written in row groups, so memory stays bounded
whatever the log's length: a sample is written once every stream has passed it by more than the
reorder window and the max gap.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.core.config import (
    MatParams,
    Params,
    TopicParams,
    load_params,
    repo_root,
    resolve_urdf,
    stage_section,
)
from pipeline.core.errors import ConfigError, DataError
from pipeline.logs import rosmsg
from pipeline.logs import schema as S

STAGE = "ingest"
_ROW_GROUP_ROWS = 16_384
_EMIT_ROWS = 2_000  # time-base samples buffered before aligning and writing them
_STALL_S = 5.0  # a stream this far behind the joint states no longer holds the others back (s)
MAT_SUFFIX = ".mat"  # YarpRobotLoggerDevice files, read through pipeline.logs.matreader
LOG_SUFFIXES = (".mcap", MAT_SUFFIX)


# --- params --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class IngestParams:
    """Section `ingest` of params.yaml (see the comments there)."""

    source: str  # directory searched recursively for *.mcap; dvc.yaml passes it to the command
    max_gap_s: float  # s, wrench/IMU/truth: widest gap between two messages that is interpolated
    max_gap_temperature_s: float  # s, the same for the (slow) temperature stream
    max_reorder_s: float  # s, largest step back of stamps in arrival order that is re-sorted
    max_nonfinite_fraction: float  # fraction of a topic's messages that may hold NaN/inf (dropped)
    skip_bad_logs: bool  # true: a bad log is a warning and is skipped; false: an error
    mat: Any = None  # MatParams (section ingest.mat): where .mat logger files keep each quantity

    def __post_init__(self) -> None:
        if not isinstance(self.source, str) or not self.source.strip():
            raise ConfigError(f"ingest.source must be a non-empty path, got {self.source!r}")
        for key in ("max_gap_s", "max_gap_temperature_s", "max_reorder_s"):
            value = getattr(self, key)
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not math.isfinite(value)
                or value <= 0
            ):
                raise ConfigError(f"ingest.{key} must be a positive number of seconds, got {value!r}")
            object.__setattr__(self, key, float(value))
        f = self.max_nonfinite_fraction
        if isinstance(f, bool) or not isinstance(f, int | float) or not 0 <= f <= 1:
            raise ConfigError(f"ingest.max_nonfinite_fraction must be in [0, 1], got {f!r}")
        object.__setattr__(self, "max_nonfinite_fraction", float(f))
        if not isinstance(self.skip_bad_logs, bool):
            raise ConfigError(f"ingest.skip_bad_logs must be true or false, got {self.skip_bad_logs!r}")
        if self.mat is not None:
            object.__setattr__(self, "mat", MatParams.from_mapping(self.mat))


# --- pure alignment functions --------------------------------------------------------------------


def align_continuous(
    target_ns: np.ndarray, source_ns: np.ndarray, values: np.ndarray, max_gap_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of a continuous signal at the target stamps, within a max gap.

    Args:
        target_ns: (N,) int64 ns, increasing.
        source_ns: (M,) int64 ns, strictly increasing.
        values: (M, K) float values at `source_ns`, finite.
        max_gap_ns: a target is ok iff a source stamp equals it, or the last source stamp before it
            and the first after it are at most this far apart.

    Returns:
        ((N, K) float64 values, NaN where not ok; (N,) bool ok).
    """
    n = len(target_ns)
    out = np.full((n, values.shape[1]), np.nan)
    if len(source_ns) == 0 or n == 0:
        return out, np.zeros(n, dtype=bool)
    after = np.searchsorted(source_ns, target_ns, side="right")  # first source stamp > target
    before = after - 1
    has_before = before >= 0
    b = np.clip(before, 0, len(source_ns) - 1)
    a = np.clip(after, 0, len(source_ns) - 1)
    exact = has_before & (source_ns[b] == target_ns)
    bracket = has_before & (after < len(source_ns)) & (source_ns[a] - source_ns[b] <= max_gap_ns)
    ok = exact | bracket
    span = (source_ns[a] - source_ns[b]).astype(np.float64)
    w = np.where(bracket & ~exact, (target_ns - source_ns[b]) / np.where(span > 0, span, 1.0), 0.0)
    interp = values[b] + w[:, None] * (values[a] - values[b])
    out[ok] = interp[ok]
    return out, ok


def align_latest(target_ns: np.ndarray, source_ns: np.ndarray, values: np.ndarray) -> np.ndarray:
    """A discrete signal at the target stamps: the latest source value at or before each (None before any).

    target_ns (N,) and source_ns (M,) int64 ns increasing; values (M,) object. Returns (N,) object.
    """
    idx = np.searchsorted(source_ns, target_ns, side="right") - 1
    out = np.full(len(target_ns), None, dtype=object)
    has = idx >= 0
    out[has] = values[idx[has]]
    return out


def arrival_order(log_time_ns: np.ndarray, file_order: np.ndarray) -> np.ndarray:
    """Permutation that puts messages in the recorder's arrival order: log time, then file position."""
    return np.lexsort((file_order, log_time_ns))


def stamp_steps_back(stamps_ns: np.ndarray, previous_max: int | None) -> np.ndarray:
    """(M,) int64: how far each stamp lies behind the largest stamp before it (arrival order), >= 0."""
    if len(stamps_ns) == 0:
        return np.zeros(0, dtype=np.int64)
    start = stamps_ns[0] if previous_max is None else max(int(previous_max), int(stamps_ns[0]))
    running = np.maximum.accumulate(np.concatenate([[start], stamps_ns[:-1]]))
    return np.maximum(running - stamps_ns, 0)


def sort_unique(stamps_ns: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Sort by stamp (stable) and drop repeated stamps, keeping the first.

    Returns (stamps, values, number of messages dropped).
    """
    perm = np.argsort(stamps_ns, kind="stable")
    s, v = stamps_ns[perm], values[perm]
    keep = np.ones(len(s), dtype=bool)
    keep[1:] = s[1:] != s[:-1]
    return s[keep], v[keep], int((~keep).sum())


def median_rate_hz(stamps_ns: np.ndarray) -> float:
    """1 / median stamp step, in Hz (NaN with fewer than 2 stamps)."""
    if len(stamps_ns) < 2:
        return float("nan")
    return 1e9 / float(np.median(np.diff(stamps_ns)))


def joint_permutation(names: Sequence[str], joints: Sequence[str]) -> tuple[np.ndarray, list[str], list[str]]:
    """Column indices that reorder a JointState's arrays into `joints` order.

    Returns (perm (len(joints),) int, names not in `joints`, `joints` missing from names).
    """
    index = {name: k for k, name in enumerate(names)}
    unknown = [n for n in names if n not in set(joints)]
    missing = [j for j in joints if j not in index]
    perm = np.array([index.get(j, -1) for j in joints], dtype=np.int64)
    return perm, unknown, missing


# --- streams -------------------------------------------------------------------------------------


@dataclass
class StreamStats:
    """Counts of one topic over a log (reported in the Parquet metadata and MLflow)."""

    topic: str
    msgtype: str
    messages: int = 0
    duplicates: int = 0  # same stamp as an earlier message: dropped
    reordered: int = 0  # arrived after a message with a later stamp: re-sorted
    nonfinite: int = 0  # NaN/inf values: dropped
    late: int = 0  # arrived after the samples around its stamp were written (too late to be used)
    rate_hz: float = float("nan")  # 1 / median stamp step
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None


class _Stream:
    """Messages of one topic between two writes: kept sorted, unique and finite."""

    def __init__(
        self,
        name: str,
        topic: str,
        msgtype: str,
        width: int,
        max_gap_ns: int,
        where: str,
        max_reorder_ns: int,
        discrete: bool = False,
        time_base: bool = False,
        finite_columns: int | None = None,
    ):
        self.name, self.topic, self.where = name, topic, where
        self.width, self.max_gap_ns, self.max_reorder_ns = width, max_gap_ns, max_reorder_ns
        self.discrete, self.time_base = discrete, time_base
        # The first `finite_columns` values must be finite for a message to be kept (all by default).
        self.finite_columns = width if finite_columns is None else finite_columns
        self.stats = StreamStats(topic, msgtype)
        self.t = np.empty(0, dtype=np.int64)
        self.v: np.ndarray = np.empty(0, dtype=object) if discrete else np.empty((0, width))
        self._new: list[tuple[np.ndarray, np.ndarray]] = []
        self.max_stamp: int | None = None
        self.max_delay: int | None = None  # largest (log time - stamp) seen, ns
        self.written_upto: int | None = None  # last time-base stamp written
        self._steps: list[float] = []  # median stamp step per merge, for the rate

    def add(self, stamps: np.ndarray, log_time: np.ndarray, order: np.ndarray, values: np.ndarray) -> None:
        perm = arrival_order(log_time, order)
        stamps, values = stamps[perm], values[perm]
        back = stamp_steps_back(stamps, self.max_stamp)
        worst = int(np.argmax(back)) if len(back) else 0
        if len(back) and back[worst] > self.max_reorder_ns:
            raise DataError(
                f"{self.where}: non-monotonic stamps on {self.topic}: message {self.stats.messages + worst} "
                f"goes back {back[worst] / 1e9:.3f} s in arrival order (clock jump or reset?; "
                f"ingest.max_reorder_s = {self.max_reorder_ns / 1e9:g} s)"
            )
        self.stats.messages += len(stamps)
        self.stats.reordered += int((back > 0).sum())
        if len(stamps):
            top = int(stamps.max())
            self.max_stamp = top if self.max_stamp is None else max(self.max_stamp, top)
            delay = int((log_time[perm] - stamps).max())
            self.max_delay = delay if self.max_delay is None else max(self.max_delay, delay)
        if not self.discrete:
            finite = np.isfinite(values[:, : self.finite_columns]).all(axis=1)
            self.stats.nonfinite += int((~finite).sum())
            stamps, values = stamps[finite], values[finite]
        if self.written_upto is not None:
            # Arrived after the rows around its stamp were written (a stream that lagged beyond _STALL_S):
            # a time-base message is dropped, another one could not change those rows any more.
            late = stamps <= self.written_upto
            self.stats.late += int(late.sum())
            if self.time_base:
                stamps, values = stamps[~late], values[~late]
        if len(stamps):
            self._new.append((stamps, values))

    def horizon(self, log_time_now: int, max_reorder_ns: int) -> int | None:
        """Stamp below which no message of this stream can still arrive (None: unknown yet).

        New messages step back at most the reorder window from the largest stamp seen, and arrive no
        earlier than the latest log time read so far (minus the largest delay seen): the second bound
        keeps a silent stream (a discrete signal that did not change) from holding everything back.
        """
        if self.max_stamp is None or self.max_delay is None:
            return None
        return max(self.max_stamp, log_time_now - self.max_delay) - max_reorder_ns

    def buffered(self) -> int:
        """Number of messages held (before removing duplicates)."""
        return len(self.t) + sum(len(s) for s, _ in self._new)

    def merged(self) -> tuple[np.ndarray, np.ndarray]:
        """All buffered messages, sorted by stamp, duplicates dropped (first arrival kept)."""
        if self._new:
            t = np.concatenate([self.t, *(s for s, _ in self._new)])
            v = np.concatenate([self.v, *(v for _, v in self._new)])
            self._new = []
            self.t, self.v, dropped = sort_unique(t, v)
            self.stats.duplicates += dropped
        return self.t, self.v

    def trim(self, written_upto: int) -> None:
        """Forget what no later sample can need, once samples up to `written_upto` are written."""
        self.written_upto = written_upto
        if len(self.t) > 1:
            self._steps.append(float(np.median(np.diff(self.t))))
        if self.time_base:
            keep = self.t > written_upto
        elif self.discrete:
            last = np.searchsorted(self.t, written_upto, side="right") - 1
            keep = np.arange(len(self.t)) >= max(last, 0)
        else:
            keep = self.t >= written_upto - self.max_gap_ns
        if len(self.t):
            self.stats.first_stamp_ns = (
                int(self.t[0]) if self.stats.first_stamp_ns is None else self.stats.first_stamp_ns
            )
            self.stats.last_stamp_ns = (
                int(self.t[-1])
                if self.stats.last_stamp_ns is None
                else max(self.stats.last_stamp_ns, int(self.t[-1]))
            )
        self.t, self.v = self.t[keep], self.v[keep]

    def finish(self) -> StreamStats:
        if self._steps:
            self.stats.rate_hz = 1e9 / float(np.median(self._steps))
        return self.stats


# --- one log -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Want:
    """A topic that ingest reads: which stream, which type, required or not."""

    topic: str
    msgtype: str
    stream: str  # "joints", "wrench", "imu", "temperature", "true", "distorted", "oracle", "contacts"
    sensor: str | None
    required: bool


def wanted_topics(topics: TopicParams, sensors: Sequence[str]) -> list[_Want]:
    """Every topic ingest reads, from the topic templates and the URDF's FT sensors."""
    out = [_Want(topics.joint_states, rosmsg.JOINT_STATE, S.JOINTS_STREAM, None, True)]
    for s in sensors:
        out += [
            _Want(topics.sensor_topic("ft_wrench", s), rosmsg.WRENCH_STAMPED, S.WRENCH_STREAM, s, True),
            _Want(topics.sensor_topic("ft_imu", s), rosmsg.IMU, S.IMU_STREAM, s, False),
            _Want(
                topics.sensor_topic("ft_temperature", s), rosmsg.TEMPERATURE, S.TEMPERATURE_STREAM, s, False
            ),
            _Want(topics.sensor_topic("sim_wrench_true", s), rosmsg.WRENCH_STAMPED, S.TRUE, s, False),
            _Want(
                topics.sensor_topic("sim_wrench_distorted", s), rosmsg.WRENCH_STAMPED, S.DISTORTED, s, False
            ),
            _Want(topics.sensor_topic("sim_wrench_oracle", s), rosmsg.WRENCH_STAMPED, S.ORACLE, s, False),
        ]
    out.append(_Want(topics.sim_contacts, rosmsg.STRING, S.CONTACTS, None, False))
    return out


_TRUTH_STREAMS = (S.TRUE, S.DISTORTED, S.ORACLE, S.CONTACTS)


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


class _AtomicParquet:
    """A Parquet file written in row groups to a temp file in the same directory, renamed on commit."""

    def __init__(self, path: Path, arrow_schema: pa.Schema):
        self.path = path
        self.tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        self.schema = arrow_schema
        self._writer: pq.ParquetWriter | None = None
        self._pieces: list[pa.Table] = []
        self._rows = 0
        self.rows_written = 0

    def write(self, columns: Mapping[str, Any]) -> None:
        table = pa.Table.from_pydict(dict(columns), schema=self.schema)
        self._pieces.append(table)
        self._rows += table.num_rows
        if self._rows >= _ROW_GROUP_ROWS:
            self._flush()

    def _flush(self) -> None:
        if not self._pieces:
            return
        if self._writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = pq.ParquetWriter(self.tmp, self.schema, compression="zstd")
        self._writer.write_table(pa.concat_tables(self._pieces), row_group_size=max(self._rows, 1))
        self.rows_written += self._rows
        self._pieces, self._rows = [], 0

    def commit(self, metadata: Mapping[bytes, Any]) -> None:
        self._flush()
        if self._writer is None:  # no rows: still a valid, empty table
            self._writer = pq.ParquetWriter(self.tmp, self.schema, compression="zstd")
        self._writer.add_key_value_metadata(
            {
                k.decode(): v if isinstance(v, str) else json.dumps(v, sort_keys=True)
                for k, v in metadata.items()
            }
        )
        self._writer.close()
        os.replace(self.tmp, self.path)

    def abort(self) -> None:
        if self._writer is not None:
            with contextlib.suppress(Exception):  # the temp file goes anyway
                self._writer.close()
        self.tmp.unlink(missing_ok=True)


def read_table_metadata(path: str | Path) -> dict[str, Any]:
    """The ``ftcal.*`` key-value metadata of a Parquet table, JSON-decoded (schema and file footer)."""
    out: dict[str, Any] = {}
    meta = pq.ParquetFile(path).metadata.metadata or {}
    schema_meta = pq.read_schema(path).metadata or {}
    for key, value in {**schema_meta, **meta}.items():
        if key.startswith(b"ftcal."):
            out[key.decode()] = json.loads(value)
    return out


def output_name(log: Path, source_dir: Path) -> str:
    """Table name of a log: its path under the source directory, without suffix, '/' -> '__'."""
    rel = log.relative_to(source_dir).with_suffix("")
    return "__".join(rel.parts)


class _LogIngest:
    """Ingests one log: reads, aligns, writes (see the module docstring)."""

    def __init__(
        self,
        path: Path,
        out_dir: Path,
        name: str,
        cfg: IngestParams,
        topics: TopicParams,
        joints: Sequence[str],
        sensors: Sequence[str],
        robot_names: Iterable[str],
    ):
        self.path, self.out_dir, self.name, self.cfg = path, out_dir, name, cfg
        self.joints, self.sensors = list(joints), list(sensors)
        self.topics = topics
        self.robot_names = set(robot_names)
        self.robot_label = next(iter(robot_names), "?")
        self.where = str(path)
        self.report = LogReport(source=str(path))
        self._perm_cache: dict[tuple[str, ...], np.ndarray] = {}

    def warn(self, message: str) -> None:
        self.report.warnings.append(f"{self.path.name}: {message}")

    def run(self, progress: Callable[[int], None] | None = None) -> LogReport:
        t0 = time.perf_counter()
        with self._open_reader() as reader:
            self._check_experiment(reader.metadata)
            wants = self._resolve(reader)
            self._make_streams(wants)
            table, truth = self._open_outputs(reader, wants)
            try:
                for batches in reader.iter_chunks([w.topic for w in wants], progress=progress):
                    for batch in batches:
                        self._add(batch)
                    if self.streams[S.JOINTS_STREAM].buffered() >= _EMIT_ROWS:
                        self._emit(table, truth, final=False)
                self._emit(table, truth, final=True)
                self._check_counts()
                meta = self._final_metadata()
                table.commit({S.META_INGEST: meta})
                if truth is not None:
                    truth.commit({S.META_INGEST: meta})
            except BaseException:
                table.abort()
                if truth is not None:
                    truth.abort()
                raise
        self.report.output = str(table.path)
        self.report.truth_output = str(truth.path) if truth is not None else None
        self.report.seconds = time.perf_counter() - t0
        return self.report

    # -- setup --

    def _open_reader(self) -> Any:
        """The log's reader: MCAP, or a logger .mat file seen as the same topics (pipeline.logs.matreader)."""
        if self.path.suffix.lower() != MAT_SUFFIX:
            return rosmsg.LogReader(self.path)
        from pipeline.logs.matreader import MatLogReader

        if self.cfg.mat is None:
            raise ConfigError(f"{self.where}: a .mat log needs the name map ingest.mat in params")
        return MatLogReader(self.path, self.topics, self.sensors, self.cfg.mat, self.joints)

    def _check_experiment(self, metadata: Mapping[str, Mapping[str, str]]) -> None:
        self.experiment = dict(metadata.get("experiment", {}))
        if not self.experiment:
            self.warn("no 'experiment' metadata record (experiment type, robot and role unknown)")
            return
        robot = self.experiment.get("robot")
        if robot and robot not in self.robot_names and Path(robot).stem not in self.robot_names:
            self.warn(f"recorded on robot {robot!r}, but params robot.urdf is {self.robot_label!r}")

    def _resolve(self, reader: rosmsg.LogReader) -> list[_Want]:
        found = reader.topics
        wants, missing = [], []
        for want in wanted_topics(self.topics, self.sensors):
            info = found.get(want.topic)
            if info is None or info.message_count == 0:
                if want.required:
                    missing.append(want.topic)
                elif want.stream in (S.IMU_STREAM, S.TEMPERATURE_STREAM):
                    self.warn(f"no {want.topic}: its columns are NaN and flagged")
                continue
            if info.msgtype != want.msgtype:
                raise DataError(
                    f"{self.where}: topic {want.topic} has type {info.msgtype}, expected {want.msgtype}"
                )
            wants.append(want)
        if missing:
            more = f" (and {len(missing) - 3} more)" if len(missing) > 3 else ""
            raise DataError(f"{self.where}: missing required topic(s) {', '.join(missing[:3])}{more}")
        self.found_topics = {t: {"type": i.msgtype, "messages": i.message_count} for t, i in found.items()}
        self.report.messages = sum(found[w.topic].message_count for w in wants)
        self.has_truth = any(w.stream in _TRUTH_STREAMS for w in wants)
        return wants

    def _make_streams(self, wants: Sequence[_Want]) -> None:
        cfg = self.cfg
        gap = round(cfg.max_gap_s * 1e9)
        reorder = round(cfg.max_reorder_s * 1e9)
        widths = {
            S.JOINTS_STREAM: 3 * len(self.joints),
            S.WRENCH_STREAM: 6,
            S.IMU_STREAM: 6,
            S.TEMPERATURE_STREAM: 1,
            S.TRUE: 6,
            S.DISTORTED: 6,
            S.ORACLE: 6,
            S.CONTACTS: 1,
        }
        self.streams: dict[str, _Stream] = {}
        self.by_topic: dict[str, _Stream] = {}
        for w in wants:
            key = w.stream if w.sensor is None else f"{w.stream}.{w.sensor}"
            max_gap = round(cfg.max_gap_temperature_s * 1e9) if w.stream == S.TEMPERATURE_STREAM else gap
            time_base = w.stream == S.JOINTS_STREAM
            stream = _Stream(
                key,
                w.topic,
                w.msgtype,
                widths[w.stream],
                max_gap,
                self.where,
                reorder,
                discrete=(w.stream == S.CONTACTS),
                time_base=time_base,
                finite_columns=len(self.joints) if time_base else None,
            )
            self.streams[key] = stream
            self.by_topic[w.topic] = stream
        self.max_gap_ns = max(s.max_gap_ns for s in self.streams.values())

    def _open_outputs(
        self, reader: rosmsg.LogReader, wants: Sequence[_Want]
    ) -> tuple[_AtomicParquet, _AtomicParquet | None]:
        base_meta = {
            S.META_EXPERIMENT: self.experiment,
            b"ftcal.source": {
                "file": str(self.path),
                "name": self.path.name,
                "bytes": reader.size_bytes,
                "topics": self.found_topics,
                "metadata": reader.metadata,
            },
        }
        table = _AtomicParquet(
            self.out_dir / f"{self.name}{S.PARQUET_SUFFIX}",
            S.arrow_schema(S.ingested_columns(self.joints, self.sensors), S.KIND_INGESTED, base_meta),
        )
        truth = None
        if self.has_truth:
            truth = _AtomicParquet(
                self.out_dir / f"{self.name}{S.TRUTH_SUFFIX}{S.PARQUET_SUFFIX}",
                S.arrow_schema(S.truth_columns(self.sensors), S.KIND_TRUTH, base_meta),
            )
        self._first_stamp: int | None = None
        self.log_time_now = -(2**62)  # latest log time read so far, ns
        return table, truth

    # -- streaming --

    def _add(self, batch: rosmsg.Batch) -> None:
        stream = self.by_topic[batch.topic]
        f = batch.fields
        if stream.name == S.JOINTS_STREAM:
            values = self._joint_values(batch)
        elif batch.msgtype == rosmsg.WRENCH_STAMPED:
            values = f["wrench"]
        elif batch.msgtype == rosmsg.IMU:
            values = np.concatenate([f["linear_acceleration"], f["angular_velocity"]], axis=1)
        elif batch.msgtype == rosmsg.TEMPERATURE:
            values = f["temperature"].reshape(-1, 1)
        else:
            values = f["data"]
        stream.add(batch.stamp_ns, batch.log_time_ns, batch.order, values)
        if len(batch):
            self.log_time_now = max(self.log_time_now, int(batch.log_time_ns.max()))

    def _joint_values(self, batch: rosmsg.Batch) -> np.ndarray:
        """(K, 3J) [position | velocity | effort] in URDF joint order; NaN where the log has none."""
        names = batch.names or ()
        perm = self._perm_cache.get(names)
        if perm is None:
            perm, unknown, missing = joint_permutation(names, self.joints)
            if unknown:
                raise DataError(
                    f"{self.where}: {batch.topic} has joints not in the URDF: {', '.join(unknown[:5])}"
                    + (f" (and {len(unknown) - 5} more)" if len(unknown) > 5 else "")
                )
            if missing:
                raise DataError(
                    f"{self.where}: {batch.topic} lacks URDF joints: {', '.join(missing[:5])}"
                    + (f" (and {len(missing) - 5} more)" if len(missing) > 5 else "")
                )
            self._perm_cache[names] = perm
        k, n = len(batch), len(names)
        out = np.full((k, 3 * len(self.joints)), np.nan)
        for slot, key in enumerate(("position", "velocity", "effort")):
            arr = batch.fields[key]
            if arr.shape[1] == 0 and key != "position":
                continue
            if arr.shape[1] != n:
                raise DataError(
                    f"{self.where}: {batch.topic}: malformed JointState ({n} names, "
                    f"{arr.shape[1]} {key} values)"
                )
            out[:, slot * len(self.joints) : (slot + 1) * len(self.joints)] = arr[:, perm]
        return out

    def _emit(self, table: _AtomicParquet, truth: _AtomicParquet | None, final: bool) -> None:
        joints = self.streams[S.JOINTS_STREAM]
        js_t, js_v = joints.merged()
        if final:
            limit = None
        else:
            reorder = round(self.cfg.max_reorder_s * 1e9)
            lead = joints.horizon(self.log_time_now, reorder)
            if lead is None:
                return
            # Samples before every live stream's horizon (minus the max gap) are final; a stream that
            # lags the joint states by more than _STALL_S (stopped, or not started) holds nothing back.
            horizons = [
                h
                for s in self.streams.values()
                if (h := s.horizon(self.log_time_now, reorder)) is not None
                and h >= lead - round(_STALL_S * 1e9)
            ]
            limit = min(horizons) - self.max_gap_ns
        n = len(js_t) if limit is None else int(np.searchsorted(js_t, limit, side="left"))
        if n == 0:
            return
        target = js_t[:n]
        if self._first_stamp is None:
            self._first_stamp = int(target[0])
        nj = len(self.joints)
        cols: dict[str, Any] = {S.STAMP: target, S.TIME: (target - self._first_stamp) / 1e9}
        for slot, quantity in enumerate((S.Q, S.DQ_ENC, S.TAU_ENC)):
            block = js_v[:n, slot * nj : (slot + 1) * nj]
            for j, name in enumerate(S.joint_cols(quantity, self.joints)):
                cols[name] = block[:, j]
        truth_cols: dict[str, Any] = {S.STAMP: cols[S.STAMP], S.TIME: cols[S.TIME]}
        for s in self.sensors:
            for stream_kind, names in (
                (S.WRENCH_STREAM, S.wrench_cols(S.FT, s)),
                (S.IMU_STREAM, S.vector_cols(S.ACC, s) + S.vector_cols(S.GYR, s)),
                (S.TEMPERATURE_STREAM, [S.temperature_col(s)]),
            ):
                values, ok = self._aligned(f"{stream_kind}.{s}", target, len(names))
                cols.update({c: values[:, k] for k, c in enumerate(names)})
                cols[S.ok_col(stream_kind, s)] = ok
            for kind in S.TRUTH_KINDS:
                values, ok = self._aligned(f"{kind}.{s}", target, 6)
                truth_cols.update({c: values[:, k] for k, c in enumerate(S.wrench_cols(kind, s))})
                truth_cols[S.ok_col(kind, s)] = ok
        contacts = self.streams.get(S.CONTACTS)
        if contacts is not None:
            ct, cv = contacts.merged()
            truth_cols[S.CONTACTS] = align_latest(target, ct, cv)
        else:
            truth_cols[S.CONTACTS] = np.full(n, None, dtype=object)
        table.write(cols)
        if truth is not None:
            truth.write(truth_cols)
        written = int(target[-1])
        for stream in self.streams.values():
            stream.trim(written)
        self.report.samples += n

    def _aligned(self, key: str, target: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
        stream = self.streams.get(key)
        if stream is None:
            return np.full((len(target), width), np.nan), np.zeros(len(target), dtype=bool)
        t, v = stream.merged()
        return align_continuous(target, t, v, stream.max_gap_ns)

    # -- checks and metadata --

    def _check_counts(self) -> None:
        if self.report.samples < 2:
            raise DataError(
                f"{self.where}: {self.topics.joint_states} has fewer than 2 usable joint-state samples"
            )
        limit = self.cfg.max_nonfinite_fraction
        for stream in self.streams.values():
            st = stream.stats
            if st.nonfinite and st.nonfinite > limit * st.messages:
                raise DataError(
                    f"{self.where}: {st.topic} has NaN/inf values in {st.nonfinite} of {st.messages} "
                    f"messages (ingest.max_nonfinite_fraction = {limit:g})"
                )
            if st.nonfinite:
                self.warn(f"{st.topic}: {st.nonfinite} messages with NaN/inf values dropped")
            if st.late:
                self.warn(f"{st.topic}: {st.late} messages arrived after their rows were written")

    def _final_metadata(self) -> dict[str, Any]:
        streams = {}
        for key, stream in self.streams.items():
            st = stream.finish()
            self.report.streams[key] = st
            streams[st.topic] = asdict(st)
        return {
            "source": str(self.path),
            "samples": self.report.samples,
            "time_base": self.topics.joint_states,
            "joints": self.joints,
            "sensors": self.sensors,
            "streams": streams,
            "max_gap_s": self.cfg.max_gap_s,
            "max_gap_temperature_s": self.cfg.max_gap_temperature_s,
            "max_reorder_s": self.cfg.max_reorder_s,
            "warnings": self.report.warnings,
        }


def ingest_log(
    path: Path,
    out_dir: Path,
    name: str,
    cfg: IngestParams,
    topics: TopicParams,
    joints: Sequence[str],
    sensors: Sequence[str],
    robot_names: Iterable[str] = (),
    progress: Callable[[int], None] | None = None,
) -> LogReport:
    """Ingest one MCAP log into ``<out_dir>/<name>.parquet`` (+ ``<name>.truth.parquet`` if simulated).

    Raises DataError (naming the file and the problem) for a log that cannot be used; then no output
    file of this log is left behind.
    """
    return _LogIngest(path, out_dir, name, cfg, topics, joints, sensors, robot_names).run(progress)


# --- the stage -----------------------------------------------------------------------------------


@dataclass
class IngestSummary:
    """What one execution of the stage did."""

    reports: list[LogReport]
    skipped: list[LogReport]
    seconds: float

    @property
    def warnings(self) -> list[str]:
        out = [w for r in self.reports for w in r.warnings]
        return out + [f"skipped {r.source}: {r.error}" for r in self.skipped]


@contextmanager
def _progress_bar(enabled: bool) -> Iterator[Any]:
    if not enabled:
        yield None
        return
    from rich.console import Console
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        DownloadColumn(),
        TimeRemainingColumn(),
        console=Console(stderr=True),
        transient=True,
    ) as progress:
        yield progress


def find_logs(source_dir: Path) -> list[Path]:
    """Every *.mcap and *.mat (logger file) under `source_dir` (recursively), sorted."""
    return sorted(p for p in source_dir.rglob("*") if p.is_file() and p.suffix.lower() in LOG_SUFFIXES)


def run(
    params: Params, source_dir: str | Path, out_dir: str | Path, *, progress: bool | None = None
) -> IngestSummary:
    """Ingest every log under `source_dir` into `out_dir`, in one MLflow run."""
    from pipeline.core.tracking import stage_run
    from pipeline.physics.robot import load_robot

    cfg = stage_section(params, STAGE, IngestParams)
    source, out = Path(source_dir), Path(out_dir)
    if not source.is_dir():
        raise DataError(f"{source}: source directory not found")
    logs = find_logs(source)
    if not logs:
        raise DataError(f"{source}: no *.mcap or *.mat logs found")
    names = [output_name(log, source) for log in logs]
    if len(set(names)) != len(names):
        raise DataError(f"{source}: two logs map to the same table name")
    urdf = resolve_urdf(params.robot.urdf, repo_root())
    robot = load_robot(urdf)
    robot_names = [params.robot.urdf, robot.name, Path(urdf).stem]
    sensors = list(robot.sensors)
    show = sys.stderr.isatty() if progress is None else progress
    run_params = {
        "ingest": asdict(cfg),
        "topics": asdict(params.topics),
        "robot": {"urdf": params.robot.urdf},
    }
    t0 = time.perf_counter()
    reports: list[LogReport] = []
    skipped: list[LogReport] = []
    with stage_run(STAGE, run_params) as active, _progress_bar(show) as bar:
        import mlflow

        mlflow.set_tags({"source_dir": str(source), "out_dir": str(out), "logs": str(len(logs))})
        for log, name in zip(logs, names, strict=True):
            task = None if bar is None else bar.add_task(log.name, total=log.stat().st_size)
            advance = None if bar is None else (lambda n, task=task: bar.advance(task, n))
            try:
                reports.append(
                    ingest_log(
                        log, out, name, cfg, params.topics, robot.joint_names, sensors, robot_names, advance
                    )
                )
            except DataError as exc:
                if not cfg.skip_bad_logs:
                    mlflow.set_tag("error", str(exc)[:5000])
                    raise
                skipped.append(LogReport(source=str(log), error=str(exc)))
                print(f"ftcal: warning: skipping {exc}", file=sys.stderr)
            finally:
                if bar is not None and task is not None:
                    bar.remove_task(task)
        summary = IngestSummary(reports, skipped, time.perf_counter() - t0)
        _log_mlflow(active, summary)
    for warning in summary.warnings:
        if not warning.startswith("skipped "):
            print(f"ftcal: warning: {warning}", file=sys.stderr)
    if not reports:
        raise DataError(f"{source}: no usable log ({len(skipped)} skipped as bad)")
    return summary


def _log_mlflow(active: Any, summary: IngestSummary) -> None:
    import mlflow

    messages = sum(r.messages for r in summary.reports)
    samples = sum(r.samples for r in summary.reports)
    metrics = {
        "logs_ingested": len(summary.reports),
        "logs_skipped": len(summary.skipped),
        "messages": messages,
        "samples": samples,
        "seconds": summary.seconds,
        "warnings": len(summary.warnings),
        "messages_per_s": messages / summary.seconds if summary.seconds > 0 else 0.0,
    }
    flags = {"duplicates": 0, "reordered": 0, "nonfinite": 0, "late": 0}
    for report in summary.reports:
        for st in report.streams.values():
            for key in flags:
                flags[key] += getattr(st, key)
    metrics.update({f"messages_{k}": v for k, v in flags.items()})
    mlflow.log_metrics({k: float(v) for k, v in metrics.items()})
    mlflow.log_text("\n".join(summary.warnings) + ("\n" if summary.warnings else ""), "warnings.txt")
    mlflow.log_dict(
        {
            "logs": [
                {
                    "source": r.source,
                    "output": r.output,
                    "truth": r.truth_output,
                    "samples": r.samples,
                    "messages": r.messages,
                    "seconds": r.seconds,
                    "streams": {k: asdict(v) for k, v in r.streams.items()},
                }
                for r in summary.reports
            ],
            "skipped": [{"source": r.source, "error": r.error} for r in summary.skipped],
        },
        "ingest_summary.json",
    )


# --- CLI -----------------------------------------------------------------------------------------


def _cmd(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    summary = run(params, args.source, args.out)
    rows = sum(r.samples for r in summary.reports)
    print(
        f"ingested {len(summary.reports)} log(s), {rows} samples, into {args.out}"
        + (f"; skipped {len(summary.skipped)} bad log(s)" if summary.skipped else "")
        + f" ({summary.seconds:.1f} s)"
    )
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal ingest SOURCE OUT`."""
    parser = subparsers.add_parser(
        STAGE,
        help="decode MCAP logs into aligned Parquet tables",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument("source", type=Path, help="directory searched recursively for *.mcap and *.mat logs")
    parser.add_argument("out", type=Path, help="output directory for <log>.parquet (+ <log>.truth.parquet)")
    parser.add_argument(
        "--params",
        type=Path,
        default=None,
        metavar="PATH",
        help="params file (default: params.yaml at the repo root)",
    )
    parser.set_defaults(func=_cmd)
