"""Every robot of icub-models loads and gives labels; non-physical inertial parameters are refused.

References: Pinocchio's own URDF parser (joint torques, total mass) and statics (a still robot standing on
one sole: its leg sensor carries the weight of all above it).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import icub_models
import numpy as np
import pinocchio as pin
import pytest

from pipeline.core.errors import RobotModelError
from pipeline.physics.dynamics import ContactCase, expected_wrenches
from pipeline.physics.robot import load_robot, resolve_urdf
from pipeline.physics.urdf import checked_inertial
from tests.conftest import GRAVITY
from tests.factories.physics import check_pinocchio_joint_torques, random_state, to_pin

ROBOTS = sorted(icub_models.get_robot_names())
# iCubNancy01's ankles: ixx 4.77 kg m^2 on a 0.643 kg link (1000x its other moments and its siblings'
# ankles): an inertia no body has, refused (labels would carry a 4.77 kg m^2 ankle's torques)
REFUSED = {"iCubNancy01": r"link l_ankle_1: inertia violates the triangle inequality"}


def _has_ft_sensors(name: str) -> bool:
    root = ET.parse(icub_models.get_model_file(name)).getroot()
    return any(el.get("type") == "force_torque" for el in root.findall("sensor"))


WITH_FT = [name for name in ROBOTS if _has_ft_sensors(name)]


def test_the_package_lists_the_robots() -> None:
    assert "iCubGenova03" in WITH_FT and "iCubGenova09" in WITH_FT and len(WITH_FT) >= 15
    for name in sorted(set(ROBOTS) - set(WITH_FT)):
        with pytest.raises(RobotModelError, match="declares no <sensor"):
            load_robot(name)


@pytest.mark.parametrize("name", WITH_FT)
def test_icub_model_loads_and_labels(name: str) -> None:
    if name in REFUSED:
        with pytest.raises(RobotModelError, match=REFUSED[name]):
            load_robot(name)
        return
    robot = load_robot(name)
    ref = robot.pinocchio_model  # Pinocchio's own parser, on the file as it is
    assert robot.total_mass() == pytest.approx(sum(i.mass for i in ref.inertias), rel=1e-12)
    check_pinocchio_joint_torques(robot, np.random.default_rng(1), 3)

    # standing still on the left sole: l_leg_ft holds up everything above it, r_leg_ft the hanging leg
    q = random_state(robot, np.random.default_rng(2), 3)[0]
    still = np.zeros_like(q)
    out = expected_wrenches(robot, q, still, still, ContactCase.make({"l_sole"}, "l_sole", (0, 0, -GRAVITY)))
    m_above = robot.mass_of(robot.sensor_sides("l_leg_ft")[0])
    m_hanging = robot.mass_of(robot.sensor_sides("r_leg_ft")[1])
    assert m_above > 0.5 * robot.total_mass() and m_hanging > 1.0
    ref_data = ref.createData()
    for k in range(q.shape[0]):
        pin.framesForwardKinematics(ref, ref_data, to_pin(robot, q[k]))
        world_T_sole = ref_data.oMf[ref.getFrameId("l_sole")]
        for sensor, weight in (("l_leg_ft", m_above), ("r_leg_ft", -m_hanging)):
            ft = robot.sensors[sensor]
            world_T_child = ref_data.oMf[ref.getFrameId(ft.child_link)]
            sole_T_s = world_T_sole.inverse() * world_T_child * ft.child_T_sensor
            # child_to_parent: what the leg exerts on the body above it, upwards in the sole (= world) frame
            f_world = sole_T_s.rotation @ out.wrench[sensor][k, :3]
            np.testing.assert_allclose(f_world, [0, 0, weight * GRAVITY], atol=1e-8, err_msg=sensor)


def _doctored(tmp_path: Path, link: str, mass: str | None = None, inertia: dict | None = None) -> Path:
    """iCubGenova03's URDF with one link's mass or inertia replaced."""
    tree = ET.parse(resolve_urdf("iCubGenova03"))
    element = next(el for el in tree.getroot().findall("link") if el.get("name") == link).find("inertial")
    if mass is not None:
        element.find("mass").set("value", mass)
    for key, value in (inertia or {}).items():
        element.find("inertia").set(key, value)
    path = tmp_path / "model.urdf"
    tree.write(path)
    return path


def test_non_physical_inertials_are_refused_naming_the_link(tmp_path: Path) -> None:
    with pytest.raises(RobotModelError, match=r"model.urdf: link r_upper_leg: negative mass -2.175 kg"):
        load_robot(_doctored(tmp_path, "r_upper_leg", mass="-2.175"))
    # a point mass with a clearly negative moment: far beyond rounding of 2.175 kg at the link's size
    bad = {"ixx": "1e-4", "iyy": "-1e-4", "izz": "1e-4", "ixy": "0", "ixz": "0", "iyz": "0"}
    with pytest.raises(RobotModelError, match=r"link r_upper_leg: inertia is not positive semidefinite"):
        load_robot(_doctored(tmp_path, "r_upper_leg", inertia=bad))
    rod = {"ixx": "1e-3", "iyy": "1e-3", "izz": "3e-3", "ixy": "0", "ixz": "0", "iyz": "0"}
    with pytest.raises(RobotModelError, match=r"link r_lower_leg: inertia violates the triangle inequality"):
        load_robot(_doctored(tmp_path, "r_lower_leg", inertia=rod))
    with pytest.raises(RobotModelError, match=r"link r_hip_1: <inertial> has a non-finite number"):
        load_robot(_doctored(tmp_path, "r_hip_1", inertia={"ixx": "nan"}))


def test_rounding_is_clamped_to_the_point_mass() -> None:
    """iCubGenova03's r_hip_2 as written (diagonal -5.4e-20 kg m^2): a point mass, which Pinocchio takes."""
    robot = load_robot("iCubGenova03")
    written = ET.parse(robot.urdf_path).getroot()
    hip_el = next(el for el in written.findall("link") if el.get("name") == "r_hip_2")
    assert float(hip_el.find("inertial/inertia").get("ixx")) < 0.0
    hip = robot.links["r_hip_2"]
    assert hip.mass == pytest.approx(0.526)
    np.testing.assert_array_equal(hip.inertia, np.zeros((3, 3)))
    for link in robot.links.values():
        if link is not None and link.mass > 0:
            assert np.all(np.diag(link.inertia) >= 0.0)
            link.to_pinocchio()
    # a valid inertia passes unchanged, bit for bit
    foot = load_robot("iCubGenova09").links["l_foot_front"]
    assert checked_inertial(foot, 0.1, "l_foot_front") is foot
