"""True robot motion for the four simulated experiment types (thesis 4.1).

Each generator returns a :class:`Motion`: smooth joint trajectories within the URDF position limits
(quintic splines through the solved postures, so velocities and accelerations are exact derivatives
of the positions), the contact set and fixed link of every sample, and, in double support, the fraction
of the load carried by the foot that is taking over (a smooth weight-transfer profile the labeller
cannot know).

World frame: for balancing and walking the ground is the plane z = 0 with z up; the soles are flat on
it. For the pole, the world frame is the root_link frame (z up). Nothing here is iCub-specific: legs
are the movable joints between root_link and each sole, everything else moves freely.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from scipy.interpolate import make_interp_spline

from pipeline.core.errors import RobotModelError
from pipeline.physics.robot import RobotModel


@dataclass
class Motion:
    """True motion of one log, sampled at the simulation rate.

    t: (N,) s. q, dq, ddq: (N, n_joints) rad, rad/s, rad/s^2 in ``robot.joint_names`` order.
    contact_sets: the distinct contact sets; contact_index: (N,) index into it per sample.
    fixed_links: per sample the link fixed in the world (a sole flat on the floor, or root_link).
    transfer: (N,) in double support the load fraction on `transfer_to[k]`'s foot, NaN elsewhere.
    transfer_to: (N,) the foot (pair name) taking over in double support, '' elsewhere.
    root_pose: (N, 4, 4) pose of root_link in the world, for plots and checks.
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

    @property
    def n(self) -> int:
        return self.t.shape[0]


@dataclass(frozen=True)
class Foot:
    """A foot of the robot: its pair name, sole link, and the links touching the floor (front, rear)."""

    name: str
    sole: str
    front_link: str
    rear_link: str

    @property
    def links(self) -> frozenset[str]:
        return frozenset((self.front_link, self.rear_link))


def smoothstep(s: np.ndarray) -> np.ndarray:
    """0 -> 1 (degree 9) with zero derivatives up to the fourth at both ends: motions built from it are
    as smooth as the quintic-spline truth, so a polynomial smoother sees no kink at phase changes."""
    s = np.clip(s, 0.0, 1.0)
    return s**5 * (126 - 420 * s + 540 * s**2 - 315 * s**3 + 70 * s**4)


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
        lower = np.array([robot.joints[n].lower for n in robot.joint_names])
        upper = np.array([robot.joints[n].upper for n in robot.joint_names])
        lower = np.where(np.isfinite(lower), lower, -np.pi)
        upper = np.where(np.isfinite(upper), upper, np.pi)
        self.lower, self.upper = lower + limit_margin, upper - limit_margin

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
        out = pin.neutral(self.model)
        out[self.to_pin] = q
        return out

    def frame_pose(self, q: np.ndarray, frame: str) -> pin.SE3:
        """Pose of `frame` in the root_link frame for joint positions q (robot order)."""
        pin.framesForwardKinematics(self.model, self.data, self._pin_q(q))
        return self.data.oMf[self.model.getFrameId(frame)].copy()

    def com(self, q: np.ndarray) -> np.ndarray:
        """Centre of mass of the whole robot in the root_link frame, m (3,)."""
        pin.framesForwardKinematics(self.model, self.data, self._pin_q(q))
        total, moment = 0.0, np.zeros(3)
        for name, inertial in self.robot.links.items():
            if inertial is None or inertial.mass == 0.0:
                continue
            pose = self.data.oMf[self.model.getFrameId(name)]
            total += inertial.mass
            moment += inertial.mass * pose.act(inertial.com)
        return moment / total

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
        fid = self.model.getFrameId(frame)
        pin_idx = np.array(
            [self.model.idx_vs[self.model.getJointId(self.robot.joint_names[j])] for j in joints]
        )
        err = np.inf
        for _ in range(iters):
            pq = self._pin_q(q)
            pin.framesForwardKinematics(self.model, self.data, pq)
            current = self.data.oMf[fid]
            if position_only:
                err_vec = target.translation - current.translation
                jac = pin.computeFrameJacobian(self.model, self.data, pq, fid, pin.LOCAL_WORLD_ALIGNED)[
                    :3, pin_idx
                ]
            else:
                err_vec = pin.log6(current.actInv(target)).vector
                jac = pin.computeFrameJacobian(self.model, self.data, pq, fid, pin.LOCAL)[:, pin_idx]
            err = np.linalg.norm(err_vec)
            if err < tol:
                return q
            # Levenberg-Marquardt with a capped step: a straight knee is singular
            step = np.linalg.solve(jac.T @ jac + 1e-4 * np.eye(len(joints)), jac.T @ err_vec)
            step *= min(1.0, 0.3 / max(np.abs(step).max(), 1e-12))
            q[joints] = np.clip(q[joints] + step, self.lower[joints], self.upper[joints])
        if err > 1e-5:
            raise RobotModelError(
                f"inverse kinematics of {frame} did not converge (error {err:.2e}): "
                "target out of reach; reduce the motion amplitude in params"
            )
        return q


