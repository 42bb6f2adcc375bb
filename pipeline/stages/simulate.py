"""Stage `simulate`: realistic robot logs with known truth, written as ROS 2 MCAP (thesis 4.1).

For every log in ``simulate.logs``: a true motion (:mod:`pipeline.sim.motion`), the true wrenches of a
"true" robot whose links have mass and COM errors (:mod:`pipeline.sim.truth`), and what the robot's
sensors make of it (:mod:`pipeline.sim.sensors`): distorted, noisy FT wrenches (the same hidden
distortion in every log), a temperature that drifts with activity, FT-board IMUs, quantised encoders.
Messages carry jittered stamps, a few are dropped or duplicated, and arrive with delays.

Outputs in the output directory: one ``<NN>_<type>_<role>.mcap`` per log (topics as ``params.topics``;
metadata record ``experiment``; truth under ``/sim/...``), ``truth.json`` (the hidden distortions and
model errors, for evaluation only), ``summary.json`` (raw and oracle errors against truth per log and
sensor), and ``plots/`` (one log per experiment type). Everything is logged to an MLflow run.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.config import Params, load_params, repo_root, resolve_urdf, stage_section
from pipeline.core.errors import ConfigError
from pipeline.physics.robot import FootPair, LinkInertial, RobotModel, load_robot
from pipeline.sim.motion import Foot, Motion, MotionGenerator, MotionParams
from pipeline.sim.sensors import (
    DistortionRanges,
    ImuNoiseParams,
    SensorDistortion,
    ThermalParams,
    distort,
    draw_distortion,
    encoder_readings,
    encoder_velocity,
    imu_readings,
    oracle_inverse,
    temperature_signals,
)
from pipeline.sim.truth import Truth, TruthComputer

EXPERIMENT_TYPES = ("pole", "balancing", "half_foot", "walking")
EPOCH_NS = 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z: stamps look like a real recording's


@dataclass(frozen=True)
class LogSpec:
    """One simulated log (an entry of ``simulate.logs``)."""

    type: str  # pole | balancing | half_foot | walking
    duration_s: float  # robot time, s
    role: str  # train | test (written into the log's metadata)
    foot: str = ""  # balancing / half_foot: the supporting foot (a robot.foot_pairs name)
    part: str = ""  # half_foot: 'front' or 'rear'

    def check(self, key: str, feet: tuple[str, ...]) -> None:
        if self.type not in EXPERIMENT_TYPES:
            raise ConfigError(f"{key}.type must be one of {', '.join(EXPERIMENT_TYPES)}, got {self.type!r}")
        if not (isinstance(self.duration_s, int | float) and 1.0 <= self.duration_s <= 7200.0):
            raise ConfigError(f"{key}.duration_s must be in [1, 7200] s, got {self.duration_s!r}")
        if self.role not in ("train", "test"):
            raise ConfigError(f"{key}.role must be train or test, got {self.role!r}")
        if self.type in ("balancing", "half_foot") and self.foot not in feet:
            raise ConfigError(f"{key}.foot must be one of {', '.join(feet)}, got {self.foot!r}")
        if self.type == "half_foot" and self.part not in ("front", "rear"):
            raise ConfigError(f"{key}.part must be front or rear, got {self.part!r}")


@dataclass(frozen=True)
class TimingParams:
    """How messages arrive (section ``simulate.timing``)."""

    jitter_s: float = 0.0005  # std of stamp jitter around the nominal period, s
    ft_offset_s: float = 0.002  # FT board clock lag behind the joint-state stamps, s
    temperature_rate_hz: float = 10.0  # temperature messages per second
    drop_rate: float = 0.001  # fraction of FT, IMU and joint-state messages lost
    duplicate_rate: float = 0.0005  # fraction of messages recorded twice
    delay_s: float = 0.003  # mean of the exponential transport delay (log time - stamp), s

    def __post_init__(self) -> None:
        for name in ("jitter_s", "ft_offset_s", "delay_s"):
            if not 0.0 <= getattr(self, name) <= 0.1:
                raise ConfigError(f"simulate.timing.{name} must be in [0, 0.1] s, got {getattr(self, name)}")
        for name in ("drop_rate", "duplicate_rate"):
            if not 0.0 <= getattr(self, name) < 0.5:
                raise ConfigError(f"simulate.timing.{name} must be in [0, 0.5), got {getattr(self, name)}")
        if not 0.1 <= self.temperature_rate_hz <= 1000:
            raise ConfigError(
                f"simulate.timing.temperature_rate_hz must be in [0.1, 1000], got {self.temperature_rate_hz}"
            )


@dataclass(frozen=True)
class SimulateParams:
    """Section ``simulate`` of params.yaml."""

    rate_hz: float  # joint-state and FT rate, Hz
    mass_error: float  # true link mass = URDF mass x (1 + uniform +- this)
    com_error_m: float  # true link COM = URDF COM + uniform +- this per axis, m
    encoder_resolution_rad: float  # encoder quantum, rad (0: none)
    encoder_noise_rad: float  # encoder white noise std before quantisation, rad
    activity_scale: float  # |joint velocity| (rad/s, norm over the limb) that counts as activity 1
    workers: int  # processes generating logs in parallel (0: one per core)
    plots: bool  # write the per-experiment-type plots
    logs: tuple[LogSpec, ...]
    motion: MotionParams = field(default_factory=MotionParams)
    sensors: DistortionRanges = field(default_factory=DistortionRanges)
    thermal: ThermalParams = field(default_factory=ThermalParams)
    imu: ImuNoiseParams = field(default_factory=ImuNoiseParams)
    timing: TimingParams = field(default_factory=TimingParams)

    def __post_init__(self) -> None:
        if not 10.0 <= self.rate_hz <= 2000.0:
            raise ConfigError(f"simulate.rate_hz must be in [10, 2000], got {self.rate_hz}")
        if not 0.0 <= self.mass_error < 0.5:
            raise ConfigError(f"simulate.mass_error must be in [0, 0.5), got {self.mass_error}")
        if not 0.0 <= self.com_error_m < 0.1:
            raise ConfigError(f"simulate.com_error_m must be in [0, 0.1) m, got {self.com_error_m}")
        for name in ("encoder_resolution_rad", "encoder_noise_rad"):
            if not 0.0 <= getattr(self, name) < 0.1:
                raise ConfigError(f"simulate.{name} must be in [0, 0.1) rad, got {getattr(self, name)}")
        if not self.activity_scale > 0:
            raise ConfigError(f"simulate.activity_scale must be > 0, got {self.activity_scale}")
        if not (isinstance(self.workers, int) and self.workers >= 0):
            raise ConfigError(f"simulate.workers must be an integer >= 0, got {self.workers!r}")
        if not self.logs:
            raise ConfigError("simulate.logs must list at least one log")


def _sub(cls: type, data: Any, key: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(f"{key} must be a mapping, got {data!r}")
    names = set(cls.__dataclass_fields__)
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"unknown key {key}.{unknown[0]} (allowed: {', '.join(sorted(names))})")
    try:
        return cls(**data)
    except TypeError as exc:
        raise ConfigError(f"{key}: {exc}") from None


def simulate_params(params: Params) -> SimulateParams:
    """Load and validate the ``simulate`` section (errors name the dotted key)."""
    where = params.raw.get("__file__", "params.yaml")
    raw = params.raw.get("simulate")
    try:
        if not isinstance(raw, dict):
            raise ConfigError("missing section simulate")
        raw = dict(raw)
        nested = {
            "motion": (MotionParams, "simulate.motion"),
            "sensors": (DistortionRanges, "simulate.sensors"),
            "thermal": (ThermalParams, "simulate.thermal"),
            "imu": (ImuNoiseParams, "simulate.imu"),
            "timing": (TimingParams, "simulate.timing"),
        }
        for key, (cls, dotted) in nested.items():
            if key in raw:
                raw[key] = _sub(cls, raw[key], dotted)
        if not isinstance(raw.get("logs"), list):
            raise ConfigError("simulate.logs must be a list of logs")
        feet = tuple(p.name for p in params.robot.foot_pairs)
        logs = []
        for i, entry in enumerate(raw["logs"]):
            spec = _sub(LogSpec, entry, f"simulate.logs[{i}]")
            spec.check(f"simulate.logs[{i}]", feet)
            logs.append(spec)
        raw["logs"] = tuple(logs)
        fake = Params(seed=params.seed, robot=params.robot, topics=params.topics, raw={"simulate": raw})
        return stage_section(fake, "simulate", SimulateParams)
    except ConfigError as exc:
        message = str(exc)
        raise ConfigError(message if message.startswith(where) else f"{where}: {message}") from None


# --------------------------------------------------------------------------- the hidden world
def true_robot(robot: RobotModel, p: SimulateParams, rng: np.random.Generator) -> tuple[RobotModel, dict]:
    """The "true" robot: every link with mass gets a mass and COM error drawn from the params."""
    overrides, errors = {}, {}
    for name in sorted(robot.links):
        inertial = robot.links[name]
        if inertial is None or inertial.mass == 0.0:
            continue
        scale = 1.0 + rng.uniform(-p.mass_error, p.mass_error)
        com = inertial.com + rng.uniform(-p.com_error_m, p.com_error_m, 3)
        overrides[name] = LinkInertial(inertial.mass * scale, com, inertial.inertia * scale)
        errors[name] = {"mass_scale": scale, "com_offset_m": (com - inertial.com).tolist()}
    return robot.with_inertials(overrides), errors


def _rng(seed: int, *stream: int) -> np.random.Generator:
    """An independent generator per (seed, stream...): results do not depend on generation order."""
    return np.random.default_rng([seed, *stream])


@dataclass
class World:
    """Everything shared by all logs of one simulation run."""

    params: Params
    sim: SimulateParams
    robot: RobotModel  # the nominal URDF (what the labeller knows)
    truth_robot: RobotModel
    feet: list[Foot]
    pairs: list[FootPair]
    distortions: dict[str, SensorDistortion]
    model_errors: dict


def build_world(params: Params, sim: SimulateParams) -> World:
    robot = load_robot(resolve_urdf(params.robot.urdf, repo_root()))
    pairs = [robot.foot_pair(p.name, p.front, p.rear, p.sole) for p in params.robot.foot_pairs]
    feet = [
        Foot(p.name, p.sole, robot.sensors[p.front].child_link, robot.sensors[p.rear].child_link)
        for p in pairs
    ]
    truth_robot, errors = true_robot(robot, sim, _rng(params.seed, 1))
    distortions = {
        s: draw_distortion(_rng(params.seed, 2, i), sim.sensors) for i, s in enumerate(robot.sensors)
    }
    for pair in pairs:
        # one foot, one mounting: its two sensors' offsets share their signs (magnitudes independent),
        # which is what makes the raw pair sums as far off as the thesis's (50-100 N)
        front, rear = distortions[pair.front].to_dict(), distortions[pair.rear].to_dict()
        rear["offset"] = (np.abs(rear["offset"]) * np.sign(front["offset"])).tolist()
        distortions[pair.rear] = SensorDistortion.from_dict(rear)
    return World(params, sim, robot, truth_robot, feet, pairs, distortions, errors)


# --------------------------------------------------------------------------- one log
def log_name(index: int, spec: LogSpec) -> str:
    extra = f"_{spec.foot}" if spec.foot else ""
    extra += f"_{spec.part}" if spec.part else ""
    return f"{index:02d}_{spec.type}{extra}_{spec.role}"


def make_motion(world: World, spec: LogSpec, rng: np.random.Generator) -> Motion:
    gen = MotionGenerator(world.robot, world.feet, world.sim.motion)
    rate = world.sim.rate_hz
    if spec.type == "pole":
        return gen.pole(rng, spec.duration_s, rate)
    if spec.type == "balancing":
        return gen.balancing(rng, spec.duration_s, rate, spec.foot)
    if spec.type == "half_foot":
        return gen.balancing(rng, spec.duration_s, rate, spec.foot, spec.part)
    return gen.walking(rng, spec.duration_s, rate)


def _stamps(rng: np.random.Generator, t: np.ndarray, offset_s: float, jitter_s: float) -> np.ndarray:
    """Monotonic int64 ns stamps: nominal times + offset + clipped jitter."""
    jitter = np.clip(rng.normal(0.0, jitter_s, t.shape), -3 * jitter_s, 3 * jitter_s)
    return EPOCH_NS + np.round((t + offset_s + jitter) * 1e9).astype(np.int64)


def _thin(rng: np.random.Generator, n: int, timing: TimingParams) -> np.ndarray:
    """Indices of the messages that reach the log: some dropped, some duplicated (sorted)."""
    keep = np.flatnonzero(rng.random(n) >= timing.drop_rate)
    dup = keep[rng.random(keep.shape[0]) < timing.duplicate_rate]
    return np.sort(np.r_[keep, dup], kind="stable")


@dataclass
class LogResult:
    """What one simulated log reports back (also into summary.json)."""

    name: str
    spec: dict
    samples: int
    messages: int
    seconds: float
    raw_rmse: dict[str, dict[str, float]]
    oracle_rmse: dict[str, dict[str, float]]
    pair_raw_rmse: dict[str, dict[str, float]]
    temperature_range: dict[str, list[float]]
    plots: list[str] = field(default_factory=list)


def _rmse(err: np.ndarray) -> dict[str, float]:
    return {
        "force": float(np.sqrt(np.mean(err[:, :3] ** 2))),
        "torque": float(np.sqrt(np.mean(err[:, 3:] ** 2))),
    }


def simulate_log(world: World, index: int, spec: LogSpec, out_dir: Path, plot: bool) -> LogResult:
    """Generate one log and write ``<out_dir>/<name>.mcap`` (atomically); returns its summary."""
    from pipeline.logs.rosmsg import LogWriter

    start = time.perf_counter()
    sim, topics, robot = world.sim, world.params.topics, world.robot
    seed = world.params.seed
    name = log_name(index, spec)
    motion = make_motion(world, spec, _rng(seed, 10, index))
    truth = TruthComputer(world.truth_robot, world.pairs, world.params.robot.gravity).compute(motion)
    n, dt = motion.n, 1.0 / sim.rate_hz
    rng = _rng(seed, 11, index)

    # the sensors: temperature from activity, distorted wrenches, IMUs, encoders
    speed = np.linalg.norm(motion.dq, axis=1)
    activity = np.clip(speed / sim.activity_scale, 0.0, 1.0)
    ft_stamps = _stamps(rng, motion.t, sim.timing.ft_offset_s, sim.timing.jitter_s)
    t_ft = (ft_stamps - EPOCH_NS) * 1e-9
    sensor_data = {}
    for i, s in enumerate(robot.sensors):
        heat = 0.8 + 0.4 * _rng(seed, 3, i).random()  # limbs heat differently; fixed per sensor
        temp_true, temp_pub = temperature_signals(rng, np.clip(activity * heat, 0, 1), dt, sim.thermal)
        # the FT board samples at its own stamps: the truth there, by interpolation of the smooth signals
        w_true = np.stack([np.interp(t_ft, motion.t, truth.wrench[s][:, a]) for a in range(6)], axis=1)
        temp_at = np.interp(t_ft, motion.t, temp_true)
        distorted, raw = distort(world.distortions[s], w_true, temp_at, rng)
        oracle = oracle_inverse(world.distortions[s], raw, temp_at)
        acc, gyro = imu_readings(rng, truth.proper_acc[s], truth.gyro[s], dt, sim.imu)
        sensor_data[s] = dict(
            true=w_true,
            distorted=distorted,
            raw=raw,
            oracle=oracle,
            acc=acc,
            gyro=gyro,
            temp=temp_pub,
            temp_true=temp_true,
        )
    q_meas = encoder_readings(rng, motion.q, sim.encoder_resolution_rad, sim.encoder_noise_rad)
    dq_meas = encoder_velocity(q_meas, dt)
    js_stamps = _stamps(rng, motion.t, 0.0, sim.timing.jitter_s)
    contact_names = [",".join(sorted(c)) for c in motion.contact_sets]
    contacts_text = np.array([",".join(sorted(c)) for c in truth.contacts], dtype=object)

    constant = len(motion.contact_sets) == 1
    metadata = {
        "experiment": {
            "type": spec.type,
            "robot": world.params.robot.urdf,
            "role": spec.role,
            "contacts": contact_names[0] if constant else "",
            "fixed_link": str(motion.fixed_links[0]) if len(set(motion.fixed_links)) == 1 else "",
            "gravity": f"0 0 {-world.params.robot.gravity}",
            "sim": "true",
            "seed": str(seed),
            "duration_s": f"{spec.duration_s:g}",
            "rate_hz": f"{sim.rate_hz:g}",
            "log": name,
            "foot": spec.foot,
            "part": spec.part,
        }
    }

    # messages, in 10 s blocks so the writer's buffer stays small
    messages = 0
    temp_every = max(1, int(round(sim.rate_hz / sim.timing.temperature_rate_hz)))
    keep_js = _thin(rng, n, sim.timing)
    keep_ft = {s: _thin(rng, n, sim.timing) for s in robot.sensors}

    def delay(m: int) -> np.ndarray:
        """Transport delays of m messages, ns: the recorder's log time lags the stamp."""
        return np.round(rng.exponential(sim.timing.delay_s, m) * 1e9).astype(np.int64)

    block = int(10 * sim.rate_hz)
    path = out_dir / f"{name}.mcap"
    with LogWriter(path, metadata=metadata) as writer:
        for b0 in range(0, n, block):
            b1 = min(n, b0 + block)
            sel = keep_js[(keep_js >= b0) & (keep_js < b1)]
            writer.joint_states(
                topics.joint_states,
                js_stamps[sel],
                robot.joint_names,
                q_meas[sel],
                dq_meas[sel],
                log_times_ns=js_stamps[sel] + delay(sel.size),
            )
            messages += sel.size
            all_rows = np.arange(b0, b1)
            writer.strings(topics.sim_contacts, js_stamps[all_rows], list(contacts_text[all_rows]))
            messages += all_rows.size
            for s in robot.sensors:
                d = sensor_data[s]
                sel = keep_ft[s][(keep_ft[s] >= b0) & (keep_ft[s] < b1)]
                stamps, logt = ft_stamps[sel], ft_stamps[sel] + delay(sel.size)
                writer.wrenches(
                    topics.sensor_topic("ft_wrench", s), stamps, s, d["raw"][sel], log_times_ns=logt
                )
                writer.imus(
                    topics.sensor_topic("ft_imu", s),
                    stamps,
                    s,
                    d["acc"][sel],
                    d["gyro"][sel],
                    log_times_ns=logt,
                )
                for kind, key in (
                    ("sim_wrench_true", "true"),
                    ("sim_wrench_distorted", "distorted"),
                    ("sim_wrench_oracle", "oracle"),
                ):
                    writer.wrenches(topics.sensor_topic(kind, s), ft_stamps[all_rows], s, d[key][all_rows])
                tsel = all_rows[all_rows % temp_every == 0]
                writer.temperatures(
                    topics.sensor_topic("ft_temperature", s),
                    ft_stamps[tsel],
                    s,
                    d["temp"][tsel],
                    log_times_ns=ft_stamps[tsel] + delay(tsel.size),
                )
                messages += 2 * sel.size + 3 * all_rows.size + tsel.size
            writer.flush()

    raw_rmse = {s: _rmse(d["raw"] - d["true"]) for s, d in sensor_data.items()}
    oracle_rmse = {s: _rmse(d["oracle"] - d["true"]) for s, d in sensor_data.items()}
    pair_rmse = {}
    for pair in world.pairs:
        err = (sensor_data[pair.front]["raw"] - sensor_data[pair.front]["true"]) @ pair.sole_X_front.T + (
            sensor_data[pair.rear]["raw"] - sensor_data[pair.rear]["true"]
        ) @ pair.sole_X_rear.T
        pair_rmse[pair.name] = _rmse(err)
    result = LogResult(
        name,
        asdict(spec),
        n,
        messages,
        time.perf_counter() - start,
        raw_rmse,
        oracle_rmse,
        pair_rmse,
        {s: [float(d["temp"].min()), float(d["temp"].max())] for s, d in sensor_data.items()},
    )
    if plot:
        from pipeline.sim.plots import plot_log

        result.plots = plot_log(out_dir / "plots", name, robot, motion, truth, sensor_data)
    return result


