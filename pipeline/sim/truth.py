"""True FT wrenches and FT-board IMU signals of a simulated motion.

The true robot (URDF with mass and COM errors) moves as :class:`pipeline.sim.motion.Motion` says.
Where one side of a sensor's cut touches nothing, its true wrench is exactly what
`pipeline.physics.dynamics` computes. Where both sides touch, the split of the ground load decides it, and
the simulator chooses that split the way a real robot's compliance would, in ways the labeller cannot
know:

- between the two feet in double support: the weight-transfer fraction of the motion (smooth, skewed
  per step), each foot's centre of pressure shifted alike so that the total moment is preserved;
- between the front and rear part of one foot: the lever rule on the foot's centre of pressure.

The true sensor wrenches then follow by superposition: RNEA rooted at one contact link gives the
readings as if all contact forces acted there; every other contact wrench on the far side of a cut is
subtracted from it. World frame of a sample: its fixed link's frame (gravity (0, 0, -g) there).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from pipeline.physics.dynamics import ContactCase, choose_root, far_side_wrenches, rooted_readings
from pipeline.physics.feet import Foot, foot_of_pair
from pipeline.physics.robot import FootPair, RobotModel, sensor_frame_name, wrench_transform
from pipeline.sim.kinematics import cross3
from pipeline.sim.motion import Motion

PROFILE_WEIGHT = 0.2  # share of the double-support split set by the motion's profile, not by statics
# A foot carrying less than this share of the load in double support carries nothing: it touches the
# floor without pressing on it, which for every label is the same as not touching. The true contact set
# is the load-bearing one, so a contact starts and ends where a foot's load leaves or reaches zero.
DEAD_ZONE = 0.05


@dataclass
class Truth:
    """True signals of one motion, per sample.

    wrench[s]: (N, 6) true reading of sensor s (its frame, its measure direction), N and Nm.
    contact_wrench[link]: (N, 6) wrench of the environment on a contact link, in the sample's world
    (fixed link) frame about its origin; zero where the link does not touch, NaN where not resolved
    (a single contact on the pole: not needed).
    proper_acc[s], gyro[s]: (N, 3) proper acceleration (m/s^2) and angular velocity (rad/s) of the
    sensor frame, in the sensor frame. world_T_sensor[s]: (N, 4, 4).
    """

    wrench: dict[str, np.ndarray]
    contact_wrench: dict[str, np.ndarray]
    proper_acc: dict[str, np.ndarray]
    gyro: dict[str, np.ndarray]
    world_T_sensor: dict[str, np.ndarray]
    contacts: list[frozenset[str]] | None = None  # per sample: the load-bearing contact links
    # (N, n_joints) true joint torques, Nm (robot.joint_names order), with pushes only; NaN where more than
    # one link touches (the ground split is not resolved for joint torques)
    joint_torque: np.ndarray | None = None
    # external[s]: (N, 6) the part of wrench[s] due to the motion's pushes and loads (zero without), N and Nm
    external: dict[str, np.ndarray] | None = None


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.cross(a, b)


def weight_wrench(robot: RobotModel, links: frozenset[str], frame: str, gravity: np.ndarray) -> np.ndarray:
    """(6,) gravity wrench on `links` (rigidly attached to link `frame`) in `frame`, about its origin."""
    total = np.zeros(6)
    for link in links:
        inertial = robot.links[link]
        if inertial is None or inertial.mass == 0.0:
            continue
        pose = robot.rigid_transform(frame, link)
        force = inertial.mass * gravity
        total += np.r_[force, _cross(pose.act(inertial.com), force)]
    return total


def split_between_points(wrench: np.ndarray, centers: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Split ground wrenches among contact areas at `centers`, carrying `fractions` of the force.

    wrench: (N, 6) total ground wrench in a frame whose z is the floor normal (z = 0 on the floor),
    about its origin. centers: (N, k, 3) area centres on the floor. fractions: (N, k), rows summing to 1.
    Each area gets its fraction of the force at its centre shifted by a common offset that keeps the
    total centre of pressure, and the same fraction of the free moment. Returns (N, k, 6) summing to
    `wrench` exactly.
    """
    force, moment = wrench[:, :3], wrench[:, 3:]
    fz = np.where(np.abs(force[:, 2]) > 1e-9, force[:, 2], 1e-9)
    cop = np.stack([-moment[:, 1] / fz, moment[:, 0] / fz, np.zeros(len(fz))], axis=1)
    free = moment - _cross(cop, force)
    shift = cop - np.einsum("nk,nkj->nj", fractions, centers)
    points = centers + shift[:, None, :]
    forces = fractions[:, :, None] * force[:, None, :]
    moments = _cross(points, forces) + fractions[:, :, None] * free[:, None, :]
    return np.concatenate([forces, moments], axis=2)


