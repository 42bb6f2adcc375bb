"""Expected FT wrenches and exact-label switches for batches of joint states (thesis 4.2, 5.4).

Arrays in, arrays out. For N samples with one contact set and one link fixed in the world:

- every FT sensor's expected wrench (N, 6) in its own frame and measure direction, and its switch:
  1 iff one side of its cut touches nothing (thesis eqs. 5.5, 5.11); else the wrench is NaN;
- every foot pair's sum in the sole frame, ``sole_X_front f_front + sole_X_rear f_rear``
  (thesis eqs. 5.8-5.10), and its switch: 1 iff the contacts lie all on the foot or all off it;
- the constant sensor -> sole wrench transforms.

Method. The tree is re-rooted at a contact link rigidly attached to the fixed link, so the root does
not move and no base kinematics is needed; FT sensor joints become 6-DoF joints held at identity.
Pinocchio's RNEA then returns, at each sensor joint, the wrench that the root side exerts on the far
side, as if every contact force acted on the root. Where the far side touches nothing that wrench is
exact; since the root itself touches, a cut with a contact-free side always has it as the far side.
The same holds for the two-joint cut of a foot pair, so the pair sum is exact wherever its switch is 1
even when neither part is. All samples run in one call of ``pinocchio.rneaInParallel``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from pipeline.core.errors import RobotModelError
from pipeline.physics.robot import FootPair, RobotModel, wrench_transform


@dataclass(frozen=True)
class ContactCase:
    """Which links touch the environment and which link is fixed in the world.

    contacts: links touching the environment (floor, pole, ...). fixed_link: a link whose frame does not
    move (a sole flat on the floor, root_link on the pole); it must be rigidly attached to one of the
    contact links. gravity: (3,) gravity acceleration expressed in the fixed link's frame, m/s^2
    (e.g. (0, 0, -9.80665) for a sole flat on level ground).
    """

    contacts: frozenset[str]
    fixed_link: str
    gravity: tuple[float, float, float]

    @staticmethod
    def make(contacts: Iterable[str], fixed_link: str, gravity: Sequence[float]) -> ContactCase:
        gravity = tuple(float(g) for g in gravity)
        if len(gravity) != 3 or not np.all(np.isfinite(gravity)):
            raise ValueError(f"gravity must be 3 finite numbers, got {gravity}")
        return ContactCase(frozenset(contacts), fixed_link, gravity)  # type: ignore[arg-type]


@dataclass
class ExpectedWrenches:
    """Labels of one batch of N samples.

    wrench[s]: (N, 6) expected reading of sensor s [fx, fy, fz (N), tx, ty, tz (Nm)] in its sensor
    frame and measure direction; NaN where switch[s] is 0. switch[s]: (N,) uint8.
    pair_sum[p]: (N, 6) foot pair p's summed wrench in its sole frame; NaN where pair_switch[p] is 0.
    sole_X_sensor[s]: (6, 6) wrench transform from sensor s's frame to its foot's sole frame.
    reading[s]: (N, 6) sensor s's reading as if every contact force acted on the root contact link
    (:func:`rooted_readings`): equal to wrench[s] where switch[s] is 1, and elsewhere still consistent, so
    that any signed sum over a cut set whose isolated part touches nothing is exact
    (:mod:`pipeline.physics.cuts`).
    """

    wrench: dict[str, np.ndarray]
    switch: dict[str, np.ndarray]
    pair_sum: dict[str, np.ndarray]
    pair_switch: dict[str, np.ndarray]
    sole_X_sensor: dict[str, np.ndarray]
    reading: dict[str, np.ndarray]


def sensor_switch(robot: RobotModel, sensor: str, contacts: Iterable[str]) -> bool:
    """Exact-label switch of `sensor` (thesis eqs. 5.5, 5.11): True iff a side of its cut touches nothing."""
    parent_side, child_side = robot.sensor_sides(sensor)
    contacts = set(contacts)
    return not (contacts & parent_side and contacts & child_side)


def pair_switch(pair: FootPair, contacts: Iterable[str]) -> bool:
    """Exact-label switch of a foot-pair sum: True iff the contacts lie all on the foot or all off it."""
    contacts = set(contacts)
    return contacts <= pair.foot_links or not (contacts & pair.foot_links)


def choose_root(robot: RobotModel, case: ContactCase) -> str:
    """The contact link rigidly attached to the fixed link (the fixed link itself if it touches)."""
    for link in (*case.contacts, case.fixed_link):
        robot.check_link(link, "contact link" if link != case.fixed_link else "fixed link")
    if not case.contacts:
        raise RobotModelError("the contact set is empty: at least one link must touch the environment")
    if case.fixed_link in case.contacts:
        return case.fixed_link
    rigid = robot.rigid_body_links(case.fixed_link)
    for link in sorted(case.contacts):
        if link in rigid:
            return link
    raise RobotModelError(
        f"fixed link {case.fixed_link!r} is not rigidly attached to any contact link "
        f"({', '.join(sorted(case.contacts))}): a link fixed in the world must be touching something"
    )


def _sensor_maps(robot: RobotModel, root: str) -> dict[str, np.ndarray]:
    """Per sensor, the (6, 6) map from RNEA's far-side wrench at its joint to its reading."""
    rooted = robot.rooted(root)
    maps = {}
    for name, ft in robot.sensors.items():
        # RNEA gives the wrench on the far side, in the joint (= child link) frame: forward -> P on Q.
        sign = 1.0 if rooted.sensor_forward[name] else -1.0
        if ft.direction == "child_to_parent":
            sign = -sign
        maps[name] = sign * wrench_transform(ft.child_T_sensor.inverse())
    return maps