# --------------------------------------------------------------------------- the stage
_WORLD: World | None = None


def _init_worker(params: Params, sim: SimulateParams) -> None:
    global _WORLD
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _WORLD = build_world(params, sim)


def _work(args: tuple[int, LogSpec, str, bool]) -> LogResult:
    index, spec, out_dir, plot = args
    assert _WORLD is not None
    return simulate_log(_WORLD, index, spec, Path(out_dir), plot)


def run(params: Params, out_dir: Path, progress: bool = True) -> list[LogResult]:
    """Simulate every configured log into `out_dir` (replaced atomically as a whole) and log to MLflow."""
    from pipeline.core.tracking import stage_run

    sim = simulate_params(params)
    world = build_world(params, sim)  # validates robot and foot pairs before any work
    out_dir = Path(out_dir)
    tmp = out_dir.with_name(out_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    first_of_type: set[str] = set()
    jobs = []
    for i, spec in enumerate(sim.logs):
        plot = sim.plots and spec.type not in first_of_type
        first_of_type.add(spec.type)
        jobs.append((i, spec, str(tmp), plot))
    robot_seconds = sum(s.duration_s for s in sim.logs)
    with stage_run(
        "simulate", {"seed": params.seed, "robot": asdict(params.robot), "simulate": params.raw["simulate"]}
    ):
        import mlflow

        start = time.perf_counter()
        workers = sim.workers or os.cpu_count() or 1
        results: list[LogResult] = []
        from rich.progress import Progress

        with Progress(disable=not progress, transient=True) as bar:
            task = bar.add_task("simulating", total=robot_seconds)
            if workers == 1 or len(jobs) == 1:
                global _WORLD
                _WORLD = world
                for job in jobs:
                    results.append(_work(job))
                    bar.advance(task, job[1].duration_s)
            else:
                with ProcessPoolExecutor(workers, initializer=_init_worker, initargs=(params, sim)) as pool:
                    # longest logs first keeps both cores busy to the end
                    order = sorted(jobs, key=lambda j: -j[1].duration_s)
                    for result, job in zip(pool.map(_work, order), order, strict=True):
                        results.append(result)
                        bar.advance(task, job[1].duration_s)
        results.sort(key=lambda r: r.name)
        wall = time.perf_counter() - start

        truth = {
            "note": "hidden simulator truth: for evaluation only, never a training input",
            "distortions": {s: d.to_dict() for s, d in world.distortions.items()},
            "model_errors": world.model_errors,
        }
        (tmp / "truth.json").write_text(json.dumps(truth, indent=1))
        summary = {
            "robot_seconds": robot_seconds,
            "wall_seconds": wall,
            "sim_seconds_per_wall_second": robot_seconds / wall,
            "logs": [asdict(r) for r in results],
        }
        (tmp / "summary.json").write_text(json.dumps(summary, indent=1))
        mlflow.log_metrics(
            {
                "robot_seconds": robot_seconds,
                "wall_seconds": wall,
                "sim_seconds_per_wall_second": robot_seconds / wall,
                "messages": sum(r.messages for r in results),
                "logs": len(results),
            }
        )
        for r in results:
            for s, e in r.raw_rmse.items():
                mlflow.log_metrics(
                    {
                        f"{r.name}.{s}.raw_rmse_force": e["force"],
                        f"{r.name}.{s}.raw_rmse_torque": e["torque"],
                        f"{r.name}.{s}.oracle_rmse_force": r.oracle_rmse[s]["force"],
                    }
                )
        mlflow.log_artifact(str(tmp / "summary.json"))
        mlflow.log_artifact(str(tmp / "truth.json"))
        if (tmp / "plots").is_dir():
            mlflow.log_artifacts(str(tmp / "plots"), artifact_path="plots")
    # swap in the new outputs only now that everything is written
    if out_dir.exists():
        old = out_dir.with_name(out_dir.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        out_dir.rename(old)
        tmp.rename(out_dir)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp.rename(out_dir)
    return results


def _cmd(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    results = run(params, Path(args.out_dir), progress=not args.quiet)
    total = sum(r.samples for r in results)
    print(f"simulate: {len(results)} logs, {total} samples -> {args.out_dir}")
    return 0


def add_cli(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate", help="generate simulated MCAP logs with known truth", description=__doc__.splitlines()[0]
    )
    p.add_argument("out_dir", help="output directory (e.g. data/sim)")
    p.add_argument("--params", type=Path, default=None, help="params file (default: repo params.yaml)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd)


__all__ = ["LogSpec", "SimulateParams", "Truth", "run", "simulate_log", "simulate_params"]