def split_front_rear(wrench: np.ndarray, x_front: float, x_rear: float) -> tuple[np.ndarray, np.ndarray]:
    """Lever-rule split of a foot's ground wrench (N, 6), in its sole frame, between the front and rear
    parts whose contact centres lie at x_front and x_rear on the sole's x axis. Exact sum."""
    force, moment = wrench[:, :3], wrench[:, 3:]
    fz = np.where(np.abs(force[:, 2]) > 1e-9, force[:, 2], 1e-9)
    x_cop, y_cop = -moment[:, 1] / fz, moment[:, 0] / fz
    lam = np.clip((x_cop - x_rear) / (x_front - x_rear), 0.0, 1.0)
    n = len(fz)
    p_front = np.stack([np.full(n, x_front), y_cop, np.zeros(n)], axis=1)
    p_rear = np.stack([np.full(n, x_rear), y_cop, np.zeros(n)], axis=1)
    f_front, f_rear = lam[:, None] * force, (1 - lam)[:, None] * force
    rest = moment - _cross(p_front, f_front) - _cross(p_rear, f_rear)
    front = np.concatenate([f_front, _cross(p_front, f_front) + lam[:, None] * rest], axis=1)
    rear = np.concatenate([f_rear, _cross(p_rear, f_rear) + (1 - lam)[:, None] * rest], axis=1)
    return front, rear


