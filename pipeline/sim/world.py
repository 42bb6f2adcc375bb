"""The hidden world of one simulation run: the true robot, the sensors' distortions, the motion generator.

Everything here is drawn once per run from the seed in params.yaml and shared by all its logs; the
labeller and the calibration only ever see the nominal URDF and the raw readings.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from pipeline.core.config import Params, repo_root, resolve_urdf
from pipeline.core.errors import ConfigError
from pipeline.logs.imu_axes import check_sensors
from pipeline.physics.feet import Foot as RobotFoot
from pipeline.physics.feet import robot_feet
from pipeline.physics.robot import FootPair, LinkInertial, RobotModel, load_robot
from pipeline.sim.distortion import SensorDistortion, draw_distortion
from pipeline.sim.kinematics import Foot
from pipeline.sim.motion import MotionGenerator
from pipeline.sim.params import SimulateParams


def stream_rng(seed: int, *stream: int) -> np.random.Generator:
    """An independent generator per (seed, stream...): results do not depend on generation order."""
    return np.random.default_rng([seed, *stream])


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
    motions: MotionGenerator  # its .p: the motion params used (URDF-derived where params say null)
    base_params: Params | None = (
        None  # deployment worlds: the params the world was built from (training seed)
    )
    # every foot with its sensors (one or two), for the true ground loads (pipeline.physics.feet)
    foot_models: list[RobotFoot] = field(default_factory=list)


def build_world(params: Params, sim: SimulateParams) -> World:
    """Load the robot, draw its model errors and every sensor's distortion, derive the motion params."""
    robot = load_robot(resolve_urdf(params.robot.urdf, repo_root()))
    models = robot_feet(robot, params.robot.foot_pairs)
    check_feet(sim, [f.name for f in models])
    check_sensors(sim.imu.axes, robot.sensors, "simulate.imu.axes")
    pairs = [f.pair for f in models if f.pair is not None]
    feet = [
        Foot(f.name, f.sole, f.front_link, f.rear_link, tuple(f.centers[0]), tuple(f.centers[1]))
        for f in models
    ]
    truth_robot, errors = true_robot(robot, sim, stream_rng(params.seed, 1))
    distortions = {
        s: draw_distortion(stream_rng(params.seed, 2, i), sim.sensors) for i, s in enumerate(robot.sensors)
    }
    for pair in pairs:
        # one foot, one mounting: its two sensors' offsets share their signs (magnitudes independent),
        # which is what makes the raw pair sums as far off as the thesis's (50-100 N)
        front, rear = distortions[pair.front].to_dict(), distortions[pair.rear].to_dict()
        rear["offset"] = (np.abs(rear["offset"]) * np.sign(front["offset"])).tolist()
        distortions[pair.rear] = SensorDistortion.from_dict(rear)
    motions = MotionGenerator(robot, feet, sim.motion)
    if sim.shift is not None:
        # a later day of the same robot: the same hidden distortions with drifted offsets; its motions and
        # noise from its own seed (every per-log stream below reads world.params.seed)
        distortions = shifted_offsets(
            distortions, sim.shift.seed, sim.shift.offset_force, sim.shift.offset_torque
        )
        shifted = replace(params, seed=sim.shift.seed)
        return World(
            shifted, sim, robot, truth_robot, feet, pairs, distortions, errors, motions, params, models
        )
    return World(params, sim, robot, truth_robot, feet, pairs, distortions, errors, motions, None, models)


def check_feet(sim: SimulateParams, feet: list[str]) -> None:
    """Every log's supporting foot is a foot of the robot (checked here when the feet come from the URDF)."""
    key = "deploy.logs" if sim.shift is not None else "simulate.logs"
    for i, spec in enumerate(sim.logs):
        if spec.type in ("balancing", "half_foot") and spec.foot not in feet:
            raise ConfigError(
                f"{key}[{i}].foot must be one of {', '.join(feet)} (the robot's feet), got {spec.foot!r}"
            )


def shifted_offsets(
    distortions: dict[str, SensorDistortion], seed: int, force_n: float, torque_nm: float
) -> dict[str, SensorDistortion]:
    """Every sensor's distortion, its offset moved per axis by uniform +- `force_n` (N) / `torque_nm` (Nm)."""
    bound = np.repeat([force_n, torque_nm], 3)
    out = {}
    for i, (name, d) in enumerate(distortions.items()):
        data = d.to_dict()
        data["offset"] = (
            np.asarray(data["offset"]) + stream_rng(seed, 4, i).uniform(-1, 1, 6) * bound
        ).tolist()
        out[name] = SensorDistortion.from_dict(data)
    return out
