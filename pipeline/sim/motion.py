"""True robot motion for the four simulated experiment types (thesis 4.1).

Each generator returns a :class:`Motion`: smooth joint trajectories within the URDF position limits
(quintic splines through the solved postures, so velocities and accelerations are exact derivatives
of the positions), the contact set and fixed link of every sample, and, in double support, the fraction
of the load carried by the foot that is taking over (a smooth weight-transfer profile the labeller
cannot know).

World frame: for balancing and walking the ground is the plane z = 0 with z up; the soles are flat on
it. For the pole, the world frame is the root_link frame (z up). Nothing here is robot-specific: legs
are the movable joints between root_link and each sole, joints with light subtrees (fingers) are held
still, everything else moves freely, and the lengths of the motions are derived from the URDF
(:mod:`pipeline.sim.derive`) unless params override them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from pipeline.core.errors import RobotModelError
from pipeline.physics.robot import RobotModel
from pipeline.sim.derive import derive_motion, measure_geometry
from pipeline.sim.gait import plan_steps, sample_gait, walking_com
from pipeline.sim.kinematics import Foot, Kinematics, interp, multisine, pose, spline
from pipeline.sim.params import MotionParams

__all__ = ["Foot", "Motion", "MotionGenerator", "MotionParams"]

FeetTargets = Callable[[int], dict[str, pin.SE3]]  # sample index -> sole poses in the world


@dataclass
class Motion:
    """True motion of one log, sampled at the simulation rate.

    t: (N,) s. q, dq, ddq: (N, n_joints) rad, rad/s, rad/s^2 in ``robot.joint_names`` order.
    contact_sets: the distinct contact sets; contact_index: (N,) index into it per sample.
    fixed_links: per sample the link fixed in the world (a sole flat on the floor, or root_link).
    transfer: (N,) in double support the load fraction on `transfer_to[k]`'s foot, NaN elsewhere.
    transfer_to: (N,) the foot (pair name) taking over in double support, '' elsewhere.
    root_pose: (N, 4, 4) pose of root_link in the world, for plots and checks.
    pushes: link -> external wrench (N, 6) on it (a hand pushing), N and Nm in the sample's world frame
    about its origin; empty for none (:mod:`pipeline.sim.push`).
    """

    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    contact_sets: list[frozenset[str]]
    contact_index: np.ndarray
    fixed_links: np.ndarray
    transfer: np.ndarray
    transfer_to: np.ndarray
    root_pose: np.ndarray
    pushes: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.t.shape[0]


def _free_joint_motion(
    kin: Kinematics,
    rng: np.random.Generator,
    t: np.ndarray,
    joints: np.ndarray,
    amplitude: float,
    p: MotionParams,
    center: np.ndarray,
) -> np.ndarray:
    """(N, len(joints)) multi-sine trajectories around `center`, `amplitude` x joint range, in limits."""
    lo, hi = kin.lower[joints], kin.upper[joints]
    amp = np.minimum(amplitude * (hi - lo), (hi - lo) / 2)
    mid = np.clip(center[joints], lo + amp, hi - amp)
    return mid + amp * multisine(rng, t, len(joints), p.f_min_hz, p.f_max_hz)


def _coarse(n: int, rate: float, com_rate: float) -> np.ndarray:
    """Indices of the samples where the CoM correction is solved (and the last one)."""
    return np.unique(np.r_[np.arange(0, n, max(1, int(round(rate / com_rate)))), n - 1])


class MotionGenerator:
    """Builds the true motions of one robot.

    `params` fields left None are derived from the URDF; ``self.p`` holds the values used and
    ``self.geometry`` what they were derived from.
    """

    def __init__(self, robot: RobotModel, feet: Sequence[Foot], params: MotionParams) -> None:
        self.robot, self.feet = robot, {f.name: f for f in feet}
        self.kin = Kinematics(robot, params.limit_margin)
        self.geometry = measure_geometry(robot, self.kin, feet, params.still_mass_fraction)
        self.p = derive_motion(params, self.geometry)
        self.leg = {f.name: self.kin.chain(f.sole) for f in feet}
        legs = set(np.concatenate(list(self.leg.values())).tolist())
        still = {robot.joint_names.index(j) for j in self.geometry.still_joints} - legs
        n_joints = len(robot.joint_names)
        self.moving = np.array([j for j in range(n_joints) if j not in still], np.intp)
        self.upper_body = np.array([j for j in self.moving if j not in legs], np.intp)
        self.home = np.clip(np.zeros(n_joints), self.kin.lower, self.kin.upper)
        self.standing_height = -self.kin.frame_pose(self.home, feet[0].sole).translation[2]
        # The world's axes are the soles' (x forward, z up); the root's orientation in them at home is the
        # soles' in the root frame, transposed: the identity for iCub 3 and ergoCub, a half turn about z for
        # iCub 2.x (whose root_link x axis points backwards). Snapped to exact +-1 / 0 where it is one.
        turn = self.kin.frame_pose(self.home, feet[0].sole).rotation.T
        self.turn = pin.SE3(
            np.round(turn) if np.allclose(turn, np.round(turn), atol=1e-6) else turn, np.zeros(3)
        )
        # start every leg solve from slightly bent knees: a straight knee is a singular posture
        for chain in self.leg.values():
            end = self.robot.joints[self.robot.joint_names[chain[-1]]].child
            target = pose([0, 0, 0.05]) * self.kin.frame_pose(self.home, end)  # 5 cm up in the root frame
            try:
                bent = self.kin.ik(self.home, end, target, chain, position_only=True)
            except RobotModelError:  # a leg straight at zero (iCub 2.x) is singular: start a tenth of the
                start = self.home.copy()  # way to the middle of every leg joint's range
                start[chain] += 0.1 * (0.5 * (self.kin.lower + self.kin.upper) - self.home)[chain]
                bent = self.kin.ik(start, end, target, chain, position_only=True)
            self.home[chain] = bent[chain]

    # ------------------------------------------------------------------ helpers
    def _home_y(self, frame: str) -> float:
        """m: lateral position of `frame` at the home posture, along the world's y axis (to the left)."""
        return float((self.turn.rotation @ self.kin.frame_pose(self.home, frame).translation)[1])

    def _time(self, duration: float, rate: float) -> np.ndarray:
        return np.arange(int(round(duration * rate))) / rate

    def _finish(
        self,
        t: np.ndarray,
        q: np.ndarray,
        contacts: list[frozenset[str]],
        fixed: np.ndarray,
        root_pose: np.ndarray,
        transfer: np.ndarray | None = None,
        transfer_to: np.ndarray | None = None,
    ) -> Motion:
        q, dq, ddq = spline(t, q)
        bad = np.flatnonzero(((q < self.kin.lower - 1e-9) | (q > self.kin.upper + 1e-9)).any(axis=0))
        if len(bad):  # the spline overshoots between samples only if the motion is too fast for the rate
            raise RobotModelError(
                "simulated joints leave their limits: " + ", ".join(self.robot.joint_names[i] for i in bad)
            )
        sets = sorted(set(contacts), key=lambda s: sorted(s))
        index = {s: i for i, s in enumerate(sets)}
        n = t.shape[0]
        return Motion(
            t,
            q,
            dq,
            ddq,
            sets,
            np.array([index[c] for c in contacts]),
            fixed,
            transfer if transfer is not None else np.full(n, np.nan),
            transfer_to if transfer_to is not None else np.full(n, "", dtype=object),
            root_pose,
        )

    def _stance_posture(
        self,
        q: np.ndarray,
        world_T_root: pin.SE3,
        feet_world: dict[str, pin.SE3],
        free: frozenset[str] = frozenset(),
    ) -> np.ndarray:
        """Solve every leg whose sole pose in the world is given, for a given root pose. Feet named in
        `free` are in the air: they keep the orientation of the pelvis (always within ankle range)."""
        for name, world_T_sole in feet_world.items():
            if name in free:  # the pelvis's orientation (the root's without the turn to the world's axes)
                world_T_sole = pin.SE3(
                    (world_T_root * self.turn.inverse()).rotation, world_T_sole.translation
                )
            target = world_T_root.actInv(world_T_sole)
            q = self.kin.ik(q, self.feet[name].sole, target, self.leg[name])
        return q

    def _balance(
        self,
        q: np.ndarray,
        root_xy: np.ndarray,
        root_rpy: np.ndarray,
        feet_world: dict[str, pin.SE3],
        com_target: np.ndarray,
        iterations: int = 3,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Move the root horizontally until the CoM is over `com_target` (x, y), legs re-solved."""
        xy = root_xy.copy()
        for _ in range(iterations):
            world_T_root = pose([xy[0], xy[1], self.p.root_height_m], root_rpy) * self.turn
            q = self._stance_posture(q, world_T_root, feet_world)
            com = world_T_root.act(self.kin.com(q))
            xy = xy + (com_target - com[:2])
        return q, xy

    def _track(
        self,
        t: np.ndarray,
        q: np.ndarray,
        rate: float,
        sway: np.ndarray,
        coarse_feet: FeetTargets,
        feet: FeetTargets,
        com_target: np.ndarray,
        free: frozenset[str] = frozenset(),
        warm_start: bool = False,
    ) -> np.ndarray:
        """Fill the legs of `q` (N, n_joints; upper body given) and return the root poses (N, 4, 4).

        The root's horizontal position keeps the CoM over `com_target` ((N, 2) m, world), solved at
        ``com_rate_hz`` with the soles at ``coarse_feet(k)`` and splined in between; then the legs are
        solved at every sample for the soles at ``feet(k)`` (feet in `free` in the air). sway: (N, 3)
        root roll, pitch, yaw, rad. `warm_start` starts the per-sample solves from the last coarse one.
        """
        n = t.shape[0]
        coarse = _coarse(n, rate, self.p.com_rate_hz)
        coarse_xy, q_k, xy = [], self.home.copy(), np.zeros(2)
        for k in coarse:
            q_k[self.upper_body] = q[k, self.upper_body]
            q_k, xy = self._balance(q_k, xy, sway[k], coarse_feet(k), com_target[k])
            coarse_xy.append(xy)
        root_xy = interp(t[coarse], np.array(coarse_xy))(t)
        root_pose = np.zeros((n, 4, 4))
        q_prev = q_k if warm_start else self.home.copy()
        for k in range(n):
            q_prev = q_prev.copy()
            q_prev[self.upper_body] = q[k, self.upper_body]
            world_T_root = pose([root_xy[k, 0], root_xy[k, 1], self.p.root_height_m], sway[k]) * self.turn
            q_prev = self._stance_posture(q_prev, world_T_root, feet(k), free)
            q[k] = q_prev
            root_pose[k] = world_T_root.homogeneous
        return root_pose

    # ------------------------------------------------------------------ experiments
    def pole(self, rng: np.random.Generator, duration: float, rate: float) -> Motion:
        """Robot clamped on the pole by root_link; every joint swings (legs and arms too)."""
        t = self._time(duration, rate)
        q = np.tile(self.home, (t.shape[0], 1))
        q[:, self.moving] = _free_joint_motion(
            self.kin, rng, t, self.moving, self.p.pole_amplitude, self.p, self.home
        )
        root = self.robot.root_link
        fixed = np.full(t.shape[0], root, dtype=object)
        return self._finish(
            t, q, [frozenset({root})] * t.shape[0], fixed, np.tile(np.eye(4), (t.shape[0], 1, 1))
        )

    def poses(self, rng: np.random.Generator, duration: float, rate: float) -> Motion:
        """Robot clamped on the pole by root_link, held still in one pose after another (a lab re-zeroing
        its sensors): the joints that swing on the pole go to postures drawn from the pole's motion, each
        held `pose_hold_s`, the moves between them `pose_move_s` long (quintic smoothstep). Starts held."""
        t = self._time(duration, rate)
        free = _free_joint_motion(self.kin, rng, t, self.moving, self.p.pole_amplitude, self.p, self.home)
        period = self.p.pose_hold_s + self.p.pose_move_s
        k = np.floor(t / period).astype(np.intp)  # the pose each sample holds or leaves
        targets = free[rng.integers(0, len(t), int(k.max()) + 2)]  # postures of the pole's swing
        s = np.clip((t - k * period - self.p.pose_hold_s) / self.p.pose_move_s, 0.0, 1.0)
        s = s**3 * (10.0 - 15.0 * s + 6.0 * s**2)  # 0 while held, 0 -> 1 during the move
        q = np.tile(self.home, (t.shape[0], 1))
        q[:, self.moving] = targets[k] + s[:, None] * (targets[k + 1] - targets[k])
        root = self.robot.root_link
        fixed = np.full(t.shape[0], root, dtype=object)
        return self._finish(
            t, q, [frozenset({root})] * t.shape[0], fixed, np.tile(np.eye(4), (t.shape[0], 1, 1))
        )

    def _support(self, foot: Foot, part: str | None) -> tuple[frozenset[str], np.ndarray]:
        """Contact links and CoM target (x, y in the sole frame, m) of balancing on `foot` (or its part):
        the middle of the foot's two parts, or `com_margin_m` inside the outer edge of one part."""
        front, rear = foot.centers(self.robot)
        if part is None:
            return foot.links, np.round(0.5 * (front + rear)[:2], 3)
        if part not in ("front", "rear"):
            raise ValueError(f"part must be None, 'front' or 'rear', got {part!r}")
        link, center = (foot.front_link, front) if part == "front" else (foot.rear_link, rear)
        com_xy = center[:2].copy()
        com_xy[0] += -self.p.com_margin_m if part == "front" else self.p.com_margin_m
        return frozenset({link}), com_xy

    def balancing(
        self, rng: np.random.Generator, duration: float, rate: float, stance: str, part: str | None = None
    ) -> Motion:
        """Balancing on the `stance` foot (whole sole, or only its 'front' / 'rear' part when `part` is
        given): the other leg, the arms and the torso move, the CoM is kept over the supporting area."""
        p, foot = self.p, self.feet[stance]
        others = [f for f in self.feet.values() if f.name != stance]
        t = self._time(duration, rate)
        n = t.shape[0]
        contacts, com_xy = self._support(foot, part)

        # free joints: upper body multi-sines; free feet wander around a lifted pose
        q = np.tile(self.home, (n, 1))
        q[:, self.upper_body] = _free_joint_motion(
            self.kin, rng, t, self.upper_body, p.upper_body_amplitude, p, self.home
        )
        wander = p.swing_motion_m * multisine(rng, t, 3 * len(others), p.f_min_hz, p.f_max_hz)
        sway = 0.03 * multisine(rng, t, 3, p.f_min_hz, p.f_max_hz)
        side = np.sign(self._home_y(foot.sole))
        sway[:, 0] -= p.stance_lean_rad * side

        home_feet = {f.name: self.kin.frame_pose(self.home, f.sole) for f in self.feet.values()}
        stance_only = {stance: pin.SE3.Identity()}

        def feet_world(k: int) -> dict[str, pin.SE3]:
            out = dict(stance_only)
            for i, other in enumerate(others):
                rel = home_feet[foot.name].actInv(home_feet[other.name])  # other sole in stance sole frame
                offset = wander[k, 3 * i : 3 * i + 3] + [p.swing_forward_m, 0.0, p.swing_lift_m]
                out[other.name] = pose(rel.translation + offset)
            return out

        free = frozenset(f.name for f in others)
        com = np.tile(com_xy, (n, 1))
        root_pose = self._track(t, q, rate, sway, lambda k: stance_only, feet_world, com, free, True)
        fixed = np.full(n, foot.sole, dtype=object)
        return self._finish(t, q, [contacts] * n, fixed, root_pose)

    def walking(self, rng: np.random.Generator, duration: float, rate: float) -> Motion:
        """Walking straight, forward then backward: double support (weight transfer) and single support
        (stance sole fixed, swing foot lifting and landing). Starts and ends in double support."""
        if len(self.feet) != 2:
            raise RobotModelError("walking needs exactly two foot pairs")
        p = self.p
        # every walk its own gait: step length +-20 %, phase durations +-10 %
        step_length = p.step_length_m * rng.uniform(0.8, 1.2)
        single_s, double_s = (
            p.single_support_s * rng.uniform(0.9, 1.1),
            p.double_support_s * rng.uniform(0.9, 1.1),
        )
        t = self._time(duration, rate)
        n = t.shape[0]
        names = list(self.feet)
        # footholds in the world: feet side by side at the start, world origin between them
        y = {f: self._home_y(self.feet[f].sole) for f in names}
        phases = plan_steps(duration, names, y, step_length, single_s, double_s, p.steps_per_direction)
        gait = sample_gait(t, phases, self.feet, p.step_lift_m, rng.uniform(0.6, 1.6, len(phases)))
        com_target = walking_com(t, phases, y, p.root_height_m)

        q = np.tile(self.home, (n, 1))
        q[:, self.upper_body] = _free_joint_motion(
            self.kin, rng, t, self.upper_body, p.upper_body_amplitude / 2, p, self.home
        )
        sway = 0.02 * multisine(rng, t, 3, p.f_min_hz, p.f_max_hz)
        sway[:, 0] -= p.stance_lean_rad * com_target[:, 1] / (0.8 * max(abs(v) for v in y.values()))

        def feet_world(k: int) -> dict[str, pin.SE3]:
            return {f: pose([gait.feet_x[k, j], y[f], gait.feet_z[k, j]]) for j, f in enumerate(names)}

        root_pose = self._track(t, q, rate, sway, feet_world, feet_world, com_target)
        return self._finish(t, q, gait.contacts, gait.fixed, root_pose, gait.transfer, gait.transfer_to)

    def standing(self, rng: np.random.Generator, duration: float, rate: float) -> Motion:
        """Standing still on both feet (double support), the CoM between them, a faint sway of the pelvis
        (0.002 rad, as a balance controller leaves it); the load split follows the statics."""
        names = list(self.feet)
        t = self._time(duration, rate)
        n = t.shape[0]
        y = {f: self._home_y(self.feet[f].sole) for f in names}
        feet = {f: pose([0.0, y[f], 0.0]) for f in names}
        q = np.tile(self.home, (n, 1))
        sway = 0.002 * multisine(rng, t, 3, self.p.f_min_hz, self.p.f_max_hz)
        com = np.tile([0.0, float(np.mean(list(y.values())))], (n, 1))
        root_pose = self._track(t, q, rate, sway, lambda k: feet, lambda k: feet, com)
        contacts = frozenset().union(*(self.feet[f].links for f in names))
        fixed = np.full(n, self.feet[names[0]].sole, dtype=object)
        transfer = np.full(n, 0.5)
        transfer_to = np.full(n, names[-1], dtype=object)
        return self._finish(t, q, [contacts] * n, fixed, root_pose, transfer, transfer_to)
