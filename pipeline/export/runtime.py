"""Running an export on a log: the exported graphs, and causal inputs per raw wrench message.

`Deployment.load(DIR)` reads ``manifest.json`` and opens each group's float64 graph with onnxruntime
(files checked against their sha256), with the offsets of a re-zeroing beside it (``offsets.json``,
`pipeline.export.offsets`) fed to every graph's ``offsets`` input. `CausalCalibrator` turns the decoded
messages of a log, chunk by chunk, into calibrated wrenches: for every raw wrench message of a modelled
sensor, the temperature (and IMU) are those of the latest message stamped at or before the wrench's
header stamp, never a later one, as a robot's loop would have them; a board whose IMU axes training mapped
(``ingest.imu_axes``, the manifest's ``imu_axes``) is read through the same map. Messages may arrive out
of stamp order (transport delays), so the wrenches of one chunk are calibrated once the next chunk has been
read: a temperature delayed by less than a chunk (seconds) is still found. A wrench stamped before its
sensor's first temperature (or IMU) message has no input yet and is counted as uncalibrated.

Each sensor's output depends on its own inputs only (``separable`` in the manifest; true of every model
family here), so a group's graph is fed one sensor's messages in that sensor's slot (and the same rows
in the other slots, whose outputs are discarded).

A graph with memory (a ``state`` entry in the manifest: the play and arx models) is run on each sensor's
wrench messages in stamp order, one call per sensor and chunk, carrying that sensor's state columns from
chunk to chunk (a fresh state at the log's first message), so that every output depends on that message and
the earlier ones only. Every wrench message moves the state, also one without its temperature yet (its
output is not written: uncalibrated), as the training's memory moves with every reading. Filters (arx) are
refused on messages at another rate than their training logs' (`pipeline.export.check.check_rate`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import DataError
from pipeline.export.cbuild import c_runtime, default_runtime
from pipeline.export.check import check_rate, run, run_state, session
from pipeline.export.offsets import Offsets
from pipeline.logs.imu_axes import to_sensor_frame

WRENCH_FIELDS = tuple(f"wrench.{k}.{a}" for k in ("force", "torque") for a in "xyz")
IMU_FIELDS = tuple(f"linear_acceleration.{a}" for a in "xyz") + tuple(f"angular_velocity.{a}" for a in "xyz")
INPUT_FIELDS = (*WRENCH_FIELDS, "temperature", *IMU_FIELDS)  # the models' input order, per sensor
HISTORY = 64  # temperature/IMU messages kept from before the current chunks (the latest by stamp)


@dataclass(frozen=True)
class SensorPlan:
    """Where one modelled sensor's inputs come from and where its calibrated wrench goes."""

    sensor: str
    group: str
    slot: int  # the sensor's position in its group's graph
    n_inputs: int  # 6, 7 or 13
    wrench_topic: str
    temperature_topic: str | None  # 7- and 13-input models only
    imu_topic: str | None  # 13-input models only
    out_topic: str


