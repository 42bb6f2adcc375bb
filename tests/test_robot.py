"""The URDF parser and the contact-rooted Pinocchio models, checked against Pinocchio's own URDF model."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from pipeline.core.errors import RobotModelError
from pipeline.physics.robot import RobotModel, load_robot, wrench_transform
from tests.factories.physics import check_pinocchio_joint_torques, random_state, to_pin

EXPECTED_SENSORS = {
    "l_arm_ft": "child_to_parent",
    "r_arm_ft": "child_to_parent",
    "l_leg_ft": "child_to_parent",
    "r_leg_ft": "child_to_parent",
    "l_foot_front_ft": "parent_to_child",
    "l_foot_rear_ft": "parent_to_child",
    "r_foot_front_ft": "parent_to_child",
    "r_foot_rear_ft": "parent_to_child",
}


def test_sensors_parsed_from_top_level_tags_only(robot: RobotModel) -> None:
    # the <gazebo> blocks repeat every sensor; only the 8 top-level tags count
    assert {s: ft.direction for s, ft in robot.sensors.items()} == EXPECTED_SENSORS
    for ft in robot.sensors.values():
        assert robot.joints[ft.joint].type == "fixed"
        assert robot.joints[ft.joint].child == ft.child_link
        assert ft.frame == "sensor"


def test_joints_match_pinocchio(robot: RobotModel) -> None:
    model = robot.pinocchio_model
    assert sorted(robot.joint_names) == sorted(model.names[1:])
    assert robot.total_mass() == pytest.approx(sum(i.mass for i in model.inertias), rel=1e-12)


def test_rooted_at_root_link_has_pinocchio_joint_torques(robot: RobotModel) -> None:
    """Same fixed base, two model builders: the joint torques of RNEA must agree."""
    check_pinocchio_joint_torques(robot, np.random.default_rng(1), 20)


@pytest.mark.parametrize("root", ["l_sole", "r_foot_front", "l_forearm"])
def test_rerooted_kinematics_match_pinocchio(robot: RobotModel, root: str) -> None:
    """Relative poses of every link are the same whichever link the tree is rooted at."""
    ref_model = robot.pinocchio_model
    ref_data = ref_model.createData()
    rooted = robot.rooted(root)
    data = rooted.model.createData()
    rng = np.random.default_rng(2)
    for q in random_state(robot, rng, 5)[0]:
        pin.framesForwardKinematics(ref_model, ref_data, to_pin(robot, q))
        qs = pin.neutral(rooted.model)
        qs[rooted.q_index] = q * rooted.sign
        pin.framesForwardKinematics(rooted.model, data, qs)
        ref_root = ref_data.oMf[ref_model.getFrameId(root)]
        for link in robot.links:
            expected = ref_root.inverse() * ref_data.oMf[ref_model.getFrameId(link)]
            got = data.oMf[rooted.model.getFrameId(link)]
            np.testing.assert_allclose(got.homogeneous, expected.homogeneous, atol=1e-9, err_msg=link)


def test_rigid_transform_and_wrench_transform(robot: RobotModel) -> None:
    model, data = robot.pinocchio_model, robot.pinocchio_model.createData()
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    a, b = "l_sole", "l_foot_front"
    expected = data.oMf[model.getFrameId(a)].inverse() * data.oMf[model.getFrameId(b)]
    np.testing.assert_allclose(robot.rigid_transform(a, b).homogeneous, expected.homogeneous, atol=1e-12)
    # wrench transform: f_a = R f_b, tau_a = R tau_b + p x R f_b
    a_T_b = robot.rigid_transform(a, b)
    f, tau = np.array([1.0, -2.0, 3.0]), np.array([0.5, 0.1, -0.2])
    got = wrench_transform(a_T_b) @ np.r_[f, tau]
    r, p = a_T_b.rotation, a_T_b.translation
    np.testing.assert_allclose(got, np.r_[r @ f, r @ tau + np.cross(p, r @ f)], atol=1e-12)
    with pytest.raises(RobotModelError, match="not rigidly attached"):
        robot.rigid_transform("l_sole", "r_sole")


def test_unknown_names_list_what_exists(icub: RobotModel) -> None:
    with pytest.raises(RobotModelError, match=r"no force_torque sensor named 'l_knee_ft'.*l_arm_ft"):
        icub.check_sensor("l_knee_ft")
    with pytest.raises(RobotModelError, match=r"no link named 'l_toe'.*l_sole"):
        icub.subtree("l_toe")
    with pytest.raises(RobotModelError, match="icub-models has: .*iCubGenova09"):
        load_robot("NoSuchRobot")
    with pytest.raises(RobotModelError, match="does not exist"):
        load_robot("/nonexistent/robot.urdf")


def test_urdf_without_ft_sensor(tmp_path) -> None:
    urdf = tmp_path / "arm.urdf"
    urdf.write_text("""<robot name="arm">
      <link name="base"/><link name="l1"><inertial><mass value="1"/>
        <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial></link>
      <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
        <limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>""")
    with pytest.raises(RobotModelError, match=r"arm.urdf: the URDF declares no <sensor"):
        load_robot(urdf)
    urdf.write_text("<robot><link name='a'/>")
    with pytest.raises(RobotModelError, match="not valid XML"):
        load_robot(urdf)


def test_with_inertials_changes_only_named_links(icub: RobotModel) -> None:
    heavy = icub.links["l_foot_front"]
    heavier = type(heavy)(mass=heavy.mass + 1.0, com=heavy.com, inertia=heavy.inertia)
    other = icub.with_inertials({"l_foot_front": heavier})
    assert other.total_mass() == pytest.approx(icub.total_mass() + 1.0)
    assert icub.links["l_foot_front"] is heavy
    with pytest.raises(RobotModelError):
        icub.with_inertials({"nope": heavier})
