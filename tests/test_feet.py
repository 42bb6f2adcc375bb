"""Feet from the URDF alone: iCub 3 / ergoCub pairs as params used to name them, iCub 2.x one sensor per
foot (labels against iDynTree, the simulator's truth against link-by-link momentum), a made-up robot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.physics.dynamics import ContactCase, expected_wrenches
from pipeline.physics.feet import box_length, derive_feet
from pipeline.physics.robot import RobotModel, load_robot
from tests.conftest import FOOT_PAIRS, GRAVITY
from tests.factories.oracles import both_sides_touch, oracle
from tests.factories.params import repo_params
from tests.idyntree_ref import random_in_limits

ICUB2 = ["iCubGenova02", "iCubGenova04"]


def test_pairs_of_icub3_and_ergocub_are_the_ones_params_named(robot: RobotModel) -> None:
    feet = derive_feet(robot)
    assert {f.name: (f.front, f.rear, f.sole) for f in feet} == FOOT_PAIRS
    for foot in feet:
        pair = robot.foot_pair(foot.name, *FOOT_PAIRS[foot.name])
        np.testing.assert_array_equal(foot.pair.sole_X_front, pair.sole_X_front)
        np.testing.assert_array_equal(foot.pair.sole_X_rear, pair.sole_X_rear)


@pytest.mark.parametrize("name", ICUB2)
def test_icub2_feet_have_one_sensor_and_no_pair(name: str) -> None:
    robot = load_robot(name)
    feet = derive_feet(robot)
    assert [(f.name, f.sole, f.sensors, f.pair) for f in feet] == [
        ("l_foot", "l_sole", ("l_foot_ft",), None),
        ("r_foot", "r_sole", ("r_foot_ft",), None),
    ]
    for foot in feet:  # the two halves' centres: before and behind the centre of mass, on the sole
        front, rear = foot.centers
        assert front[0] > rear[0] and front[2] == rear[2] == 0.0
        assert 0.05 < front[0] - rear[0] < 0.15  # half of a 10-30 cm foot


_BOX = (0.24, 0.1, 0.04)  # m: length, width, height of the made-up robot's right heel
_URDF = """<robot name="biped">
  <link name="base"><inertial><mass value="5"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/>
  </inertial></link>
  <link name="left_shank"><inertial><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="left_paw"><inertial><mass value="0.5"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.002" iyz="0" izz="0.002"/></inertial></link>
  <link name="left_sole"/>
  <link name="right_shank"><inertial><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="right_toe"><inertial><mass value="0.2"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.001"/></inertial></link>
  <link name="right_heel"><inertial><origin xyz="0 0 0" rpy="0 0 1.5707963267948966"/><mass value="{m}"/>
    <inertia ixx="{iyy}" ixy="0" ixz="0" iyy="{ixx}" iyz="0" izz="{izz}"/></inertial></link>
  <link name="right_sole"/>
  <joint name="left_knee" type="revolute"><parent link="base"/><child link="left_shank"/>
    <origin xyz="0 0.1 -0.3"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="left_ft_joint" type="fixed"><parent link="left_shank"/><child link="left_paw"/>
    <origin xyz="0 0 -0.3"/></joint>
  <joint name="left_sole_joint" type="fixed"><parent link="left_paw"/><child link="left_sole"/>
    <origin xyz="0 0 -0.05"/></joint>
  <joint name="right_knee" type="revolute"><parent link="base"/><child link="right_shank"/>
    <origin xyz="0 -0.1 -0.3"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="right_heel_joint" type="fixed"><parent link="right_shank"/><child link="right_heel"/>
    <origin xyz="-0.05 0 -0.3"/></joint>
  <joint name="right_toe_joint" type="fixed"><parent link="right_shank"/><child link="right_toe"/>
    <origin xyz="0.07 0 -0.3"/></joint>
  <joint name="right_sole_joint" type="fixed"><parent link="right_heel"/><child link="right_sole"/>
    <origin xyz="0.05 0 -0.05"/></joint>
  <sensor name="paw_ft" type="force_torque"><parent joint="left_ft_joint"/>
    <force_torque><frame>child</frame><measure_direction>child_to_parent</measure_direction></force_torque>
  </sensor>
  <sensor name="heel_ft" type="force_torque"><parent joint="right_heel_joint"/>
    <force_torque><frame>child</frame><measure_direction>parent_to_child</measure_direction></force_torque>
  </sensor>
  <sensor name="toe_ft" type="force_torque"><parent joint="right_toe_joint"/>
    <force_torque><frame>child</frame><measure_direction>parent_to_child</measure_direction></force_torque>
  </sensor>