def _pose(xyz: Sequence[float], rpy: Sequence[float] = (0.0, 0.0, 0.0)) -> pin.SE3:
    return pin.SE3(pin.rpy.rpyToMatrix(*[float(a) for a in rpy]), np.asarray(xyz, float))


def _interp(t: np.ndarray, y: np.ndarray, k: int = 5):
    """Interpolating spline of order k (lower, odd, when there are too few points for k)."""
    while k > 1 and len(t) <= k:
        k -= 2
    return make_interp_spline(t, y, k=k, axis=0)


def _spline(t: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, velocities, accelerations of the quintic spline through the postures (C4: smooth
    accelerations, and no boundary condition forcing them at the ends)."""
    spline = _interp(t, q)
    return spline(t), spline(t, 1), spline(t, 2)


def _free_joint_motion(
    kin: Kinematics,
    rng: np.random.Generator,
    t: np.ndarray,
    joints: np.ndarray,
    amplitude: float,
    f_min: float,
    f_max: float,
    center: np.ndarray,
) -> np.ndarray:
    """(N, len(joints)) multi-sine trajectories around `center`, `amplitude` x joint range, in limits."""
    lo, hi = kin.lower[joints], kin.upper[joints]
    amp = np.minimum(amplitude * (hi - lo), (hi - lo) / 2)
    mid = np.clip(center[joints], lo + amp, hi - amp)
    return mid + amp * multisine(rng, t, len(joints), f_min, f_max)


@dataclass(frozen=True)
class MotionParams:
    """Shape of the simulated motions (section `simulate.motion`)."""

    limit_margin: float = 0.03  # rad (m for prismatic) kept free at both ends of every joint range
    f_min_hz: float = 0.05  # lowest frequency of the free joints' multi-sines
    f_max_hz: float = 0.5  # highest
    pole_amplitude: float = 0.35  # free-joint swing on the pole, fraction of the joint range
    upper_body_amplitude: float = 0.2  # arms, torso, head while balancing/walking, fraction of range
    root_height_m: float = 0.59  # root_link height above the sole while standing (legs bent)
    stance_lean_rad: float = 0.1  # pelvis roll towards the supporting foot (keeps the hips in range)
    swing_lift_m: float = 0.03  # balancing: how high the free foot is held, m
    swing_forward_m: float = 0.12  # balancing: how far forward the free foot is held, m
    swing_motion_m: float = 0.015  # balancing: free-foot wander, m
    step_length_m: float = 0.08  # walking: step length, m
    step_lift_m: float = 0.03  # walking: swing-foot clearance, m
    single_support_s: float = 0.8  # walking: single-support duration, s
    double_support_s: float = 0.4  # walking: double-support duration, s
    steps_per_direction: int = 8  # walking: steps forward, then as many backward
    com_rate_hz: float = 10.0  # rate of the centre-of-mass correction (spline in between)


class MotionGenerator:
    """Builds the true motions of one robot."""

    def __init__(self, robot: RobotModel, feet: Sequence[Foot], params: MotionParams) -> None:
        self.robot, self.feet, self.p = robot, {f.name: f for f in feet}, params
        self.kin = Kinematics(robot, params.limit_margin)
        self.leg = {f.name: self.kin.chain(f.sole) for f in feet}
        legs = np.concatenate(list(self.leg.values()))
        self.upper_body = np.array([j for j in range(len(robot.joint_names)) if j not in set(legs)], np.intp)
        self.home = np.clip(np.zeros(len(robot.joint_names)), self.kin.lower, self.kin.upper)
        self.standing_height = -self.kin.frame_pose(self.home, feet[0].sole).translation[2]
        # start every leg solve from slightly bent knees: a straight knee is a singular posture
        for chain in self.leg.values():
            bent = self.kin.ik(
                self.home,
                self.robot.joints[self.robot.joint_names[chain[-1]]].child,
                self.kin.frame_pose(self.home, self.robot.joints[self.robot.joint_names[chain[-1]]].child)
                * _pose([0, 0, 0.05]),
                chain,
                position_only=True,
            )
            self.home[chain] = bent[chain]

    # ------------------------------------------------------------------ helpers
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
        q, dq, ddq = _spline(t, q)
        if np.any(q < self.kin.lower - 1e-9) or np.any(q > self.kin.upper + 1e-9):
            bad = np.flatnonzero(((q < self.kin.lower - 1e-9) | (q > self.kin.upper + 1e-9)).any(axis=0))
            # the spline overshoots between samples only if the motion is too fast for the rate
            q = np.clip(q, self.kin.lower, self.kin.upper)
            if len(bad):
                raise RobotModelError(
                    "simulated joints leave their limits: "
                    + ", ".join(self.robot.joint_names[i] for i in bad)
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
            if name in free:
                world_T_sole = pin.SE3(world_T_root.rotation, world_T_sole.translation)
            target = world_T_root.actInv(world_T_sole)
            q = self.kin.ik(q, self.feet[name].sole, target, self.leg[name])
        return q

    def _balance(
        self,
        q: np.ndarray,
        root_xy: np.ndarray,
        root_z: float,
        root_rpy: np.ndarray,
        feet_world: dict[str, pin.SE3],
        com_target: np.ndarray,
        iterations: int = 3,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Move the root horizontally until the CoM is over `com_target` (x, y), legs re-solved."""
        xy = root_xy.copy()
        for _ in range(iterations):
            world_T_root = _pose([xy[0], xy[1], root_z], root_rpy)
            q = self._stance_posture(q, world_T_root, feet_world)
            com = world_T_root.act(self.kin.com(q))
            xy = xy + (com_target - com[:2])
        return q, xy

    # ------------------------------------------------------------------ experiments
    def pole(self, rng: np.random.Generator, duration: float, rate: float) -> Motion:
        """Robot clamped on the pole by root_link; every joint swings (legs and arms too)."""
        t = self._time(duration, rate)
        q = np.tile(self.home, (t.shape[0], 1))
        all_joints = np.arange(len(self.robot.joint_names))
        q[:, all_joints] = _free_joint_motion(
            self.kin, rng, t, all_joints, self.p.pole_amplitude, self.p.f_min_hz, self.p.f_max_hz, self.home
        )
        root = self.robot.root_link
        fixed = np.full(t.shape[0], root, dtype=object)
        return self._finish(
            t, q, [frozenset({root})] * t.shape[0], fixed, np.tile(np.eye(4), (t.shape[0], 1, 1))
        )

    def balancing(
        self, rng: np.random.Generator, duration: float, rate: float, stance: str, part: str | None = None
    ) -> Motion:
        """Balancing on the `stance` foot (whole sole, or only its 'front' / 'rear' part when `part` is
        given): the other leg, the arms and the torso move, the CoM is kept over the supporting area."""
        foot = self.feet[stance]
        others = [f for f in self.feet.values() if f.name != stance]
        t = self._time(duration, rate)
        n = t.shape[0]
        sole_T_front = self.robot.rigid_transform(foot.sole, foot.front_link).translation
        sole_T_rear = self.robot.rigid_transform(foot.sole, foot.rear_link).translation
        if part is None:
            contacts, com_xy = foot.links, np.zeros(2)
        elif part in ("front", "rear"):
            link = foot.front_link if part == "front" else foot.rear_link
            contacts = frozenset({link})
            com_xy = (sole_T_front if part == "front" else sole_T_rear)[:2].copy()
            com_xy[0] += -0.01 if part == "front" else 0.01  # inside the edge of the supporting part
        else:
            raise ValueError(f"part must be None, 'front' or 'rear', got {part!r}")

        # free joints: upper body multi-sines; free feet wander around a lifted pose
        q = np.tile(self.home, (n, 1))
        q[:, self.upper_body] = _free_joint_motion(
            self.kin,
            rng,
            t,
            self.upper_body,
            self.p.upper_body_amplitude,
            self.p.f_min_hz,
            self.p.f_max_hz,
            self.home,
        )
        wander = self.p.swing_motion_m * multisine(rng, t, 3 * len(others), self.p.f_min_hz, self.p.f_max_hz)
        sway = 0.03 * multisine(rng, t, 3, self.p.f_min_hz, self.p.f_max_hz)
        side = np.sign(self.kin.frame_pose(self.home, foot.sole).translation[1])
        sway[:, 0] -= self.p.stance_lean_rad * side

        # root and free-foot targets, then the CoM correction at a coarse rate, then legs at full rate
        coarse = np.unique(np.r_[np.arange(0, n, max(1, int(round(rate / self.p.com_rate_hz)))), n - 1])
        root_xy = np.zeros((n, 2))
        q_k, xy = self.home.copy(), np.zeros(2)
        home_feet = {f.name: self.kin.frame_pose(self.home, f.sole) for f in self.feet.values()}
        world_T_stance_home = pin.SE3.Identity()

        def free_feet(k: int) -> dict[str, pin.SE3]:
            out = {}
            for i, other in enumerate(others):
                rel = home_feet[foot.name].actInv(home_feet[other.name])  # other sole in stance sole frame
                offset = wander[k, 3 * i : 3 * i + 3] + [self.p.swing_forward_m, 0.0, self.p.swing_lift_m]
                out[other.name] = _pose(rel.translation + offset)
            return out

        coarse_xy = []
        for k in coarse:
            q_k[self.upper_body] = q[k, self.upper_body]
            q_k, xy = self._balance(
                q_k, xy, self.p.root_height_m, sway[k], {stance: world_T_stance_home}, com_xy
            )
            coarse_xy.append(xy)
        root_xy = _interp(t[coarse], np.array(coarse_xy))(t)

        root_pose = np.zeros((n, 4, 4))
        q_prev = q_k
        for k in range(n):
            q_prev = q_prev.copy()
            q_prev[self.upper_body] = q[k, self.upper_body]
            world_T_root = _pose([root_xy[k, 0], root_xy[k, 1], self.p.root_height_m], sway[k])
            feet_world = {stance: world_T_stance_home, **free_feet(k)}
            q_prev = self._stance_posture(q_prev, world_T_root, feet_world, frozenset(f.name for f in others))
            q[k] = q_prev
            root_pose[k] = world_T_root.homogeneous
        fixed = np.full(n, foot.sole, dtype=object)
        return self._finish(t, q, [contacts] * n, fixed, root_pose)

    def _walking_com(self, t: np.ndarray, phases: list, y: dict[str, float]) -> np.ndarray:
        """(N, 2) CoM path of a dynamically feasible walk (linear inverted pendulum): a sideways sway
        phase-locked to the steps, over the stance foot at mid single support, with an amplitude whose
        ZMP (= c - z/g c'') stays on the feet; forward, a spline through the stance feet at mid stance."""
        singles = [(0.5 * (a + b), foot) for a, b, kind, foot, *_ in phases if kind == "ss"]
        step_period = phases[1][1] - phases[1][0] + phases[2][1] - phases[2][0]
        omega2 = (np.pi / step_period) ** 2
        zmp_gain = 1.0 + self.p.root_height_m * omega2 / 9.81  # ZMP amplitude / CoM amplitude
        half_width = min(abs(v) for v in y.values())
        amplitude = 0.6 * half_width / zmp_gain
        t_first, first_foot = singles[0]
        side = np.sign(y[first_foot])
        lateral = side * amplitude * np.cos(np.pi * (t - t_first) / step_period)
        lateral *= smoothstep(t / t_first)  # start from standing still
        knots_t = np.r_[0.0, [m for m, _ in singles]]
        knots_x = np.r_[0.0, [x for x in self._stance_x(phases)]]
        forward = _interp(knots_t, knots_x)(np.clip(t, 0, knots_t[-1]))
        return np.stack([forward, lateral], axis=1)

    @staticmethod
    def _stance_x(phases: list) -> list[float]:
        """Stance-foot x at each single support, replaying the footsteps."""
        x: dict[str, float] = {}
        out = []
        for _, _, kind, foot, swing, _x_from, x_to in phases:
            if kind == "ss":
                out.append(x.get(foot, 0.0))
                x[swing] = x_to
        return out

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
        home = {f: self.kin.frame_pose(self.home, self.feet[f].sole) for f in names}
        # footholds in the world: feet side by side at the start, world origin between them
        y = {f: home[f].translation[1] for f in names}
        first = min(names, key=lambda f: y[f])  # start swinging the right (lowest y) foot
        second = next(f for f in names if f != first)
        x = {f: 0.0 for f in names}

        # phase timeline: (start, end, kind, stance/new-stance foot, swing foot, x_from, x_to)
        phases = []
        t0 = 1.0
        phases.append((0.0, t0, "ds", second, None, 0.0, 0.0))
        swing, stance, step, direction = first, second, 0, 1.0
        while t0 < duration:
            target = x[stance] + direction * step_length
            if step == 0 or step == p.steps_per_direction:
                target = x[stance] + direction * step_length / 2  # half steps to start and stop
            phases.append((t0, t0 + single_s, "ss", stance, swing, x[swing], target))
            x[swing] = target
            t0 += single_s
            phases.append((t0, t0 + double_s, "ds", swing, stance, 0.0, 0.0))
            t0 += double_s
            swing, stance = stance, swing
            step += 1
            if step == p.steps_per_direction + 1:
                if abs(x[swing] - x[stance]) < 1e-9:
                    direction, step = -direction, 0
                else:  # bring the feet side by side before turning back
                    step = p.steps_per_direction
        # per-sample: contacts, fixed sole, transfer, feet and CoM targets
        contacts: list[frozenset[str]] = []
        fixed = np.empty(n, dtype=object)
        transfer = np.full(n, np.nan)
        transfer_to = np.full(n, "", dtype=object)
        feet_x = np.zeros((n, 2))
        feet_z = np.zeros((n, 2))
        com_target = np.zeros((n, 2))
        skews = rng.uniform(0.6, 1.6, len(phases))
        x_now = {f: 0.0 for f in names}
        k = 0
        for i, (start, end, kind, foot, swing_foot, x_from, x_to) in enumerate(phases):
            while k < n and t[k] < end:
                s = (t[k] - start) / (end - start)
                if kind == "ss":
                    contacts.append(self.feet[foot].links)
                    fixed[k] = self.feet[foot].sole
                    x_now[swing_foot] = x_from + (x_to - x_from) * smoothstep(np.array(s))
                    z = p.step_lift_m * 1024 * (s * (1 - s)) ** 5  # still at both ends up to the snap
                    feet_z[k, names.index(swing_foot)] = z
                else:
                    contacts.append(self.feet[names[0]].links | self.feet[names[1]].links)
                    other = next(f for f in names if f != foot)
                    fixed[k] = self.feet[other].sole if i > 0 else self.feet[foot].sole
                    alpha = float(smoothstep(np.array(s ** skews[i])))
                    transfer[k], transfer_to[k] = alpha, foot
                for j, f in enumerate(names):
                    feet_x[k, j] = x_now[f]
                k += 1
            if k >= n:
                break

        com_target = self._walking_com(t, phases, y)
        q = np.tile(self.home, (n, 1))
        q[:, self.upper_body] = _free_joint_motion(
            self.kin, rng, t, self.upper_body, p.upper_body_amplitude / 2, p.f_min_hz, p.f_max_hz, self.home
        )
        sway = 0.02 * multisine(rng, t, 3, p.f_min_hz, p.f_max_hz)
        sway[:, 0] -= p.stance_lean_rad * com_target[:, 1] / (0.8 * max(abs(v) for v in y.values()))

        def feet_world(k: int) -> dict[str, pin.SE3]:
            return {f: _pose([feet_x[k, j], y[f], feet_z[k, j]]) for j, f in enumerate(names)}

        coarse = np.unique(np.r_[np.arange(0, n, max(1, int(round(rate / p.com_rate_hz)))), n - 1])
        coarse_xy, q_k, xy = [], self.home.copy(), np.zeros(2)
        for k in coarse:
            q_k[self.upper_body] = q[k, self.upper_body]
            q_k, xy = self._balance(q_k, xy, p.root_height_m, sway[k], feet_world(k), com_target[k])
            coarse_xy.append(xy)
        root_xy = _interp(t[coarse], np.array(coarse_xy))(t)
        root_pose = np.zeros((n, 4, 4))
        q_prev = self.home.copy()
        for k in range(n):
            q_prev = q_prev.copy()
            q_prev[self.upper_body] = q[k, self.upper_body]
            world_T_root = _pose([root_xy[k, 0], root_xy[k, 1], p.root_height_m], sway[k])
            q_prev = self._stance_posture(q_prev, world_T_root, feet_world(k))
            q[k] = q_prev
            root_pose[k] = world_T_root.homogeneous
        return self._finish(t, q, contacts, fixed, root_pose, transfer, transfer_to)