class TruthComputer:
    """Computes :class:`Truth` for motions of one (true) robot."""

    def __init__(self, robot: RobotModel, feet: Sequence[Foot | FootPair], gravity: float) -> None:
        """`feet`: every foot with its sensors (`pipeline.physics.feet`; a FootPair stands for its foot)."""
        self.g = np.array([0.0, 0.0, -gravity])
        self.robot = robot
        self.pairs = [foot_of_pair(robot, f) if isinstance(f, FootPair) else f for f in feet]
        self.pair_of_link = {}
        for pair in self.pairs:
            for link in pair.foot_links:
                self.pair_of_link[link] = pair

    def _kinematics(
        self, root: str, fixed: str, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, links: Sequence[str]
    ) -> tuple[dict, dict, dict, dict]:
        """Per-sample frame kinematics on the model rooted at `root`: sensor poses, IMU signals, and
        poses of `links`, all in the world (= `fixed`) frame."""
        rooted = self.robot.rooted(root)
        model, data = rooted.model, rooted.model.createData()
        fixed_T_root = self.robot.rigid_transform(fixed, root)
        g_root = fixed_T_root.rotation.T @ self.g
        n = q.shape[0]
        qs = rooted.neutral_batch(n)
        qs[:, rooted.q_index] = q * rooted.sign
        vs, accs = np.zeros((n, model.nv)), np.zeros((n, model.nv))
        vs[:, rooted.v_index], accs[:, rooted.v_index] = dq * rooted.sign, ddq * rooted.sign
        sensor_ids = {s: model.getFrameId(sensor_frame_name(s)) for s in self.robot.sensors}
        link_ids = {link: model.getFrameId(link) for link in links}
        pose = {s: np.zeros((n, 4, 4)) for s in sensor_ids}
        acc = {s: np.zeros((n, 3)) for s in sensor_ids}
        gyro = {s: np.zeros((n, 3)) for s in sensor_ids}
        link_pose = {link: np.zeros((n, 4, 4)) for link in links}
        local = pin.ReferenceFrame.LOCAL
        for k in range(n):
            pin.forwardKinematics(model, data, qs[k], vs[k], accs[k])
            pin.updateFramePlacements(model, data)
            for s, fid in sensor_ids.items():
                placement = data.oMf[fid]
                pose[s][k] = placement.homogeneous
                gyro[s][k] = pin.getFrameVelocity(model, data, fid, local).angular
                acc[s][k] = (
                    pin.getFrameClassicalAcceleration(model, data, fid, local).linear
                    - placement.rotation.T @ g_root
                )
            for link, fid in link_ids.items():
                link_pose[link][k] = data.oMf[fid].homogeneous
        world = fixed_T_root.homogeneous
        pose = {s: world @ v for s, v in pose.items()}
        link_pose = {link: world @ v for link, v in link_pose.items()}
        return pose, acc, gyro, link_pose

    def compute(self, motion: Motion) -> Truth:
        robot, n = self.robot, motion.n
        wrench = {s: np.zeros((n, 6)) for s in robot.sensors}
        contact_links = sorted(set().union(*motion.contact_sets))
        contact_wrench = {c: np.zeros((n, 6)) for c in contact_links}
        proper_acc = {s: np.zeros((n, 3)) for s in robot.sensors}
        gyro = {s: np.zeros((n, 3)) for s in robot.sensors}
        world_T_sensor = {s: np.zeros((n, 4, 4)) for s in robot.sensors}
        external = {s: np.zeros((n, 6)) for s in robot.sensors} if motion.pushes else None

        keys = sorted(
            {(int(c), str(f)) for c, f in zip(motion.contact_index, motion.fixed_links, strict=True)}
        )
        for contact_id, fixed in keys:
            contacts = motion.contact_sets[contact_id]
            idx = np.flatnonzero((motion.contact_index == contact_id) & (motion.fixed_links == fixed))
            q, dq, ddq = motion.q[idx], motion.dq[idx], motion.ddq[idx]
            case = ContactCase.make(contacts, fixed, self.g)
            root, asif = rooted_readings(robot, q, dq, ddq, case)
            pose, acc, gyr, link_pose = self._kinematics(
                root, fixed, q, dq, ddq, [p.sole for p in self.pairs] + list(contacts)
            )
            for s in robot.sensors:
                proper_acc[s][idx], gyro[s][idx], world_T_sensor[s][idx] = acc[s], gyr[s], pose[s]

            ground = self._ground_wrenches(case, root, asif, link_pose, motion, idx)
            if ground is None:  # one contact link: every cut has a free side, nothing to split
                for c in contacts:
                    contact_wrench[c][idx] = np.nan
                for s in robot.sensors:
                    wrench[s][idx] = asif[s]
                if motion.pushes:
                    self._subtract_pushes(wrench, external, idx, root, pose, motion)
                continue
            for c, g_c in ground.items():
                contact_wrench[c][idx] = g_c
            rooted = robot.rooted(root)
            for s, ft in robot.sensors.items():
                parent_side, child_side = robot.sensor_sides(s)
                far = child_side if rooted.sensor_forward[s] else parent_side
                sign = (1.0 if ft.direction == "parent_to_child" else -1.0) * (
                    1.0 if rooted.sensor_forward[s] else -1.0
                )
                total = asif[s].copy()
                inv = np.linalg.inv(pose[s])
                for c, g_c in ground.items():
                    if c == root or c not in far:
                        continue
                    # world wrench -> sensor frame: rotate, then move the moment to the sensor origin
                    rot, pos = inv[:, :3, :3], inv[:, :3, 3]
                    f_s = np.einsum("nij,nj->ni", rot, g_c[:, :3])
                    t_s = np.einsum("nij,nj->ni", rot, g_c[:, 3:]) + _cross(pos, f_s)
                    total -= sign * np.concatenate([f_s, t_s], axis=1)
                wrench[s][idx] = total
            if motion.pushes:
                self._subtract_pushes(wrench, external, idx, root, pose, motion)
        # the load-bearing contact set: a foot whose ground wrench is exactly zero does not touch; a foot
        # that bears load touches with every link it has on the floor (a part may carry little)
        contacts = []
        for k in range(n):
            declared = motion.contact_sets[motion.contact_index[k]]
            idle = set()
            for pair in self.pairs:
                links = [c for c in declared if c in pair.foot_links]
                if links and all(np.all(contact_wrench[c][k] == 0.0) for c in links):
                    idle.update(links)
            bearing = frozenset(declared - idle)
            contacts.append(bearing if bearing else declared)
        torque = joint_torques(robot, motion, self.g) if motion.pushes else None
        return Truth(wrench, contact_wrench, proper_acc, gyro, world_T_sensor, contacts, torque, external)

    def _subtract_pushes(
        self,
        wrench: dict[str, np.ndarray],
        external: dict[str, np.ndarray],
        idx: np.ndarray,
        root: str,
        pose: dict,
        motion: Motion,
    ) -> None:
        """Superpose the pushes of `motion` (samples `idx`) on the sensors whose far side they act on; each
        sensor's share also goes to `external`."""
        rooted = self.robot.rooted(root)
        for s, ft in self.robot.sensors.items():
            parent_side, child_side = self.robot.sensor_sides(s)
            far = child_side if rooted.sensor_forward[s] else parent_side
            sign = (1.0 if ft.direction == "parent_to_child" else -1.0) * (
                1.0 if rooted.sensor_forward[s] else -1.0
            )
            inv = np.linalg.inv(pose[s])
            rot, pos = inv[:, :3, :3], inv[:, :3, 3]
            for link, w in motion.pushes.items():
                if link not in far:
                    continue
                f_s = np.einsum("nij,nj->ni", rot, w[idx, :3])
                t_s = np.einsum("nij,nj->ni", rot, w[idx, 3:]) + _cross(pos, f_s)
                share = -sign * np.concatenate([f_s, t_s], axis=1)
                wrench[s][idx] += share
                external[s][idx] += share

    def _ground_wrenches(
        self,
        case: ContactCase,
        root: str,
        asif: dict[str, np.ndarray],
        link_pose: dict[str, np.ndarray],
        motion: Motion,
        idx: np.ndarray,
    ) -> dict[str, np.ndarray] | None:
        """The environment's wrench on every contact link (world frame), or None for one contact."""
        if len(case.contacts) == 1:
            return None
        root_pair = self.pair_of_link.get(root)
        if root_pair is None or any(c not in self.pair_of_link for c in case.contacts):
            raise NotImplementedError(f"contact set {sorted(case.contacts)}: only feet can share the load")
        robot = self.robot
        # total ground wrench, in the fixed sole frame: the root foot is static, so
        # ground = -(rest of the robot on the foot, i.e. the as-if pair sum) - (the foot's own weight)
        pair_sum = root_pair.rest_on_foot(asif)
        total = -pair_sum - weight_wrench(robot, root_pair.foot_links, root_pair.sole, self.g)
        fixed_X_sole = wrench_transform(robot.rigid_transform(case.fixed_link, root_pair.sole))
        total = total @ fixed_X_sole.T

        by_name = {self.pair_of_link[c].name: self.pair_of_link[c] for c in case.contacts}
        feet = [by_name[name] for name in sorted(by_name)]
        n = len(idx)
        if len(feet) == 1:
            per_foot = {feet[0].name: total}
        else:
            share = motion.transfer[idx]
            to = motion.transfer_to[idx]
            fractions = np.zeros((n, len(feet)))
            for j, foot in enumerate(feet):
                mine = np.array([t == foot.name for t in to])
                fractions[:, j] = np.where(mine, share, (1 - share) / (len(feet) - 1))
            if len(feet) == 2:
                # statics: the load follows the centre of pressure between the feet (lever rule), and the
                # motion's skewed weight-transfer profile perturbs it (the part no model can know)
                c_a, c_b = link_pose[feet[0].sole][:, :3, 3], link_pose[feet[1].sole][:, :3, 3]
                fz = np.where(np.abs(total[:, 2]) > 1e-9, total[:, 2], 1e-9)
                cop = np.stack([-total[:, 4] / fz, total[:, 3] / fz], axis=1)
                span = (c_b - c_a)[:, :2]
                lever = np.clip(
                    np.einsum("ni,ni->n", cop - c_a[:, :2], span) / np.einsum("ni,ni->n", span, span),
                    0.0,
                    1.0,
                )
                on_b = (1 - PROFILE_WEIGHT) * lever + PROFILE_WEIGHT * fractions[:, 1]
                on_b = np.clip((on_b - DEAD_ZONE) / (1 - 2 * DEAD_ZONE), 0.0, 1.0)
                fractions = np.stack([1 - on_b, on_b], axis=1)
            centers = np.stack([link_pose[f.sole][:, :3, 3] for f in feet], axis=1)
            parts = split_between_points(total, centers, fractions)
            per_foot = {f.name: parts[:, j] for j, f in enumerate(feet)}

        out = {}
        for foot in feet:
            world_T_sole = link_pose[foot.sole]
            touching = [c for c in case.contacts if c in foot.foot_links]
            g_world = per_foot[foot.name]
            if len(touching) == 1:
                out[touching[0]] = g_world
                continue
            # to the sole frame, split by the lever rule, back to the world frame
            rot, pos = world_T_sole[:, :3, :3], world_T_sole[:, :3, 3]
            f_sole = np.einsum("nji,nj->ni", rot, g_world[:, :3])
            t_sole = np.einsum("nji,nj->ni", rot, g_world[:, 3:] - _cross(pos, g_world[:, :3]))
            front_link = robot.sensors[foot.front].child_link
            rear_link = robot.sensors[foot.rear].child_link
            x_f = robot.rigid_transform(foot.sole, front_link).translation[0]
            x_r = robot.rigid_transform(foot.sole, rear_link).translation[0]
            front, rear = split_front_rear(np.concatenate([f_sole, t_sole], axis=1), x_f, x_r)
            for link, w in ((front_link, front), (rear_link, rear)):
                f_w = np.einsum("nij,nj->ni", rot, w[:, :3])
                t_w = np.einsum("nij,nj->ni", rot, w[:, 3:]) + _cross(pos, f_w)
                out[link] = np.concatenate([f_w, t_w], axis=1)
        return out