</robot>
"""


def test_a_made_up_biped_gets_its_feet_and_box_lengths(tmp_path: Path) -> None:
    """Nothing iCub-specific: feet found by the rigid ends of the tree and the *sole links; the front of a
    pair is the part further along the sole's x axis (whatever the file's order); box length from inertia."""
    m, (a, b, c) = 0.6, _BOX
    box = {
        "m": m,
        "ixx": m * (b * b + c * c) / 12,
        "iyy": m * (a * a + c * c) / 12,
        "izz": m * (a * a + b * b) / 12,
    }
    # given in an inertial frame turned a quarter about z (x' = the link's y): the box's length a lies
    # along the link's and the sole's x axis
    path = tmp_path / "biped.urdf"
    path.write_text(_URDF.format(**box))
    robot = load_robot(path)
    feet = {f.name: f for f in derive_feet(robot)}
    assert set(feet) == {"left_foot", "right_foot"}
    assert feet["left_foot"].sensors == ("paw_ft",) and feet["left_foot"].pair is None
    right = feet["right_foot"]
    assert right.sensors == ("toe_ft", "heel_ft") and right.pair is not None and right.sole == "right_sole"
    assert box_length(robot, "right_heel", "right_sole") == pytest.approx(a, rel=1e-9)
    assert box_length(robot, "right_heel", "right_sole") != pytest.approx(b)
    readings = {"toe_ft": np.array([[0, 0, 10.0, 0, 0, 0]]), "heel_ft": np.array([[0, 0, 30.0, 0, 0, 0]])}
    np.testing.assert_allclose(right.rest_on_foot(readings)[0, :3], [0, 0, 40.0])  # parent_to_child: +


@pytest.mark.parametrize("name", ICUB2)
def test_icub2_labels_match_idyntree(name: str) -> None:
    """Expected wrenches of iCub 2.x (one sensor per foot) against iDynTree's estimator, 1e-6 N / Nm:
    on the pole, on each foot, in double support (every sensor with a free side)."""
    robot = load_robot(name)
    gravity = np.array([0.0, 0.0, -GRAVITY])
    cases = {
        "pole": (["root_link"], "root_link"),
        "left": (["l_foot"], "l_sole"),
        "double": (["l_foot", "r_foot"], "r_sole"),
    }
    for k, (case, (contacts, fixed)) in enumerate(cases.items()):
        q, dq, ddq = random_in_limits(robot.urdf_path, robot.joint_names, 100, np.random.default_rng(k))
        ours = expected_wrenches(robot, q, dq, ddq, ContactCase.make(contacts, fixed, gravity), [])
        ref = oracle(robot).expected(q, dq, ddq, contacts, fixed, gravity)
        compared = 0
        for sensor in robot.sensors:
            if both_sides_touch(str(robot.urdf_path), sensor, contacts):
                assert not ours.switch[sensor].any(), f"{sensor} {case}"
                continue
            np.testing.assert_allclose(
                ours.wrench[sensor], ref[sensor], rtol=0, atol=1e-6, err_msg=f"{sensor} {case}"
            )
            compared += 1
        assert compared == {"pole": 6, "left": 6, "double": 2}[case]


@pytest.mark.parametrize("kind", ["half_foot", "walking"])
def test_icub2_simulated_truth_balances_momentum(tmp_path: Path, kind: str) -> None:
    """The simulator on iCub 2.x from the URDF alone (feet, their halves, the root turned half a turn
    to the soles' axes): every sensor's true reading against Newton-Euler link by link, double support
    included (the ground load split between two one-sensor feet)."""
    import yaml

    from pipeline.core.config import load_params
    from pipeline.sim.experiment import make_motion
    from pipeline.sim.params import LogSpec, simulate_params
    from pipeline.sim.truth import TruthComputer
    from pipeline.sim.world import build_world, stream_rng
    from tests.factories.physics import assert_momentum_balance

    data = repo_params()
    data["robot"]["urdf"] = "iCubGenova02"
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    params = load_params(tmp_path / "params.yaml")
    world = build_world(params, simulate_params(params))
    spec = LogSpec(
        kind,
        6.0 if kind == "walking" else 2.0,
        "train",
        "r_foot" if kind == "half_foot" else "",
        "front" if kind == "half_foot" else "",
    )
    motion = make_motion(world, spec, stream_rng(0, 1))
    truth = TruthComputer(world.robot, world.foot_models, GRAVITY).compute(motion)
    assert len({frozenset(c) for c in motion.contact_sets}) >= (3 if kind == "walking" else 1)
    assert_momentum_balance(world.robot, motion, truth)
