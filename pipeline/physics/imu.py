"""What an IMU fixed in an FT sensor's frame reads, from the joint kinematics and the link fixed in the world.

An accelerometer reads the proper acceleration (specific force) of its origin, ``a - g``: at rest minus
gravity, +9.81 m/s^2 "up"; a gyroscope the angular velocity. Both are expressed in the sensor frame (the
URDF's ``<frame>sensor</frame>`` with the tag's ``<origin>``, `pipeline.physics.robot`), the frame the
simulator's boards read in. For N samples of one contact case the model is rooted at the contact link
rigidly attached to the fixed link (as for the labels, `pipeline.physics.dynamics`): its root does not move,
so every frame's motion follows from q, dq, ddq alone, and gravity is the case's, in the fixed link's frame.

Per sample: Pinocchio's forward kinematics (positions, velocities, accelerations), then per sensor its
frame's placement, its velocity and its classical acceleration, both in the local (sensor) frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from pipeline.physics.dynamics import ContactCase, choose_root
from pipeline.physics.robot import RobotModel, sensor_frame_name


@dataclass
class SensorMotion:
    """An FT sensor frame's motion over N samples, in the sensor frame.

    rest: (N, 3) minus gravity, m/s^2: what a still accelerometer reads. motion: (N, 3) the classical
    acceleration of the frame's origin, m/s^2 (zero at rest). angular: (N, 3) angular velocity, rad/s.
    The proper acceleration an accelerometer reads is ``rest + motion``.
    """

    rest: np.ndarray
    motion: np.ndarray
    angular: np.ndarray

    @property
    def proper(self) -> np.ndarray:
        """(N, 3) proper acceleration, m/s^2."""
        return self.rest + self.motion


def sensor_motion(
    robot: RobotModel,
    q: np.ndarray,
    dq: np.ndarray,
    ddq: np.ndarray,
    case: ContactCase,
    sensors: Sequence[str] | None = None,
) -> dict[str, SensorMotion]:
    """The motion of each sensor frame of `sensors` (default: all) over N samples of one contact case.

    q, dq, ddq: (N, n_joints) rad, rad/s, rad/s^2 in ``robot.joint_names`` order; `case` gives the link
    fixed in the world and gravity in its frame (m/s^2).
    """
    names = list(robot.sensors if sensors is None else sensors)
    root = choose_root(robot, case)
    rooted = robot.rooted(root)
    model = rooted.model
    data = model.createData()
    g_root = robot.rigid_transform(root, case.fixed_link).rotation @ np.asarray(case.gravity, dtype=float)
    n = len(q)
    qs = rooted.neutral_batch(n)
    qs[:, rooted.q_index] = q * rooted.sign
    vs, accs = np.zeros((n, model.nv)), np.zeros((n, model.nv))
    vs[:, rooted.v_index], accs[:, rooted.v_index] = dq * rooted.sign, ddq * rooted.sign
    ids = [model.getFrameId(sensor_frame_name(s)) for s in names]
    out = {s: SensorMotion(np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))) for s in names}
    local = pin.ReferenceFrame.LOCAL
    for k in range(n):
        pin.forwardKinematics(model, data, qs[k], vs[k], accs[k])
        for s, fid in zip(names, ids, strict=True):
            rotation = pin.updateFramePlacement(model, data, fid).rotation
            m = out[s]
            m.rest[k] = -(rotation.T @ g_root)
            m.motion[k] = pin.getFrameClassicalAcceleration(model, data, fid, local).linear
            m.angular[k] = pin.getFrameVelocity(model, data, fid, local).angular
    return out


__all__ = ["SensorMotion", "sensor_motion"]
