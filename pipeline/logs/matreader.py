"""A YarpRobotLoggerDevice ``.mat`` log read as the topics of the MCAP contract.

`MatLogReader` offers what ingest uses of `rosmsg.LogReader` (``path``, ``size_bytes``, ``metadata``,
``topics``, ``iter_chunks``): each quantity is found in the file through the name map of params
(`MatParams`, section ``ingest.mat``) and handed out as the `rosmsg.Batch` of the contract topic it
stands for (``topics.*`` of params), so that a .mat log goes through exactly the alignment and checks of
an MCAP log. Per URDF FT sensor: the wrench (required), the FT-board temperature and the FT-board IMU
(accelerometer and gyroscope samples with equal stamps; optional). Joint positions are the time base,
with the logger's own velocities and torques matched to them by stamp (NaN where a sample lacks them).

A logger sample has no receive time apart from its stamp (the logger loop's clock at the start of the
iteration), so log time = stamp, and the file order is the sample order.

The experiment metadata (the MCAP ``experiment`` record: type, robot, role, contacts, window, segments...)
comes from a YAML sidecar beside the .mat (``<stem>.yaml``, `pipeline.logs.sidecar`); without ``robot``
the file's ``yarp_robot_name`` is used.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.config import MatParams, TopicParams
from pipeline.logs import rosmsg
from pipeline.logs.matlog import Leaf, MatLog, iter_windows
from pipeline.logs.sidecar import read_sidecar

CHUNK_ROWS = 3_000  # joint-state samples per chunk handed out (30 s at 100 Hz): memory stays bounded


def sidecar_path(path: Path, suffix: str) -> Path:
    """The experiment metadata file of a .mat log: same stem, `suffix` (e.g. '.yaml')."""
    return path.with_suffix(suffix)


def joint_name_differences(file_joints: Sequence[str], urdf_joints: Sequence[str]) -> str | None:
    """None if the names agree as sets; else a one-line description of the differences."""
    unknown = [j for j in file_joints if j not in set(urdf_joints)]
    missing = [j for j in urdf_joints if j not in set(file_joints)]
    if not unknown and not missing:
        return None

    def listing(names: list[str]) -> str:
        return ", ".join(names[:8]) + (f" (and {len(names) - 8} more)" if len(names) > 8 else "")

    parts = []
    if unknown:
        parts.append(f"not in the URDF: {listing(unknown)}")
    if missing:
        parts.append(f"URDF joints missing from the file: {listing(missing)}")
    return "; ".join(parts)


@dataclass
class _Source:
    """One contract topic and the channels it is read from."""

    topic: str
    msgtype: str
    leaves: dict[str, Leaf]  # field -> channel
    count: int = 0
    extra: dict[str, Any] = field(default_factory=dict)


class MatLogReader:
    """A logger .mat file seen as contract topics (see the module docstring). DataError on bad input.

    `joints`: the URDF joints that the file's description_list must name (None: no check, as for
    conversion). `sensors`: the URDF FT sensors whose channels are wanted.
    """

    def __init__(
        self,
        path: str | Path,
        topics: TopicParams,
        sensors: Sequence[str],
        cfg: MatParams,
        joints: Sequence[str] | None = None,
        chunk_rows: int = CHUNK_ROWS,
    ):
        self.path = Path(path)
        self.chunk_rows = int(chunk_rows)
        self.warnings: list[str] = []
        # before opening: cheap check first
        experiment = read_sidecar(sidecar_path(self.path, cfg.sidecar_suffix), self.path)
        self._log = MatLog(self.path)
        try:
            self.size_bytes = self._log.size_bytes
            if joints is not None:
                diff = joint_name_differences(self._log.joints, joints)
                if diff:
                    raise self._log.error(f"joint names of {self._log.root}/description_list: {diff}")
            if not experiment.get("robot") and self._log.robot_name:
                experiment["robot"] = self._log.robot_name
            self._sources = self._resolve(topics, sensors, cfg)
        except BaseException:
            self._log.close()
            raise
        self.metadata = {
            "experiment": experiment,
            "mat": {
                "format": self._log.format,
                "root": self._log.root,
                "yarp_robot_name": self._log.robot_name or "",
                "channels": {
                    s.topic: ",".join(leaf.channel for leaf in s.leaves.values()) for s in self._sources
                },
            },
        }
        self.topics = {
            s.topic: rosmsg.TopicInfo(s.topic, s.msgtype, s.count) for s in self._sources if s.count
        }

    # -- channel resolution --

    def _first(self, candidates: Iterable[str]) -> Leaf | None:
        """The first candidate channel present (possibly empty), else None."""
        for channel in candidates:
            leaf = self._log.leaf(channel)
            if leaf is not None:
                return leaf
        return None

    def _check_width(self, leaf: Leaf, width: int) -> None:
        if len(leaf) and leaf.width != width:
            raise self._log.error(
                f"channel {leaf.channel} has {leaf.width} values per sample, expected {width}"
            )

    def _resolve(self, topics: TopicParams, sensors: Sequence[str], cfg: MatParams) -> list[_Source]:
        log = self._log
        positions = log.leaf(cfg.joint_positions)
        if positions is None or not len(positions):
            state = "is empty" if positions is not None else "is missing (ingest.mat.joint_positions)"
            raise log.error(f"joint-position channel {cfg.joint_positions} {state}")
        self._check_width(positions, len(log.joints))
        leaves = {"position": positions}
        for key, name in (("velocity", cfg.joint_velocities), ("effort", cfg.joint_torques)):
            leaf = log.leaf(name)
            if leaf is not None and len(leaf):
                self._check_width(leaf, len(log.joints))
                leaves[key] = leaf
        self.time_base = positions
        out = [_Source(topics.joint_states, rosmsg.JOINT_STATE, leaves, len(positions))]
        for s in sensors:
            tried = cfg.channels("ft", s)
            ft = self._first(tried)
            if ft is None or not len(ft):
                group = tried[0].rsplit("/", 1)[0] if "/" in tried[0] else ""
                has = ", ".join(log.children(group)) or "none"
                problem = (
                    f"is empty ({ft.channel})" if ft is not None else f"not found (tried {', '.join(tried)})"
                )
                raise log.error(f"FT channel of sensor {s} {problem}; {group or 'the file'} has: {has}")
            self._check_width(ft, 6)
            out.append(
                _Source(topics.sensor_topic("ft_wrench", s), rosmsg.WRENCH_STAMPED, {"wrench": ft}, len(ft))
            )
            temp = self._first(cfg.channels("temperature", s))
            if temp is not None and len(temp):
                self._check_width(temp, 1)
                out.append(
                    _Source(
                        topics.sensor_topic("ft_temperature", s),
                        rosmsg.TEMPERATURE,
                        {"temperature": temp},
                        len(temp),
                    )
                )
            acc = self._first(cfg.channels("accelerometer", s))
            gyr = self._first(cfg.channels("gyroscope", s))
            if acc is not None and gyr is not None and len(acc) and len(gyr):
                self._check_width(acc, 3)
                self._check_width(gyr, 3)
                common = _common_count(acc.stamps_ns, gyr.stamps_ns)
                imu = {"linear_acceleration": acc, "angular_velocity": gyr}
                out.append(_Source(topics.sensor_topic("ft_imu", s), rosmsg.IMU, imu, common))
        return out

    # -- reading --

    def iter_chunks(
        self, topics: Iterable[str] | None = None, *, progress: Callable[[int], None] | None = None, **_: Any
    ) -> Iterator[list[rosmsg.Batch]]:
        """Yield the wanted topics' batches, chunk by chunk: every channel cut at the same stamps, one cut
        every `chunk_rows` joint-state samples, so at most one chunk of each channel is in memory."""
        wanted = set(self.topics) if topics is None else set(topics)
        sources = [s for s in self._sources if s.topic in wanted and s.count]
        edges = self.time_base.stamps_ns[self.chunk_rows :: self.chunk_rows]
        windows = {
            (id(s), key): iter_windows(leaf.stamps_ns, edges)
            for s in sources
            for key, leaf in s.leaves.items()
        }
        done = 0
        for k in range(len(edges) + 1):
            batches = []
            for s in sources:
                rows = {key: next(windows[(id(s), key)]) for key in s.leaves}
                batch = self._batch(s, rows)
                if batch is not None and len(batch):
                    batches.append(batch)
            yield batches
            if progress is not None:
                now = self.size_bytes * (k + 1) // (len(edges) + 1)
                progress(now - done)
                done = now

    def _batch(self, source: _Source, rows: Mapping[str, tuple[int, int]]) -> rosmsg.Batch | None:
        leaves = source.leaves
        main = next(iter(leaves))  # the field whose stamps the topic's messages carry
        a, b = rows[main]
        stamps = leaves[main].stamps_ns[a:b]
        fields = {main: leaves[main].read(a, b)}
        names = None
        if source.msgtype == rosmsg.JOINT_STATE:
            names = tuple(self._log.joints)
            for key in ("velocity", "effort"):
                if key in leaves:
                    fields[key] = _matched(leaves[key], rows[key], stamps)
                else:
                    fields[key] = np.empty((len(stamps), 0))
        elif source.msgtype == rosmsg.IMU:
            gyr = leaves["angular_velocity"]
            ga, gb = rows["angular_velocity"]
            gyr_stamps = gyr.stamps_ns[ga:gb]
            if not np.array_equal(stamps, gyr_stamps):  # equal when both were read at every instant
                keep = np.isin(stamps, gyr_stamps)
                stamps, fields[main] = stamps[keep], fields[main][keep]
            fields["angular_velocity"] = _matched(gyr, (ga, gb), stamps)
        elif source.msgtype == rosmsg.TEMPERATURE:
            fields[main] = fields[main].reshape(-1)
        order = np.arange(a, a + len(stamps), dtype=np.int64)
        return rosmsg.Batch(source.topic, source.msgtype, stamps, stamps, stamps, order, fields, names)

    def close(self) -> None:
        self._log.close()

    def __enter__(self) -> MatLogReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _common_count(a: np.ndarray, b: np.ndarray) -> int:
    """Number of distinct stamps in both `a` and `b` (int64 ns)."""
    if np.array_equal(a, b) and (len(a) < 2 or (np.diff(a) > 0).all()):
        return len(a)
    return len(np.intersect1d(a, b))


def _matched(leaf: Leaf, rows: tuple[int, int], stamps: np.ndarray) -> np.ndarray:
    """(len(stamps), k) values of `leaf` at exactly these stamps, from its rows [a, b); NaN where none."""
    a, b = rows
    own = leaf.stamps_ns[a:b]
    values = leaf.read(a, b)
    if np.array_equal(own, stamps):
        return values
    out = np.full((len(stamps), leaf.width), np.nan)
    if len(own) == 0:
        return out
    idx = np.clip(np.searchsorted(own, stamps), 0, len(own) - 1)
    hit = own[idx] == stamps
    out[hit] = values[idx[hit]]
    return out
