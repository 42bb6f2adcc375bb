"""Test D from the noise level up: known pushes added to a day's logs through each sensor's own distortion.

On every simulated log of a deployment day (its truth and the day's hidden distortions known,
``data/deploy/<day>/truth.json``) a push p(t), the change of the true wrench at the sensor (sensor frame,
N and Nm), is added by superposition: the raw reading becomes ``raw + reading(w + p) - reading(w)`` with
``reading = static_distortion + hysteresis_term`` (`pipeline.sim.distortion`, hysteresis over the whole
log), so the log's own noise, temperature and IMU stay as logged. Each model reports the change
``f(x') - f(x)`` on those inputs: the deployed export (its onnxruntime graph, `Deployment.predict`), the
oracle (`oracle_inverse`, the static part's exact inverse) and raw (the factory map: the reading's change).

Pushes (``deploy.scales``), each a half-sine pulse of ``pulse_s`` (a held load: a plateau of ``load_s``
with `RAMP_S` ramps), at seeded free slots of the log:

- ``force``: a force of M N along +-x, +-y, +-z at a lever ``k r`` (r: the sensor's site, `pipeline.sim
  .sites`, in the sensor frame at the URDF's zero configuration; k in ``levers``): ``p = [f; k r x f]``;
- ``moment``: a pure moment of M Nm along +-tx, +-ty, +-tz;
- ``random``: M N times a seeded random 6-D unit direction u, ``p = M [u_f; L u_t]`` (L = max(|r|, 5 cm));
- ``load``: m kg held at the site: ``m g`` along gravity in the sensor frame (the FT board's mean
  accelerometer over the hold: at rest it reads -g), at the lever r, signed as the simulator signs an
  external wrench on the free side.

Per (family, magnitude) and model, pooled over the day's logs and the samples where the push is above
`ON_SHARE` of its peak: per axis the slope ``sum(c_a p_a) / sum(p_a^2)`` (c the reported change; None on
an axis the family does not move) and the change error ``RMS(c - p) / RMS(p)`` over the force axes
(``error``) and the torque axes (``error_torque``). Forces also per lever scale. `judge` gives the verdict.
Every model runs over the whole log with the pushes in it (a model with memory from a fresh state at its
first sample, as deployed), and is read on the pushes' samples. The held loads give the step responses
(`pipeline.deploy.steps`): the reported change of a load over its hold, against its true profile.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.sim.distortion import SensorDistortion, hysteresis_term, oracle_inverse, static_distortion

FAMILIES = ("force", "moment", "random", "load")
JUDGED = ("force",)  # the families the verdict reads (every magnitude, every force axis)
MODELS = ("deployed", "oracle", "raw")
ON_SHARE = 0.3  # samples where the push's profile is above this share of its peak are scored
RAMP_S = 0.3  # a held load is put on and taken off over this long (raised-cosine ramps), s
FIRST_S = 1.0  # no push before this (the hysteresis state of the log settles), s
MIN_LEVER_M = 0.05  # torque scale of a random 6-D direction: the site's lever, at least this, m
MEASURED = 1e-2  # an axis is measured when its sum of p^2 is above this share of the family's largest
ERROR_FLOOR = 0.02  # the oracle's change error is floored at this (2 % of the push) when judging ratios

Predict = Callable[
    [np.ndarray], np.ndarray
]  # (M, k) one sensor's inputs (wrench, temperature, ...) -> (M, 6)


@dataclass(frozen=True)
class Push:
    """One push of a pass: its peak wrench (sensor frame, N / Nm), where it lies and its profile."""

    family: str
    magnitude: float  # N (force, random), Nm (moment), kg (load)
    lever: float | None  # scale of the site's lever (force pushes), else None
    wrench: np.ndarray  # (6,) peak change of the true wrench at the sensor
    start: int  # first sample
    length: int  # samples
    ramp: float = 0.0  # a held load: share of `length` in each ramp (0: a half-sine pulse)

    def profile(self) -> np.ndarray:
        """(length,) in [0, 1]: a half-sine, or a plateau with raised-cosine ramps."""
        s = (np.arange(self.length) + 0.5) / self.length
        if self.ramp <= 0:
            return np.sin(np.pi * s)
        up, down = np.clip(s / self.ramp, 0, 1), np.clip((1 - s) / self.ramp, 0, 1)
        return 0.5 - 0.5 * np.cos(np.pi * np.minimum(up, down))


def variants(family: str, magnitude: float, lever_m: np.ndarray, levers: Sequence[float], rng: Any) -> list:
    """[(lever scale or None, (6,) peak wrench)] of one pass (loads: built per hold, see `load_wrench`)."""
    out: list[tuple[float | None, np.ndarray]] = []
    if family == "force":
        for k in levers:
            for a in range(3):
                for sign in (1.0, -1.0):
                    f = np.zeros(3)
                    f[a] = sign * magnitude
                    out.append((float(k), np.r_[f, np.cross(k * lever_m, f)]))
    elif family == "moment":
        for a in range(3, 6):
            for sign in (1.0, -1.0):
                p = np.zeros(6)
                p[a] = sign * magnitude
                out.append((None, p))
    elif family == "random":
        scale = max(float(np.linalg.norm(lever_m)), MIN_LEVER_M)
        for _ in range(max(len(levers), 1) * 6):
            u = rng.standard_normal(6)
            u /= np.linalg.norm(u)
            out.append((None, magnitude * np.r_[u[:3], scale * u[3:]]))
    return out


def load_wrench(
    mass_kg: float, acc: np.ndarray, gravity: float, lever_m: np.ndarray, sign: float
) -> np.ndarray:
    """(6,) the wrench of `mass_kg` held at `lever_m` (sensor frame, m), its weight along gravity as the
    FT board's accelerometer `acc` ((M, 3) m/s^2, proper acceleration) reads it on average: ``-mean(acc)``."""
    mean = np.nanmean(acc, axis=0) if len(acc) else np.full(3, np.nan)
    norm = float(np.linalg.norm(mean))
    down = -mean / norm if np.isfinite(norm) and norm > 1e-6 else np.array([0.0, 0.0, -1.0])
    f = sign * mass_kg * gravity * down
    return np.r_[f, np.cross(lever_m, f)]


