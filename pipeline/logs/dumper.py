"""A YARP dataDumper run read as the topics of the MCAP contract (format: the reference and
docs/recorded-logs.md).

A run is a folder of port folders, one per dumped port, each with ``info.log`` and ``data.log``: the
dumper's own layout ``<run>/<robot>/<part>/<port>/`` (one robot prefix folder, e.g. ``icub``), or folders
the recorder named (``rightLegFT/``, ``rightLegPos/``), at any depth. What a folder holds is the port that
its info.log names (``/icub/right_leg/analog:o``: robot prefix ``icub``, part ``right_leg``, port
``analog:o``), never its folder name; a folder of the dumper's layout whose info.log names none (a port
that never connected) is taken as its path says. `DumperRunReader` offers what ingest uses of
`rosmsg.LogReader` (``path``, ``size_bytes``, ``metadata``, ``topics``, ``iter_chunks``), through the maps
of ``ingest.dumper`` (`DumperParams`):

- each FT part's ``analog:o`` port -> the wrench topic of its URDF sensor (stamped by the sender);
- the control boards' joint ports (the first of ``ingest.dumper.joint_ports`` a board has with data:
  ``stateExt:o``, or ``state:o`` with positions only) -> one joint-state topic. The first part of
  ``ingest.dumper.time_base`` present in the run is the time base: each of its messages is one
  joint-state message, and every other board's positions (velocities, torques) are interpolated at its
  stamp within ``ingest.max_gap_s`` (`pipeline.logs.align.align_continuous`, after dropping their
  duplicate stamps). A time-base message with no position of another board within that gap is dropped
  and counted (the time base then has a gap, as for a lost message). Degrees become radians; a board's
  velocities and torques that its port does not carry are NaN.

Arrival order: the reception time where the dumper wrote one (two-time form), else the file order, so
stamps stepping back in a file are re-sorted or are a clock jump, exactly as for an MCAP log.

A port folder without ``data.log`` (or with an empty one), or a URDF FT sensor with no port in the run, is
an absent stream: the ``recording`` metadata record (`pipeline.logs.sidecar`) names it, ingest leaves its
columns NaN and flagged and names it in its summary. Joints of absent boards are NaN. What a run holds
beside the contract's ports is not read and named once in the ingest summary (the record's ``not_read``):
ports that no map names (a skin board's ``/icub/right_leg/inertialMTB``, an estimator's
``/wholeBodyDynamics/...`` or ``/QuaternionEKF/...`` outputs), and folders of a port that never connected
(no port in their info.log, no data); ``ingest.dumper.ignore`` leaves a part, port or folder out without
naming it. Two folders holding one port, contract ports of two robot prefixes, are errors, as are bad lines
(`pipeline.logs.dumper_text`) and a folder with data whose info.log names no port. The experiment metadata
comes from the sidecar ``<run>.yaml`` beside the run folder.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.config import TopicParams
from pipeline.core.errors import ConfigError, DataError
from pipeline.logs import rosmsg
from pipeline.logs.align import align_continuous, sort_unique
from pipeline.logs.dumper_text import PortData, read_analog, read_info, read_joint_port
from pipeline.logs.matlog import iter_windows
from pipeline.logs.params import DumperParams
from pipeline.logs.sidecar import ENCODERS, RECORDING, absent_record, encoders_record, read_sidecar
from pipeline.logs.smoothing import quantisation_step

DATA, INFO = "data.log", "info.log"
CHUNK_ROWS = 3_000  # time-base messages per chunk handed out


def _is_port(folder: Path) -> bool:
    return (folder / INFO).is_file() or (folder / DATA).is_file()


def port_folders(run: Path) -> list[Path]:
    """The port folders under `run` (not itself), sorted: folders holding info.log or data.log, and
    folders holding no folder (a port that never wrote anything), at any depth."""
    out, stack = [], [run]
    while stack:
        folder = stack.pop()
        subs = sorted((d for d in folder.iterdir() if d.is_dir()), reverse=True)
        if folder != run and (_is_port(folder) or not subs):
            out.append(folder)
            continue
        stack.extend(subs)
    return sorted(out)


def is_run(path: Path, sidecar_suffix: str = ".yaml") -> bool:
    """Whether `path` is a dataDumper run: a folder (not a port folder) holding port folders at any depth
    with the experiment sidecar ``<run><sidecar_suffix>`` beside it, or in the dumper's layout: a folder
    ``<robot>/<part>/<port>`` whose info.log names that very port."""
    if not path.is_dir() or _is_port(path):
        return False
    if sidecar_of(path, sidecar_suffix).is_file() and any(_is_port(p) for p in path.rglob("*") if p.is_dir()):
        return True
    return any(
        read_info(info)["port"] == "/" + info.parent.relative_to(path).as_posix()
        for info in path.glob(f"*/*/*/{INFO}")
    )


def sidecar_of(run: Path, suffix: str) -> Path:
    """The experiment sidecar of a run: ``<run><suffix>`` beside the run folder."""
    return run.with_name(run.name + suffix)


@dataclass
class _Port:
    robot: str
    part: str
    port: str
    folder: Path
    info: dict[str, str]

    @property
    def name(self) -> str:
        return f"{self.part}/{self.port}"

    @property
    def data(self) -> Path | None:
        return _data(self.folder)


def _data(folder: Path) -> Path | None:
    """A port folder's data.log, None where it has none or an empty one (the port never sent)."""
    path = folder / DATA
    return path if path.is_file() and path.stat().st_size > 0 else None


