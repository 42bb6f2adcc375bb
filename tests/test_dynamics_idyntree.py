"""Our expected FT wrenches against iDynTree's ExtWrenchesAndJointTorquesEstimator (test-only oracle).

For every contact case, >= 200 random in-limit (q, dq, ddq): every sensor agrees within 1e-6 N / Nm
wherever our switch is 1, and our switch is 0 exactly where the contact set leaves both sides of the
sensor's cut touching (sides computed from the URDF by tests/factories/oracles.py, independently of
pipeline.physics.robot).
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.physics.dynamics import ContactCase, expected_wrenches
from pipeline.physics.robot import RobotModel
from tests.conftest import GRAVITY, foot_pairs
from tests.factories.oracles import both_sides_touch, oracle
from tests.idyntree_ref import random_in_limits

N_SAMPLES = 200
CASES = {
    "pole": (["root_link"], "root_link"),
    "l_sole_fixed": (["l_foot_front", "l_foot_rear"], "l_sole"),
    "r_sole_fixed": (["r_foot_front", "r_foot_rear"], "r_sole"),
    "only_l_foot_front": (["l_foot_front"], "l_sole"),
    "only_r_foot_rear": (["r_foot_rear"], "r_sole"),
    "double_support": (["l_foot_front", "l_foot_rear", "r_foot_front", "r_foot_rear"], "l_sole"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_expected_wrenches_match_idyntree(robot: RobotModel, name: str) -> None:
    contacts, fixed = CASES[name]
    gravity = np.array([0.0, 0.0, -GRAVITY])
    rng = np.random.default_rng(list(CASES).index(name))
    q, dq, ddq = random_in_limits(robot.urdf_path, robot.joint_names, N_SAMPLES, rng)
    ours = expected_wrenches(robot, q, dq, ddq, ContactCase.make(contacts, fixed, gravity), foot_pairs(robot))
    ref = oracle(robot).expected(q, dq, ddq, contacts, fixed, gravity)
    assert set(ref) == set(robot.sensors)
    compared = 0
    for sensor in robot.sensors:
        touching = both_sides_touch(str(robot.urdf_path), sensor, contacts)
        np.testing.assert_array_equal(
            ours.switch[sensor],
            np.full(N_SAMPLES, 0 if touching else 1),
            err_msg=f"switch of {sensor} in {name}",
        )
        if not touching:
            np.testing.assert_allclose(
                ours.wrench[sensor], ref[sensor], rtol=0, atol=1e-6, err_msg=f"{sensor} in {name}"
            )
            compared += 1
    assert compared == sum(not both_sides_touch(str(robot.urdf_path), s, contacts) for s in robot.sensors)
    if name == "double_support":
        assert compared == 2  # only the arms
    else:
        assert compared >= 6
