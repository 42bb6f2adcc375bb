"""Robot model: the URDF, its 6-axis force/torque sensors, and Pinocchio models of it.

Conventions (they follow the URDF and iDynTree; docs/labels.md, "The physics: expected wrenches"):

- A link's frame is the frame of the joint that has it as child. A joint's `<origin>` is the pose
  of the joint frame in the parent link frame; a revolute joint then rotates about `<axis>`
  (expressed in the joint frame): ``child = parent * origin * Rot(axis, q)``.
- An FT sensor sits on a fixed joint. It cuts the tree into the parent side P (the side of the
  joint's parent link) and the child side Q. Its reading is expressed in the sensor frame, which for
  ``<frame>sensor</frame>`` is the child link frame composed with the sensor's ``<origin>``
  (``child`` / ``parent`` select the child / parent link frame), with the moment about its origin.
  ``child_to_parent``: the wrench that Q exerts on P; ``parent_to_child``: the wrench P exerts on Q.
- Wrenches and twists are ordered ``[linear (N or m/s), angular (Nm or rad/s)]``, as Pinocchio does.

Dynamics are computed on *contact-rooted* Pinocchio models: the kinematic tree re-rooted at a link
that is fixed in the world, with every FT sensor joint replaced by a 6-DoF joint held at identity.
The joint torque of that 6-DoF joint from RNEA is then the full wrench transmitted through the
sensor, exactly (see :mod:`pipeline.physics.dynamics`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np
import pinocchio as pin

from pipeline.core.errors import RobotModelError
from pipeline.physics.urdf import (
    FTSensor,
    LinkInertial,
    URDFJoint,
    parse_urdf_parts,
    resolve_urdf,
    rpy_to_matrix,
)

_UNIT_AXES = {(1.0, 0.0, 0.0): "X", (0.0, 1.0, 0.0): "Y", (0.0, 0.0, 1.0): "Z"}


# --------------------------------------------------------------------------- SE(3) helper
def wrench_transform(a_T_b: pin.SE3) -> np.ndarray:
    """The (6, 6) matrix mapping a wrench [f; tau] in frame b (moment about b's origin) to frame a.

    ``f_a = R f_b`` and ``tau_a = R tau_b + p x (R f_b)`` for ``a_T_b = (R, p)``.
    """
    return np.asarray(a_T_b.toDualActionMatrix())


# --------------------------------------------------------------------------- foot pairs
@dataclass(frozen=True)
class FootPair:
    """The front and rear FT sensors of one foot and the sole frame their sum is expressed in.

    sole_X_front / sole_X_rear: (6, 6) wrench transforms from each sensor frame to the sole frame
    (constant: the sensors and the sole are rigidly attached). foot_links: the links the two sensors
    cut off together (the foot parts).
    """

    name: str
    front: str
    rear: str
    sole: str
    sole_X_front: np.ndarray = field(repr=False)
    sole_X_rear: np.ndarray = field(repr=False)
    foot_links: frozenset[str] = field(repr=False)


@dataclass
class RootedModel:
    """A Pinocchio model of the robot re-rooted at `root` (a link fixed in the world).

    q_index / v_index / sign: for robot joint k (in ``RobotModel.joint_names`` order) the index in
    this model's configuration / velocity and the factor (+1 or -1) that maps the URDF joint value
    to this model's. sensor_v_index[s]: first of the 6 velocity indices of sensor s's 6-DoF joint;
    sensor_forward[s]: True if the root is on the parent side of s.
    """

    root: str
    model: pin.Model
    q_index: np.ndarray
    v_index: np.ndarray
    sign: np.ndarray
    sensor_v_index: dict[str, int]
    sensor_forward: dict[str, bool]
    link_joint: dict[str, int]
    link_placement: dict[str, pin.SE3]
    _pools: dict[tuple[float, float, float], pin.ModelPool] = field(default_factory=dict, repr=False)

    def neutral_batch(self, n: int) -> np.ndarray:
        """(n, nq) configurations with every joint at zero and every sensor joint at identity."""
        return np.tile(pin.neutral(self.model), (n, 1))

    def pool(self, gravity_root: np.ndarray, n_threads: int) -> pin.ModelPool:
        """A ModelPool whose models carry `gravity_root` (m/s^2, root frame), cached."""
        key = tuple(float(g) for g in gravity_root)
        pool = self._pools.get(key)
        if pool is None or pool.size() < n_threads:
            model = self.model.copy()
            model.gravity = pin.Motion(np.asarray(key), np.zeros(3))
            pool = pin.ModelPool(model, n_threads)
            self._pools[key] = pool
        return pool


# --------------------------------------------------------------------------- the robot
@dataclass
class RobotModel:
    """A URDF robot with its FT sensors. Build with :func:`load_robot`.

    joint_names: the movable joints, in URDF file order: the column order of every joint array.
    """

    urdf_path: Path
    name: str
    links: dict[str, LinkInertial | None]
    joints: dict[str, URDFJoint]
    sensors: dict[str, FTSensor]
    joint_names: list[str]
    _rooted: dict[str, RootedModel] = field(default_factory=dict, repr=False)

    # ----------------------------------------------------------------- tree structure
    @cached_property
    def root_link(self) -> str:
        children = {j.child for j in self.joints.values()}
        roots = [name for name in self.links if name not in children]
        return roots[0]

    @cached_property
    def _adjacency(self) -> dict[str, list[URDFJoint]]:
        adj: dict[str, list[URDFJoint]] = {name: [] for name in self.links}
        for joint in self.joints.values():
            adj[joint.parent].append(joint)
            adj[joint.child].append(joint)
        return adj

    @cached_property
    def _sensor_joints(self) -> dict[str, FTSensor]:
        return {s.joint: s for s in self.sensors.values()}

    def check_link(self, link: str, what: str = "link") -> str:
        """Return `link` if the URDF has it, else raise naming the links that exist."""
        if link not in self.links:
            raise RobotModelError(
                f"{self.urdf_path}: no {what} named {link!r}; links are: {', '.join(sorted(self.links))}"
            )
        return link

    def check_sensor(self, sensor: str) -> FTSensor:
        """Return the FT sensor named `sensor`, else raise naming the sensors that exist."""
        if sensor not in self.sensors:
            raise RobotModelError(
                f"{self.urdf_path}: no force_torque sensor named {sensor!r}; "
                f"sensors are: {', '.join(sorted(self.sensors))}"
            )
        return self.sensors[sensor]

    def subtree(self, link: str) -> frozenset[str]:
        """The links of the URDF subtree rooted at `link` (itself included)."""
        self.check_link(link)
        out, stack = set(), [link]
        children: dict[str, list[str]] = {}
        for joint in self.joints.values():
            children.setdefault(joint.parent, []).append(joint.child)
        while stack:
            current = stack.pop()
            out.add(current)
            stack.extend(children.get(current, []))
        return frozenset(out)

    def sensor_sides(self, sensor: str) -> tuple[frozenset[str], frozenset[str]]:
        """(parent side P, child side Q) of the cut made by `sensor`, as sets of link names."""
        ft = self.check_sensor(sensor)
        child_side = self.subtree(ft.child_link)
        return frozenset(self.links) - child_side, child_side

    def rigid_transform(self, a: str, b: str) -> pin.SE3:
        """Pose of link frame `b` in link frame `a` when they are connected by fixed joints only.

        Raises RobotModelError if a movable joint lies between them.
        """
        self.check_link(a)
        self.check_link(b)
        # breadth-first search over fixed joints only
        placement = {a: pin.SE3.Identity()}
        queue = deque([a])
        while queue:
            current = queue.popleft()
            if current == b:
                return placement[b]
            for joint in self._adjacency[current]:
                if joint.movable:
                    continue
                if joint.parent == current and joint.child not in placement:
                    placement[joint.child] = placement[current] * joint.origin
                    queue.append(joint.child)
                elif joint.child == current and joint.parent not in placement:
                    placement[joint.parent] = placement[current] * joint.origin.inverse()
                    queue.append(joint.parent)
        raise RobotModelError(
            f"{self.urdf_path}: links {a!r} and {b!r} are not rigidly attached (a movable joint lies between)"
        )

    def rigid_body_links(self, link: str) -> frozenset[str]:
        """All links rigidly attached to `link` (through fixed joints, FT sensor joints included)."""
        self.check_link(link)
        seen, stack = {link}, [link]
        while stack:
            current = stack.pop()
            for joint in self._adjacency[current]:
                if joint.movable:
                    continue
                other = joint.child if joint.parent == current else joint.parent
                if other not in seen:
                    seen.add(other)
                    stack.append(other)
        return frozenset(seen)

    def sensor_pose_in_link(self, sensor: str, link: str) -> pin.SE3:
        """Pose of `sensor`'s frame in the frame of `link` (rigidly attached to the sensor's child)."""
        ft = self.check_sensor(sensor)
        return self.rigid_transform(link, ft.child_link) * ft.child_T_sensor

    def total_mass(self) -> float:
        """Sum of all link masses, kg."""
        return float(sum(i.mass for i in self.links.values() if i is not None))

    def mass_of(self, links: Iterable[str]) -> float:
        """Sum of the masses of `links`, kg."""
        return float(sum(self.links[n].mass for n in links if self.links[n] is not None))

    # ----------------------------------------------------------------- foot pairs
    def foot_pair(self, name: str, front: str, rear: str, sole: str) -> FootPair:
        """Validate a foot pair and precompute its sensor -> sole wrench transforms."""
        ft_front, ft_rear = self.check_sensor(front), self.check_sensor(rear)
        self.check_link(sole, "sole link")
        if ft_front.direction != ft_rear.direction:
            raise RobotModelError(
                f"{self.urdf_path}: foot pair {name!r}: {front} and {rear} have different measure_direction"
            )
        q_front, q_rear = self.sensor_sides(front)[1], self.sensor_sides(rear)[1]
        if q_front & q_rear:
            raise RobotModelError(
                f"{self.urdf_path}: foot pair {name!r}: the child sides of {front} and {rear} overlap"
            )
        return FootPair(
            name=name,
            front=front,
            rear=rear,
            sole=sole,
            sole_X_front=wrench_transform(self.sensor_pose_in_link(front, sole)),
            sole_X_rear=wrench_transform(self.sensor_pose_in_link(rear, sole)),
            foot_links=q_front | q_rear,
        )

    # ----------------------------------------------------------------- Pinocchio models
    @cached_property
    def pinocchio_model(self) -> pin.Model:
        """Pinocchio's own URDF model (root_link as fixed base), for kinematics and cross-checks."""
        return pin.buildModelFromUrdf(str(self.urdf_path))

    def rooted(self, root: str) -> RootedModel:
        """The contact-rooted model for `root` (cached): see the module docstring."""
        self.check_link(root)
        if root not in self._rooted:
            self._rooted[root] = self._build_rooted(root)
        return self._rooted[root]

    def _build_rooted(self, root: str) -> RootedModel:
        model = pin.Model()
        model.name = f"{self.name}@{root}"
        link_joint = {root: 0}
        link_placement = {root: pin.SE3.Identity()}
        joint_entry: dict[str, tuple[int, float]] = {}  # urdf joint -> (pinocchio joint id, sign)
        sensor_jid: dict[str, int] = {}
        sensor_forward: dict[str, bool] = {}
        self._append_link(model, root, 0, pin.SE3.Identity())

        stack = [root]
        while stack:
            current = stack.pop()
            for joint in self._adjacency[current]:
                forward = joint.parent == current
                other = joint.child if forward else joint.parent
                if other in link_joint:
                    continue
                jid, here = link_joint[current], link_placement[current]
                sensor = self._sensor_joints.get(joint.name)
                if joint.movable or sensor is not None:
                    # the new joint frame is the URDF joint frame (= the child link frame)
                    placement = here * joint.origin if forward else here
                    if sensor is not None:
                        jmodel, sign = pin.JointModelFreeFlyer(), 1.0
                    else:
                        jmodel, sign = _joint_model(joint)
                    new_jid = model.addJoint(jid, jmodel, placement, f"{joint.name}")
                    if sensor is not None:
                        sensor_jid[sensor.name] = new_jid
                        sensor_forward[sensor.name] = forward
                    else:
                        joint_entry[joint.name] = (new_jid, sign if forward else -sign)
                    link_joint[other] = new_jid
                    # child = joint frame; parent = joint frame * origin^-1 (reversed traversal)
                    link_placement[other] = pin.SE3.Identity() if forward else joint.origin.inverse()
                else:
                    link_joint[other] = jid
                    link_placement[other] = here * joint.origin if forward else here * joint.origin.inverse()
                self._append_link(model, other, link_joint[other], link_placement[other])
                stack.append(other)

        for sensor in self.sensors.values():  # the frame each reading is expressed in
            child = sensor.child_link
            model.addFrame(
                pin.Frame(
                    sensor_frame_name(sensor.name),
                    link_joint[child],
                    0,
                    link_placement[child] * sensor.child_T_sensor,
                    pin.FrameType.OP_FRAME,
                )
            )
        q_index = np.array([model.idx_qs[joint_entry[n][0]] for n in self.joint_names], dtype=np.intp)
        v_index = np.array([model.idx_vs[joint_entry[n][0]] for n in self.joint_names], dtype=np.intp)
        sign = np.array([joint_entry[n][1] for n in self.joint_names])
        return RootedModel(
            root=root,
            model=model,
            q_index=q_index,
            v_index=v_index,
            sign=sign,
            sensor_v_index={s: model.idx_vs[j] for s, j in sensor_jid.items()},
            sensor_forward=sensor_forward,
            link_joint=link_joint,
            link_placement=link_placement,
        )

    def _append_link(self, model: pin.Model, link: str, jid: int, placement: pin.SE3) -> None:
        inertial = self.links[link]
        # a massless link's rotational inertia counts too (iCub 2.x torso_1), as in Pinocchio's parser
        if inertial is not None and (inertial.mass > 0.0 or np.any(inertial.inertia)):
            model.appendBodyToJoint(jid, inertial.to_pinocchio(), placement)
        model.addFrame(pin.Frame(link, jid, 0, placement, pin.FrameType.BODY))

    # ----------------------------------------------------------------- variants
    def with_inertials(self, overrides: Mapping[str, LinkInertial]) -> RobotModel:
        """A copy of this robot whose named links have other inertial parameters (e.g. a "true" robot
        with mass and COM errors). Unknown link names raise."""
        links = dict(self.links)
        for name, inertial in overrides.items():
            self.check_link(name)
            links[name] = inertial
        out = replace(self, links=links, _rooted={})
        out.__dict__.pop("pinocchio_model", None)
        return out


