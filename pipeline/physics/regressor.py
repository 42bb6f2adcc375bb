"""The FT sensors' expected readings as linear functions of the links' inertial parameters.

For one contact case (the contact-rooted model of :mod:`pipeline.physics.dynamics`: root link fixed,
gravity in its frame), every sensor's rooted reading is linear in the inertial parameters of the links on
its far side (the side away from the root):

    reading_s(q, dq, ddq) = sum_L Y_sL(q, dq, ddq) pi_L

``pi_L`` (10,) are link L's parameters in its own URDF frame, in Pinocchio's order
``[m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz]`` (kg, kg m, kg m^2; the rotational
inertia about the link frame's origin). Method: Pinocchio's joint torque regressor of the rooted model gives
every joint's generalised force as linear in its bodies' parameters (each body in its joint's frame); an
FT sensor's 6-DoF joint rows are the wrench through it, mapped to the sensor's frame and measure direction
as :func:`pipeline.physics.dynamics.rooted_readings` maps RNEA's; and a link appended to a joint body at
placement P contributes ``placement_map(P) pi_L`` to that body (linear: mass, first moment moved and
rotated, inertia by the parallel-axis rule). The regressor depends on the motion only, not on the masses,
so labels for other inertial parameters are ``label + Y delta``. Known loads are part of the labels they
are given with and stay fixed.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from pipeline.physics.dynamics import ContactCase, _sensor_maps, choose_root
from pipeline.physics.robot import RobotModel

PARAMS = 10  # inertial parameters per link
PARAM_NAMES = ("m", "mcx", "mcy", "mcz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")


def skew(v: np.ndarray) -> np.ndarray:
    """The 3x3 cross-product matrix S(v): ``S(v) @ w = v x w``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def sym(i: np.ndarray) -> np.ndarray:
    """The 3x3 symmetric matrix of the 6 inertia entries (xx, xy, yy, xz, yz, zz)."""
    xx, xy, yy, xz, yz, zz = i
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


def entries(m: np.ndarray) -> np.ndarray:
    """The 6 inertia entries (xx, xy, yy, xz, yz, zz) of a symmetric 3x3 matrix, the inverse of `sym`."""
    return np.array([m[0, 0], m[0, 1], m[1, 1], m[0, 2], m[1, 2], m[2, 2]])


def move_params(pi: np.ndarray, placement: pin.SE3) -> np.ndarray:
    """(10,) the parameters `pi` of a body in frame b expressed in frame a, for `placement` = pose of b in
    a: ``m' = m``, ``h' = R h + m p``, ``I'_o = R I_o R^T + S(Rh)^T S(p) + S(p)^T S(Rh) + m S(p)^T S(p)``
    (S the cross-product matrix), linear in `pi`."""
    r, p = placement.rotation, placement.translation
    m, h, inertia = pi[0], pi[1:4], sym(pi[4:])
    rh = r @ h
    sp, srh = skew(p), skew(rh)
    moved = r @ inertia @ r.T + srh.T @ sp + sp.T @ srh + m * sp.T @ sp
    return np.r_[m, rh + m * p, entries(moved)]


def placement_map(placement: pin.SE3) -> np.ndarray:
    """(10, 10) the linear map `move_params` as a matrix."""
    return np.column_stack([move_params(e, placement) for e in np.eye(PARAMS)])


def link_params(robot: RobotModel, links: Sequence[str]) -> np.ndarray:
    """(len(links) * 10,) the URDF's parameters of `links` in their own frames (zeros for massless ones)."""
    out = np.zeros((len(links), PARAMS))
    for k, link in enumerate(links):
        inertial = robot.links[link]
        if inertial is not None and inertial.mass > 0:
            out[k] = inertial.to_pinocchio().toDynamicParameters()
    return out.reshape(-1)


class ReadingRegressor:
    """Per contact case, the map from a batch of joint states to every sensor's reading regressor.

    `links`: the links whose parameters are the unknowns (column blocks of 10, in this order).
    """

    def __init__(self, robot: RobotModel, case: ContactCase, links: Sequence[str]) -> None:
        self.robot, self.links = robot, list(links)
        root = choose_root(robot, case)
        rooted = robot.rooted(root)
        self.rooted = rooted
        self.model = rooted.model.copy()
        r_fixed = robot.rigid_transform(root, case.fixed_link).rotation
        self.model.gravity = pin.Motion(r_fixed @ np.asarray(case.gravity), np.zeros(3))
        self.data = self.model.createData()
        maps = _sensor_maps(robot, root)
        self.sensors = list(robot.sensors)
        # link k's parameters reach its joint's body (column block jid - 1 of Pinocchio's regressor) through
        # placement_map; the root's own body (joint 0) never moves and is in no reading
        jids = np.array([rooted.link_joint[link] for link in self.links])
        self._moving = np.flatnonzero(jids > 0)
        self._columns = (PARAMS * (jids[self._moving] - 1))[:, None] + np.arange(PARAMS)  # (L', 10)
        self._blocks = np.stack([placement_map(rooted.link_placement[self.links[k]]) for k in self._moving])
        self._rows = np.concatenate([np.arange(6) + rooted.sensor_v_index[s] for s in self.sensors])
        self._maps = np.stack([maps[s] for s in self.sensors])  # (S, 6, 6)

    def __call__(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        """(N, S, 6, 10 L) regressors of every sensor's reading (sensor frame, measure direction) for the
        joint states q, dq, ddq (N, n_joints) in ``robot.joint_names`` order (rad, rad/s, rad/s^2)."""
        rooted, model, data = self.rooted, self.model, self.data
        n = len(q)
        qs = np.tile(pin.neutral(model), (n, 1))
        vs, accs = np.zeros((n, model.nv)), np.zeros((n, model.nv))
        qs[:, rooted.q_index] = q * rooted.sign
        vs[:, rooted.v_index] = dq * rooted.sign
        accs[:, rooted.v_index] = ddq * rooted.sign
        s_count, n_rows = len(self.sensors), len(self._rows)
        joint_rows = np.empty((n, n_rows, len(self._moving), PARAMS))
        for i in range(n):
            y = pin.computeJointTorqueRegressor(model, data, qs[i], vs[i], accs[i])
            joint_rows[i] = y[self._rows][:, self._columns]
        moving = len(self._moving)
        stacked = joint_rows.transpose(2, 0, 1, 3).reshape(moving, n * n_rows, PARAMS)
        per_link = np.matmul(stacked, self._blocks).reshape(moving, n, n_rows, PARAMS)  # batched BLAS
        out = np.zeros((n, n_rows, len(self.links), PARAMS))
        out[:, :, self._moving] = per_link.transpose(1, 2, 0, 3)
        return np.matmul(self._maps[None], out.reshape(n, s_count, 6, -1))


__all__ = [
    "PARAMS",
    "PARAM_NAMES",
    "ReadingRegressor",
    "entries",
    "link_params",
    "move_params",
    "placement_map",
    "skew",
    "sym",
]
