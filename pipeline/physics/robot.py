"""Robot model: the URDF, its 6-axis force/torque sensors, and Pinocchio models of it.

Conventions (they follow the URDF and iDynTree, see ARCHITECTURE.md "Physics"):

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

import xml.etree.ElementTree as ET
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np
import pinocchio as pin

from pipeline.core.errors import RobotModelError

_MOVABLE_TYPES = ("revolute", "continuous", "prismatic")
_UNIT_AXES = {(1.0, 0.0, 0.0): "X", (0.0, 1.0, 0.0): "Y", (0.0, 0.0, 1.0): "Z"}


# --------------------------------------------------------------------------- small SE(3) helpers
def rpy_to_matrix(rpy: Iterable[float]) -> np.ndarray:
    """URDF roll-pitch-yaw (rad, fixed axes X then Y then Z) -> rotation matrix (3, 3)."""
    r, p, y = (float(v) for v in rpy)
    return pin.rpy.rpyToMatrix(r, p, y)


def wrench_transform(a_T_b: pin.SE3) -> np.ndarray:
    """The (6, 6) matrix mapping a wrench [f; tau] in frame b (moment about b's origin) to frame a.

    ``f_a = R f_b`` and ``tau_a = R tau_b + p x (R f_b)`` for ``a_T_b = (R, p)``.
    """
    return np.asarray(a_T_b.toDualActionMatrix())


# --------------------------------------------------------------------------- URDF elements
@dataclass(frozen=True)
class LinkInertial:
    """Inertial parameters of one link, in the link frame.

    mass: kg. com: (3,) centre of mass in the link frame, m. inertia: (3, 3) rotational inertia about
    the centre of mass, axes of the link frame, kg m^2.
    """

    mass: float
    com: np.ndarray
    inertia: np.ndarray

    def to_pinocchio(self) -> pin.Inertia:
        return pin.Inertia(self.mass, np.asarray(self.com, float), np.asarray(self.inertia, float))


@dataclass(frozen=True)
class URDFJoint:
    """One URDF joint. origin: pose of the joint frame in the parent link frame. axis: (3,) unit,
    in the joint frame. Limits in rad (or m), rad/s, Nm; +-inf when the URDF gives none."""

    name: str
    type: str
    parent: str
    child: str
    origin: pin.SE3
    axis: np.ndarray
    lower: float = -np.inf
    upper: float = np.inf
    velocity: float = np.inf
    effort: float = np.inf

    @property
    def movable(self) -> bool:
        return self.type in _MOVABLE_TYPES


@dataclass(frozen=True)
class FTSensor:
    """A 6-axis force/torque sensor as declared by ``<sensor type="force_torque">``.

    joint: the fixed joint it sits on; parent_link / child_link: that joint's links.
    frame: 'sensor', 'child' or 'parent' (URDF ``<frame>``). direction: 'child_to_parent' or
    'parent_to_child'. child_T_sensor: pose of the frame its reading is expressed in, relative to the
    child link frame.
    """

    name: str
    joint: str
    parent_link: str
    child_link: str
    frame: str
    direction: str
    child_T_sensor: pin.SE3 = field(repr=False)


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
        if inertial is not None and inertial.mass > 0.0:
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
def resolve_urdf(urdf: str | Path) -> Path:
    """A URDF path, or the name of a robot shipped by the `icub-models` package -> URDF path."""
    path = Path(urdf).expanduser()
    if path.is_file():
        return path.resolve()
    import icub_models

    names = sorted(icub_models.get_robot_names())
    if str(urdf) in names:
        return Path(icub_models.get_model_file(str(urdf)))
    if path.suffix == ".urdf" or "/" in str(urdf):
        raise RobotModelError(f"URDF file {path} does not exist")
    raise RobotModelError(
        f"robot {urdf!r} is neither a URDF file nor an icub-models robot; icub-models has: {', '.join(names)}"
    )


def _floats(text: str | None, n: int, default: float, where: str) -> np.ndarray:
    if text is None:
        return np.full(n, default)
    try:
        values = np.array([float(v) for v in text.split()])
    except ValueError as exc:
        raise RobotModelError(f"{where}: cannot read numbers from {text!r}") from exc
    if values.shape != (n,):
        raise RobotModelError(f"{where}: expected {n} numbers, got {text!r}")
    return values


def _origin(element: ET.Element | None, where: str) -> pin.SE3:
    if element is None:
        return pin.SE3.Identity()
    xyz = _floats(element.get("xyz"), 3, 0.0, where)
    rpy = _floats(element.get("rpy"), 3, 0.0, where)
    return pin.SE3(rpy_to_matrix(rpy), xyz)


def _inertial(link: ET.Element, where: str) -> LinkInertial | None:
    element = link.find("inertial")
    if element is None:
        return None
    mass_el = element.find("mass")
    mass = float(mass_el.get("value", "0")) if mass_el is not None else 0.0
    origin = _origin(element.find("origin"), where)
    i = element.find("inertia")
    names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    ixx, ixy, ixz, iyy, iyz, izz = (float(i.get(k, "0")) if i is not None else 0.0 for k in names)
    inertia_com = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    rot = origin.rotation
    return LinkInertial(mass=mass, com=origin.translation.copy(), inertia=rot @ inertia_com @ rot.T)


def parse_urdf(path: Path) -> RobotModel:
    """Parse links, joints and top-level ``<sensor type="force_torque">`` elements of a URDF."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise RobotModelError(f"{path}: not valid XML ({exc})") from exc
    if root.tag != "robot":
        raise RobotModelError(f"{path}: root element is <{root.tag}>, expected <robot>")

    links = {}
    for link in root.findall("link"):
        links[link.get("name")] = _inertial(link, f"{path}: link {link.get('name')}")

    joints: dict[str, URDFJoint] = {}
    for el in root.findall("joint"):
        name, jtype = el.get("name"), el.get("type")
        where = f"{path}: joint {name}"
        if jtype not in (*_MOVABLE_TYPES, "fixed"):
            raise RobotModelError(
                f"{where}: joint type {jtype!r} is not supported (revolute, continuous, prismatic or fixed)"
            )
        parent, child = el.find("parent"), el.find("child")
        if parent is None or child is None:
            raise RobotModelError(f"{where}: missing <parent> or <child>")
        axis_el = el.find("axis")
        axis = _floats(axis_el.get("xyz") if axis_el is not None else None, 3, 0.0, where)
        if axis_el is None:
            axis = np.array([1.0, 0.0, 0.0])
        if jtype in _MOVABLE_TYPES:
            norm = np.linalg.norm(axis)
            if norm == 0.0:
                raise RobotModelError(f"{where}: zero <axis>")
            axis = axis / norm
        limit = el.find("limit")
        lims = {}
        if limit is not None and jtype != "continuous":
            for key in ("lower", "upper", "velocity", "effort"):
                if limit.get(key) is not None:
                    lims[key] = float(limit.get(key))
        joints[name] = URDFJoint(
            name=name,
            type=jtype,
            parent=parent.get("link"),
            child=child.get("link"),
            origin=_origin(el.find("origin"), where),
            axis=axis,
            **lims,
        )
        for end in (joints[name].parent, joints[name].child):
            if end not in links:
                raise RobotModelError(f"{where}: refers to link {end!r}, which the URDF does not define")

    sensors: dict[str, FTSensor] = {}
    for el in root.findall("sensor"):  # top level only: <gazebo> copies are ignored
        if el.get("type") != "force_torque":
            continue
        name = el.get("name")
        where = f"{path}: sensor {name}"
        parent = el.find("parent")
        joint_name = parent.get("joint") if parent is not None else None
        if joint_name not in joints:
            raise RobotModelError(f"{where}: parent joint {joint_name!r} does not exist")
        joint = joints[joint_name]
        if joint.type != "fixed":
            raise RobotModelError(f"{where}: its joint {joint_name} is {joint.type}, expected fixed")
        frame = (el.findtext("force_torque/frame") or "child").strip()
        direction = (el.findtext("force_torque/measure_direction") or "child_to_parent").strip()
        if frame not in ("sensor", "child", "parent"):
            raise RobotModelError(f"{where}: <frame> must be sensor, child or parent, got {frame!r}")
        if direction not in ("child_to_parent", "parent_to_child"):
            raise RobotModelError(
                f"{where}: <measure_direction> must be child_to_parent or parent_to_child, got {direction!r}"
            )
        if frame == "sensor":
            child_T_sensor = _origin(el.find("origin"), where)
        elif frame == "child":
            child_T_sensor = pin.SE3.Identity()
        else:
            child_T_sensor = joint.origin.inverse()
        sensors[name] = FTSensor(
            name, joint_name, joint.parent, joint.child, frame, direction, child_T_sensor
        )

    model = RobotModel(
        urdf_path=path,
        name=root.get("name", path.stem),
        links=links,
        joints=joints,
        sensors=sensors,
        joint_names=[j.name for j in joints.values() if j.movable],
    )
    children = [j.child for j in joints.values()]
    if len(set(children)) != len(children) or len([n for n in links if n not in set(children)]) != 1:
        raise RobotModelError(f"{path}: the links and joints do not form a tree with one root")
    return model


def load_robot(urdf: str | Path) -> RobotModel:
    """Load a robot from a URDF path or an icub-models robot name (e.g. ``iCubGenova09``)."""
    path = resolve_urdf(urdf)
    robot = parse_urdf(path)
    if not robot.sensors:
        raise RobotModelError(f'{path}: the URDF declares no <sensor type="force_torque">')
    return robot