def sensor_frame_name(sensor: str) -> str:
    """Name of an FT sensor's measurement frame in the contact-rooted models (links may share the name)."""
    return f"ftsensor:{sensor}"


def _joint_model(joint: URDFJoint) -> tuple[pin.JointModel, float]:
    """Pinocchio joint model for a movable URDF joint and the sign mapping URDF q to it."""
    axis = np.asarray(joint.axis, float)
    revolute = joint.type in ("revolute", "continuous")
    for sign in (1.0, -1.0):
        key = tuple(float(v) for v in sign * axis)
        if key in _UNIT_AXES:
            letter = _UNIT_AXES[key]
            return getattr(pin, f"JointModel{'R' if revolute else 'P'}{letter}")(), sign
    if revolute:
        return pin.JointModelRevoluteUnaligned(axis), 1.0
    return pin.JointModelPrismaticUnaligned(axis), 1.0


# --------------------------------------------------------------------------- loading
def parse_urdf(path: Path) -> RobotModel:
    """Parse a URDF file into a RobotModel (see :func:`pipeline.physics.urdf.parse_urdf_parts`)."""
    parts = parse_urdf_parts(path)
    return RobotModel(
        urdf_path=path,
        name=parts.name,
        links=parts.links,
        joints=parts.joints,
        sensors=parts.sensors,
        joint_names=[j.name for j in parts.joints.values() if j.movable],
    )


def load_robot(urdf: str | Path) -> RobotModel:
    """Load a robot from a URDF path or an icub-models robot name (e.g. ``iCubGenova09``)."""
    path = resolve_urdf(urdf)
    robot = parse_urdf(path)
    if not robot.sensors:
        raise RobotModelError(f'{path}: the URDF declares no <sensor type="force_torque">')
    return robot


__all__ = [
    "FTSensor",
    "FootPair",
    "LinkInertial",
    "RobotModel",
    "RootedModel",
    "URDFJoint",
    "load_robot",
    "parse_urdf",
    "resolve_urdf",
    "rpy_to_matrix",
    "sensor_frame_name",
    "wrench_transform",
]
