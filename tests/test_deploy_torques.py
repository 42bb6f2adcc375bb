"""Joint torques from a leg's FT sensor (pipeline.physics.torques) against the simulator's true torques.

The simulator gets its joint torques from RNEA over the whole tree plus ``-J^T w`` for each push; the
estimator sees only the sensor's wrench and the links between the sensor and each joint. Fed the true
wrench, the true robot and the true motion, the two must agree to rounding, pushes included.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.core.config import load_params
from pipeline.core.errors import RobotModelError
from pipeline.physics.torques import limb_joints, sensor_joint_torques
from pipeline.sim.experiment import push_links
from pipeline.sim.params import PushParams, simulate_params
from pipeline.sim.push import add_pushes, push_profile
from pipeline.sim.truth import TruthComputer
from pipeline.sim.world import build_world, stream_rng


@pytest.fixture(scope="module")
def pushed():
    params = load_params()
    sim = dataclasses.replace(simulate_params(params), push=PushParams(80.0, 0.5, 1.0, (1.0, 0.5, 0.0)))
    world = build_world(params, sim)
    motion = world.motions.pole(stream_rng(5, 6), 2.0, 100.0)
    motion = add_pushes(world.motions.kin, motion, push_links(world), sim.push)
    truth = TruthComputer(world.truth_robot, world.pairs, params.robot.gravity).compute(motion)
    return world, motion, truth, np.array([0.0, 0.0, -params.robot.gravity])


@pytest.mark.parametrize("sensor,sole", [("l_leg_ft", "l_sole"), ("r_leg_ft", "r_sole")])
def test_leg_torques_equal_true_torques(pushed, sensor, sole):
    world, motion, truth, g = pushed
    joints = limb_joints(world.robot, sole)
    assert len(joints) == 6 and joints[0].endswith("hip_pitch")
    est = sensor_joint_torques(
        world.truth_robot,
        sensor,
        joints,
        motion.q,
        motion.dq,
        motion.ddq,
        truth.wrench[sensor],
        "root_link",
        g,
    )
    true = truth.joint_torque[:, [world.robot.joint_names.index(j) for j in joints]]
    np.testing.assert_allclose(est, true, atol=1e-6)
    # the pushes matter: without them the true hip torques would differ by tens of Nm
    pushed_rows = np.abs(motion.pushes[push_links(world)[0 if sensor.startswith("l") else 1]]).sum(axis=1) > 0
    assert pushed_rows.any()


def test_leg_torques_equal_idyntree_estimator_pushes_included(pushed):
    """Test C's estimator against iDynTree's ExtWrenchesAndJointTorquesEstimator on the same states and
    wrenches: the robot on the pole pushed at each ankle, every FT sensor reading its true wrench; iDynTree
    estimates each subtree's unknown contact (the pole clamp, the pushed ankles, the free hands and foot
    parts) from the sensors and its joint torques. The estimator's leg joint torques from the leg sensor
    agree."""
    from tests.idyntree_ref import IDynTreeFT

    world, motion, _, g = pushed
    truth = TruthComputer(world.robot, world.pairs, -g[2]).compute(motion)  # the nominal robot's truth
    robot = world.robot
    rows = np.linspace(0, motion.n - 1, 40).astype(int)
    pushes = np.abs(np.stack([motion.pushes[link] for link in push_links(world)])).sum(axis=(0, 2))
    assert (pushes[rows] > 1.0).sum() >= 10  # pushed samples among those compared
    ref = IDynTreeFT(robot.urdf_path, robot.joint_names)
    contacts = ["root_link", *push_links(world), "l_hand", "r_hand", "l_foot_front", "l_foot_rear"]
    contacts += ["r_foot_front", "r_foot_rear"]
    q, dq, ddq = motion.q[rows], motion.dq[rows], motion.ddq[rows]
    measured = {s: truth.wrench[s][rows] for s in robot.sensors}
    reference = ref.estimated_torques(q, dq, ddq, contacts, "root_link", g, measured)
    for sensor, sole in (("l_leg_ft", "l_sole"), ("r_leg_ft", "r_sole")):
        joints = limb_joints(robot, sole)
        est = sensor_joint_torques(robot, sensor, joints, q, dq, ddq, measured[sensor], "root_link", g)
        columns = [robot.joint_names.index(j) for j in joints]
        np.testing.assert_allclose(est, reference[:, columns], rtol=0, atol=1e-6, err_msg=sensor)


def test_push_profile_turns_and_peak():
    p = PushParams(50.0, 1.0, 4.0, (0.0, 3.0, 4.0))
    assert p.direction == pytest.approx((0.0, 0.6, 0.8))
    t = np.arange(0, 16, 0.01)
    force, who = push_profile(t, p, 2)
    assert force.max() == pytest.approx(50.0, rel=1e-3)
    starts = t[np.flatnonzero(np.diff((who >= 0).astype(int)) == 1) + 1]
    np.testing.assert_allclose(starts, [2.01, 6.01, 10.01, 14.01], atol=0.011)
    assert [int(who[np.searchsorted(t, s)]) for s in starts] == [0, 1, 0, 1]


def test_joint_off_the_sensor_path_is_refused(pushed):
    world, motion, truth, g = pushed
    with pytest.raises(RobotModelError, match="not on a path through l_leg_ft"):
        sensor_joint_torques(
            world.robot,
            "l_leg_ft",
            ["r_knee"],
            motion.q,
            motion.dq,
            motion.ddq,
            truth.wrench["l_leg_ft"],
            "root_link",
            g,
        )
