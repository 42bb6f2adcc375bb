"""One simulated log: true motion -> true wrenches -> what the sensors make of it -> MCAP.

The motion comes from :mod:`pipeline.sim.motion`, the true wrenches of the "true" robot from
:mod:`pipeline.sim.truth`, the sensor readings from :mod:`pipeline.sim.distortion` and
:mod:`pipeline.sim.sensors`, the file from :mod:`pipeline.sim.recording`. Each log draws from its own
random streams (seed, stream, log index), so a log does not depend on which process generates it.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from pipeline.core.errors import ConfigError
from pipeline.core.io import atomic_path
from pipeline.logs.imu_axes import to_board
from pipeline.logs.serials import serial_record
from pipeline.physics.loads import META_KEY as META_LOADS
from pipeline.physics.loads import Load, loads_to_metadata, with_loads
from pipeline.sim.distortion import distort, oracle_inverse
from pipeline.sim.motion import Motion
from pipeline.sim.params import LogSpec
from pipeline.sim.recording import EPOCH_NS, Recording, stamps, write_recording
from pipeline.sim.sensors import encoder_readings, encoder_velocity, imu_readings, temperature_signals
from pipeline.sim.sites import KIND_FOOT, KIND_HAND, Site, interaction_sites
from pipeline.sim.truth import Truth, TruthComputer
from pipeline.sim.world import World, stream_rng


@dataclass
class LogResult:
    """What one simulated log reports back (also into summary.json). Errors: RMSE against the truth,
    per sensor (or foot pair, summed in the sole frame), force N and torque Nm."""

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


def sites(world: World) -> list[Site]:
    """Every FT sensor's site (`pipeline.sim.sites`), with the interaction params' overrides."""
    soles = {s: foot.sole for foot in world.foot_models for s in foot.sensors}
    given = world.sim.interaction.sites if world.sim.interaction is not None else None
    return interaction_sites(world.robot, soles, given)


def resolve_loads(world: World, spec: LogSpec) -> list[Load]:
    """The loads of a known-load log: 'hands' / 'feet' mean every hand / foot sensor's site (the point
    then offsets the site's), anything else a URDF link."""
    out = []
    for entry in spec.loads:
        kind = {"hands": KIND_HAND, "feet": KIND_FOOT}.get(entry.link)
        if kind is None:
            world.robot.check_link(entry.link, "load link")
            out.append(Load(entry.link, entry.mass_kg, entry.point))
            continue
        for site in sites(world):
            if site.kind == kind:
                point = tuple(float(a + b) for a, b in zip(site.point, entry.point, strict=True))
                out.append(Load(site.link, entry.mass_kg, point))  # type: ignore[arg-type]
    return out


def make_motion(world: World, spec: LogSpec, rng: np.random.Generator) -> Motion:
    """The true motion of the log `spec` at the simulation rate."""
    gen, rate = world.motions, world.sim.rate_hz
    if spec.type in ("pole", "known_load"):
        motion = gen.pole(rng, spec.duration_s, rate)
        if world.sim.push is not None and spec.type == "pole":
            from pipeline.sim.push import add_pushes

            motion = add_pushes(gen.kin, motion, push_links(world), world.sim.push)
        return motion
    if spec.type == "interaction":
        from pipeline.sim.push import add_interaction, interaction_events

        if world.sim.interaction is None:
            raise ConfigError("an interaction log needs deploy.interaction (deployment logs only)")
        motion = gen.pole(rng, spec.duration_s, rate)
        events = interaction_events(sites(world), world.sim.interaction)
        return add_interaction(gen.kin, motion, events, world.params.robot.gravity, spec.duration_s)
    if spec.type == "standing":
        return gen.standing(rng, spec.duration_s, rate)
    if spec.type == "poses":
        return gen.poses(rng, spec.duration_s, rate)
    if spec.type == "balancing":
        return gen.balancing(rng, spec.duration_s, rate, spec.foot)
    if spec.type == "half_foot":
        return gen.balancing(rng, spec.duration_s, rate, spec.foot, spec.part)
    return gen.walking(rng, spec.duration_s, rate)


def push_links(world: World) -> list[str]:
    """The links pushed in pole logs: per foot, the link that carries its sensors (the ankle), below every
    leg joint and above the foot sensors."""
    return [world.robot.sensors[foot.front].parent_link for foot in world.foot_models]


def sensor_readings(
    world: World, motion: Motion, truth: Truth, t_ft: np.ndarray, rng: np.random.Generator
) -> dict[str, dict[str, np.ndarray]]:
    """Per FT sensor: the truth at the FT board's sample times `t_ft` (s) and what the sensor reads.

    Keys: ``true``, ``distorted``, ``raw``, ``oracle`` (N, 6) N/Nm; ``acc`` (N, 3) m/s^2; ``gyro`` (N, 3)
    rad/s; ``temp`` (published) and ``temp_true`` (N,) deg C. The temperature follows the activity
    (joint speed); each sensor heats by its own fixed factor.
    """
    sim, seed, dt = world.sim, world.params.seed, 1.0 / world.sim.rate_hz
    activity = np.clip(np.linalg.norm(motion.dq, axis=1) / sim.activity_scale, 0.0, 1.0)
    out = {}
    for i, s in enumerate(world.robot.sensors):
        heat = 0.8 + 0.4 * stream_rng(seed, 3, i).random()
        temp_true, temp_pub = temperature_signals(rng, np.clip(activity * heat, 0, 1), dt, sim.thermal)
        # the FT board samples at its own stamps: the truth there, by interpolation of the smooth signals
        w_true = np.stack([np.interp(t_ft, motion.t, truth.wrench[s][:, a]) for a in range(6)], axis=1)
        temp_at = np.interp(t_ft, motion.t, temp_true)
        step = float(np.median(np.diff(t_ft))) if len(t_ft) > 1 else dt
        distorted, raw = distort(world.distortions[s], w_true, temp_at, rng, step)
        acc, gyro = imu_readings(rng, truth.proper_acc[s], truth.gyro[s], dt, sim.imu)
        if s in sim.imu.axes:  # a board whose IMU is mounted in other axes reads in them
            acc, gyro = np.split(to_board(np.c_[acc, gyro], sim.imu.axes[s]), 2, axis=1)
        out[s] = dict(
            true=w_true,
            distorted=distorted,
            raw=raw,
            oracle=oracle_inverse(world.distortions[s], raw, temp_at),
            acc=acc,
            gyro=gyro,
            temp=temp_pub,
            temp_true=temp_true,
        )
        if truth.external is not None:
            ext = truth.external[s]
            out[s]["external"] = np.stack([np.interp(t_ft, motion.t, ext[:, a]) for a in range(6)], axis=1)
    return out


