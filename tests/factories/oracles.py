"""The test-only iDynTree oracle (tests/idyntree_ref.py), one estimator per robot shared by the dynamics
tests, and the sides of a sensor's cut computed from the URDF, independently of pipeline.physics.robot."""

from __future__ import annotations

import xml.etree.ElementTree as ET

from pipeline.physics.robot import RobotModel
from tests.idyntree_ref import IDynTreeFT

_ORACLES: dict[str, IDynTreeFT] = {}


def oracle(robot: RobotModel) -> IDynTreeFT:
    """The iDynTree estimator of `robot` (its URDF, the robot's joint order), made once per URDF."""
    key = str(robot.urdf_path)
    if key not in _ORACLES:
        _ORACLES[key] = IDynTreeFT(robot.urdf_path, robot.joint_names)
    return _ORACLES[key]


def both_sides_touch(urdf: str, sensor: str, contacts: list[str]) -> bool:
    """Cut the URDF graph at the sensor's joint; do contacts lie in both connected components?"""
    root = ET.parse(urdf).getroot()
    joint = next(s.find("parent").get("joint") for s in root.findall("sensor") if s.get("name") == sensor)
    edges = [
        (j.find("parent").get("link"), j.find("child").get("link"))
        for j in root.findall("joint")
        if j.get("name") != joint
    ]
    start = next(j.find("child").get("link") for j in root.findall("joint") if j.get("name") == joint)
    side, grew = {start}, True
    while grew:
        grew = False
        for a, b in edges:
            if (a in side) != (b in side):
                side |= {a, b}
                grew = True
    inside = [c in side for c in contacts]
    return any(inside) and not all(inside)