def schedule(n: int, dt: float, length_s: float, count: int, rng: Any) -> list[tuple[int, int]]:
    """Up to `count` (start, length) slots of `length_s` each, a gap of half a slot between slots, after
    FIRST_S, drawn at random among the log's slots (sorted). Empty when the log is too short."""
    length = max(int(round(length_s / dt)), 2)
    period = length + max(length // 2, 1)
    first = int(round(FIRST_S / dt))
    starts = np.arange(first, n - length, period)
    if not len(starts):
        return []
    pick = np.sort(rng.choice(starts, size=min(count, len(starts)), replace=False))
    return [(int(s), length) for s in pick]


def raw_change(
    d: SensorDistortion, true: np.ndarray, temperature: np.ndarray, push: np.ndarray
) -> np.ndarray:
    """(N, 6) the change of the noise-free reading, ``reading(w + p) - reading(w)``, N / Nm.

    true, push: (N, 6) true wrench and push (sensor frame, one continuous log: the hysteresis state starts
    at its first sample); temperature: (N,) deg C."""
    before = static_distortion(d, true, temperature) + hysteresis_term(d, true)
    after = static_distortion(d, true + push, temperature) + hysteresis_term(d, true + push)
    return after - before


class Tally:
    """Sums per (key, model): sum(c p), sum(p^2), sum((c - p)^2) per axis (6,) each; the loads' step
    responses (`steps`)."""

    def __init__(self) -> None:
        from pipeline.deploy.steps import Steps

        self.sums: dict[tuple[Any, str], np.ndarray] = {}
        self.steps = Steps()

    def add(self, key: Any, model: str, change: np.ndarray, push: np.ndarray) -> None:
        s = self.sums.setdefault((key, model), np.zeros((3, 6)))
        s += np.stack([(change * push).sum(0), (push**2).sum(0), ((change - push) ** 2).sum(0)])

    def merge(self, other: Tally) -> None:
        for k, v in other.sums.items():
            self.sums[k] = self.sums.get(k, 0.0) + v
        self.steps.merge(other.steps)

    def entry(self, key: Any, model: str) -> dict[str, Any] | None:
        """{"slopes": 6 (None: axis not moved), "error": force axes, "error_torque": torque axes}."""
        s = self.sums.get((key, model))
        if s is None:
            return None
        cp, pp, ee = s
        out: dict[str, Any] = {}
        for name, axes in (("error", slice(0, 3)), ("error_torque", slice(3, 6))):
            total = pp[axes].sum()
            out[name] = _round(np.sqrt(ee[axes].sum() / total)) if total > 0 else None
        top = pp.max()
        out["slopes"] = [
            _round(cp[a] / pp[a]) if top > 0 and pp[a] > MEASURED * top else None for a in range(6)
        ]
        return out


def _round(v: float) -> float:
    return float(round(float(v), 4))


def log_tally(
    d: SensorDistortion,
    inputs: np.ndarray,
    true: np.ndarray,
    models: Mapping[str, Predict],
    pushes: Sequence[Sequence[Push]],
) -> Tally:
    """The tally of one sensor on one log: `inputs` (N, k) its logged model inputs (raw wrench, temperature
    in column 6, then the rest); `true` (N, 6) its true wrench; `models` name -> predictor; `pushes` the
    passes, each a list of non-overlapping pushes added to the log together. Rows with a non-finite input
    or truth are not scored."""
    ok = np.isfinite(inputs).all(axis=1) & np.isfinite(true).all(axis=1)
    temperature = np.nan_to_num(inputs[:, 6], nan=float(np.nanmean(inputs[:, 6]) if ok.any() else 25.0))
    w = np.nan_to_num(true)
    inputs = _held_over_gaps(inputs)
    base = {m: f(inputs) for m, f in models.items()}
    tally = Tally()
    for batch in pushes:
        if not batch:
            continue
        p = np.zeros((len(w), 6))
        scored = np.zeros(len(w), dtype=bool)
        for push in batch:
            prof = push.profile()
            p[push.start : push.start + push.length] = prof[:, None] * push.wrench
            scored[push.start : push.start + push.length] = prof > ON_SHARE
        moved = inputs.copy()
        moved[:, :6] += raw_change(d, w, temperature, p)
        outputs = {m: f(moved) for m, f in models.items()}
        rows = np.flatnonzero(scored & ok)
        changes = {m: outputs[m][rows] - base[m][rows] for m in models}
        for push in batch:
            if push.family == "load":
                window = slice(push.start, push.start + push.length)
                for m in models:
                    tally.steps.add(m, outputs[m][window] - base[m][window], p[window], push.wrench)
            sel = (rows >= push.start) & (rows < push.start + push.length)
            keys = [(push.family, push.magnitude)]
            if push.lever is not None:
                keys.append(("lever", push.lever, push.magnitude))
            for key in keys:
                for m, c in changes.items():
                    tally.add(key, m, c[sel], p[rows[sel]])
    return tally


def _held_over_gaps(inputs: np.ndarray) -> np.ndarray:
    """`inputs` with each non-finite value replaced by the column's last finite one before it (the first
    finite one at the start; 0 if none): what a model with memory reads is the reading as it last was."""
    import pandas as pd

    frame = pd.DataFrame(np.asarray(inputs, dtype=np.float64))
    return np.nan_to_num(frame.ffill().bfill().to_numpy(np.float64))


def reference_models(d: SensorDistortion, deployed: Predict) -> dict[str, Predict]:
    """The three models of the test: the deployed predictor, the oracle and raw, on one sensor's inputs."""
    return {
        "deployed": deployed,
        "oracle": lambda x: oracle_inverse(d, x[:, :6], x[:, 6]),
        "raw": lambda x: np.array(x[:, :6], dtype=np.float64),
    }


def sensor_rng(seed: int, day: str, sensor: str, log: str) -> np.random.Generator:
    """The generator of one sensor's pushes on one log, from ``deploy.seed`` and the day, sensor, log."""
    return np.random.default_rng([seed, zlib.crc32(f"{day}/{sensor}/{log}".encode())])


def plan_pushes(
    sp: Any,
    n: int,
    dt: float,
    lever_m: np.ndarray,
    acc: np.ndarray | None,
    gravity: float,
    sign: float,
    rng: Any,
) -> list[list[Push]]:
    """Every pass of one sensor on one log (`sp`: ``deploy.scales``): one per (family, magnitude); acc:
    (N, 3) the FT board's accelerometer (None: no loads)."""
    passes: list[list[Push]] = []
    mags = {"force": sp.force_n, "moment": sp.moment_nm, "random": sp.force_n}
    for family in ("force", "moment", "random"):
        for mag in mags[family]:
            options = variants(family, float(mag), lever_m, sp.levers, rng)
            slots = schedule(n, dt, sp.pulse_s, sp.pulses, rng)
            first = int(rng.integers(len(options)))
            passes.append(
                [
                    Push(family, float(mag), options[(first + i) % len(options)][0],
                         options[(first + i) % len(options)][1], s, ln)
                    for i, (s, ln) in enumerate(slots)
                ]
            )  # fmt: skip
    if acc is not None and np.isfinite(acc).any():
        ramp = RAMP_S / (sp.load_s + 2 * RAMP_S)

        def wrench(a: np.ndarray, mass: float) -> np.ndarray:
            return load_wrench(mass, a, gravity, lever_m, sign)

        for mass in sp.load_kg:
            slots = schedule(n, dt, sp.load_s + 2 * RAMP_S, max(sp.pulses // 6, 1), rng)
            passes.append(
                [
                    Push("load", float(mass), None, wrench(acc[s : s + ln], mass), s, ln, ramp)
                    for s, ln in slots
                ]
            )  # fmt: skip
    return passes


def sensor_result(tally: Tally, sp: Any, lever_m: np.ndarray) -> dict[str, Any]:
    """One sensor's JSON entry: per family and magnitude each model's `Tally.entry`, per lever the force
    pushes' change errors per force magnitude."""
    mags = {"force": sp.force_n, "moment": sp.moment_nm, "random": sp.force_n, "load": sp.load_kg}
    out: dict[str, Any] = {"lever_m": [_round(v) for v in lever_m]}
    for family in FAMILIES:
        rows = {}
        for mag in mags[family]:
            row = {m: tally.entry((family, float(mag)), m) for m in MODELS}
            if all(v is not None for v in row.values()):
                rows[f"{float(mag):g}"] = row
        if rows:
            out[family] = rows
    steps = tally.steps.entry()
    if steps:
        out["step"] = steps
    levers = {}
    for k in sp.levers:
        per = {m: [(tally.entry(("lever", float(k), float(f)), m) or {}).get("error") for f in sp.force_n]
               for m in ("deployed", "oracle")}  # fmt: skip
        if any(v is not None for v in per["deployed"]):
            levers[f"{float(k):g}"] = per
    out["levers"] = levers
    return out


def row_judgement(row: Mapping[str, Any], family: str) -> tuple[float | None, str, float | None]:
    """(worst slope excess ``|s - 1| - |s_oracle - 1|`` over the measured axes, its axis, the change error
    over the oracle's floored at `ERROR_FLOOR`) of one magnitude's row of a family."""
    dep, ora = row["deployed"], row["oracle"]
    pairs = [(abs(s - 1) - abs(o - 1), _AXES[a]) for a, (s, o) in enumerate(zip(dep["slopes"], ora["slopes"],
             strict=True)) if s is not None and o is not None]  # fmt: skip
    excess, axis = max(pairs) if pairs else (None, "")
    key = "error_torque" if family == "moment" else "error"
    ratio = None if dep[key] is None or ora[key] is None else dep[key] / max(ora[key], ERROR_FLOOR)
    return excess, axis, ratio


def judge(entry: Mapping[str, Any], tolerance: float, target: float) -> dict[str, Any]:
    """The verdict of one sensor: at every magnitude of the `JUDGED` families and every measured axis of
    theirs, the deployed slope's error ``|s - 1|`` at most the oracle's plus `tolerance`, and the change
    error at most `target` x the oracle's (floored at `ERROR_FLOOR`). Reports the worst of each and where."""
    excess, ratio, where_s, where_e = -np.inf, -np.inf, "", ""
    for family in JUDGED:
        for mag, row in (entry.get(family) or {}).items():
            x, axis, r = row_judgement(row, family)
            if x is not None and x > excess:
                excess, where_s = x, f"{mag} {axis}"
            if r is not None and r > ratio:
                ratio, where_e = r, mag
    if not np.isfinite(excess):
        return {"pass": True, "worst_slope_excess": None, "worst_change_ratio": None}
    ok = excess <= tolerance and ratio <= target
    return {
        "pass": bool(ok),
        "worst_slope_excess": _round(excess),
        "at_slope": where_s,
        "worst_change_ratio": _round(ratio),
        "at_change": where_e,
    }


_AXES = ("fx", "fy", "fz", "tx", "ty", "tz")


def sensor_levers(
    robot: Any, params: Any, dp: Any, sensors: Sequence[str]
) -> dict[str, tuple[np.ndarray, float]]:
    """Sensor -> (its site's point in its frame at the URDF's zero configuration (3,) m, the sign of an
    external force on its free side in its reading: +1 where it reads the free side's wrench on the other)."""
    from pipeline.physics.feet import robot_feet
    from pipeline.sim.kinematics import Kinematics
    from pipeline.sim.sites import free_side, interaction_sites

    soles = {s: foot.sole for foot in robot_feet(robot, params.robot.foot_pairs) for s in foot.sensors}
    sites = {site.sensor: site for site in interaction_sites(robot, soles, dp.interaction.sites)}
    kin, q0 = Kinematics(robot, 0.0), np.zeros(len(robot.joint_names))
    out = {}
    for s in sensors:
        ft, site = robot.sensors[s], sites[s]
        pose = kin.frame_pose(q0, ft.child_link) * ft.child_T_sensor
        point = pose.actInv(kin.frame_pose(q0, site.link).act(np.asarray(site.point, dtype=float)))
        child_free = ft.child_link in free_side(robot, s)
        sign = (-1.0 if ft.direction == "parent_to_child" else 1.0) * (1.0 if child_free else -1.0)
        out[s] = (np.asarray(point, dtype=float), sign)
    return out


def day_scales(ctx: Any, logs: Sequence[Any]) -> dict[str, Any]:
    """Test D from the noise level up of one group on one day (`ctx`: `pipeline.deploy.group.GroupDay`),
    on every log of `logs` with truth: sensor -> `sensor_result` with its `judge` verdict. Empty when no log
    has truth (recorded logs: no distortion to push through)."""
    import json

    import pandas as pd

    from pipeline.calib.data import input_cols
    from pipeline.export.runtime import Deployment
    from pipeline.logs import schema as S

    simulated = [g for g in logs if g.truth is not None and (g.source.parent / "truth.json").is_file()]
    if not simulated:
        return {}
    sp, deployment = ctx.dp.scales, Deployment.load(ctx.exported)
    entry = deployment.groups()[ctx.group]
    n = int(entry["training"][ctx.group]["inputs_per_sensor"])
    slots = {s: i for i, s in enumerate(entry["sensors"]) if s in ctx.sensors}
    levers = sensor_levers(ctx.robot, ctx.params, ctx.dp, list(slots))
    tallies = {s: Tally() for s in slots}
    for log in simulated:
        truth_file = json.loads((log.source.parent / "truth.json").read_text(encoding="utf-8"))
        table = pd.read_parquet(log.labelled)
        truth = table[[S.STAMP]].merge(pd.read_parquet(log.truth), on=S.STAMP, how="left")
        dt = float(np.median(np.diff(table[S.TIME].to_numpy(np.float64))))
        for s, slot in slots.items():
            d = SensorDistortion.from_dict(truth_file["distortions"][s])
            x = table[input_cols(s, 13)].to_numpy(np.float64)
            models = reference_models(
                d, lambda rows, g=ctx.group, k=slot: _predict(deployment, g, k, rows[:, :n])
            )
            lever, sign = levers[s]
            rng = sensor_rng(ctx.dp.seed, ctx.day, s, log.name)
            passes = plan_pushes(sp, len(x), dt, lever, x[:, 7:10], ctx.params.robot.gravity, sign, rng)
            true = truth[S.wrench_cols(S.TRUE, s)].to_numpy(np.float64)
            tallies[s].merge(log_tally(d, x, true, models, passes))
    out = {}
    for s, tally in tallies.items():
        result = sensor_result(tally, sp, levers[s][0])
        result["verdict"] = judge(result, ctx.dp.slope_tolerance, ctx.dp.push_rmse_target)
        out[s] = result
    return out


def _predict(deployment: Any, group: str, slot: int, rows: np.ndarray) -> np.ndarray:
    if not len(rows):
        return np.zeros((0, 6))
    return deployment.predict(group, {slot: rows})[slot]


def worst_slope(slopes: Sequence[float | None], axes: Any = range(6)) -> float | None:
    """The slope farthest from 1 among `axes` (None if none measured)."""
    values = [slopes[a] for a in axes if slopes[a] is not None]
    return max(values, key=lambda v: abs(v - 1)) if values else None


def summary_keys(result: Mapping[str, Any]) -> dict[str, Any]:
    """A day's few numbers of this test (`pipeline.deploy.verdict.summarize`), from its merged result
    (sensor -> entry): per sensor its verdict's worst numbers and, per force magnitude, the worst-axis slope
    and change error of the deployed model and the oracle (``ds.<sensor>.<M>N.<what>``); ``ds.passed``."""
    out: dict[str, Any] = {}
    for sensor, e in result.items():
        v = e["verdict"]
        for key in ("worst_slope_excess", "worst_change_ratio"):
            if v.get(key) is not None:
                out[f"ds.{sensor}.{key}"] = v[key]
        out[f"ds.{sensor}.passed"] = v["pass"]
        for mag, row in (e.get("force") or {}).items():
            for model, prefix in (("deployed", ""), ("oracle", "oracle_")):
                slope = worst_slope(row[model]["slopes"], range(3))
                if slope is not None:
                    out[f"ds.{sensor}.{mag}N.{prefix}slope"] = slope
                if row[model]["error"] is not None:
                    out[f"ds.{sensor}.{mag}N.{prefix}error"] = row[model]["error"]
    if result:
        out["ds.passed"] = all(e["verdict"]["pass"] for e in result.values())
    return out


def headline_keys(summary: Mapping[str, Any]) -> dict[str, Any]:
    """``deployment.json``'s part of this test: the worst slope excess and change ratio of the day
    (``ds_slope``, ``ds_change``) and per sensor and force magnitude [deployed slope, its change error,
    the oracle's slope, its change error] (``d_scales``)."""
    out: dict[str, Any] = {}
    for key, suffix in (("ds_slope", ".worst_slope_excess"), ("ds_change", ".worst_change_ratio")):
        values = [v for k, v in summary.items() if k.startswith("ds.") and k.endswith(suffix)]
        if values:
            out[key] = round(float(max(values)), 4)
    table: dict[str, dict[str, list[float | None]]] = {}
    for k, v in summary.items():
        parts = k.split(".")
        if len(parts) == 4 and parts[0] == "ds" and parts[2].endswith("N"):
            row = table.setdefault(parts[1], {}).setdefault(parts[2], [None] * 4)
            row[("slope", "error", "oracle_slope", "oracle_error").index(parts[3])] = round(float(v), 3)
    if table:
        out["d_scales"] = table
    return out