class DumperRunReader:
    """A dataDumper run seen as contract topics (see the module docstring). DataError on bad input.

    `sensors` / `joints`: the URDF's FT sensors and joints.
    """

    def __init__(
        self,
        path: str | Path,
        topics: TopicParams,
        sensors: Sequence[str],
        cfg: DumperParams,
        joints: Sequence[str],
        chunk_rows: int = CHUNK_ROWS,
        max_gap_s: float = 0.025,
    ):
        self.path = Path(path)
        self.cfg, self.topic_names, self.chunk_rows = cfg, topics, int(chunk_rows)
        self.max_gap_ns = round(max_gap_s * 1e9)
        self.warnings: list[str] = []
        self.steps: dict[str, float] = {}  # joint -> encoder step on its own board's readings, rad
        self.not_read: list[str] = []  # what the run holds beside the contract's ports
        experiment = read_sidecar(sidecar_of(self.path, cfg.sidecar_suffix), self.path)
        ports = self._ports()
        self.size_bytes = sum(p.data.stat().st_size for p in ports if p.data is not None)
        absent_streams = [p.name for p in ports if p.data is None]
        self.wrenches, absent_topics = self._wrenches(ports, sensors, absent_streams)
        state_ports = self._joint_map(ports, joints)
        if not self.wrenches:
            raise DataError(f"{self.path}: no FT port ({cfg.ft_port}) with a {DATA} (the run has no wrench)")
        if not state_ports:
            raise DataError(
                f"{self.path}: no control-board port ({', '.join(cfg.joint_ports)}) with a {DATA}"
            )
        rank = {part: k for k, part in enumerate(cfg.time_base)}
        state_ports.sort(key=lambda p: rank.get(p[0].part, len(rank)))
        if state_ports[0][0].part not in rank:
            have = ", ".join(p[0].part for p in state_ports)
            raise DataError(
                f"{self.path}: none of the boards of ingest.dumper.time_base ({', '.join(cfg.time_base)}) "
                f"has a {DATA} (boards with one: {have})"
            )
        self.time_base = state_ports[0][0].name
        self.joint_names = [name for _, _, names in state_ports for name in names]  # the columns' order
        self.dropped_rows = 0  # time-base messages without another board's positions
        self.joint_rows = self._joint_states(state_ports)
        absent_joints = [j for j in joints if j not in set(self.joint_names)]
        kept = {p.part: p.name for p in ports if p.port in cfg.joint_ports}  # the run's joint port per part
        by_stream = {  # each absent board -> its joints, so that labels name the stream they lack
            kept.get(part, f"{part}/{cfg.joint_ports[0]}"): [j for j in axes if j in set(absent_joints)]
            for part, axes in cfg.joints.items()
            if any(j in set(absent_joints) for j in axes)
        }
        self.metadata = {
            "experiment": experiment,
            RECORDING: absent_record(absent_topics, absent_joints, absent_streams, by_stream, self.not_read),
            ENCODERS: encoders_record(self.steps),
            "dumper": {
                "robot": ports[0].robot if ports else "",
                "time_base": self.time_base,
                "time_base_dropped": self.dropped_rows,
                "ports": {p.name: self._port_info(p) for p in ports},
            },
        }
        self.sources = [(topics.joint_states, rosmsg.JOINT_STATE, self.joint_rows)] + [
            (topics.sensor_topic("ft_wrench", s), rosmsg.WRENCH_STAMPED, d) for s, d in self.wrenches.items()
        ]
        self.topics = {t: rosmsg.TopicInfo(t, m, len(d.stamp_ns)) for t, m, d in self.sources}

    # -- layout --

    def _identify(self, folder: Path) -> _Port | None:
        """The port a folder holds, from its info.log (else from the dumper's layout); None: ignored."""
        info = read_info(folder / INFO)
        rel = folder.relative_to(self.path).as_posix()
        name = info["port"] or (f"/{rel}" if len(rel.split("/")) == 3 else "")
        if rel in self.cfg.ignore:
            return None
        if not name and _data(folder) is None:
            self.not_read.append(f"{rel} (never connected)")
            return None
        if not name:
            raise DataError(
                f"{folder}: its {INFO} names no port, so what it holds is unknown (ingest.dumper.ignore "
                "skips a folder)"
            )
        elements = name.strip("/").split("/")
        if not all(elements):
            raise DataError(f"{folder}: port {name!r} of its {INFO} is not /<robot>/<part>/<port>")
        if len(elements) < 3:  # not a robot's port (an estimator's output, /<module>/<port>)
            self.not_read.append(name)
            return None
        *robot, part, port = elements
        if part in self.cfg.ignore or f"{part}/{port}" in self.cfg.ignore:
            return None
        return _Port("/".join(robot), part, port, folder, info)

    def _ports(self) -> list[_Port]:
        """Every port the maps name, sorted by part and port; the others are listed in `not_read`. Two
        folders of one port and ports of two robot prefixes are errors."""
        cfg, out = self.cfg, {}
        for folder in port_folders(self.path):
            p = self._identify(folder)
            if p is None:
                continue
            wanted = (p.port == cfg.ft_port and p.part in cfg.ft_ports) or (
                p.port in cfg.joint_ports and p.part in cfg.joints
            )
            if not wanted:  # a port no map names: named once in the summary, not read
                self.not_read.append(f"/{p.robot}/{p.name}")
                continue
            if p.name in out:
                raise DataError(f"{self.path}: {out[p.name].folder} and {folder} both hold port {p.name}")
            out[p.name] = p
        robots = sorted({p.robot for p in out.values()})
        if len(robots) > 1:
            raise DataError(
                f"{self.path}: a dataDumper run holds one robot's ports, found: {', '.join(robots)}"
            )
        return [out[k] for k in sorted(out, key=lambda k: (out[k].part, out[k].port))]

    def _wrenches(
        self, ports: Sequence[_Port], sensors: Sequence[str], absent: list[str]
    ) -> tuple[dict[str, PortData], list[str]]:
        cfg, out = self.cfg, {}
        found = {p.part: p for p in ports if p.port == cfg.ft_port}
        for part, port in found.items():
            sensor = cfg.ft_ports[part]
            if sensor not in sensors:
                raise ConfigError(
                    f"{port.folder}: ingest.dumper.ft_ports.{part}: {sensor!r} is not an FT sensor of the "
                    f"URDF (have: {', '.join(sensors)})"
                )
            if port.data is not None:
                data = read_analog(port.data)
                self.warnings += data.warnings
                if len(data):
                    out[sensor] = data
        part_of = {s: p for p, s in cfg.ft_ports.items()}
        absent_topics = []
        for sensor in sensors:
            if sensor not in out:
                absent_topics.append(self.topic_names.sensor_topic("ft_wrench", sensor))
                if part_of.get(sensor) not in found:
                    absent.append(f"{sensor} (no {part_of.get(sensor, '?')}/{cfg.ft_port})")
        return out, absent_topics

    def _joint_map(self, ports: Sequence[_Port], joints: Sequence[str]) -> list:
        """[(port, axis indices, URDF joint names)] of the boards with data, in the map's order."""
        cfg = self.cfg
        found: dict[str, _Port] = {}
        for name in cfg.joint_ports:  # each board's first joint port with data
            for p in ports:
                if p.port == name and p.data is not None:
                    found.setdefault(p.part, p)
        out = []
        for part, axes in cfg.joints.items():
            if part not in found:
                continue
            for k, joint in enumerate(axes):
                if joint is not None and joint not in set(joints):
                    raise ConfigError(
                        f"{found[part].folder}: ingest.dumper.joints.{part}[{k}]: {joint!r} is not a joint "
                        "of the URDF"
                    )
            idx = [k for k, j in enumerate(axes) if j is not None]
            out.append((found[part], idx, [axes[k] for k in idx]))
        return out

    def _joint_states(self, state_ports: list) -> PortData:
        """The time base's messages with every board's joints (see the module docstring)."""
        port, idx, names = state_ports[0]
        base = read_joint_port(port.data, len(self.cfg.joints[port.part]), port.info["stamp"])
        self.warnings += base.warnings
        values = {k: [v[:, idx]] for k, v in base.values.items()}
        self._find_steps(names, values["position"][0])
        keep = np.ones(len(base), dtype=bool)
        for other, other_idx, other_names in state_ports[1:]:
            data = read_joint_port(other.data, len(self.cfg.joints[other.part]), other.info["stamp"])
            self.warnings += data.warnings
            order = np.lexsort((np.arange(len(data)), data.recv_ns))  # arrival order, then first kept
            stamps, rows, dropped = sort_unique(data.stamp_ns[order], np.arange(len(data))[order])
            if dropped:
                self.warnings.append(f"{other.data}: {dropped} messages with an already seen stamp dropped")
            self._find_steps(other_names, data.values["position"][rows][:, other_idx])
            for key, v in data.values.items():
                aligned, ok = align_continuous(base.stamp_ns, stamps, v[rows][:, other_idx], self.max_gap_ns)
                if key == "position":
                    keep &= ok
                values[key].append(aligned)
            if not keep.any():
                raise DataError(
                    f"{other.data}: no message within ingest.max_gap_s of a {self.time_base} stamp "
                    "(its stamps are on another clock?)"
                )
        self.dropped_rows = int((~keep).sum())
        if self.dropped_rows:
            self.warnings.append(
                f"{port.data}: {self.dropped_rows} of {len(keep)} time-base messages dropped: another board "
                "had no joint positions within ingest.max_gap_s of them"
            )
        merged = {k: np.concatenate(v, axis=1)[keep] for k, v in values.items()}
        return PortData(port.data, base.stamp_ns[keep], base.recv_ns[keep], merged, base.two_times)

    def _find_steps(self, names: Sequence[str], positions: np.ndarray) -> None:
        """Each joint's encoder step on its board's own readings (rad, `quantisation_step`), where found."""
        for k, name in enumerate(names):
            step = quantisation_step(positions[:, k])
            if step > 0:
                self.steps[name] = step

    def _port_info(self, port: _Port) -> dict[str, Any]:
        return {"type": port.info["type"], "port": port.info["port"], "data": port.data is not None}

    # -- reading --

    def iter_chunks(
        self, topics: Iterable[str] | None = None, *, progress: Callable[[int], None] | None = None, **_: Any
    ) -> Iterator[list[rosmsg.Batch]]:
        """The wanted topics' batches, every stream cut at the same stamps (one cut every `chunk_rows`
        time-base messages)."""
        wanted = set(self.topics) if topics is None else set(topics)
        edges = np.sort(self.joint_rows.stamp_ns)[self.chunk_rows :: self.chunk_rows]
        sources = [s for s in self.sources if s[0] in wanted]
        # cut in file order where stamps step back a little (re-sorted by ingest), by stamp otherwise
        windows = [iter_windows(np.maximum.accumulate(d.stamp_ns), edges) for _, _, d in sources]
        done = 0
        for k in range(len(edges) + 1):
            batches = []
            for (topic, msgtype, data), win in zip(sources, windows, strict=True):
                a, b = next(win)
                if b > a:
                    batches.append(self._batch(topic, msgtype, data, a, b))
            yield batches
            if progress is not None:
                now = self.size_bytes * (k + 1) // (len(edges) + 1)
                progress(now - done)
                done = now

    def _batch(self, topic: str, msgtype: str, data: PortData, a: int, b: int) -> rosmsg.Batch:
        stamps, recv = data.stamp_ns[a:b], data.recv_ns[a:b]
        order = np.arange(a, b, dtype=np.int64)
        fields = {k: v[a:b] for k, v in data.values.items()}
        names = tuple(self.joint_names) if msgtype == rosmsg.JOINT_STATE else None
        return rosmsg.Batch(topic, msgtype, recv, recv, stamps, order, fields, names)

    def close(self) -> None:
        pass

    def __enter__(self) -> DumperRunReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
