"""Where the world meets each FT sensor's limb: the point a push or a carried load acts on.

Every FT sensor cuts the robot in two; with the robot on the pole (root_link clamped) one side hangs free.
The *site* of a sensor is where an external force on that free side is most natural, derived from the URDF
alone so that nothing here is robot-specific:

- a foot sensor (its free side holds a sole frame and no other FT sensor): its child link (the foot part),
  at the point of the sole plane below the part's origin;
- a sensor with other FT sensors below it (a leg): the link that carries them (the ankle), at its origin;
- any other sensor (an arm): the end of its limb (the hand), found by following the kinematic chain from
  the sensor while it does not branch into two or more links with mass, at the link's origin.

A site names a link and a point in that link's frame (m); ``deploy.interaction.sites`` overrides it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from pipeline.core.errors import ConfigError
from pipeline.physics.robot import RobotModel

KIND_FOOT, KIND_ANKLE, KIND_HAND = "sole", "ankle", "hand"


@dataclass(frozen=True)
class Site:
    """The place where sensor `sensor`'s free side meets the world."""

    sensor: str
    link: str
    point: tuple[float, float, float]  # in the link frame, m
    kind: str  # sole, ankle or hand (how it was derived; "given" when params set it)


def free_side(robot: RobotModel, sensor: str) -> frozenset[str]:
    """The side of `sensor`'s cut that does not hold root_link (what hangs free on the pole)."""
    parent_side, child_side = robot.sensor_sides(sensor)
    return parent_side if robot.root_link in child_side else child_side


def _children(robot: RobotModel) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for joint in robot.joints.values():
        out.setdefault(joint.parent, []).append(joint.child)
    return out


def _limb_end(robot: RobotModel, start: str) -> str:
    """Follow the chain from `start` while exactly one child subtree has mass; return where it stops."""
    children = _children(robot)
    current = start
    while True:
        massive = [c for c in children.get(current, []) if robot.mass_of(robot.subtree(c)) > 0.0]
        if len(massive) != 1:
            return current
        current = massive[0]


def _sole_point(robot: RobotModel, link: str, sole: str) -> tuple[float, float, float]:
    """The point of the sole plane (z = 0 of `sole`) below `link`'s origin, in `link`'s frame."""
    sole_T_link = robot.rigid_transform(sole, link)
    below = sole_T_link.translation.copy()
    below[2] = 0.0
    return tuple(float(v) for v in sole_T_link.inverse().act(below))


def derive_site(robot: RobotModel, sensor: str, soles: Mapping[str, str]) -> Site:
    """The site of `sensor` (module docstring). `soles`: sole frame of each foot sensor (the foot pairs'
    sensors); a sensor whose free side holds a sole frame and no other FT sensor is a foot sensor too."""
    ft = robot.check_sensor(sensor)
    side = free_side(robot, sensor)
    below = [s for s, other in robot.sensors.items() if s != sensor and other.child_link in side]
    on_sole = [soles[sensor]] if sensor in soles else [f for f in set(soles.values()) if f in side]
    if below:
        # the link carrying the FT sensors below, nearest to this one (the ankle above the foot sensors)
        parents = {robot.sensors[s].parent_link for s in below}
        carriers = [p for p in parents if not any(robot.sensors[s].child_link in robot.subtree(p) and
                    robot.sensors[s].parent_link != p for s in below)]  # fmt: skip
        link = sorted(carriers or parents)[0]
        return Site(sensor, link, (0.0, 0.0, 0.0), KIND_ANKLE)
    start = ft.child_link if ft.child_link in side else ft.parent_link
    if on_sole:
        return Site(sensor, start, _sole_point(robot, start, on_sole[0]), KIND_FOOT)
    return Site(sensor, _limb_end(robot, start), (0.0, 0.0, 0.0), KIND_HAND)


def interaction_sites(
    robot: RobotModel, soles: Mapping[str, str], given: Mapping[str, Mapping[str, object]] | None = None
) -> list[Site]:
    """The site of every FT sensor of `robot` (sorted by sensor), `given` ones (sensor -> {link, point})
    replacing the derived ones. Raises ConfigError naming the key for an unknown sensor or link."""
    given = dict(given or {})
    for sensor, entry in given.items():
        if sensor not in robot.sensors:
            raise ConfigError(
                f"deploy.interaction.sites.{sensor}: not an FT sensor of the robot "
                f"(sensors: {', '.join(sorted(robot.sensors))})"
            )
        link = entry.get("link")
        if link not in robot.links:
            raise ConfigError(f"deploy.interaction.sites.{sensor}.link: no link {link!r} in the URDF")
    out = []
    for sensor in sorted(robot.sensors):
        if sensor in given:
            entry = given[sensor]
            point = np.asarray(entry.get("point", (0.0, 0.0, 0.0)), dtype=float)
            out.append(Site(sensor, str(entry["link"]), tuple(float(v) for v in point), "given"))
        else:
            out.append(derive_site(robot, sensor, soles))
    return out
