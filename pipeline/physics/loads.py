"""Known loads: point masses rigidly attached to links of the robot (the classic in-situ calibration trick).

A known mass at a known point of a hand or a foot breaks the relation a free limb's wrenches otherwise
follow (a free arm's torque is its own weight's moment: torque ~ c x force), so its labels excite
directions of wrench space no free motion does. A load becomes part of the robot model: the link's
inertial parameters gain a point mass, and every expected wrench (RNEA) includes its weight and inertia.

In a log a load is declared in the experiment metadata (MCAP record ``experiment``, or a sidecar's
``loads``) as a JSON list ``[{"link": ..., "mass_kg": ..., "point": [x, y, z]}]``, point in the link frame
(m).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from pipeline.core.errors import DataError
from pipeline.physics.robot import RobotModel
from pipeline.physics.urdf import LinkInertial

META_KEY = "loads"  # key of the experiment metadata


@dataclass(frozen=True)
class Load:
    """A point mass of `mass_kg` at `point` (m, in `link`'s frame)."""

    link: str
    mass_kg: float
    point: tuple[float, float, float]

    def to_dict(self) -> dict[str, Any]:
        return {"link": self.link, "mass_kg": self.mass_kg, "point": list(self.point)}


def loads_to_metadata(loads: Sequence[Load]) -> str:
    """The metadata value of `loads` (a JSON list)."""
    return json.dumps([load.to_dict() for load in loads])


def loads_from_metadata(experiment: Mapping[str, Any], where: str) -> list[Load]:
    """The loads an experiment record declares (none without the key). Raises DataError naming `where`."""
    raw = experiment.get(META_KEY)
    if raw in (None, "", "[]"):
        return []
    try:
        entries = json.loads(raw) if isinstance(raw, str) else raw
        out = []
        for e in entries:
            point = tuple(float(v) for v in e.get("point", (0.0, 0.0, 0.0)))
            mass = float(e["mass_kg"])
            if len(point) != 3 or not all(map(math.isfinite, point)) or not 0 < mass < math.inf:
                raise ValueError(f"bad mass or point in {e!r}")
            out.append(Load(str(e["link"]), mass, point))  # type: ignore[arg-type]
    except (TypeError, ValueError, KeyError, AttributeError) as exc:
        raise DataError(
            f"{where}: experiment metadata {META_KEY!r} must be a list of {{link, mass_kg, point}}: {exc}"
        ) from None
    return out


def with_loads(robot: RobotModel, loads: Sequence[Load], where: str = "") -> RobotModel:
    """`robot` with each load's point mass added to its link's inertial parameters (itself without loads).

    Raises DataError naming `where` for a link the URDF does not have.
    """
    if not loads:
        return robot
    total: dict[str, pin.Inertia] = {}
    for load in loads:
        if load.link not in robot.links:
            raise DataError(f"{where}: load on link {load.link!r}, which the URDF {robot.name} does not have")
        own = robot.links[load.link]
        base = total.get(load.link, own.to_pinocchio() if own is not None else pin.Inertia.Zero())
        mass = pin.Inertia(load.mass_kg, np.asarray(load.point, dtype=float), np.zeros((3, 3)))
        total[load.link] = base + mass
    overrides = {
        link: LinkInertial(float(i.mass), np.array(i.lever), np.array(i.inertia)) for link, i in total.items()
    }
    return robot.with_inertials(overrides)
