"""Cut sets: which sets the URDF graph gives, their summed labels against iDynTree and a static case."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from pipeline.physics.cuts import CutSet, cut_poses, cut_sums, find_cut_sets, sensor_poses
from pipeline.physics.dynamics import ContactCase, expected_wrenches
from pipeline.physics.robot import RobotModel
from tests.conftest import GRAVITY, foot_pairs
from tests.factories.oracles import oracle
from tests.factories.physics import DOUBLE, wrench_X
from tests.idyntree_ref import random_in_limits

LEGS = frozenset({"l_leg_ft", "r_leg_ft"})
FEET = frozenset({"l_foot_front_ft", "l_foot_rear_ft", "r_foot_front_ft", "r_foot_rear_ft"})
L_SHANK = frozenset({"l_leg_ft", "l_foot_front_ft", "l_foot_rear_ft"})
R_SHANK = frozenset({"r_leg_ft", "r_foot_front_ft", "r_foot_rear_ft"})
L_FOOT = frozenset({"l_foot_front_ft", "l_foot_rear_ft"})
R_FOOT = frozenset({"r_foot_front_ft", "r_foot_rear_ft"})


def cuts_by_members(robot: RobotModel, max_sensors: int = 4) -> dict[frozenset[str], CutSet]:
    return {frozenset(c.sensors): c for c in find_cut_sets(robot, foot_pairs(robot), max_sensors)}


def test_cut_sets_from_the_urdf_graph(robot: RobotModel) -> None:
    cuts = cuts_by_members(robot)
    mixed = {L_FOOT | {"r_leg_ft"}, R_FOOT | {"l_leg_ft"}}
    assert set(cuts) == {LEGS, FEET, L_SHANK, R_SHANK, L_FOOT, R_FOOT, *mixed}
    assert set(cuts_by_members(robot, 2)) == {LEGS, L_FOOT, R_FOOT}
    assert cuts[L_FOOT].pair == "l_foot" and cuts[L_FOOT].frame == "l_sole" and cuts[LEGS].pair is None
    # the parts: upper body (arms, head, root), everything above the feet, thigh + shank
    legs, feet, shank = cuts[LEGS].part, cuts[FEET].part, cuts[L_SHANK].part
    assert {"root_link", "l_hip_2", "r_hip_2"} <= legs and "l_hip_3" not in legs
    assert legs < feet and shank < feet and not legs & shank
    assert not shank & (cuts[L_FOOT].others[0] | cuts[L_FOOT].others[1])
    total = robot.total_mass()
    for cut in cuts.values():  # the parts tile the robot
        assert robot.mass_of(cut.part) + sum(robot.mass_of(o) for o in cut.others) == pytest.approx(total)
    assert cuts[LEGS].on_part and not cuts[FEET].on_part and cuts[L_SHANK].signs == (1.0, 1.0, 1.0)
    # the leg pair, the four feet and a shank are exact in double support; no member alone is
    for members in (LEGS, FEET, L_SHANK, R_SHANK):
        assert cuts[members].switch(DOUBLE) and cuts[members].switch(["root_link"])
    assert not cuts[LEGS].switch(["l_foot_front", "root_link"])
    assert cuts[L_SHANK].switch(DOUBLE + ["root_link", "l_foot_front"])  # the shank never touches


CASES = {
    "double_support": (DOUBLE, "l_sole"),
    "double_support_r": (DOUBLE, "r_sole"),
    "half_l_front_and_r_rear": (["l_foot_front", "r_foot_rear"], "l_sole"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_cut_sums_match_idyntree(robot: RobotModel, name: str) -> None:
    """Where only the sum is exact: ours == sum of iDynTree's per-sensor estimates mapped with iDynTree's
    own kinematics to the common frame, 1e-6 N / Nm, random in-limit (q, dq, ddq)."""
    contacts, fixed = CASES[name]
    n = 60
    q, dq, ddq = random_in_limits(robot.urdf_path, robot.joint_names, n, np.random.default_rng(7))
    gravity = np.array([0.0, 0.0, -GRAVITY])
    ours = expected_wrenches(robot, q, dq, ddq, ContactCase.make(contacts, fixed, gravity))
    ref = oracle(robot).expected(q, dq, ddq, contacts, fixed, gravity)
    compared = set()
    for members, cut in cuts_by_members(robot).items():
        if not cut.switch(contacts):
            continue
        mine = cut_sums(cut, ours.reading, cut_poses(robot, cut, q))
        theirs = np.zeros((n, 6))
        for sensor, sign in zip(cut.sensors, cut.signs, strict=True):
            poses = oracle(robot).sensor_poses(q, cut.frame, sensor)
            theirs += sign * np.einsum("nij,nj->ni", np.array([wrench_X(h) for h in poses]), ref[sensor])
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-6, err_msg=f"{cut.name} in {name}")
        if not any(ours.switch[s][0] for s in members):
            compared.add(members)
    if name.startswith("double"):
        assert {LEGS, FEET, L_SHANK, R_SHANK} <= compared  # exact sums where no member is exact
    else:  # a foot's free part is exact alone, so the shanks are not "sum only" here; the legs are
        assert LEGS in compared


def test_static_sums_are_the_parts_weight(robot: RobotModel) -> None:
    """Standing still in double support: each sum is the isolated part's weight (mass and centre of mass
    from the URDF inertials, placed with Pinocchio's own URDF model), +- as the sensors read it."""
    n = 5
    q, _, _ = random_in_limits(robot.urdf_path, robot.joint_names, n, np.random.default_rng(3))
    zero = np.zeros_like(q)
    g_sole = np.array([0.0, 0.0, -GRAVITY])
    out = expected_wrenches(robot, q, zero, zero, ContactCase.make(DOUBLE, "l_sole", g_sole))
    model = robot.pinocchio_model
    data = model.createData()
    cuts = [c for c in cuts_by_members(robot).values() if c.switch(DOUBLE)]
    assert len(cuts) == 6  # all but the single-foot pairs
    for cut in cuts:
        sums = cut_sums(cut, out.reading, cut_poses(robot, cut, q))
        for k in range(n):
            qp = np.zeros(model.nq)
            for j, name in enumerate(robot.joint_names):
                qp[model.idx_qs[model.getJointId(name)]] = q[k, j]
            pin.framesForwardKinematics(model, data, qp)
            frame_T_sole = (
                data.oMf[model.getFrameId(cut.frame)].inverse() * data.oMf[model.getFrameId("l_sole")]
            )
            moment_mass, mass = np.zeros(3), 0.0
            for link in cut.part:
                inertial = robot.links[link]
                if inertial is not None and model.existFrame(link):
                    frame_T_link = (
                        data.oMf[model.getFrameId(cut.frame)].inverse() * data.oMf[model.getFrameId(link)]
                    )
                    moment_mass += inertial.mass * frame_T_link.act(inertial.com)
                    mass += inertial.mass
            assert mass == pytest.approx(robot.mass_of(cut.part))
            force = -mass * (frame_T_sole.rotation @ g_sole)  # what holds the part up
            expected = np.r_[force, np.cross(moment_mass / mass, force)]
            if not cut.on_part:
                expected = -expected
            np.testing.assert_allclose(sums[k], expected, rtol=0, atol=1e-5 * robot.total_mass() * GRAVITY)


def test_sensor_poses_compose_the_fixed_transforms(robot: RobotModel) -> None:
    """Sensors rigidly attached to the frame: the per-sample pose equals the constant transform."""
    cut = cuts_by_members(robot)[FEET]
    q, _, _ = random_in_limits(robot.urdf_path, robot.joint_names, 4, np.random.default_rng(1))
    pose = sensor_poses(robot, cut.frame, "l_foot_rear_ft", q)
    const = robot.sensor_pose_in_link("l_foot_rear_ft", cut.frame)
    np.testing.assert_allclose(pose[:, :9], np.tile(const.rotation.ravel(), (4, 1)), atol=1e-15)
    np.testing.assert_allclose(pose[:, 9:], np.tile(const.translation, (4, 1)), atol=1e-15)
    assert set(cut.moving) == {"r_foot_front_ft", "r_foot_rear_ft"}
