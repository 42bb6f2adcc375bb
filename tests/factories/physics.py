"""Physics computed another way than the package does: per-link Newton-Euler on Pinocchio frame
kinematics (no RNEA), RNEA on Pinocchio's own URDF model, the momentum balance of every cut, and a wrench
transform written out by hand. Wrenches are [f; tau] in N and Nm, joint states in the robot's joint order.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from pipeline.physics.robot import RobotModel, wrench_transform
from pipeline.sim.motion import Foot
from tests.conftest import GRAVITY

G = (0.0, 0.0, -GRAVITY)  # m/s^2, in the fixed link's frame
# the contact links of each foot
L_FOOT, R_FOOT = {"l_foot_front", "l_foot_rear"}, {"r_foot_front", "r_foot_rear"}
# the contacts of double support (both feet, front and rear)
DOUBLE = ["l_foot_front", "l_foot_rear", "r_foot_front", "r_foot_rear"]
# the motion generator's feet: (foot, sole, front contact, rear contact)
FEET = [
    Foot("l_foot", "l_sole", "l_foot_front", "l_foot_rear"),
    Foot("r_foot", "r_sole", "r_foot_front", "r_foot_rear"),
]


def random_state(robot: RobotModel, rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    """(q, dq, ddq), each (n, joints) in the robot's joint order, drawn from `rng`: positions uniform within
    the joint limits (rad), velocities in [-1, 1] rad/s, accelerations in [-5, 5] rad/s^2."""
    lower = np.array([robot.joints[j].lower for j in robot.joint_names])
    upper = np.array([robot.joints[j].upper for j in robot.joint_names])
    q = rng.uniform(lower, upper, (n, len(lower)))
    return q, rng.uniform(-1, 1, q.shape), rng.uniform(-5, 5, q.shape)


def random_states(robot: RobotModel, n: int, seed: int, moving: bool = True) -> tuple[np.ndarray, ...]:
    """`random_state` from a generator seeded with `seed`; velocities and accelerations 0 unless `moving`."""
    q, dq, ddq = random_state(robot, np.random.default_rng(seed), n)
    scale = 1.0 if moving else 0.0
    return q, scale * dq, scale * ddq


def to_pin(robot: RobotModel, x: np.ndarray) -> np.ndarray:
    """Robot joint order -> Pinocchio's own model order."""
    model = robot.pinocchio_model
    out = np.zeros(model.nq)
    for k, name in enumerate(robot.joint_names):
        out[model.idx_qs[model.getJointId(name)]] = x[k]
    return out


def check_pinocchio_joint_torques(robot: RobotModel, rng: np.random.Generator, n: int) -> None:
    """RNEA's joint torques of the model rooted at root_link equal those of Pinocchio's own URDF model,
    in `n` random states."""
    rooted = robot.rooted(robot.root_link)
    ref_model = robot.pinocchio_model
    ref_data, data = ref_model.createData(), rooted.model.createData()
    for q, dq, ddq in zip(*random_state(robot, rng, n), strict=True):
        tau_ref = pin.rnea(ref_model, ref_data, to_pin(robot, q), to_pin(robot, dq), to_pin(robot, ddq))
        qs = pin.neutral(rooted.model)
        vs, accs = np.zeros(rooted.model.nv), np.zeros(rooted.model.nv)
        qs[rooted.q_index], vs[rooted.v_index], accs[rooted.v_index] = (
            q * rooted.sign,
            dq * rooted.sign,
            ddq * rooted.sign,
        )
        tau = pin.rnea(rooted.model, data, qs, vs, accs)[rooted.v_index] * rooted.sign
        np.testing.assert_allclose(
            tau, [tau_ref[ref_model.idx_vs[ref_model.getJointId(n)]] for n in robot.joint_names], atol=1e-9
        )