def log_metadata(
    world: World, spec: LogSpec, name: str, motion: Motion, loads: list[Load]
) -> dict[str, dict[str, str]]:
    """The MCAP metadata record ``experiment`` (contacts and fixed link only where constant; the loads of a
    known-load log; the sensors' serials of ``robot.serials``, `pipeline.logs.serials`)."""
    robot_params = world.params.robot
    extra = {META_LOADS: loads_to_metadata(loads)} if loads else {}
    return {
        "experiment": {
            "type": spec.type,
            "robot": robot_params.urdf,
            "role": spec.role,
            "contacts": ",".join(sorted(motion.contact_sets[0])) if len(motion.contact_sets) == 1 else "",
            "fixed_link": str(motion.fixed_links[0]) if len(set(motion.fixed_links)) == 1 else "",
            "gravity": f"0 0 {-robot_params.gravity}",
            "sim": "true",
            "seed": str(world.params.seed),
            "duration_s": f"{spec.duration_s:g}",
            "rate_hz": f"{world.sim.rate_hz:g}",
            "log": name,
            "foot": spec.foot,
            "part": spec.part,
            **serial_record(robot_params.serials),
            **extra,
        }
    }


def _rmse(err: np.ndarray) -> dict[str, float]:
    return {
        "force": float(np.sqrt(np.mean(err[:, :3] ** 2))),
        "torque": float(np.sqrt(np.mean(err[:, 3:] ** 2))),
    }


def _errors(world: World, data: dict[str, dict[str, np.ndarray]]) -> tuple[dict, dict, dict]:
    """Raw and oracle RMSE per sensor, and raw RMSE of each foot pair's sum in the sole frame."""
    raw = {s: _rmse(d["raw"] - d["true"]) for s, d in data.items()}
    oracle = {s: _rmse(d["oracle"] - d["true"]) for s, d in data.items()}
    pairs = {}
    for pair in world.pairs:
        front, rear = data[pair.front], data[pair.rear]
        err = (front["raw"] - front["true"]) @ pair.sole_X_front.T + (
            rear["raw"] - rear["true"]
        ) @ pair.sole_X_rear.T
        pairs[pair.name] = _rmse(err)
    return raw, oracle, pairs


def simulate_log(world: World, index: int, spec: LogSpec, out_dir: Path, plot: bool) -> LogResult:
    """Generate one log and write ``<out_dir>/<name>.mcap`` (atomically); returns its summary."""
    start = time.perf_counter()
    sim, seed, name = world.sim, world.params.seed, spec.name(index)
    motion = make_motion(world, spec, stream_rng(seed, 10, index))
    loads = resolve_loads(world, spec)
    truth_robot = with_loads(world.truth_robot, loads, name)  # a known mass is known exactly
    truth = TruthComputer(truth_robot, world.foot_models, world.params.robot.gravity).compute(motion)
    rng = stream_rng(seed, 11, index)
    ft_stamps = stamps(rng, motion.t, sim.timing.ft_offset_s, sim.timing.jitter_s)
    data = sensor_readings(world, motion, truth, (ft_stamps - EPOCH_NS) * 1e-9, rng)
    q_meas = encoder_readings(rng, motion.q, sim.encoder_resolution_rad, sim.encoder_noise_rad)
    rec = Recording(
        metadata=log_metadata(world, spec, name, motion, loads),
        joint_names=world.robot.joint_names,
        js_stamps=stamps(rng, motion.t, 0.0, sim.timing.jitter_s),
        q=q_meas,
        dq=encoder_velocity(q_meas, 1.0 / sim.rate_hz),
        contacts=np.array([",".join(sorted(c)) for c in truth.contacts], dtype=object),
        ft_stamps=ft_stamps,
        sensors=data,
        joint_torque=truth.joint_torque,
    )
    with atomic_path(out_dir / f"{name}.mcap") as tmp:
        messages = write_recording(tmp, rec, world.params.topics, sim.timing, sim.rate_hz, rng)
    raw, oracle, pairs = _errors(world, data)
    temps = {s: [float(d["temp"].min()), float(d["temp"].max())] for s, d in data.items()}
    result = LogResult(
        name, asdict(spec), motion.n, messages, time.perf_counter() - start, raw, oracle, pairs, temps
    )
    if plot:
        from pipeline.sim.plots import plot_log

        result.plots = plot_log(out_dir / "plots", name, world.robot, motion, truth, data)
    return result
