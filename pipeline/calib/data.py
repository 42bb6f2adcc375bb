"""A sensor group's samples: reading the labelled tables, whole-log split, errors against exact labels.

Split: logs whose ``ftcal.experiment`` metadata says ``role: test`` are the test set; ``train.val_logs``
training logs are held out as validation, whole logs, chosen by a seeded draw that takes at most one log
per experiment kind (type, foot, part) and never a kind's last training log (the same for every group);
the cross-validation folds (``train.folds``) hold out the next logs of the same kinds.

Samples: a sample is used when every input stream of the group's sensors is ok (wrench, temperature, IMU:
the same samples for every model); training keeps those with at least one switch set (the others
contribute nothing to the loss). Errors are computed where the label is exact: a sensor's where its switch
is 1, a foot's sum where ``sw.<pair>`` is 1. ``rmse_labelled`` pools the squared errors of all of a group's
exact labels (sensor parts and sum) and decides validation; ``rmse`` is the headline (the sensor's, or the
foot's sum, as the thesis reports).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.calib.cuts import CutTerm, cut_sums_np
from pipeline.calib.params import GroupParams
from pipeline.calib.scores import wrench_errors
from pipeline.core.config import Params
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.lowpass import lowpass_memory, memory_of, nominal_period
from pipeline.logs import schema as S

ROLE_TRAIN, ROLE_TEST = "train", "test"
FEET = "feet"  # in a group's sensors: every foot sensor of the robot (pipeline.physics.feet)
SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class Group:
    """What a group trains: its sensors (1, a foot's front and rear, or several coupled by cut sets), for a
    foot the transforms, for several sensors the cut sets among them (`pipeline.calib.cuts`)."""

    name: str
    sensors: tuple[str, ...]
    pair: str | None = None
    transforms: np.ndarray | None = None  # (S, 6, 6) sole_X_sensor, row-major, force first
    cuts: tuple[CutTerm, ...] = ()
    n_inputs: int = 13  # inputs per sensor of the group's largest network: 7 needs no IMU
    tested: tuple[str, ...] | None = None  # the sensors with exact labels of their own on the test logs
    left_out: tuple[tuple[str, str], ...] = ()  # (sensor, why) of the sensors without any exact label
    widths: tuple[tuple[float, ...], ...] | None = None  # the play model's widths (K, 6), None: no play model
    time_constants: tuple[float, ...] | None = None  # the arx model's filters (J,) s, None: no arx model
    windows: tuple[float, ...] | None = None  # the windowed network's time constants (J,) s, None: none

    @property
    def headlines(self) -> tuple[str, ...]:
        """The names whose errors are the group's headlines: the sensor, or the foot's sum; for several
        sensors, each sensor in no foot pair (a leg, an iCub 2.x foot) with exact labels of its own on the
        test logs (`tested`, where known), then each foot pair's sum."""
        if self.pair is not None:
            return (self.pair,)
        if len(self.sensors) == 1:
            return (self.sensors[0],)
        pairs = [c for c in self.cuts if c.pair is not None]
        in_pair = {self.sensors[m] for c in pairs for m in c.members}
        own = [s for s in self.sensors if s not in in_pair and (self.tested is None or s in self.tested)]
        return (*own, *(c.label for c in pairs)) or (self.sensors[0],)

    @property
    def headline(self) -> str:
        """The first headline."""
        return self.headlines[0]


def input_cols(sensor: str, n_inputs: int = 13) -> list[str]:
    """Input columns of one sensor's network (6, 7 or 13), in the order of `pipeline.calib.models`."""
    cols = [*S.wrench_cols(S.FT, sensor)] + ([S.temperature_col(sensor)] if n_inputs >= 7 else [])
    if n_inputs == 13:
        cols += S.vector_cols(S.ACC, sensor) + S.vector_cols(S.GYR, sensor)
    return cols


def _ok_cols(sensor: str) -> list[str]:
    return [S.ok_col(stream, sensor) for stream in (S.WRENCH_STREAM, S.TEMPERATURE_STREAM, S.IMU_STREAM)]


@dataclass
class GroupData:
    """Samples of a group whose inputs are all ok: arrays over N samples and S sensors.

    x (N, S, 13) raw inputs; labels (N, S, 6) N/Nm, NaN where the switch is 0; switches (N, S) bool;
    sum_label (N, 6) and sum_switch (N,) bool (``sw.<pair>``) for a foot, else None; log (N,) index into
    the log names; stamp (N,) ns; time (N,) s. The float arrays but time hold float32 values (`_read_log`).
    """

    log: np.ndarray
    stamp: np.ndarray
    time: np.ndarray
    x: np.ndarray
    labels: np.ndarray
    switches: np.ndarray
    sum_label: np.ndarray | None = None
    sum_switch: np.ndarray | None = None
    cut_labels: np.ndarray | None = None  # (N, C, 6) cut-set sums, NaN where the switch is 0
    cut_switches: np.ndarray | None = None  # (N, C) bool
    poses: np.ndarray | None = None  # (N, P, 12) the cut sets' moving members' poses (CutTerm)
    memory: np.ndarray | None = None  # (N, S, 6 K + 6 J) the play and arx models' memory (`memory_of`)
    period: np.ndarray | None = None  # (N,) s the sample period of each sample's log (with memory)
    window: np.ndarray | None = None  # (N, S, 6 J) the windowed network's filter outputs (`lowpass_memory`)

    def __len__(self) -> int:
        return len(self.log)

    def subset(self, mask: np.ndarray) -> GroupData:
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        return GroupData(**{k: None if v is None else v[mask] for k, v in values.items()})

    @property
    def alpha_sum(self) -> np.ndarray | None:
        """Switch of the sum term, eq. 5.12: sw_pair (1 - prod_s sw_s)."""
        if self.sum_switch is None:
            return None
        return self.sum_switch & ~self.switches.all(axis=1)

    def cut_alpha(self, cuts: Sequence[CutTerm]) -> np.ndarray | None:
        """(N, C) bool switches of the cut-set terms: sw_cut (1 - prod_{s in cut} sw_s), as eq. 5.12."""
        if self.cut_switches is None:
            return None
        every = np.stack([self.switches[:, list(c.members)].all(axis=1) for c in cuts], axis=1)
        return self.cut_switches & ~every

    def labelled(self) -> np.ndarray:
        """(N,) bool: samples with at least one term in the loss."""
        mask = self.switches.any(axis=1)
        if self.cut_switches is not None:
            mask = mask | self.cut_switches.any(axis=1)
        return mask | self.alpha_sum if self.sum_switch is not None else mask


@dataclass(frozen=True)
class LogInfo:
    name: str  # the table's file name without .parquet
    path: Path
    role: str  # train | test
    kind: str  # experiment type[/foot[/part]], e.g. half_foot/l_foot/front
    known_load: bool = False  # the experiment declares known loads (pipeline.physics.loads)
    simulated: bool = False  # the simulator wrote it (experiment ``sim: true``): a log with truth
    span: tuple[float, float] | None = None  # s of time_s: a time block of the table (`time_blocks`)


def find_logs(in_dir: Path) -> list[LogInfo]:
    """The labelled tables of `in_dir` with their role and experiment type, sorted by name."""
    if not in_dir.is_dir():
        raise DataError(f"{in_dir}: labelled directory not found")
    paths = sorted(in_dir.glob(f"*{S.PARQUET_SUFFIX}"))
    if not paths:
        raise DataError(f"{in_dir}: no labelled *.parquet tables")
    logs = []
    for path in paths:
        try:
            schema = pq.read_schema(path)
        except (OSError, pa.ArrowException) as exc:
            raise DataError(f"{path}: cannot read Parquet table: {exc}") from None
        experiment = S.read_metadata(schema, S.META_EXPERIMENT) or {}
        role = str(experiment.get("role", "")).strip()
        if role not in (ROLE_TRAIN, ROLE_TEST):
            raise DataError(
                f"{path}: experiment metadata role must be {ROLE_TRAIN!r} or {ROLE_TEST!r}, got {role!r}"
            )
        # its kind: type, foot and part where given (balancing on the left foot loads it otherwise)
        kind = "/".join(
            str(experiment[k]) for k in ("type", "foot", "part") if str(experiment.get(k, "")).strip()
        )
        loaded = str(experiment.get("loads", "")).strip() not in ("", "[]")
        simulated = str(experiment.get("sim", "")).strip().lower() == "true"
        logs.append(LogInfo(path.name[: -len(S.PARQUET_SUFFIX)], path, role, kind, loaded, simulated))
    return logs


def expand_feet(gp: GroupParams, logs: Sequence[LogInfo]) -> GroupParams:
    """`gp` with `FEET` in its `sensors` replaced by every foot sensor of the labelled tables (their
    ``ftcal.label`` feet, by foot name, front before rear): the same group on any robot's feet."""
    if gp.sensors is None or FEET not in gp.sensors:
        return gp
    meta = S.read_metadata(pq.read_schema(logs[0].path), S.META_LABEL) or {}
    feet = meta.get("feet") or {
        name: {"sensors": [p["front"], p["rear"]]} for name, p in (meta.get("pairs") or {}).items()
    }
    names = [str(s) for _, foot in sorted(feet.items()) for s in foot.get("sensors", ())]
    if not names:
        where = f"{logs[0].path}: train.groups.{gp.name}.sensors"
        raise DataError(f"{where} names {FEET!r}, but the labelled tables know no foot")
    sensors = [n for s in gp.sensors for n in (names if s == FEET else [s])]
    return replace(gp, sensors=tuple(dict.fromkeys(sensors)))


def resolve_group(gp: GroupParams, params: Params, logs: Sequence[LogInfo]) -> Group:
    """The group `gp` trains, checked against the labelled tables (see `_resolve_group`)."""
    return replace(
        _resolve_group(gp, params, logs),
        n_inputs=max(gp.inputs),
        windows=gp.windowed(),
    )


def _resolve_group(gp: GroupParams, params: Params, logs: Sequence[LogInfo]) -> Group:
    """The sensors (and transforms) of a group, checked against robot.foot_pairs and the tables."""
    first = pq.read_schema(logs[0].path)
    names = set(first.names)
    key = f"train.groups.{gp.name}"
    if gp.sensor is not None:
        if S.wrench_cols(S.FT, gp.sensor)[0] not in names:
            have = ", ".join(S.sensors_of(first.names)) or "none"
            raise ConfigError(
                f"{key}.sensor: {gp.sensor!r} is not an FT sensor of the labelled tables (have: {have})"
            )
        return Group(gp.name, (gp.sensor,))
    if gp.sensors is not None:
        have = S.sensors_of(first.names)
        for sensor in gp.sensors:
            if sensor not in have:
                raise ConfigError(
                    f"{key}.sensors: {sensor!r} is not an FT sensor of the labelled tables (have: "
                    f"{', '.join(have) or 'none'})"
                )
        return Group(gp.name, gp.sensors, cuts=_cut_terms(gp.sensors, logs))
    pairs = _foot_pairs(params, logs)
    if gp.pair not in pairs:
        raise ConfigError(
            f"{key}.pair: {gp.pair!r} is not a foot pair of the robot (have: {', '.join(pairs) or 'none'})"
        )
    name, sensors = gp.pair, pairs[gp.pair]
    transforms = None
    for log in logs:
        meta = S.read_metadata(pq.read_schema(log.path), S.META_LABEL) or {}
        entry = (meta.get("pairs") or {}).get(name)
        try:
            t = np.array([entry["sole_X_front"], entry["sole_X_rear"]], dtype=np.float64).reshape(2, 6, 6)
        except (TypeError, KeyError, ValueError):
            raise DataError(
                f"{log.path}: metadata ftcal.label has no 6x6 pairs.{name}.sole_X_front/rear"
            ) from None
        if transforms is not None and not np.allclose(t, transforms, rtol=1e-9, atol=1e-12):
            raise DataError(f"{log.path}: pairs.{name} transforms differ from {logs[0].name}'s")
        transforms = t
    return Group(gp.name, sensors, name, transforms)


def _foot_pairs(params: Params, logs: Sequence[LogInfo]) -> dict[str, tuple[str, str]]:
    """The robot's foot pairs, name -> (front, rear): robot.foot_pairs of params, else those the labelled
    tables were labelled with (the pairs of the URDF's feet, metadata ``ftcal.label``)."""
    if params.robot.foot_pairs is not None:
        return {p.name: (p.front, p.rear) for p in params.robot.foot_pairs}
    meta = S.read_metadata(pq.read_schema(logs[0].path), S.META_LABEL) or {}
    return {str(k): (str(v["front"]), str(v["rear"])) for k, v in (meta.get("pairs") or {}).items()}


def _cut_terms(sensors: Sequence[str], logs: Sequence[LogInfo]) -> tuple[CutTerm, ...]:
    """The cut sets of the labelled metadata whose members are all among `sensors` (same in every log)."""
    entries = None
    for log in logs:
        meta = S.read_metadata(pq.read_schema(log.path), S.META_LABEL) or {}
        cuts = meta.get("cut_sets")
        if not isinstance(cuts, dict):
            raise DataError(f"{log.path}: metadata ftcal.label has no cut_sets (relabel with this version)")
        if entries is not None and cuts != entries:
            raise DataError(f"{log.path}: cut_sets metadata differs from {logs[0].name}'s")
        entries = cuts
    pair_labels = {c["label"] for c in entries.values() if c["label"] != S.cut_set_name(c["sensors"])}
    out = []
    for name, c in sorted(entries.items()):
        if not set(c["sensors"]) <= set(sensors):
            continue
        try:
            members = tuple(sensors.index(s) for s in c["sensors"])
            fixed = np.zeros((len(members), 6, 6))
            moving = []
            for k, s in enumerate(c["sensors"]):
                if s in c["X"]:
                    fixed[k] = c["signs"][s] * np.asarray(c["X"][s], dtype=np.float64).reshape(6, 6)
                else:
                    moving.append((k, float(c["signs"][s])))
            pose_cols = tuple(tuple(c["pose_columns"][c["sensors"][k]]) for k, _ in moving)
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(
                f"{logs[0].path}: metadata ftcal.label cut_sets.{name} is incomplete: {exc}"
            ) from None
        pair = c["label"] if c["label"] in pair_labels else None
        out.append(CutTerm(c["label"], members, fixed, tuple(moving), pose_cols, pair))
    return tuple(out)


def _input_ok(log: LogInfo, group: Group, sensor: str, col: Any) -> np.ndarray:
    """(N,) bool: the sensor's input streams the group's networks need are ok (wrench; temperature from 7
    inputs on; the FT board's IMU for 13). A needed stream absent from the whole log is an error naming it."""
    streams = [S.WRENCH_STREAM] + ([S.TEMPERATURE_STREAM] if group.n_inputs >= 7 else [])
    streams += [S.IMU_STREAM] if group.n_inputs == 13 else []
    ok = np.ones(len(col(S.STAMP)), dtype=bool)
    for stream in streams:
        flag = col(S.ok_col(stream, sensor)).astype(bool)
        if len(flag) and not flag.any():
            what = {S.IMU_STREAM: "IMU (accelerometer, gyroscope)", S.TEMPERATURE_STREAM: "temperature"}
            key = f"train.groups.{group.name}.inputs"
            need = {
                S.IMU_STREAM: f"a 13-input network needs it ({key}: [7] trains without it)",
                S.TEMPERATURE_STREAM: f"7- and 13-input models need it ({key}: [6] uses the wrench alone)",
            }.get(stream, "every model of the group needs it")
            flag_col = S.ok_col(stream, sensor)
            raise DataError(
                f"{log.path}: no {what.get(stream, stream)} for {sensor} ({flag_col} is false on every "
                f"sample): {need}"
            )
        ok &= flag
    return ok


def _read_log(log: LogInfo, group: Group, index: int) -> GroupData:
    wanted = [S.STAMP, S.TIME]
    for sensor in group.sensors:
        wanted += input_cols(sensor) + _ok_cols(sensor) + S.wrench_cols(S.EXPECTED, sensor)
        wanted.append(S.switch_col(sensor))
    if group.pair is not None:
        wanted += S.wrench_cols(S.EXPECTED, group.pair) + [S.switch_col(group.pair)]
    for cut in group.cuts:
        wanted += S.wrench_cols(S.EXPECTED, cut.label) + [S.switch_col(cut.label)]
        wanted += [c for cols in cut.pose_cols for c in cols]
    try:
        table = pq.read_table(log.path, columns=wanted)
    except (OSError, pa.ArrowException) as exc:
        names = set(pq.read_schema(log.path).names)
        missing = [c for c in wanted if c not in names]
        detail = f"missing column {missing[0]}" if missing else str(exc)
        raise DataError(f"{log.path}: not a labelled table for {group.name}: {detail}") from None

    def col(name: str) -> np.ndarray:
        return table.column(name).to_numpy(zero_copy_only=False)

    def block(names: Sequence[str]) -> np.ndarray:
        # Every value a model reads or is scored against, rounded to float32 (what the networks compute in)
        # and held in float64: tables that differ in float64's last bits (another machine's smoothing and
        # labelling) train the same networks, unless a value lies within that difference of a float32
        # rounding boundary (2e-9 of the values per float64 step of difference). Far below any sensor's
        # noise: a float32 step is 6e-5 N at 1 kN.
        return (
            np.column_stack([col(c).astype(np.float32).astype(np.float64) for c in names])
            if table.num_rows
            else np.empty((0, len(names)))
        )

    n = table.num_rows
    ok = np.ones(n, dtype=bool)
    x, labels, switches = [], [], []
    for sensor in group.sensors:
        ok &= _input_ok(log, group, sensor, col)
        x.append(block(input_cols(sensor)))
        labels.append(block(S.wrench_cols(S.EXPECTED, sensor)))
        switches.append(col(S.switch_col(sensor)).astype(bool))
    data = GroupData(
        log=np.full(n, index, dtype=np.int64),
        stamp=col(S.STAMP).astype(np.int64),
        time=col(S.TIME).astype(np.float64),
        x=np.stack(x, axis=1),
        labels=np.stack(labels, axis=1),
        switches=np.stack(switches, axis=1),
    )
    if group.pair is not None:
        data.sum_label = block(S.wrench_cols(S.EXPECTED, group.pair))
        data.sum_switch = col(S.switch_col(group.pair)).astype(bool)
    if group.cuts:
        data.cut_labels = np.stack([block(S.wrench_cols(S.EXPECTED, c.label)) for c in group.cuts], axis=1)
        data.cut_switches = np.stack([col(S.switch_col(c.label)).astype(bool) for c in group.cuts], axis=1)
        poses = [block(cols) for c in group.cuts for cols in c.pose_cols]
        data.poses = np.stack(poses, axis=1) if poses else np.zeros((n, 0, 12))
        p = 0
        for c, cut in enumerate(group.cuts):  # a sum needs its members' poses
            for _ in cut.moving:
                data.cut_switches[:, c] &= np.isfinite(data.poses[:, p]).all(axis=1)
                p += 1
        data.poses = np.nan_to_num(data.poses)
    period = nominal_period(data.time)
    if log.span is not None:  # a time block: its rows, the memory starting afresh at its start
        inside = (data.time >= log.span[0]) & (data.time < log.span[1])
        data, ok = data.subset(inside), ok[inside]
    if group.widths is not None or group.time_constants is not None:  # over every reading, before any pick
        data.memory = memory_of(data.x, group.widths, group.time_constants, period)
        data.period = np.full(len(data.x), period)
        data.window = None if group.windows is None else lowpass_memory(data.x, group.windows, period)
    ok &= np.isfinite(data.x[:, :, : group.n_inputs]).all(axis=(1, 2))
    data = data.subset(ok)
    exact = [(n, data.labels[:, s], data.switches[:, s]) for s, n in enumerate(group.sensors)]
    exact += [(c.label, data.cut_labels[:, k], data.cut_switches[:, k]) for k, c in enumerate(group.cuts)]
    exact += [(group.pair, data.sum_label, data.sum_switch)] if data.sum_switch is not None else []
    for name, labels, switch in exact:
        if not np.isfinite(labels[switch]).all():
            raise DataError(f"{log.path}: {S.EXPECTED}.{name} is not finite where {S.switch_col(name)} is 1")
    return data


def concat(parts: Sequence[GroupData]) -> GroupData:
    """The samples of `parts`, one after the other."""

    def joined(name: str) -> np.ndarray | None:
        return None if getattr(parts[0], name) is None else np.concatenate([getattr(p, name) for p in parts])

    return GroupData(**{f.name: joined(f.name) for f in fields(GroupData)})


def derive_seed(seed: int, *parts: str | int) -> int:
    """A 32-bit seed from the master seed and names/numbers (stable across runs and platforms)."""
    words = [seed] + [zlib.crc32(p.encode()) if isinstance(p, str) else int(p) for p in parts]
    return int(np.random.SeedSequence(words).generate_state(1)[0])


def load_group_data(group: Group, logs: Sequence[LogInfo]) -> GroupData:
    return concat([_read_log(log, group, i) for i, log in enumerate(logs)])


# --- errors --------------------------------------------------------------------------------------


def group_errors(group: Group, data: GroupData, pred: np.ndarray) -> dict[str, Any]:
    """Errors of predictions (N, S, 6) against the exact labels of `data` (see the module docstring)."""
    out: dict[str, Any] = {}
    squares = []
    for s, sensor in enumerate(group.sensors):
        m = data.switches[:, s]
        out[sensor] = wrench_errors(pred[m, s], data.labels[m, s])
        squares.append(((pred[m, s] - data.labels[m, s]) ** 2).ravel())
    if group.pair is not None:
        m = data.sum_switch
        total = np.einsum("sij,nsj->ni", group.transforms, pred[m])
        out[group.pair] = wrench_errors(total, data.sum_label[m])
        squares.append(((total - data.sum_label[m]) ** 2).ravel())
    if group.cuts:
        sums = cut_sums_np(group.cuts, pred, data.poses)
        for c, cut in enumerate(group.cuts):
            m = data.cut_switches[:, c]
            out[cut.label] = wrench_errors(sums[m, c], data.cut_labels[m, c])
            squares.append(((sums[m, c] - data.cut_labels[m, c]) ** 2).ravel())
    pooled = np.concatenate(squares)
    out["rmse_labelled"] = math.sqrt(float(pooled.mean())) if pooled.size else math.nan
    out["rmse"] = out[group.headline]["rmse"]
    if len(group.headlines) > 1:  # several headlines: their squared errors pooled
        n = sum(out[h]["samples"] for h in group.headlines)
        mse = sum(out[h]["mse"] * out[h]["samples"] for h in group.headlines if out[h]["samples"])
        out["rmse"] = math.sqrt(mse / n) if n else math.nan
    return out