@dataclass
class Deployment:
    """An export directory: its manifest, one onnxruntime session (float64 graph) per group, and the
    offsets every graph runs with (none: the calibration as delivered)."""

    path: Path
    manifest: dict[str, Any]
    sessions: dict[str, Any] = field(repr=False)
    offsets: Offsets = field(default_factory=Offsets)
    manifest_sha256: str = ""

    @property
    def robot(self) -> str:
        return str(self.manifest.get("robot") or "")

    def groups(self) -> dict[str, dict[str, Any]]:
        """group -> its graph entry (every graph but the fused one)."""
        fused = self.manifest.get("fused")
        return {g: e for g, e in self.manifest["graphs"].items() if g != fused}

    def sensors(self) -> list[str]:
        """Every sensor the export models, in the groups' order."""
        return [s for entry in self.groups().values() for s in entry["sensors"]]

    def serials(self) -> dict[str, str | None]:
        """Sensor -> the serial of the sensor its calibration was trained for (None: not recorded)."""
        return {s: v for entry in self.groups().values() for s, v in (entry.get("serials") or {}).items()}

    def imu_axes(self) -> dict[str, tuple[str, str, str] | None]:
        """Sensor -> its board's IMU axes that training mapped (`ingest.imu_axes`), applied to the board's
        readings before the graph (None: the board reads in the sensor frame)."""
        return {
            s: tuple(v) if v else None  # type: ignore[misc]
            for entry in self.groups().values()
            for s, v in (entry.get("imu_axes") or {}).items()
        }

    def with_offsets(self, offsets: Offsets) -> Deployment:
        """The same export and sessions, run with `offsets` (an empty `Offsets`: as delivered)."""
        from dataclasses import replace

        unknown = sorted(set(offsets.values) - set(self.sensors()))
        if unknown:
            raise DataError(f"{self.path}: offsets of {unknown[0]}, a sensor the export does not model")
        return replace(self, offsets=offsets)

    @classmethod
    def load(
        cls, path: str | Path, threads: int = 1, offsets: Path | bool = True, runtime: str | None = None
    ) -> Deployment:
        """Read `path`/manifest.json and open the float64 graphs with onnxruntime, or with `runtime` "c" their
        C calibrators (default `default_runtime`); `offsets`: True, those of `path`/offsets.json if it
        exists; False, none; a path, that file's (it must exist). Raises DataError naming the file."""
        from pipeline.export import offsets as O
        from pipeline.export.manifest import MANIFEST_FILE, read_manifest, sha256_file

        path = Path(path)
        file = path / MANIFEST_FILE
        if not path.is_dir():
            raise DataError(f"{path}: models directory not found (run `dvc repro`, or pass --models)")
        manifest = read_manifest(path)
        sessions: dict[str, Any] = {}
        deployment = cls(path, manifest, sessions, manifest_sha256=sha256_file(file))
        beside = path / O.FILE
        chosen = offsets if isinstance(offsets, Path) else (beside if offsets and beside.is_file() else None)
        if chosen is not None:
            deployment.offsets = O.read_offsets(chosen, deployment.manifest_sha256, deployment.sensors())
        for group, entry in deployment.groups().items():
            graph = path / entry["files"]["float64"]
            if (runtime or default_runtime()) == "c":  # the generated C calibrator beside the graph
                sessions[group] = c_runtime(graph.parent, entry)
                continue
            if not graph.is_file():
                raise DataError(f"{graph}: not found (listed in {file})")
            if sha256_file(graph) != entry["sha256"]["float64"]:
                raise DataError(f"{graph}: sha256 differs from {file}'s (file changed after export)")
            try:
                sessions[group] = session(graph, threads)
            except Exception as exc:  # noqa: BLE001 (onnxruntime raises its own types)
                raise DataError(f"{graph}: onnxruntime cannot load it: {str(exc).splitlines()[0]}") from None
        return deployment

    def plans(self, topics: Any) -> list[SensorPlan]:
        """One plan per sensor of the export, topics from the params' templates. DataError if a graph's
        inputs are not the per-sensor layout this command feeds (INPUT_FIELDS)."""
        out = []
        for group, entry in self.groups().items():
            training = entry["training"][group]
            n = int(training["inputs_per_sensor"])
            if not training.get("separable"):
                raise DataError(
                    f"{self.path}: {group}'s model is not separable by sensor; cannot run per message"
                )
            for slot, sensor in enumerate(entry["sensors"]):
                fields = [c["field"] for c in entry["inputs"][slot * n : (slot + 1) * n]]
                owners = {c["sensor"] for c in entry["inputs"][slot * n : (slot + 1) * n]}
                if tuple(fields) != INPUT_FIELDS[:n] or owners != {sensor}:
                    raise DataError(
                        f"{self.path}: inputs of {sensor} in {group}'s graph are {fields}, "
                        f"not {list(INPUT_FIELDS[:n])}"
                    )
                wrench = topics.sensor_topic("ft_wrench", sensor)
                out.append(
                    SensorPlan(
                        sensor,
                        group,
                        slot,
                        n,
                        wrench,
                        topics.sensor_topic("ft_temperature", sensor) if n >= 7 else None,
                        topics.sensor_topic("ft_imu", sensor) if n == 13 else None,
                        wrench + "_calibrated",
                    )
                )
        return out

    def state_columns(self, group: str) -> dict[int, list[int]] | None:
        """slot -> its columns of the group's graph's state (None: a memoryless graph)."""
        entry = self.groups()[group]
        if "state" not in entry:
            return None
        sensors = entry["sensors"]
        return {
            k: [c["index"] for c in entry["state"]["columns"] if c["sensor"] == s]
            for k, s in enumerate(sensors)
        }

    def predict(
        self, group: str, inputs: Mapping[int, np.ndarray], state: dict[int, np.ndarray] | None = None
    ) -> dict[int, np.ndarray]:
        """Calibrated wrenches {slot: (n_slot, 6)} of a group's sensors from their inputs {slot: (n_slot,
        n_inputs)}, float64, in one graph call: the slots' rows side by side (a slot with fewer rows, or
        none, repeats rows of another; separable models make their outputs irrelevant). A graph with memory
        takes each slot's rows as its consecutive samples, one call per slot, from `state` (slot -> its
        state columns, updated in place; None or a slot not in it: a fresh start)."""

        entry = self.groups()[group]
        n_slots = len(entry["sensors"])
        columns = self.state_columns(group)
        if columns is not None:
            out = {}
            for slot, x in inputs.items():
                if not len(x):
                    continue
                initial = np.full(int(entry["state"]["shape"][0]), np.nan)
                if state is not None and slot in state:
                    initial[columns[slot]] = state[slot]
                offsets = self.offsets.input_vector(entry)
                y, last = run_state(self.sessions[group], np.tile(x, n_slots), offsets, initial)
                out[slot] = y[:, slot * 6 : (slot + 1) * 6].astype(np.float64)
                if state is not None:
                    state[slot] = np.asarray(last, dtype=np.float64)[columns[slot]]
            return out
        rows = max(len(x) for x in inputs.values())
        filler = next(x for x in inputs.values() if len(x))
        columns = []
        for slot in range(n_slots):
            x = inputs.get(slot)
            x = filler if x is None or not len(x) else x
            columns.append(x[np.arange(rows) % len(x)])
        y = run(self.sessions[group], np.concatenate(columns, axis=1), self.offsets.input_vector(entry))
        return {
            slot: y[: len(x), slot * 6 : (slot + 1) * 6].astype(np.float64)
            for slot, x in inputs.items()
            if len(x)
        }


