"""Joint torques estimated from one FT sensor, as a whole-body estimator does (thesis 6.3, Test C).

The sensor measures the wrench through its cut. The torque of a joint j on the same limb follows from it
and the motion of the links *between* the sensor and j, whatever acts beyond (a push, a contact):

- j between the fixed link and the sensor (hip pitch and roll above a leg sensor): the wrench through j
  onto its far side is the sensor's far-side wrench carried to j plus the rate of change of momentum minus
  gravity of the links between them;
- j beyond the sensor (knee, ankle): it is the sensor's far-side wrench carried to j minus that of the
  links between them.

No external wrench may act on the links between (true for a push on the foot, the floor under a sole).
Method: the model rooted at the link fixed in the world (:meth:`RobotModel.rooted`), one forward pass of
Pinocchio per sample for velocities, accelerations and placements; each link's Newton-Euler wrench
``I (a - g) + v x* I v`` in its joint frame. Wrenches [f (N); tau (Nm)], torques Nm (N for prismatic
joints) in the URDF joint's sign convention.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from pipeline.core.errors import RobotModelError
from pipeline.physics.robot import RobotModel, sensor_frame_name


def limb_joints(robot: RobotModel, link: str) -> list[str]:
    """The movable joints on the path from root_link to `link`, root first (a leg: hip to ankle)."""
    parent_joint = {j.child: j for j in robot.joints.values()}
    out, current = [], robot.check_link(link)
    while current in parent_joint:
        joint = parent_joint[current]
        if joint.movable:
            out.append(joint.name)
        current = joint.parent
    return out[::-1]


def _subtree(model: pin.Model, jid: int) -> set[int]:
    """Pinocchio joint ids of the subtree of joint `jid` (itself included)."""
    return {i for i in range(1, model.njoints) if jid in _ancestors(model, i)}


def _ancestors(model: pin.Model, jid: int) -> list[int]:
    out = [jid]
    while out[-1] != 0:
        out.append(model.parents[out[-1]])
    return out


def sensor_joint_torques(
    robot: RobotModel,
    sensor: str,
    joints: Sequence[str],
    q: np.ndarray,
    dq: np.ndarray,
    ddq: np.ndarray,
    wrench: np.ndarray,
    fixed_link: str,
    gravity: Sequence[float],
) -> np.ndarray:
    """(N, len(joints)) torques of `joints`, Nm, from the reading of `sensor` (module docstring); with
    several readings (K, N, 6), (K, N, len(joints)): the kinematics of each sample computed once for all.

    q, dq, ddq: (N, n_joints) rad, rad/s, rad/s^2 in ``robot.joint_names`` order. wrench: (N, 6) the
    sensor's reading in its frame and measure direction, N / Nm (or (K, N, 6): K readings, e.g. raw and
    calibrated). fixed_link: the link fixed in the world; gravity: (3,) m/s^2 in its frame. Raises
    RobotModelError for a joint not on a path through the sensor.
    """
    ft = robot.check_sensor(sensor)
    rooted = robot.rooted(fixed_link)
    model = rooted.model.copy()  # its own gravity: the cached model stays as it is
    data = model.createData()
    model.gravity = pin.Motion(np.asarray(gravity, dtype=float), np.zeros(3))
    s_jid = next(j for j in range(1, model.njoints) if model.idx_vs[j] == rooted.sensor_v_index[sensor])
    s_frame = model.frames[model.getFrameId(sensor_frame_name(sensor))]
    far = _subtree(model, s_jid)
    # the reading -> the wrench the fixed link's side exerts on the far side, in the sensor joint frame
    sign = (1.0 if ft.direction == "parent_to_child" else -1.0) * (
        1.0 if rooted.sensor_forward[sensor] else -1.0
    )
    plans = []
    for name in joints:
        if name not in robot.joint_names:
            raise RobotModelError(f"{robot.urdf_path}: {name!r} is not a movable joint")
        k = robot.joint_names.index(name)
        jid = next(j for j in range(1, model.njoints) if model.idx_vs[j] == rooted.v_index[k])
        if jid in far:  # beyond the sensor: subtract the links from the sensor to j
            between, sub = sorted(far - _subtree(model, jid)), -1.0
        elif s_jid in _subtree(model, jid):  # between the fixed link and the sensor: add them
            between, sub = sorted(_subtree(model, jid) - far), 1.0
        else:
            raise RobotModelError(f"{robot.urdf_path}: joint {name!r} is not on a path through {sensor}")
        plans.append((jid, between, sub, rooted.sign[k]))

    n = q.shape[0]
    qs = rooted.neutral_batch(n)
    qs[:, rooted.q_index] = q * rooted.sign
    vs, accs = np.zeros((n, model.nv)), np.zeros((n, model.nv))
    vs[:, rooted.v_index], accs[:, rooted.v_index] = dq * rooted.sign, ddq * rooted.sign
    bodies = sorted({b for _, between, _, _ in plans for b in between})
    wrenches = np.asarray(wrench, dtype=float)
    many = wrenches.ndim == 3
    wrenches = wrenches if many else wrenches[None]
    out = np.zeros((len(wrenches), n, len(joints)))
    for i in range(n):
        pin.forwardKinematics(model, data, qs[i], vs[i], accs[i])
        pin.computeJointJacobians(model, data, qs[i])
        own = {}
        for b in bodies:
            g_local = pin.Motion(data.oMi[b].rotation.T @ model.gravity.linear, np.zeros(3))
            inertia, v = model.inertias[b], data.v[b]
            own[b] = inertia * (data.a[b] - g_local) + v.cross(inertia * v)
        w_far = [s_frame.placement.act(pin.Force(sign * w)) for w in wrenches[:, i]]  # sensor joint frame
        for c, (jid, between, sub, urdf_sign) in enumerate(plans):
            j_inv = data.oMi[jid].inverse()
            to_joint = j_inv * data.oMi[s_jid]
            links = [(j_inv * data.oMi[b]).act(own[b]) * sub for b in between]
            axis = pin.getJointJacobian(model, data, jid, pin.LOCAL)[:, model.idx_vs[jid]]
            for k, w in enumerate(w_far):
                total = to_joint.act(w)
                for link in links:
                    total = total + link
                out[k, i, c] = urdf_sign * float(axis @ total.vector)
    return out if many else out[0]
