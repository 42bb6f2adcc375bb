"""Expected FT wrenches against physics computed another way (per-link Newton-Euler, statics).

The reference sums, over the links of the free side of a cut, each link's rate of change of momentum
minus gravity (``I (a - g) + v x* I v`` from Pinocchio frame kinematics, no RNEA), and maps it to the
sensor's convention by hand. The iDynTree comparison lives in test_dynamics_idyntree.py.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from pipeline.core.errors import RobotModelError
from pipeline.physics.dynamics import ContactCase, expected_wrenches, pair_switch, sensor_switch
from pipeline.physics.robot import RobotModel
from tests.conftest import GRAVITY, foot_pairs
from tests.factories.physics import L_FOOT, R_FOOT, G, LinkNewtonEuler, random_states, reference_reading

CASES = {
    "pole": ({"root_link"}, "root_link"),
    "l_single_support": (L_FOOT, "l_sole"),
    "r_single_support": (R_FOOT, "r_sole"),
    "l_half_foot_front": ({"l_foot_front"}, "l_sole"),
    "r_half_foot_rear": ({"r_foot_rear"}, "r_sole"),
    "double_support": (L_FOOT | R_FOOT, "l_sole"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_moving_robot_matches_link_newton_euler(robot: RobotModel, name: str) -> None:
    contacts, fixed = CASES[name]
    case = ContactCase.make(contacts, fixed, G)
    q, dq, ddq = random_states(robot, 6, seed=list(CASES).index(name))
    out = expected_wrenches(robot, q, dq, ddq, case, foot_pairs(robot))
    ne = LinkNewtonEuler(robot, fixed, np.asarray(G))
    for k in range(q.shape[0]):
        ne.set_state(q[k], dq[k], ddq[k])
        for sensor in robot.sensors:
            if out.switch[sensor][k]:
                np.testing.assert_allclose(
                    out.wrench[sensor][k],
                    reference_reading(ne, sensor, contacts),
                    atol=1e-8,
                    err_msg=f"{name} {sensor}",
                )
            else:
                assert np.isnan(out.wrench[sensor][k]).all()
        for pair in foot_pairs(robot):
            if not out.pair_switch[pair.name][k]:
                assert np.isnan(out.pair_sum[pair.name][k]).all()
                continue
            # the whole-foot cut: wrench the rest of the robot exerts on the foot parts, in the sole frame
            sole = ne.pose(pair.sole)
            rest = frozenset(robot.links) - pair.foot_links
            cut = (
                ne.required_wrench(pair.foot_links, sole)
                if not contacts & pair.foot_links
                else -ne.required_wrench(rest, sole)
            )
            np.testing.assert_allclose(
                out.pair_sum[pair.name][k], cut, atol=1e-8, err_msg=f"{name} {pair.name}"
            )


def test_static_stance_leg_carries_weight_above(robot: RobotModel) -> None:
    """Standing still on the left sole: l_leg_ft holds up all above it, r_leg_ft the hanging leg."""
    case = ContactCase.make(L_FOOT, "l_sole", G)
    q, dq, ddq = random_states(robot, 5, seed=3, moving=False)
    out = expected_wrenches(robot, q, dq, ddq, case, foot_pairs(robot))
    ne = LinkNewtonEuler(robot, "l_sole", np.asarray(G))
    above = robot.sensor_sides("l_leg_ft")[0]
    hanging = robot.sensor_sides("r_leg_ft")[1]
    m_above, m_hanging = robot.mass_of(above), robot.mass_of(hanging)
    assert 20.0 < m_above < robot.total_mass()
    for k in range(q.shape[0]):
        ne.set_state(q[k], dq[k], ddq[k])
        # child_to_parent = what the leg exerts on the body above: the body's weight, upwards (world z)
        world_T_s = ne.sensor_frame("l_leg_ft")
        f_world = world_T_s.rotation @ out.wrench["l_leg_ft"][k, :3]
        np.testing.assert_allclose(f_world, [0, 0, m_above * GRAVITY], atol=1e-8)
        # its moment about the sensor origin is that of the weight acting at the centre of mass above
        com = (
            sum(
                robot.links[n].mass * ne.pose(n).act(robot.links[n].com)
                for n in above
                if robot.links[n] is not None
            )
            / m_above
        )
        tau_world = world_T_s.rotation @ out.wrench["l_leg_ft"][k, 3:]
        np.testing.assert_allclose(tau_world, np.cross(com - world_T_s.translation, f_world), atol=1e-8)
        # the swing leg pulls the body down with its weight
        f_swing = ne.sensor_frame("r_leg_ft").rotation @ out.wrench["r_leg_ft"][k, :3]
        np.testing.assert_allclose(f_swing, [0, 0, -m_hanging * GRAVITY], atol=1e-8)
        # the left pair sum, in the sole frame (= world here), pushes the foot down with the rest's weight
        m_rest = robot.total_mass() - robot.mass_of(foot_pairs(robot)[0].foot_links)
        np.testing.assert_allclose(out.pair_sum["l_foot"][k, :3], [0, 0, -m_rest * GRAVITY], atol=1e-8)


def test_pair_sum_is_sum_of_parts_where_parts_are_exact(robot: RobotModel) -> None:
    """On the pole every part is exact; the pair sum must equal the mapped sum of the parts (eq. 5.9)."""
    case = ContactCase.make({"root_link"}, "root_link", G)
    q, dq, ddq = random_states(robot, 50, seed=4)
    out = expected_wrenches(robot, q, dq, ddq, case, foot_pairs(robot))
    for pair in foot_pairs(robot):
        mapped = out.wrench[pair.front] @ pair.sole_X_front.T + out.wrench[pair.rear] @ pair.sole_X_rear.T
        np.testing.assert_allclose(out.pair_sum[pair.name], mapped, atol=1e-9)
        np.testing.assert_array_equal(out.sole_X_sensor[pair.front], pair.sole_X_front)


# Thesis switches: eq. 5.5 (legs), 5.11 (foot parts); the pair switch is the graph-cut rule of the sum
# (docs/labels.md), which eq. 5.12 applies where the parts alone are not exact.
SWITCH_TABLE = {
    #                       l_leg r_leg lff lfr rff rfr l_arm r_arm | l_foot r_foot
    "l_single_support": ((1, 1, 0, 0, 1, 1, 1, 1), (1, 1)),
    "r_single_support": ((1, 1, 1, 1, 0, 0, 1, 1), (1, 1)),
    "double_support": ((0, 0, 0, 0, 0, 0, 1, 1), (0, 0)),
    "l_half_foot_front": ((1, 1, 1, 1, 1, 1, 1, 1), (1, 1)),
    "r_half_foot_rear": ((1, 1, 1, 1, 1, 1, 1, 1), (1, 1)),
    "pole": ((1, 1, 1, 1, 1, 1, 1, 1), (1, 1)),
}
SENSOR_ORDER = (
    "l_leg_ft",
    "r_leg_ft",
    "l_foot_front_ft",
    "l_foot_rear_ft",
    "r_foot_front_ft",
    "r_foot_rear_ft",
    "l_arm_ft",
    "r_arm_ft",
)


@pytest.mark.parametrize("name", list(SWITCH_TABLE))
def test_switches_follow_thesis(robot: RobotModel, name: str) -> None:
    contacts, fixed = CASES[name]
    sensors, pairs = SWITCH_TABLE[name]
    assert tuple(int(sensor_switch(robot, s, contacts)) for s in SENSOR_ORDER) == sensors
    assert tuple(int(pair_switch(p, contacts)) for p in foot_pairs(robot)) == pairs
    out = expected_wrenches(
        robot, *random_states(robot, 3, seed=5), ContactCase.make(contacts, fixed, G), foot_pairs(robot)
    )
    assert tuple(int(out.switch[s][0]) for s in SENSOR_ORDER) == sensors


def test_bad_contact_cases_are_named(icub: RobotModel) -> None:
    q, dq, ddq = random_states(icub, 2, seed=6)
    with pytest.raises(RobotModelError, match="'r_sole' is not rigidly attached to any contact link"):
        expected_wrenches(icub, q, dq, ddq, ContactCase.make(L_FOOT, "r_sole", G))
    with pytest.raises(RobotModelError, match="no contact link named 'l_toe'"):
        expected_wrenches(icub, q, dq, ddq, ContactCase.make({"l_toe"}, "l_sole", G))
    with pytest.raises(ValueError, match=r"q must have shape \(N, 32\)"):
        expected_wrenches(icub, q[:, :5], dq, ddq, ContactCase.make(L_FOOT, "l_sole", G))
    q[0, 0] = np.nan
    with pytest.raises(ValueError, match="q contains NaN"):
        expected_wrenches(icub, q, dq, ddq, ContactCase.make(L_FOOT, "l_sole", G))


def test_gravity_direction_of_fixed_frame_is_used(icub: RobotModel) -> None:
    """Pole with root_link tilted: gravity in the root frame rotates the static readings accordingly."""
    q, dq, ddq = random_states(icub, 4, seed=7, moving=False)
    rot = pin.rpy.rpyToMatrix(0.3, -0.2, 0.5)
    upright = expected_wrenches(icub, q, dq, ddq, ContactCase.make({"root_link"}, "root_link", G))
    tilted = expected_wrenches(icub, q, dq, ddq, ContactCase.make({"root_link"}, "root_link", rot.T @ G))
    for s in icub.sensors:
        assert not np.allclose(upright.wrench[s], tilted.wrench[s])
        # static forces have the same magnitude whatever the tilt
        np.testing.assert_allclose(
            np.linalg.norm(upright.wrench[s][:, :3], axis=1),
            np.linalg.norm(tilted.wrench[s][:, :3], axis=1),
            rtol=1e-10,
        )
