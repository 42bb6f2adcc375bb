"""What the robot meets: interaction sites, known loads, the interaction log's truth, and Test D.

References: the sole plane and the URDF tree for the sites; finite differences of positions for a point's
acceleration; the weight of a point mass carried to the sensor frame by hand for a load's label; the
simulator's truth without pushes for the pushes' share; hand-made answers for Test D's slopes.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pipeline.deploy.interaction import fidelity, judge
from pipeline.physics.dynamics import ContactCase, expected_wrenches
from pipeline.physics.loads import Load, loads_from_metadata, loads_to_metadata, with_loads
from pipeline.physics.robot import RobotModel
from pipeline.sim.interaction import InteractionParams
from pipeline.sim.kinematics import Kinematics
from pipeline.sim.motion import MotionGenerator, MotionParams
from pipeline.sim.push import LOAD, PUSH, add_interaction, interaction_events
from pipeline.sim.sites import KIND_ANKLE, KIND_FOOT, KIND_HAND, free_side, interaction_sites
from pipeline.sim.truth import TruthComputer
from tests.conftest import FOOT_PAIRS, GRAVITY, foot_pairs
from tests.factories.physics import FEET

SOLES = {s: sole for front, rear, sole in FOOT_PAIRS.values() for s in (front, rear)}
INTERACTION = InteractionParams(
    force_n=(10.0, 40.0),
    duration_s=0.5,
    period_s=0.8,
    directions=((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    sites={},
    load_kg=2.0,
    load_s=1.0,
)


def test_sites_are_hands_ankles_and_sole_points(robot: RobotModel) -> None:
    sites = {s.sensor: s for s in interaction_sites(robot, SOLES)}
    assert set(sites) == set(robot.sensors)
    for sensor, site in sites.items():
        assert site.link in free_side(robot, sensor)
        if sensor in SOLES:  # a foot part, pushed on the sole plane below it
            assert site.kind == KIND_FOOT and site.link == robot.sensors[sensor].child_link
            on_sole = robot.rigid_transform(SOLES[sensor], site.link).act(np.asarray(site.point))
            assert on_sole[2] == pytest.approx(0.0, abs=1e-12)
        elif sensor.endswith("leg_ft"):  # the link carrying the foot sensors
            assert site.kind == KIND_ANKLE
            assert all(robot.sensors[s].parent_link == site.link for s in SOLES if s[0] == sensor[0])
        else:  # an arm: the end of the limb, where the chain branches into fingers (or ends)
            assert site.kind == KIND_HAND and "hand" in site.link


def test_point_acceleration_matches_finite_differences(icub: RobotModel) -> None:
    kin = Kinematics(icub, 0.0)
    rng = np.random.default_rng(0)
    n = len(icub.joint_names)
    q0, dq, ddq = rng.normal(0, 0.3, n), rng.normal(0, 0.5, n), rng.normal(0, 1.0, n)
    point, h = np.array([0.02, -0.01, 0.05]), 1e-4

    def at(t: float) -> np.ndarray:
        return kin.point_motion(q0 + dq * t + 0.5 * ddq * t * t, dq + ddq * t, ddq, "r_hand", point)[0]

    _, acc = kin.point_motion(q0, dq, ddq, "r_hand", point)
    np.testing.assert_allclose(acc, (at(h) - 2 * at(0.0) + at(-h)) / h**2, atol=1e-6)


def test_a_known_load_adds_its_weight_to_the_label(icub: RobotModel) -> None:
    """Robot still on the pole: the arm sensor's label changes by the load's weight, carried by hand to
    the sensor frame (force rotated, moment about the sensor origin)."""
    point, mass = np.array([0.03, -0.02, 0.01]), 2.0
    loaded = with_loads(icub, [Load("r_hand", mass, tuple(point))])
    q = np.random.default_rng(1).normal(0, 0.3, (1, len(icub.joint_names)))
    zero = np.zeros_like(q)
    case = ContactCase.make({"root_link"}, "root_link", (0, 0, -GRAVITY))
    before = expected_wrenches(icub, q, zero, zero, case, []).wrench["r_arm_ft"][0]
    after = expected_wrenches(loaded, q, zero, zero, case, []).wrench["r_arm_ft"][0]
    kin = Kinematics(icub, 0.0)
    ft = icub.sensors["r_arm_ft"]
    sensor = kin.frame_pose(q[0], ft.child_link) * icub.sensor_pose_in_link("r_arm_ft", ft.child_link)
    at = kin.frame_pose(q[0], "r_hand").act(point)
    weight = sensor.rotation.T @ np.array([0.0, 0.0, -mass * GRAVITY])
    lever = sensor.rotation.T @ (at - sensor.translation)
    # child_to_parent: the hand side pulls on the shoulder with its weight
    np.testing.assert_allclose(after - before, np.r_[weight, np.cross(lever, weight)], atol=1e-9)


def test_loads_metadata_round_trip_and_errors() -> None:
    loads = [Load("r_hand", 1.5, (0.05, 0.0, 0.0)), Load("l_foot_rear", 1.0, (0.0, 0.0, -0.02))]
    assert loads_from_metadata({"loads": loads_to_metadata(loads)}, "x") == loads
    assert loads_from_metadata({}, "x") == []
    with pytest.raises(Exception, match="log.mcap: experiment metadata 'loads'"):
        loads_from_metadata({"loads": '[{"link": "r_hand"}]'}, "log.mcap")


def test_interaction_schedule(icub: RobotModel) -> None:
    sites = interaction_sites(icub, SOLES)
    events = interaction_events(sites, INTERACTION)
    pushes = [e for e in events if e.kind == PUSH]
    loads = [e for e in events if e.kind == LOAD]
    assert len(pushes) == len(sites) * len(INTERACTION.directions)
    assert {e.site.sensor for e in loads} == {s.sensor for s in sites if s.kind == KIND_HAND}
    assert {e.magnitude for e in pushes} == {10.0, 20.0, 30.0, 40.0}
    for a, b in zip(events, events[1:], strict=False):
        assert b.start_s >= a.end_s  # one at a time


def test_pushes_share_of_the_truth_is_what_they_add(icub: RobotModel) -> None:
    gen = MotionGenerator(icub, FEET, MotionParams())
    sites = [s for s in interaction_sites(icub, SOLES) if s.sensor in ("r_arm_ft", "l_foot_rear_ft")]
    events = interaction_events(sites, INTERACTION)
    duration = max(e.end_s for e in events) + 0.5
    still = gen.pole(np.random.default_rng(2), duration, 100)
    pushed = add_interaction(gen.kin, still, events, GRAVITY, duration)
    computer = TruthComputer(icub, foot_pairs(icub), GRAVITY)
    with_pushes, without = computer.compute(pushed), computer.compute(replace(still, pushes={}))
    for s in icub.sensors:
        np.testing.assert_allclose(
            with_pushes.wrench[s] - with_pushes.external[s], without.wrench[s], atol=1e-9
        )
    hand = with_pushes.external["r_arm_ft"]
    assert np.abs(hand[:, :3]).max() > 30.0  # the pushes reach the arm ...
    assert np.abs(with_pushes.external["l_arm_ft"]).max() == 0.0  # ... and not the other one
    with pytest.raises(Exception, match="need .* s"):
        add_interaction(gen.kin, still, events, GRAVITY, duration / 2)


def _synthetic(n: int = 3000) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(time, true, external, load mask): pushes along changing axes in windows, a slow motion besides."""
    t = np.arange(n) / 100.0
    true_free = np.c_[10 * np.sin(0.3 * t)[:, None].repeat(3, 1), np.sin(0.2 * t)[:, None].repeat(3, 1)]
    external = np.zeros((n, 6))
    for k, start in enumerate(range(100, n - 200, 150)):
        window = slice(start, start + 50)
        profile = np.sin(np.linspace(0, np.pi, 50))
        external[window, k % 3] = 30 * profile
        external[window, 3 + (k + 1) % 3] = 3 * profile
    load = np.zeros(n, bool)
    return t, true_free + external, external, load