def joint_torques(robot: RobotModel, motion: Motion, gravity: np.ndarray) -> np.ndarray:
    """(N, n_joints) true joint torques, Nm, of samples where one link touches (NaN elsewhere).

    RNEA on the model rooted at that link gives the torques as if no other force acted; each push wrench
    w (world frame, about its origin) then adds ``-J^T w`` with J the Jacobian of its link's frame.
    """
    out = np.full((motion.n, len(robot.joint_names)), np.nan)
    for contact_id, contact_set in enumerate(motion.contact_sets):
        if len(contact_set) != 1:
            continue
        for fixed in sorted(set(motion.fixed_links[motion.contact_index == contact_id].tolist())):
            idx = np.flatnonzero((motion.contact_index == contact_id) & (motion.fixed_links == fixed))
            root = choose_root(robot, ContactCase.make(contact_set, fixed, gravity))
            fixed_T_root = robot.rigid_transform(fixed, root)
            g_root = fixed_T_root.rotation.T @ gravity
            rooted = robot.rooted(root)
            q, dq, ddq = motion.q[idx], motion.dq[idx], motion.ddq[idx]
            tau = far_side_wrenches(robot, root, g_root, q, dq, ddq)
            root_X_fixed = wrench_transform(fixed_T_root.inverse())
            model, data = rooted.model, rooted.model.createData()
            qs = rooted.neutral_batch(len(idx))
            qs[:, rooted.q_index] = q * rooted.sign
            for link, w in motion.pushes.items():
                fid = model.getFrameId(link)
                w_root = w[idx] @ root_X_fixed.T
                for j in np.flatnonzero(w_root.any(axis=1)):  # the pushed samples
                    pin.framesForwardKinematics(model, data, qs[j])
                    jac = pin.computeFrameJacobian(model, data, qs[j], fid, pin.LOCAL_WORLD_ALIGNED)
                    p = data.oMf[fid].translation
                    about = np.concatenate((w_root[j, :3], w_root[j, 3:] - cross3(p, w_root[j, :3])))
                    tau[j] -= jac.T @ about
            out[idx] = tau[:, rooted.v_index] * rooted.sign
    return out