class LinkNewtonEuler:
    """Per-link Newton-Euler on the model rooted at the fixed link (its frame is the world frame)."""

    def __init__(self, robot: RobotModel, root: str, gravity_root: np.ndarray) -> None:
        self.robot, self.rooted = robot, robot.rooted(root)
        self.model = self.rooted.model
        self.data = self.model.createData()
        self.gravity = gravity_root

    def set_state(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> None:
        r = self.rooted
        qs, vs, accs = pin.neutral(self.model), np.zeros(self.model.nv), np.zeros(self.model.nv)
        qs[r.q_index], vs[r.v_index], accs[r.v_index] = q * r.sign, dq * r.sign, ddq * r.sign
        pin.forwardKinematics(self.model, self.data, qs, vs, accs)
        pin.updateFramePlacements(self.model, self.data)

    def pose(self, link: str) -> pin.SE3:
        """Pose of `link` in the world (= root) frame."""
        return self.data.oMf[self.model.getFrameId(link)]

    def required_wrench(self, links: set[str] | frozenset[str], frame: pin.SE3) -> np.ndarray:
        """sum over `links` of (dh/dt - m g) as a wrench in `frame` (a world pose), [f; tau about origin]."""
        total = np.zeros(6)
        for link in links:
            inertial = self.robot.links[link]
            if inertial is None or inertial.mass == 0.0:
                continue
            fid = self.model.getFrameId(link)
            world_T_link = self.data.oMf[fid]
            v = pin.getFrameVelocity(self.model, self.data, fid, pin.LOCAL)
            a = pin.getFrameAcceleration(self.model, self.data, fid, pin.LOCAL)
            g_link = pin.Motion(world_T_link.rotation.T @ self.gravity, np.zeros(3))
            inertia = inertial.to_pinocchio()
            f_link = inertia * (a - g_link) + v.cross(inertia * v)
            total += wrench_transform(frame.inverse() * world_T_link) @ f_link.vector
        return total

    def sensor_frame(self, sensor: str) -> pin.SE3:
        ft = self.robot.sensors[sensor]
        return self.pose(ft.child_link) * ft.child_T_sensor


def reference_reading(ne: LinkNewtonEuler, sensor: str, contacts: set[str]) -> np.ndarray:
    """The sensor's reading from the free side of its cut: F(P on Q) = w(Q) if Q is free, else -w(P)."""
    parent_side, child_side = ne.robot.sensor_sides(sensor)
    frame = ne.sensor_frame(sensor)
    p_on_q = (
        ne.required_wrench(child_side, frame)
        if not contacts & child_side
        else -ne.required_wrench(parent_side, frame)
    )
    return p_on_q if ne.robot.sensors[sensor].direction == "parent_to_child" else -p_on_q


def assert_momentum_balance(robot: RobotModel, motion, truth) -> None:
    """Every sensor's true reading and the contact wrenches against Newton-Euler link by link (25 samples)."""
    icub = robot
    samples = np.linspace(0, motion.n - 1, 25).astype(int)
    for k in samples:
        fixed = motion.fixed_links[k]
        contacts = motion.contact_sets[motion.contact_index[k]]
        ne = LinkNewtonEuler(icub, fixed, np.array([0.0, 0.0, -GRAVITY]))
        ne.set_state(motion.q[k], motion.dq[k], motion.ddq[k])
        world = ne.pose(fixed)
        ground = {c: truth.contact_wrench[c][k] for c in contacts}
        if not any(np.isnan(g).any() for g in ground.values()):
            total = ne.required_wrench(frozenset(icub.links), world)
            np.testing.assert_allclose(sum(ground.values()), total, atol=1e-7)
            assert all(g[2] >= -1e-9 for g in ground.values()), "the floor only pushes"
        for s, ft in icub.sensors.items():
            _, child_side = icub.sensor_sides(s)
            frame = ne.sensor_frame(s)
            on_child = [c for c in contacts if c in child_side]
            if on_child and any(np.isnan(ground[c]).any() for c in on_child):
                continue  # single contact: checked in test_dynamics through expected_wrenches
            p_on_q = ne.required_wrench(child_side, frame)
            for c in on_child:
                p_on_q = p_on_q - wrench_transform(frame.inverse()) @ ground[c]
            expected = p_on_q if ft.direction == "parent_to_child" else -p_on_q
            np.testing.assert_allclose(truth.wrench[s][k], expected, atol=1e-7, err_msg=f"{s} {k}")


def wrench_X(h: np.ndarray) -> np.ndarray:
    """Wrench transform [[R, 0], [p^ R, R]] of a 4x4 pose, written out independently of the package."""
    rot, p = h[:3, :3], h[:3, 3]
    skew = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
    return np.block([[rot, np.zeros((3, 3))], [skew @ rot, rot]])
