"""The feet of a robot: which FT sensors cut each foot off its leg, its sole frame, its contact parts.

A foot is found in the URDF without names of sensors or groups: the FT sensors whose child side holds no
movable joint (a rigid end of the tree) and that share a parent link (the ankle) form one foot; its sole is
the link ending in ``sole`` rigidly attached to that side (``l_sole``), and its name the sole's with
``sole`` -> ``foot`` (``l_foot``). iCub 3 and ergoCub feet have two sensors (front and rear: the one whose
part lies further along the sole's x axis is the front), iCub 2.x feet one. Only a foot with two sensors is
a foot pair (`pipeline.physics.robot.FootPair`: the summed label in the sole frame, a pair group); every
foot serves contact detection and the simulator. ``robot.foot_pairs`` in params, when given, names the
pairs instead (and then the feet are those pairs).

The parts of a foot that touch the floor are its sensors' child links (front, rear); each has a contact
centre in the sole frame: the link's origin for a two-part foot. A one-part foot's front and rear
centres are a quarter of its length before and behind its centre of mass (on the sole's x axis), the
length being that of the uniform box with the foot's mass and inertia (`box_length`): the centres of
its two halves.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from pipeline.core.errors import RobotModelError
from pipeline.physics.robot import FootPair, RobotModel, wrench_transform

SOLE_SUFFIX = "sole"


@dataclass(frozen=True)
class Foot:
    """One foot. sensors: (front, rear) or (the one sensor,); sole_X: (6, 6) wrench transform of each
    sensor's frame to the sole frame; signs: +1 where a sensor reads what the rest of the robot exerts
    on the foot (parent_to_child), -1 otherwise; foot_links: every link the sensors cut off; contact
    links (front, rear; equal for one sensor) and their centres (2, 3) in the sole frame, m."""

    name: str
    sole: str
    sensors: tuple[str, ...]
    sole_X: tuple[np.ndarray, ...] = field(repr=False)
    signs: tuple[float, ...]
    foot_links: frozenset[str] = field(repr=False)
    front_link: str
    rear_link: str
    centers: np.ndarray = field(repr=False)
    pair: FootPair | None = None

    @property
    def front(self) -> str:
        return self.sensors[0]

    @property
    def rear(self) -> str:
        return self.sensors[-1]

    @property
    def links(self) -> frozenset[str]:
        """The links that touch the floor when the whole foot does."""
        return frozenset((self.front_link, self.rear_link))

    def rest_on_foot(self, readings: Mapping[str, np.ndarray]) -> np.ndarray:
        """(N, 6) wrench the rest of the robot exerts on the foot, in the sole frame (moment about its
        origin), from its sensors' readings (N, 6) in their frames and measure directions."""
        return sum(
            sign * (np.asarray(readings[s]) @ x.T)
            for s, x, sign in zip(self.sensors, self.sole_X, self.signs, strict=True)
        )


def box_length(robot: RobotModel, link: str, frame: str) -> float:
    """m: the length along `frame`'s x axis of the uniform box with `link`'s mass and inertia
    (I_yy + I_zz - I_xx = m a^2 / 6 about the centre of mass, axes of `frame`)."""
    inertial = robot.links[link]
    if inertial is None or inertial.mass <= 0:
        raise RobotModelError(f"{robot.urdf_path}: foot link {link!r} has no mass: set robot.foot_pairs")
    rot = robot.rigid_transform(frame, link).rotation
    inertia = rot @ np.asarray(inertial.inertia) @ rot.T
    d = np.diag(inertia)
    return float(np.sqrt(max(6.0 * (d[1] + d[2] - d[0]) / inertial.mass, 0.0)))


def make_foot(robot: RobotModel, name: str, sole: str, sensors: Sequence[str]) -> Foot:
    """A foot of one sensor, or of two (front, rear: then also its `FootPair`)."""
    fts = [robot.check_sensor(s) for s in sensors]
    robot.check_link(sole, "sole link")
    links = frozenset().union(*(robot.sensor_sides(s)[1] for s in sensors))
    sole_x = tuple(wrench_transform(robot.sensor_pose_in_link(s, sole)) for s in sensors)
    signs = tuple(1.0 if ft.direction == "parent_to_child" else -1.0 for ft in fts)
    pair = robot.foot_pair(name, sensors[0], sensors[1], sole) if len(sensors) == 2 else None
    front_link, rear_link = fts[0].child_link, fts[-1].child_link
    if pair is not None:
        centers = np.array(
            [robot.rigid_transform(sole, link).translation for link in (front_link, rear_link)]
        )
    else:
        com = robot.rigid_transform(sole, front_link).act(robot.links[front_link].com)
        quarter = box_length(robot, front_link, sole) / 4.0
        centers = np.array([[com[0] + quarter, com[1], 0.0], [com[0] - quarter, com[1], 0.0]])
    return Foot(name, sole, tuple(sensors), sole_x, signs, links, front_link, rear_link, centers, pair)


def derive_feet(robot: RobotModel) -> list[Foot]:
    """The feet of the URDF (module docstring), sorted by name."""
    groups: dict[str, list[str]] = {}
    for s, ft in robot.sensors.items():
        child_side = robot.sensor_sides(s)[1]
        if not any(j.movable and j.child in child_side for j in robot.joints.values()):
            groups.setdefault(ft.parent_link, []).append(s)
    feet = []
    for parent, sensors in sorted(groups.items()):
        links = frozenset().union(*(robot.rigid_body_links(robot.sensors[s].child_link) for s in sensors))
        soles = sorted(link for link in links if link.endswith(SOLE_SUFFIX))
        if len(soles) != 1 or len(sensors) > 2:
            raise RobotModelError(
                f"{robot.urdf_path}: cannot tell the foot below {parent} (FT sensors {', '.join(sensors)}; "
                f"links ending in '{SOLE_SUFFIX}': {', '.join(soles) or 'none'}): set robot.foot_pairs"
            )
        sole = soles[0]
        if len(sensors) == 2:
            x = [robot.rigid_transform(sole, robot.sensors[s].child_link).translation[0] for s in sensors]
            sensors = sorted(sensors, key=lambda s: -x[sensors.index(s)])
        name = sole[: -len(SOLE_SUFFIX)] + "foot" if sole != SOLE_SUFFIX else parent
        feet.append(make_foot(robot, name, sole, sensors))
    return sorted(feet, key=lambda f: f.name)


def foot_of_pair(robot: RobotModel, pair: FootPair) -> Foot:
    """The foot of a foot pair."""
    return make_foot(robot, pair.name, pair.sole, (pair.front, pair.rear))


def robot_feet(robot: RobotModel, foot_pairs: Sequence | None) -> list[Foot]:
    """The feet: those of ``robot.foot_pairs`` (FootPairParams: name, front, rear, sole) when params give
    it, else derived from the URDF."""
    if foot_pairs is None:
        return derive_feet(robot)
    return [make_foot(robot, p.name, p.sole, (p.front, p.rear)) for p in foot_pairs]


def robot_pairs(robot: RobotModel, foot_pairs: Sequence | None) -> list[FootPair]:
    """The foot pairs (feet of two sensors) of `robot_feet`, in its order."""
    return [f.pair for f in robot_feet(robot, foot_pairs) if f.pair is not None]