def test_test_d_known_answers() -> None:
    t, true, external, load = _synthetic()
    offset = np.r_[20.0, -15, 30, 1, -2, 3]
    outputs = {
        "raw": true + offset,  # a factory map: offsets only, slope 1
        "calibrated": true - 0.5 * external,  # reports half of every push
        "oracle": true.copy(),
    }
    entry = fidelity(t, true, external, outputs, load)
    np.testing.assert_allclose(entry["pushes"]["raw"]["slopes"], 1.0, atol=1e-9)
    np.testing.assert_allclose(entry["pushes"]["calibrated"]["slopes"], 0.5, atol=1e-9)
    assert entry["pushes"]["oracle"]["rmse_force"] == pytest.approx(0.0)
    assert entry["pushes"]["raw"]["rmse_force"] == pytest.approx(np.sqrt(np.mean(offset[:3] ** 2)))
    assert entry["pushes"]["calibrated"]["rmse_change_force"] == pytest.approx(
        np.sqrt(np.mean((0.5 * external[np.abs(external).max(axis=1) > 1e-6, :3]) ** 2))
    )
    assert not judge(entry, 0.1, 1.5)["pass"]
    # 5 % more than the push and a constant offset (the day's drift): the change is right but for 5 %
    good = fidelity(t, true, external, {**outputs, "calibrated": true + 0.05 * external + 0.1}, load)
    verdict = judge(good, 0.1, 1e9)
    assert verdict["pass"] and verdict["worst_slope_excess"] == pytest.approx(0.05, abs=1e-9)
    # an oracle that over-reports by hysteresis (slope 1.15) does not make a faithful model fail
    biased = {**outputs, "oracle": true + 0.15 * external, "calibrated": true + 0.02 * external}
    verdict = judge(fidelity(t, true, external, biased, load), 0.1, 1e9)
    assert verdict["pass"] and verdict["slope_gap"] == pytest.approx(1 - 1.02 / 1.15, abs=1e-9)
