"""The reading regressor against references computed without it.

Readings: RNEA on the contact-rooted model (:func:`rooted_readings`) for every sensor, and the per-link
Newton-Euler of test_dynamics.py wherever a sensor's label is exact; the same on a robot with other
inertial values (the regressor is computed on the URDF robot only) and on one whose dropped links are
massless. Parameters: Pinocchio's own inertia transform (``Inertia.se3Action``) and the definition of the
rotational inertia about the frame origin.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pinocchio as pin
import pytest

from pipeline.physics.dynamics import ContactCase, choose_root, rooted_readings, sensor_switch
from pipeline.physics.regressor import (
    PARAM_NAMES,
    PARAMS,
    ReadingRegressor,
    link_params,
    move_params,
    placement_map,
)
from pipeline.physics.robot import LinkInertial, RobotModel
from tests.factories.physics import L_FOOT, G, LinkNewtonEuler, random_states, reference_reading

TILT = pin.rpy.rpyToMatrix(0.3, -0.2, 0.5)
CASES = {
    # on a tilted pole: root link fixed, no other contact, gravity off its z axis
    "pole": ContactCase.make({"root_link"}, "root_link", TILT.T @ np.asarray(G)),
    # standing on the left foot: rooted at a foot part, the fixed sole another link of that body
    "l_single_support": ContactCase.make(L_FOOT, "l_sole", G),
}
N = 3  # moving states per case
DROPPED = ("chest", "r_lower_leg", "l_hand", "head")  # links the subset regressor leaves out
MASSLESS = ("l_sole", "chest_imu_0", "base_link")  # URDF links without mass


def massive_links(robot: RobotModel) -> list[str]:
    return [name for name, i in robot.links.items() if i is not None and i.mass > 0]


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    return pin.exp3(rng.uniform(-np.pi, np.pi, 3))


def random_inertia(rng: np.random.Generator) -> pin.Inertia:
    """A physical inertia (kg, m, kg m^2): about its COM that of a cloud of points, so positive definite
    and meeting the triangle inequality."""
    a = rng.normal(0.0, 0.1, (3, 3))
    sigma = a @ a.T  # second moment of the mass distribution about its COM, per kg
    mass = rng.uniform(0.1, 5.0)
    return pin.Inertia(mass, rng.normal(0.0, 0.1, 3), mass * (np.trace(sigma) * np.eye(3) - sigma))


def other_robot(robot: RobotModel, seed: int) -> RobotModel:
    """`robot` with every massive link's mass scaled, COM moved by up to 3 cm and rotational inertia
    scaled and turned: another physical robot with the same kinematics."""
    rng = np.random.default_rng(seed)
    overrides = {}
    for name in massive_links(robot):
        inertial, r = robot.links[name], random_rotation(rng)
        scale = rng.uniform(0.7, 1.3)
        overrides[name] = LinkInertial(
            inertial.mass * scale,
            inertial.com + rng.uniform(-0.03, 0.03, 3),
            r @ (rng.uniform(0.5, 1.5) * inertial.inertia) @ r.T,
        )
    return robot.with_inertials(overrides)


def assert_readings(y: np.ndarray, pi: np.ndarray, expected: dict, sensors: list[str], what: str) -> None:
    """`y @ pi` equals `expected` ({sensor: (N, 6)}) to 1e-9 of each sensor's largest reading."""
    for k, sensor in enumerate(sensors):
        ref = expected[sensor]
        scale = np.abs(ref).max()
        assert scale > 1e-3, f"{what} {sensor}: no reading to compare"
        np.testing.assert_allclose(y[:, k] @ pi, ref, rtol=0, atol=1e-9 * scale, err_msg=f"{what} {sensor}")


@pytest.fixture(scope="module", params=list(CASES))
def rig(request: pytest.FixtureRequest, icub: RobotModel) -> SimpleNamespace:
    """One contact case: its regressor of all massive links at N random moving states."""
    case = CASES[request.param]
    links = massive_links(icub)
    reg = ReadingRegressor(icub, case, links)
    states = random_states(icub, N, seed=40 + list(CASES).index(request.param))
    return SimpleNamespace(name=request.param, case=case, links=links, reg=reg, states=states, y=reg(*states))


def test_readings_equal_rnea_and_newton_euler(icub: RobotModel, rig: SimpleNamespace) -> None:
    sensors = list(icub.sensors)
    assert rig.y.shape == (N, len(sensors), 6, PARAMS * len(rig.links))
    pi = link_params(icub, rig.links)
    _, rnea = rooted_readings(icub, *rig.states, rig.case)
    assert_readings(rig.y, pi, rnea, sensors, rig.name)
    # where a label is exact, also against Newton-Euler summed link by link over the free side
    root = choose_root(icub, rig.case)
    gravity = icub.rigid_transform(root, rig.case.fixed_link).rotation @ np.asarray(rig.case.gravity)
    ne = LinkNewtonEuler(icub, root, gravity)
    exact = [s for s in sensors if sensor_switch(icub, s, rig.case.contacts)]
    assert len(exact) >= 6
    for i in range(N):
        ne.set_state(*(a[i] for a in rig.states))
        for sensor in exact:
            ref = reference_reading(ne, sensor, set(rig.case.contacts))
            got = rig.y[i, sensors.index(sensor)] @ pi
            scale = np.abs(ref).max()
            np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * scale, err_msg=f"{rig.name} {sensor}")