class _Stream:
    """Recent messages of one input stream: stamps (n,) int64 ns, values (n, k), sorted by stamp."""

    def __init__(self, width: int) -> None:
        self.stamp = np.empty(0, dtype=np.int64)
        self.value = np.empty((0, width))
        self.last = 0  # messages added by the latest chunk

    def add(self, stamp: np.ndarray, value: np.ndarray) -> None:
        """Append one chunk's messages; keep the latest (by stamp) previous chunk's count + HISTORY."""
        keep = min(len(self.stamp), self.last + HISTORY)
        stamps = np.concatenate([self.stamp[len(self.stamp) - keep :], stamp])
        values = np.concatenate([self.value[len(self.value) - keep :], value.reshape(len(stamp), -1)])
        order = np.argsort(stamps, kind="stable")
        self.stamp, self.value, self.last = stamps[order], values[order], len(stamp)

    def at(self, stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(values (m, k), found (m,)): the latest message stamped at or before each stamp."""
        k = np.searchsorted(self.stamp, stamps, side="right") - 1
        found = k >= 0
        return self.value[np.maximum(k, 0)], found


@dataclass
class Calibrated:
    """Calibrated wrenches of one sensor's raw messages: headers and times copied from the raw ones."""

    plan: SensorPlan
    stamp: np.ndarray  # (n,) int64 ns, header stamps
    log_time: np.ndarray  # (n,) int64 ns
    publish_time: np.ndarray  # (n,) int64 ns
    frame_id: np.ndarray  # (n,) object
    wrench: np.ndarray  # (n, 6) N, Nm


class CausalCalibrator:
    """Feeds decoded chunks; returns the calibrated wrenches of the previous chunk (module docstring)."""

    def __init__(self, deployment: Deployment, plans: Sequence[SensorPlan]) -> None:
        self.deployment = deployment
        self.plans = {p.wrench_topic: p for p in plans}
        self._temperature = {p.sensor: _Stream(1) for p in plans if p.temperature_topic}
        self._imu = {p.sensor: _Stream(6) for p in plans if p.imu_topic}
        self._by_topic: dict[str, tuple[str, str]] = {}
        for p in plans:
            if p.temperature_topic:
                self._by_topic[p.temperature_topic] = ("temperature", p.sensor)
            if p.imu_topic:
                self._by_topic[p.imu_topic] = ("imu", p.sensor)
        self._axes = deployment.imu_axes()  # boards whose IMU training saw mapped (ingest.imu_axes)
        self._pending: list[Any] = []
        self._states: dict[str, dict[int, np.ndarray]] = {
            p.group: {} for p in plans if deployment.state_columns(p.group) is not None
        }  # group -> slot -> its carried state (graphs with memory)
        self._rated: set[tuple[str, int]] = set()  # (group, slot) whose rate matched their filters'
        self.uncalibrated: dict[str, int] = {p.sensor: 0 for p in plans}
        self.calibrated: dict[str, int] = {p.sensor: 0 for p in plans}

    def topics(self) -> list[str]:
        return [*self.plans, *self._by_topic]

    def feed(self, batches: Iterable[Any]) -> list[Calibrated]:
        """Take one chunk's batches (`rosmsg.Batch`); return the previous chunk's calibrated wrenches."""
        wrenches = []
        fresh: dict[tuple[str, str], list[tuple[np.ndarray, np.ndarray]]] = {}
        for b in batches:
            if b.topic in self.plans:
                wrenches.append(b)
            elif b.topic in self._by_topic:
                kind, _ = key = self._by_topic[b.topic]
                if kind == "temperature":
                    value = b.fields["temperature"].reshape(-1, 1)
                else:  # in the sensor frame, as training read it
                    value = to_sensor_frame(
                        np.concatenate([b.fields["linear_acceleration"], b.fields["angular_velocity"]], 1),
                        self._axes.get(key[1]),
                    )
                fresh.setdefault(key, []).append((b.stamp_ns, value))
        for (kind, sensor), parts in fresh.items():
            stream = self._temperature[sensor] if kind == "temperature" else self._imu[sensor]
            stream.add(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]))
        ready, held = self._ready(self._pending, wrenches)
        out = self._calibrate(ready)
        self._pending = held + wrenches
        return out

    def _ready(self, pending: list[Any], incoming: list[Any]) -> tuple[list[Any], list[Any]]:
        """(the pending wrenches to calibrate now, those held for the next chunk): a sensor with memory's
        messages stamped at or after the earliest of its `incoming` ones wait, so that its state moves in
        stamp order across chunks (a message delayed past a chunk's end still comes in its turn)."""
        from dataclasses import replace

        horizon: dict[str, int] = {}
        for b in incoming:
            if len(b) and self.plans[b.topic].group in self._states:
                horizon[b.topic] = min(horizon.get(b.topic, b.stamp_ns.min()), int(b.stamp_ns.min()))
        ready, held = [], []
        for b in pending:
            later = b.stamp_ns >= horizon.get(b.topic, np.iinfo(np.int64).max)
            if not later.any():
                ready.append(b)
                continue
            for part, rows in ((ready, ~later), (held, later)):
                if rows.any():
                    part.append(replace(
                        b, log_time_ns=b.log_time_ns[rows], publish_time_ns=b.publish_time_ns[rows],
                        stamp_ns=b.stamp_ns[rows], order=b.order[rows],
                        fields={k: v[rows] for k, v in b.fields.items()},
                    ))  # fmt: skip
        return ready, held

    def flush(self) -> list[Calibrated]:
        """The calibrated wrenches of the last chunk fed."""
        out = self._calibrate(self._pending)
        self._pending = []
        return out

    def _calibrate(self, batches: Sequence[Any]) -> list[Calibrated]:
        """Calibrate wrench batches: their inputs, then one graph call per group (with memory: per sensor,
        its messages in stamp order, every one moving its state)."""
        todo: dict[str, list[tuple[Any, SensorPlan, np.ndarray, np.ndarray]]] = {}
        for b in batches:
            plan = self.plans[b.topic]
            parts, ok = [b.fields["wrench"]], np.ones(len(b), dtype=bool)
            if plan.temperature_topic:
                temperature, ok = self._temperature[plan.sensor].at(b.stamp_ns)
                parts.append(np.where(ok[:, None], temperature, np.nan))
            if plan.imu_topic:
                imu, ok_imu = self._imu[plan.sensor].at(b.stamp_ns)
                parts.append(np.where(ok_imu[:, None], imu, np.nan))
                ok &= ok_imu
            self.uncalibrated[plan.sensor] += int((~ok).sum())
            fed = np.ones(len(b), dtype=bool) if plan.group in self._states else ok
            if fed.any():
                todo.setdefault(plan.group, []).append((b, plan, ok, np.concatenate(parts, axis=1)[fed]))
        out = []
        for group, items in todo.items():
            y = self._run_group(group, items)
            for (b, plan, ok, _), rows in zip(items, y, strict=True):
                wrench = rows[ok] if group in self._states else rows  # with memory every row was fed
                self.calibrated[plan.sensor] += len(wrench)
                if not len(wrench):
                    continue
                times = (b.stamp_ns[ok], b.log_time_ns[ok], b.publish_time_ns[ok])
                out.append(Calibrated(plan, *times, b.fields["frame_id"][ok], wrench))
        return out

    def _run_group(self, group: str, items: Sequence[tuple[Any, SensorPlan, np.ndarray, np.ndarray]]) -> list:
        """Each item's outputs (its fed rows, in its order): one call for the group, or with memory one per
        slot on its rows sorted by stamp, from and into the slot's carried state."""
        inputs: dict[int, list[np.ndarray]] = {}
        stamps: dict[int, list[np.ndarray]] = {}
        for b, plan, _, x in items:
            inputs.setdefault(plan.slot, []).append(x)
            stamps.setdefault(plan.slot, []).append(b.stamp_ns)  # used with memory only: every row fed
        joined = {slot: np.concatenate(xs) for slot, xs in inputs.items()}
        if group not in self._states:
            y = self.deployment.predict(group, joined)
        else:
            period = self.deployment.groups()[group]["state"].get("period_s")
            for plan in {p.slot: p for _, p, _, _ in items}.values() if period else ():
                if (group, plan.slot) not in self._rated and check_rate(
                    plan.wrench_topic, np.concatenate(stamps[plan.slot]), float(period)
                ):
                    self._rated.add((group, plan.slot))
            order = {slot: np.argsort(np.concatenate(t), kind="stable") for slot, t in stamps.items()}
            sorted_y = self.deployment.predict(
                group, {slot: x[order[slot]] for slot, x in joined.items()}, self._states[group]
            )
            y = {}
            for slot, rows in sorted_y.items():
                y[slot] = np.empty_like(rows)
                y[slot][order[slot]] = rows
        taken: dict[int, int] = {}
        out = []
        for _, plan, _, x in items:
            k = taken.get(plan.slot, 0)
            taken[plan.slot] = k + len(x)
            out.append(y[plan.slot][k : k + len(x)])
        return out


