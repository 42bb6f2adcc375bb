"""One MCAP log -> one aligned Parquet table (plus the simulated truth apart), streamed.

Every wanted topic (`wanted_topics`: the joint states, per FT sensor its wrench, IMU and temperature, and
the simulator's truth) is decoded chunk by chunk (`pipeline.logs.mcap_read`) and aligned on the
joint-state header stamps, which are the time base of the log (one row per joint-state sample, columns in
`pipeline.logs.schema`; alignment rules in `pipeline.logs.align`). The table is written in row groups,
so memory stays bounded whatever the log's length: a sample is written once every stream has passed it
by more than the reorder window and the max gap.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.core.config import TopicParams
from pipeline.core.errors import DataError
from pipeline.logs import rosmsg
from pipeline.logs import schema as S
from pipeline.logs.align import Stream, StreamStats, align_continuous, align_latest, joint_permutation
from pipeline.logs.imu_axes import to_sensor_frame
from pipeline.logs.readers import open_log
from pipeline.logs.segments import SplitTables
from pipeline.logs.sidecar import declared_absent, describe_absent
from pipeline.logs.tables import AtomicParquet, LogReport

if TYPE_CHECKING:
    from pipeline.logs.params import IngestParams

_EMIT_ROWS = 2_000  # time-base samples buffered before aligning and writing them
_STALL_S = 5.0  # a stream this far behind the joint states no longer holds the others back (s)

# --- one log -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Want:
    """A topic that ingest reads: which stream, which type, required or not."""

    topic: str
    msgtype: str
    # "joints", "wrench", "imu", "temperature", "true", "distorted", "oracle", "external", "contacts"
    stream: str
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
            _Want(topics.sensor_topic("sim_wrench_external", s), rosmsg.WRENCH_STAMPED, S.EXTERNAL, s, False),
        ]
    out.append(_Want(topics.sim_contacts, rosmsg.STRING, S.CONTACTS, None, False))
    return out


_TRUTH_STREAMS = (S.TRUE, S.DISTORTED, S.ORACLE, S.EXTERNAL, S.CONTACTS)


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
        self._delay_ns: int | None = None  # joint states' median (log time - stamp), ns
        self._restamped: set[str] = set()

    def warn(self, message: str) -> None:
        self.report.warnings.append(f"{self.path.name}: {message}")

    def run(self, progress: Callable[[int], None] | None = None) -> LogReport:
        t0 = time.perf_counter()
        with self._open_reader() as reader:
            for warning in getattr(reader, "warnings", []):
                self.warn(warning)
            self._check_experiment(reader.metadata)
            wants = self._resolve(reader)
            self._make_streams(wants)
            table, truth = self._open_outputs(reader, wants)
            try:
                for batches in reader.iter_chunks([w.topic for w in wants], progress=progress):
                    self._add_chunk(batches)
                    if self.streams[S.JOINTS_STREAM].buffered() >= _EMIT_ROWS:
                        self._emit(table, truth, final=False)
                self._emit(table, truth, final=True)
                self._check_counts()
                table.check()
                meta = self._final_metadata()
                table.commit({S.META_INGEST: meta})
                if truth is not None:
                    truth.commit({S.META_INGEST: meta})
            except BaseException:
                table.abort()
                if truth is not None:
                    truth.abort()
                raise
        self.report.output = str(table.tables[0].path)
        self.report.outputs = [str(t.path) for t in table.tables]
        self.report.kept = sum(table.rows)
        self.report.truth_output = str(truth.tables[0].path) if truth is not None else None
        self.report.seconds = time.perf_counter() - t0
        return self.report

    # -- setup --

    def _open_reader(self) -> Any:
        """The log's reader (pipeline.logs.readers: MCAP, logger .mat, dataDumper run)."""
        return open_log(self.path, self.cfg, self.topics, self.sensors, self.joints)

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
        declared = declared_absent(reader.metadata)
        absent = [j for j in declared["joints"] if j in self.joints]
        fixed = self.cfg.fixed_joints  # joints the log lacks that the lab declared still: filled, not absent
        self.fixed = {j: math.radians(v) for j, v in fixed.items() if j in absent}
        self.absent_joints = [j for j in absent if j not in self.fixed]
        self.report.fixed = sorted(self.fixed)
        self.report.absent += declared["streams"]
        self.report.not_read = declared["not_read"]
        wants, missing = [], []
        lacking: dict[str, list[str]] = {}  # stream kind -> sensors without it
        for want in wanted_topics(self.topics, self.sensors):
            info = found.get(want.topic)
            if info is None or info.message_count == 0:
                if want.required and want.topic not in declared["topics"]:
                    missing.append(want.topic)
                elif want.stream in (S.IMU_STREAM, S.TEMPERATURE_STREAM, S.WRENCH_STREAM):
                    lacking.setdefault(want.stream, []).append(str(want.sensor))
                continue
            if info.msgtype != want.msgtype:
                raise DataError(
                    f"{self.where}: topic {want.topic} has type {info.msgtype}, expected {want.msgtype}"
                )
            wants.append(want)
        if missing:
            more = f" (and {len(missing) - 3} more)" if len(missing) > 3 else ""
            raise DataError(f"{self.where}: missing required topic(s) {', '.join(missing[:3])}{more}")
        for entry, warning in describe_absent(lacking, self.sensors, self.topics):
            self.report.absent.append(entry)
            self.warn(warning)
        self.found_topics = {t: {"type": i.msgtype, "messages": i.message_count} for t, i in found.items()}
        self.report.messages = sum(found[w.topic].message_count for w in wants)
        self.has_truth = any(w.stream in _TRUTH_STREAMS for w in wants)
        return wants

    def _make_streams(self, wants: Sequence[_Want]) -> None:
        cfg = self.cfg
        gap = round(cfg.max_gap_s * 1e9)
        reorder = round(cfg.max_reorder_s * 1e9)
        widths = {S.JOINTS_STREAM: 3 * len(self.joints), S.TEMPERATURE_STREAM: 1, S.CONTACTS: 1}
        widths.update(dict.fromkeys((S.WRENCH_STREAM, S.IMU_STREAM, *S.TRUTH_KINDS), 6))
        self.streams: dict[str, Stream] = {}
        self.by_topic: dict[str, Stream] = {}
        present = [k for k, j in enumerate(self.joints) if j not in set(self.absent_joints)]
        frozen = round(cfg.max_frozen_s * 1e9)
        for w in wants:
            key = w.stream if w.sensor is None else f"{w.stream}.{w.sensor}"
            max_gap = round(cfg.max_gap_temperature_s * 1e9) if w.stream == S.TEMPERATURE_STREAM else gap
            time_base = w.stream == S.JOINTS_STREAM
            stream = Stream(
                key,
                w.topic,
                w.msgtype,
                widths[w.stream],
                max_gap,
                self.where,
                reorder,
                discrete=(w.stream == S.CONTACTS),
                time_base=time_base,
                finite_columns=np.array(present) if time_base else None,
                max_frozen_ns=frozen if w.stream == S.WRENCH_STREAM else None,
            )
            self.streams[key] = stream
            self.by_topic[w.topic] = stream
        # a sample is written once every stream is this far past it: the widest gap bridged, and the span
        # after which a run of identical readings is known to be frozen
        self.max_gap_ns = max(s.max_gap_ns + (s.max_frozen_ns or 0) for s in self.streams.values())

    def _open_outputs(
        self, reader: rosmsg.LogReader, wants: Sequence[_Want]
    ) -> tuple[SplitTables, SplitTables | None]:
        """The table (and truth) writers: the whole log, or one table per segment of the experiment."""
        source = {
            "file": str(self.path),
            "name": self.path.name,
            "bytes": reader.size_bytes,
            "topics": self.found_topics,
            "metadata": reader.metadata,
        }

        def opener(kind: str, columns: list[str], suffix: str) -> Callable[[str, dict], AtomicParquet]:
            def open_table(name: str, experiment: dict) -> AtomicParquet:
                meta = {S.META_EXPERIMENT: experiment, S.META_SOURCE: source}
                path = self.out_dir / f"{name}{suffix}{S.PARQUET_SUFFIX}"
                return AtomicParquet(path, S.arrow_schema(columns, kind, meta))

            return open_table

        columns = S.ingested_columns(self.joints, self.sensors)
        where = str(self.path)
        table = SplitTables(self.name, self.experiment, opener(S.KIND_INGESTED, columns, ""), where)
        truth = None
        if self.has_truth:
            truth_open = opener(S.KIND_TRUTH, S.truth_columns(self.sensors), S.TRUTH_SUFFIX)
            truth = SplitTables(self.name, self.experiment, truth_open, where)
        self._first_stamp: int | None = None
        self.log_time_now = -(2**62)  # latest log time read so far, ns
        return table, truth

    # -- streaming --

    def _add_chunk(self, batches: Sequence[rosmsg.Batch]) -> None:
        """Add the batches of one chunk, each stream's at once (one arrival order across its batches)."""
        parts: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]] = {}
        for batch in batches:
            if len(batch):
                stream = self.by_topic[batch.topic]
                values = self._values(stream, batch)
                parts.setdefault(stream.name, []).append(
                    (batch.stamp_ns, batch.log_time_ns, batch.order, values)
                )
                self.log_time_now = max(self.log_time_now, int(batch.log_time_ns.max()))
        for key in sorted(parts, key=lambda k: k != S.JOINTS_STREAM):  # the time base first
            stamps, log_time, order, values = (np.concatenate(x) for x in zip(*parts[key], strict=True))
            stream = self.streams[key]
            zero = stamps == 0
            stream.stats.zero_stamps += int(zero.sum())
            if zero.all() and self.cfg.unstamped_fallback and not stream.time_base:
                stamps = log_time - self._time_base_delay(stream)
            elif stream.time_base and self._delay_ns is None:
                self._delay_ns = int(np.median(log_time - stamps))
            stream.add(stamps, log_time, order, values)

    def _time_base_delay(self, stream: Stream) -> int:
        """ns: the joint states' median (log time - stamp), for a stream re-stamped with its log time."""
        delay = 0 if self._delay_ns is None else self._delay_ns
        if stream.topic not in self._restamped:
            self._restamped.add(stream.topic)
            self.warn(
                f"{stream.topic}: every header stamp is zero (the driver does not stamp): using its log "
                f"time minus {delay / 1e9:.4f} s, the joint states' median delay (ingest.unstamped_fallback)"
            )
        return delay

    def _values(self, stream: Stream, batch: rosmsg.Batch) -> np.ndarray:
        """(K, width) values of a batch for its stream (object (K,) for the contacts)."""
        f = batch.fields
        if stream.name == S.JOINTS_STREAM:
            return self._joint_values(batch)
        if batch.msgtype == rosmsg.WRENCH_STAMPED:
            return f["wrench"]
        if batch.msgtype == rosmsg.IMU:  # a board whose axes ingest.imu_axes maps: in the sensor frame
            axes = self.cfg.imu_axes.get(stream.name.removeprefix(S.IMU_STREAM + "."))
            return to_sensor_frame(
                np.concatenate([f["linear_acceleration"], f["angular_velocity"]], axis=1), axes
            )
        if batch.msgtype == rosmsg.TEMPERATURE:
            return f["temperature"].reshape(-1, 1)
        return f["data"]

    def _joint_values(self, batch: rosmsg.Batch) -> np.ndarray:
        """(K, 3J) [position | velocity | effort] in URDF joint order; NaN where the log has none."""
        names = batch.names or ()
        perm = self._perm_cache.get(names)
        if perm is None:
            perm, unknown, missing = joint_permutation(names, self.joints)
            missing = [j for j in missing if j not in set(self.absent_joints) and j not in self.fixed]
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
            block = np.where(perm >= 0, arr[:, perm] if n else np.nan, np.nan)  # absent joints: NaN
            out[:, slot * len(self.joints) : (slot + 1) * len(self.joints)] = block
        for joint, position in self.fixed.items():  # declared still: its position, no velocity
            out[:, [self.joints.index(joint), len(self.joints) + self.joints.index(joint)]] = [position, 0.0]
        return out

    def _emit(self, table: SplitTables, truth: SplitTables | None, final: bool) -> None:
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
                if (stream := self.streams.get(f"{stream_kind}.{s}")) is not None:
                    frozen = stream.frozen_at(target) & ok
                    ok &= ~frozen
                    values[frozen] = np.nan
                    stream.stats.frozen_samples += int(frozen.sum())
                    stream.stats.usable_samples += int(ok.sum())
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
            if st.frozen_samples:
                sensor = stream.name.split(".", 1)[1]
                self.report.frozen[sensor] = st.frozen_samples
                share = st.frozen_samples / self.report.samples
                self.warn(
                    f"{st.topic}: frozen (identical readings for over ingest.max_frozen_s = "
                    f"{self.cfg.max_frozen_s:g} s) on {st.frozen_samples} samples ({share:.1%}): flagged"
                )
            wrench = stream.name.startswith(S.WRENCH_STREAM + ".")
            if wrench and st.usable_samples == 0 and not st.frozen_samples:
                raise DataError(f"{self.where}: {st.topic}: no usable sample ({self._why_unusable(st)})")
            if st.nonfinite and st.nonfinite > limit * st.messages:
                raise DataError(
                    f"{self.where}: {st.topic} has NaN/inf values in {st.nonfinite} of {st.messages} "
                    f"messages (ingest.max_nonfinite_fraction = {limit:g})"
                )
            if st.nonfinite:
                self.warn(f"{st.topic}: {st.nonfinite} messages with NaN/inf values dropped")
            if st.late:
                self.warn(f"{st.topic}: {st.late} messages arrived after their rows were written")

    def _why_unusable(self, st: StreamStats) -> str:
        if st.messages and st.zero_stamps == st.messages:
            return (
                "every header stamp is zero: the driver does not stamp; ingest.unstamped_fallback: true "
                "uses the log times instead"
            )
        if st.messages == st.nonfinite:
            return "every message holds NaN/inf values"
        return (
            f"no message within ingest.max_gap_s = {self.cfg.max_gap_s:g} s of a "
            f"{self.topics.joint_states} stamp: its stamps are on another clock, or it has too few messages"
        )

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
            **{k: getattr(self.cfg, k) for k in ("max_gap_s", "max_gap_temperature_s", "max_reorder_s")},
            "warnings": self.report.warnings,
            "absent": self.report.absent,
            "not_read": self.report.not_read,
            "fixed_joints": {j: self.cfg.fixed_joints[j] for j in self.report.fixed},  # deg, declared
            "frozen_samples": self.report.frozen,
            "max_frozen_s": self.cfg.max_frozen_s,
            "imu_axes": {s: list(axes) for s, axes in self.cfg.imu_axes.items() if s in self.sensors},
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
    """Ingest one log (MCAP, logger .mat, dataDumper run) into ``<out_dir>/<name>.parquet`` (+
    ``<name>.truth.parquet`` if simulated), or one table per segment of its experiment metadata
    (`pipeline.logs.segments`).

    Raises DataError (naming the file and the problem) for a log that cannot be used; then no output
    file of this log is left behind.
    """
    log = _LogIngest(path, out_dir, name, cfg, topics, joints, sensors, robot_names)
    return log.run(progress)