def test_a_reading_has_columns_of_its_far_side_links_only(icub: RobotModel, rig: SimpleNamespace) -> None:
    """A sensor's reading depends on the links beyond its cut as seen from the root, and on all of them."""
    root = choose_root(icub, rig.case)
    blocks = rig.y.reshape(N, len(icub.sensors), 6, len(rig.links), PARAMS)
    for k, sensor in enumerate(icub.sensors):
        parent_side, child_side = icub.sensor_sides(sensor)
        far = parent_side if root in child_side else child_side
        for j, link in enumerate(rig.links):
            nonzero = np.abs(blocks[:, k, :, j]).max()
            if link in far:
                assert nonzero > 1e-3, f"{rig.name} {sensor}: no column for {link}"
            else:
                assert nonzero == 0.0, f"{rig.name} {sensor}: {link} is on the root's side"


def test_other_inertials_are_the_same_regressor_times_their_params(
    icub: RobotModel, rig: SimpleNamespace
) -> None:
    """The regressor depends on the motion only: on a robot with other masses, COMs and inertias, RNEA
    gives the URDF robot's regressor times that robot's parameters."""
    other = other_robot(icub, seed=7)
    _, readings = rooted_readings(other, *rig.states, rig.case)
    _, urdf = rooted_readings(icub, *rig.states, rig.case)
    for sensor in icub.sensors:  # the two robots' readings differ far beyond the tolerance
        assert np.abs(readings[sensor] - urdf[sensor]).max() > 1e-4 * np.abs(urdf[sensor]).max()
    assert_readings(rig.y, link_params(other, rig.links), readings, list(icub.sensors), rig.name)
    own = ReadingRegressor(other, rig.case, rig.links)(*rig.states)
    np.testing.assert_allclose(own, rig.y, rtol=0, atol=1e-12 * np.abs(rig.y).max())


def test_absent_and_massless_links_contribute_nothing(icub: RobotModel, rig: SimpleNamespace) -> None:
    """Links left out of `links` have no columns; massless ones have zero parameters: the subset's
    readings are those of a robot whose left-out links weigh nothing."""
    kept = [link for link in rig.links if link not in DROPPED]
    links = [*kept, *MASSLESS]
    y = ReadingRegressor(icub, rig.case, links)(*rig.states)
    assert y.shape[-1] == PARAMS * len(links)
    pi = link_params(icub, links)
    np.testing.assert_array_equal(pi[PARAMS * len(kept) :], 0.0)
    # the kept links' columns are those of the regressor of every link
    full = rig.y.reshape(N, -1, 6, len(rig.links), PARAMS)
    columns = full[:, :, :, [rig.links.index(link) for link in kept]].reshape(*y.shape[:3], -1)
    np.testing.assert_array_equal(y[..., : PARAMS * len(kept)], columns)
    nothing = LinkInertial(0.0, np.zeros(3), np.zeros((3, 3)))
    light = icub.with_inertials(dict.fromkeys(DROPPED, nothing))
    np.testing.assert_array_equal(link_params(light, DROPPED), 0.0)
    _, readings = rooted_readings(light, *rig.states, rig.case)
    _, urdf = rooted_readings(icub, *rig.states, rig.case)
    assert max(np.abs(readings[s] - urdf[s]).max() for s in icub.sensors) > 1.0  # N or Nm
    assert_readings(y, pi, readings, list(icub.sensors), rig.name)


def test_move_params_is_pinocchios_inertia_transform() -> None:
    rng = np.random.default_rng(11)
    for _ in range(5):
        placement = pin.SE3(random_rotation(rng), rng.normal(0.0, 0.3, 3))
        inertia = random_inertia(rng)
        pi = inertia.toDynamicParameters()
        moved = move_params(pi, placement)
        np.testing.assert_allclose(moved, inertia.se3Action(placement).toDynamicParameters(), atol=1e-12)
        np.testing.assert_allclose(placement_map(placement) @ pi, moved, atol=1e-12)
        # moving there and back is the identity map
        back = placement_map(placement.inverse()) @ placement_map(placement)
        np.testing.assert_allclose(back, np.eye(PARAMS), atol=1e-12)


def test_link_params_are_in_the_documented_order(icub: RobotModel) -> None:
    """m, first moment m c, then the inertia about the link frame's origin, I_c + m (|c|^2 1 - c c^T)."""
    links = ["l_upper_arm", "r_lower_leg"]
    for link, pi in zip(links, link_params(icub, links).reshape(-1, PARAMS), strict=True):
        inertial = icub.links[link]
        m, c = inertial.mass, np.asarray(inertial.com)
        about_origin = inertial.inertia + m * (c @ c * np.eye(3) - np.outer(c, c))
        named = dict(zip(PARAM_NAMES, pi, strict=True))
        expected = {"m": m, "mcx": m * c[0], "mcy": m * c[1], "mcz": m * c[2]}
        for axis, (a, b) in {"xx": (0, 0), "xy": (0, 1), "yy": (1, 1), "xz": (0, 2), "yz": (1, 2)}.items():
            expected[f"I{axis}"] = about_origin[a, b]
        expected["Izz"] = about_origin[2, 2]
        for name, value in expected.items():
            assert named[name] == pytest.approx(value, rel=1e-12, abs=1e-15), f"{link} {name}"