def _check_batch(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, n_joints: int) -> int:
    for label, arr in (("q", q), ("dq", dq), ("ddq", ddq)):
        if arr.ndim != 2 or arr.shape[1] != n_joints:
            raise ValueError(f"{label} must have shape (N, {n_joints}), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{label} contains NaN or inf")
    if not q.shape == dq.shape == ddq.shape:
        raise ValueError(f"q, dq, ddq shapes differ: {q.shape}, {dq.shape}, {ddq.shape}")
    return q.shape[0]


def far_side_wrenches(
    robot: RobotModel,
    root: str,
    gravity_root: np.ndarray,
    q: np.ndarray,
    dq: np.ndarray,
    ddq: np.ndarray,
    n_threads: int | None = None,
) -> np.ndarray:
    """RNEA on the model rooted at `root`: (N, nv) generalised forces of that model.

    q, dq, ddq: (N, n_joints) in ``robot.joint_names`` order (rad, rad/s, rad/s^2).
    gravity_root: (3,) gravity in the root link frame, m/s^2.
    """
    rooted = robot.rooted(root)
    n = q.shape[0]
    nv = rooted.model.nv
    # Fortran-ordered (nq, N) buffers are what Eigen reads without a copy.
    qs = np.asfortranarray(rooted.neutral_batch(n).T)
    vs = np.zeros((nv, n), order="F")
    accs = np.zeros((nv, n), order="F")
    qs[rooted.q_index, :] = (q * rooted.sign).T
    vs[rooted.v_index, :] = (dq * rooted.sign).T
    accs[rooted.v_index, :] = (ddq * rooted.sign).T
    threads = n_threads or os.cpu_count() or 1
    tau = np.zeros((nv, n), order="F")
    if n:
        pin.rneaInParallel(threads, rooted.pool(gravity_root, threads), qs, vs, accs, tau)
    return tau.T


def rooted_readings(
    robot: RobotModel,
    q: np.ndarray,
    dq: np.ndarray,
    ddq: np.ndarray,
    case: ContactCase,
    n_threads: int | None = None,
) -> tuple[str, dict[str, np.ndarray]]:
    """Every sensor's reading as if all contact forces acted on the root contact link.

    Returns (root link, {sensor: (N, 6)} in sensor frame and measure direction). Exact wherever the
    sensor's switch is 1; elsewhere a hypothetical load distribution (the simulator corrects it with
    the true contact wrenches by superposition). Inputs as :func:`expected_wrenches`.
    """
    q, dq, ddq = (np.asarray(a, dtype=float) for a in (q, dq, ddq))
    _check_batch(q, dq, ddq, len(robot.joint_names))
    root = choose_root(robot, case)
    root_R_fixed = robot.rigid_transform(root, case.fixed_link).rotation
    gravity_root = root_R_fixed @ np.asarray(case.gravity)
    tau = far_side_wrenches(robot, root, gravity_root, q, dq, ddq, n_threads)
    rooted = robot.rooted(root)
    maps = _sensor_maps(robot, root)
    readings = {}
    for name in robot.sensors:
        i = rooted.sensor_v_index[name]
        readings[name] = tau[:, i : i + 6] @ maps[name].T
    return root, readings


def expected_wrenches(
    robot: RobotModel,
    q: np.ndarray,
    dq: np.ndarray,
    ddq: np.ndarray,
    case: ContactCase,
    foot_pairs: Sequence[FootPair] = (),
    n_threads: int | None = None,
) -> ExpectedWrenches:
    """Expected FT wrenches, switches and foot-pair sums for N samples of one contact case.

    q, dq, ddq: (N, n_joints) joint positions (rad), velocities (rad/s), accelerations (rad/s^2) in
    ``robot.joint_names`` order. See :class:`ExpectedWrenches` for the outputs.
    """
    _, raw = rooted_readings(robot, q, dq, ddq, case, n_threads)
    n = raw[next(iter(raw))].shape[0]
    wrench, switch = {}, {}
    for name in robot.sensors:
        on = sensor_switch(robot, name, case.contacts)
        switch[name] = np.full(n, on, dtype=np.uint8)
        wrench[name] = raw[name] if on else np.full((n, 6), np.nan)

    pair_sum, pair_sw, sole_X = {}, {}, {}
    for pair in foot_pairs:
        sole_X[pair.front], sole_X[pair.rear] = pair.sole_X_front, pair.sole_X_rear
        on = pair_switch(pair, case.contacts)
        pair_sw[pair.name] = np.full(n, on, dtype=np.uint8)
        total = raw[pair.front] @ pair.sole_X_front.T + raw[pair.rear] @ pair.sole_X_rear.T
        pair_sum[pair.name] = total if on else np.full((n, 6), np.nan)
    return ExpectedWrenches(wrench, switch, pair_sum, pair_sw, sole_X, raw)
