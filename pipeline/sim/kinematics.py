"""Kinematics of the simulated robot: fixed-base (root_link) Pinocchio forward kinematics, leg inverse
kinematics, the centre of mass, and the smooth curves every simulated motion is built from.

Joint vectors are in ``robot.joint_names`` order (rad, m for prismatic joints); poses are
``pinocchio.SE3`` in the root_link frame unless said otherwise; lengths in m.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from scipy.interpolate import make_interp_spline

from pipeline.core.errors import RobotModelError
from pipeline.physics.robot import RobotModel


@dataclass(frozen=True)
class Foot:
    """A foot of the robot: its name, sole link, and the links touching the floor (front, rear; the same
    link for a foot of one part), with the centres of its front and rear contact parts in the sole frame
    (m; None: the links' origins, as for a foot whose two parts are links of their own)."""

    name: str
    sole: str
    front_link: str
    rear_link: str
    front_center: tuple[float, float, float] | None = None
    rear_center: tuple[float, float, float] | None = None

    @property
    def links(self) -> frozenset[str]:
        return frozenset((self.front_link, self.rear_link))

    def centers(self, robot: RobotModel) -> tuple[np.ndarray, np.ndarray]:
        """(front, rear) contact centres, (3,) each, in the sole frame, m."""
        front = self.front_center or robot.rigid_transform(self.sole, self.front_link).translation
        rear = self.rear_center or robot.rigid_transform(self.sole, self.rear_link).translation
        return np.asarray(front, dtype=float), np.asarray(rear, dtype=float)


def smoothstep(s: np.ndarray) -> np.ndarray:
    """0 -> 1 (degree 9) with zero derivatives up to the fourth at both ends: motions built from it are
    as smooth as the quintic-spline truth, so a polynomial smoother sees no kink at phase changes."""
    s = np.clip(s, 0.0, 1.0)
    return s**5 * (126 - 420 * s + 540 * s**2 - 315 * s**3 + 70 * s**4)


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of two (3,) float vectors: the products and differences of np.cross (the same bits), without
    its overhead per call (for loops over samples)."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def multisine(
    rng: np.random.Generator, t: np.ndarray, n: int, f_min: float, f_max: float, n_terms: int = 3
) -> np.ndarray:
    """(len(t), n) sums of `n_terms` sines per column with random frequencies in [f_min, f_max] Hz and
    phases, normalised to peak 1 over `t`."""
    out = np.zeros((t.shape[0], n))
    for j in range(n):
        freqs = rng.uniform(f_min, f_max, n_terms)
        amps = rng.uniform(0.3, 1.0, n_terms)
        phases = rng.uniform(0, 2 * np.pi, n_terms)
        out[:, j] = (amps * np.sin(2 * np.pi * freqs * t[:, None] + phases)).sum(axis=1)
    peak = np.abs(out).max(axis=0)
    return out / np.where(peak > 0, peak, 1.0)