def sensors_in_topics(template: str, topics: Iterable[str]) -> list[str]:
    """Sensor names whose topic of `template` (with {sensor}) is among `topics`."""
    head, _, tail = template.partition("{sensor}")
    return sorted(
        t[len(head) : len(t) - len(tail)]
        for t in topics
        if t.startswith(head)
        and t.endswith(tail)
        and len(t) > len(head) + len(tail)
        and "/" not in t[len(head) : len(t) - len(tail)]
    )


def check_robot(deployment: Deployment, metadata: Mapping[str, Mapping[str, str]], where: Path) -> None:
    """DataError if the log says it was recorded on another robot than the export's."""
    recorded = str((metadata.get("experiment") or {}).get("robot") or "")
    robot = deployment.robot
    if recorded and robot and recorded != robot and Path(recorded).stem != Path(robot).stem:
        raise DataError(
            f"{where}: recorded on robot {recorded!r}, but the models in {deployment.path} are of {robot!r}"
        )


def plan_log(reader: Any, deployment: Deployment, topics: Any) -> tuple[list[SensorPlan], list[str]]:
    """(the plans of the modelled sensors present in the log of `reader` (`LogReader`), warnings).

    DataError if the log cannot be calibrated by these models: another robot's, a modelled sensor of
    another serial than its calibration's (`pipeline.export.identity`), or a modelled sensor's
    temperature or IMU topic (an input of its model) missing or of another type, or no modelled sensor.
    """
    from pipeline.export.identity import check_serials
    from pipeline.logs.rosmsg import IMU, TEMPERATURE, WRENCH_STAMPED

    check_robot(deployment, reader.metadata, reader.path)
    present = {t: info for t, info in reader.topics.items() if info.message_count}
    plans, modelled = [], set()
    for plan in deployment.plans(topics):
        modelled.add(plan.sensor)
        if plan.wrench_topic not in present:
            continue
        for topic, msgtype in (
            (plan.wrench_topic, WRENCH_STAMPED),
            (plan.temperature_topic, TEMPERATURE),
            (plan.imu_topic, IMU),
        ):
            if topic is None:
                continue
            if topic not in present:
                need = f"its {plan.n_inputs}-input model ({plan.group})"
                raise DataError(f"{reader.path}: has {plan.wrench_topic} but no {topic}, an input of {need}")
            if present[topic].msgtype != msgtype:
                raise DataError(
                    f"{reader.path}: topic {topic} has type {present[topic].msgtype}, expected {msgtype}"
                )
        plans.append(plan)
    if not plans:
        raise DataError(
            f"{reader.path}: none of the sensors of {deployment.path} ({', '.join(sorted(modelled))}) has "
            f"messages on {topics.ft_wrench} (models of another robot, or other topic names?)"
        )
    serials = deployment.serials()
    experiment = reader.metadata.get("experiment")
    warnings = check_serials(
        {p.sensor: serials.get(p.sensor) for p in plans}, experiment, reader.path, deployment.path
    )
    others = sorted(set(sensors_in_topics(topics.ft_wrench, present)) - modelled)
    warnings += [f"{reader.path}: no model for {s}: its wrenches pass through uncalibrated" for s in others]
    return plans, warnings


def calibrated_messages(
    deployment: Deployment, reader: Any, topics: Any
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Sensor -> (stamps (n,) int64 ns, calibrated wrenches (n, 6) N/Nm) of every raw wrench message of a
    modelled sensor in the log of `reader` that has causal inputs, sorted by stamp (`ftcal calibrate`'s
    values, without writing a copy)."""
    plans, _ = plan_log(reader, deployment, topics)
    calibrator = CausalCalibrator(deployment, plans)
    parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for batches in reader.iter_chunks(calibrator.topics()):
        for c in calibrator.feed(batches):
            parts.setdefault(c.plan.sensor, []).append((c.stamp, c.wrench))
    for c in calibrator.flush():
        parts.setdefault(c.plan.sensor, []).append((c.stamp, c.wrench))
    out = {}
    for sensor, chunks in parts.items():
        t = np.concatenate([c[0] for c in chunks])
        order = np.argsort(t, kind="stable")
        out[sensor] = (t[order], np.concatenate([c[1] for c in chunks])[order])
    return out
