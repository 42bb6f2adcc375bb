"""The simulator's truth against physics computed link by link (momentum balance of every cut)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.physics.robot import RobotModel
from pipeline.sim.motion import MotionGenerator, MotionParams
from pipeline.sim.truth import TruthComputer, split_front_rear
from tests.conftest import GRAVITY, foot_pairs
from tests.factories.physics import FEET, assert_momentum_balance


@pytest.fixture(scope="module")
def motions(icub: RobotModel) -> dict:
    gen = MotionGenerator(icub, FEET, MotionParams())
    rng = np.random.default_rng(0)
    return {
        "pole": gen.pole(rng, 2.0, 100),
        "balancing": gen.balancing(rng, 2.0, 100, "l_foot"),
        "half_foot": gen.balancing(rng, 2.0, 100, "r_foot", "front"),
        "walking": gen.walking(rng, 6.0, 100),
    }


@pytest.mark.parametrize("kind", ["pole", "balancing", "half_foot", "walking"])
def test_every_cut_balances_momentum(icub: RobotModel, motions: dict, kind: str) -> None:
    """For every sensor: reading == required wrench of a side minus the contact wrenches on that side;
    for the whole robot: sum of contact wrenches == rate of change of momentum minus gravity."""
    motion = motions[kind]
    truth = TruthComputer(icub, foot_pairs(icub), GRAVITY).compute(motion)
    assert_momentum_balance(icub, motion, truth)


def test_lever_split_is_exact_and_follows_cop() -> None:
    rng = np.random.default_rng(1)
    wrench = np.c_[rng.normal(0, 20, (50, 2)), rng.uniform(100, 400, 50), rng.normal(0, 5, (50, 3))]
    front, rear = split_front_rear(wrench, 0.06, -0.06)
    np.testing.assert_allclose(front + rear, wrench, atol=1e-12)
    # a centre of pressure on the front centre puts the whole load on the front part
    w = np.array([[0.0, 0.0, 300.0, 0.0, -0.06 * 300.0, 0.0]])
    front, rear = split_front_rear(w, 0.06, -0.06)
    np.testing.assert_allclose(rear, 0.0, atol=1e-12)


@pytest.mark.parametrize("kind", ["pole", "balancing", "walking"])
def test_imu_equals_idyntree_frame_acceleration_and_velocity(
    icub: RobotModel, motions: dict, kind: str
) -> None:
    """Every FT board's accelerometer (proper acceleration, m/s^2) and gyroscope (rad/s), in its sensor frame,
    against iDynTree's classical acceleration and angular velocity of the sensor frame (gravity (0, 0, -g)
    in the still link's frame: root_link on the pole, the stance sole otherwise) on the same motion."""
    from tests.idyntree_ref import IDynTreeFT

    motion = motions[kind]
    truth = TruthComputer(icub, foot_pairs(icub), GRAVITY).compute(motion)
    ref = IDynTreeFT(icub.urdf_path, icub.joint_names)
    rows = np.linspace(0, motion.n - 1, 24).astype(int)
    g = np.array([0.0, 0.0, -GRAVITY])
    moving = 0.0
    for fixed in sorted(set(motion.fixed_links[rows])):
        k = rows[motion.fixed_links[rows] == fixed]
        for s in icub.sensors:
            acc, gyro = ref.imu(motion.q[k], motion.dq[k], motion.ddq[k], str(fixed), g, s)
            np.testing.assert_allclose(truth.proper_acc[s][k], acc, rtol=0, atol=1e-8, err_msg=f"{s} {fixed}")
            np.testing.assert_allclose(truth.gyro[s][k], gyro, rtol=0, atol=1e-9, err_msg=f"{s} {fixed}")
            moving = max(
                moving, float(np.abs(gyro).max()), float(np.abs(np.linalg.norm(acc, axis=1) - GRAVITY).max())
            )
    assert moving > 0.1  # the boards move: rotation rates and accelerations beyond gravity are checked


def test_imu_of_a_still_robot_reads_gravity_rotated_into_each_sensor_frame(
    icub: RobotModel, motions: dict
) -> None:
    """Exact case: the robot held still (dq = ddq = 0): every accelerometer reads -g rotated into its frame
    (R^T (0, 0, +g), R the sensor's orientation in the world), every gyroscope zero."""
    motion = motions["pole"]
    still = dataclasses.replace(motion, dq=np.zeros_like(motion.dq), ddq=np.zeros_like(motion.ddq))
    truth = TruthComputer(icub, foot_pairs(icub), GRAVITY).compute(still)
    for s in icub.sensors:
        rotation = truth.world_T_sensor[s][:, :3, :3]
        expected = np.einsum("nji,j->ni", rotation, [0.0, 0.0, GRAVITY])
        np.testing.assert_allclose(truth.proper_acc[s], expected, rtol=0, atol=1e-9, err_msg=s)
        np.testing.assert_allclose(truth.gyro[s], 0.0, atol=1e-12, err_msg=s)
    tilted = [s for s in icub.sensors if np.abs(truth.proper_acc[s][:, :2]).max() > 1.0]
    assert len(tilted) >= 4  # frames not aligned with the world: R and R^T differ there