class Kinematics:
    """Fixed-base (root_link) Pinocchio kinematics in robot.joint_names order, with leg IK and the CoM."""

    def __init__(self, robot: RobotModel, limit_margin: float) -> None:
        self.robot = robot
        self.model = robot.pinocchio_model
        self.data = self.model.createData()
        self.to_pin = np.array([self.model.idx_qs[self.model.getJointId(n)] for n in robot.joint_names])
        self.to_pin_v = np.array([self.model.idx_vs[self.model.getJointId(n)] for n in robot.joint_names])
        lower = np.array([robot.joints[n].lower for n in robot.joint_names])
        upper = np.array([robot.joints[n].upper for n in robot.joint_names])
        lower = np.where(np.isfinite(lower), lower, -np.pi)
        upper = np.where(np.isfinite(upper), upper, np.pi)
        self.lower, self.upper = lower + limit_margin, upper - limit_margin
        self._neutral = pin.neutral(self.model)
        # (frame id, mass kg, COM (3,) m in the link frame) of every link with mass, in robot.links order
        self._masses = [
            (self.model.getFrameId(name), inertial.mass, inertial.com)
            for name, inertial in robot.links.items()
            if inertial is not None and inertial.mass != 0.0
        ]
        self._total_mass = 0.0
        for _, mass, _ in self._masses:  # summed in the same order as the moments
            self._total_mass += mass

    def chain(self, link: str) -> np.ndarray:
        """Indices (robot order) of the movable joints between root_link and `link`."""
        robot = self.robot
        parent_joint = {j.child: j for j in robot.joints.values()}
        out, current = [], robot.check_link(link)
        while current in parent_joint:
            joint = parent_joint[current]
            if joint.movable:
                out.append(robot.joint_names.index(joint.name))
            current = joint.parent
        if current != robot.root_link:
            raise RobotModelError(f"{link} is not below {robot.root_link}")
        return np.array(out[::-1], dtype=np.intp)

    def _pin_q(self, q: np.ndarray) -> np.ndarray:
        out = self._neutral.copy()
        out[self.to_pin] = q
        return out

    def frame_pose(self, q: np.ndarray, frame: str) -> pin.SE3:
        """Pose of `frame` in the root_link frame for joint positions q (robot order)."""
        pin.framesForwardKinematics(self.model, self.data, self._pin_q(q))
        return self.data.oMf[self.model.getFrameId(frame)].copy()

    def point_motion(
        self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, frame: str, point: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Position (3,) m and classical acceleration (3,) m/s^2 of `point` (in `frame`'s frame, m), both in
        the root_link frame, for joint positions, velocities and accelerations in robot order."""
        v, a = np.zeros(self.model.nv), np.zeros(self.model.nv)
        v[self.to_pin_v], a[self.to_pin_v] = dq, ddq
        pin.forwardKinematics(self.model, self.data, self._pin_q(q), v, a)
        fid = self.model.getFrameId(frame)
        placement = pin.updateFramePlacement(self.model, self.data, fid)
        aligned = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        vel = pin.getFrameVelocity(self.model, self.data, fid, aligned)
        acc = pin.getFrameClassicalAcceleration(self.model, self.data, fid, aligned)
        r = placement.rotation @ np.asarray(point, dtype=float)
        w, alpha = vel.angular, pin.getFrameAcceleration(self.model, self.data, fid, aligned).angular
        return placement.translation + r, acc.linear + cross3(alpha, r) + cross3(w, cross3(w, r))

    def com(self, q: np.ndarray) -> np.ndarray:
        """Centre of mass of the whole robot in the root_link frame, m (3,)."""
        pin.framesForwardKinematics(self.model, self.data, self._pin_q(q))
        moment = np.zeros(3)
        for fid, mass, com in self._masses:
            moment += mass * self.data.oMf[fid].act(com)
        return moment / self._total_mass

    def ik(
        self,
        q: np.ndarray,
        frame: str,
        target: pin.SE3,
        joints: np.ndarray,
        iters: int = 100,
        tol: float = 1e-9,
        position_only: bool = False,
    ) -> np.ndarray:
        """Joint positions (robot order) putting `frame` at `target` (root frame) by moving `joints` only.

        Damped Gauss-Newton on the SE(3) error (or on the position error only), clipped to the joint
        limits (minus the margin); raises RobotModelError if the target is out of reach.
        """
        q = q.copy()
        model, data = self.model, self.data
        fid = model.getFrameId(frame)
        columns = self.to_pin_v[joints]  # the Jacobian's columns of `joints`
        lower, upper = self.lower[joints], self.upper[joints]
        damping = 1e-4 * np.eye(len(joints))
        err = np.inf
        for _ in range(iters):
            pq = self._pin_q(q)
            pin.forwardKinematics(model, data, pq)
            current = pin.updateFramePlacement(model, data, fid)
            if position_only:
                err_vec = target.translation - current.translation
            else:
                err_vec = pin.log6(current.actInv(target)).vector
            err = math.sqrt(err_vec.dot(err_vec))  # = np.linalg.norm, without its overhead
            if err < tol:
                return q
            if position_only:
                jac = pin.computeFrameJacobian(model, data, pq, fid, pin.LOCAL_WORLD_ALIGNED)[:3, columns]
            else:
                jac = pin.computeFrameJacobian(model, data, pq, fid, pin.LOCAL)[:, columns]
            # Levenberg-Marquardt with a capped step: a straight knee is singular
            step = np.linalg.solve(jac.T @ jac + damping, jac.T @ err_vec)
            step *= min(1.0, 0.3 / max(np.abs(step).max(), 1e-12))
            q[joints] = np.clip(q[joints] + step, lower, upper)
        if err > 1e-5:
            raise RobotModelError(
                f"inverse kinematics of {frame} did not converge (error {err:.2e}): "
                "target out of reach; reduce the motion amplitude in params"
            )
        return q


def pose(xyz: Sequence[float], rpy: Sequence[float] = (0.0, 0.0, 0.0)) -> pin.SE3:
    return pin.SE3(pin.rpy.rpyToMatrix(*[float(a) for a in rpy]), np.asarray(xyz, float))


def interp(t: np.ndarray, y: np.ndarray, k: int = 5):
    """Interpolating spline of order k (lower, odd, when there are too few points for k)."""
    while k > 1 and len(t) <= k:
        k -= 2
    return make_interp_spline(t, y, k=k, axis=0)


def spline(t: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, velocities, accelerations of the quintic spline through the postures (C4: smooth
    accelerations, and no boundary condition forcing them at the ends)."""
    curve = interp(t, q)
    return curve(t), curve(t, 1), curve(t, 2)
