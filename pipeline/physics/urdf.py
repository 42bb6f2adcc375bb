"""URDF parsing: links, joints and ``<sensor type="force_torque">`` tags into plain dataclasses.

Conventions (URDF and iDynTree): a joint's ``<origin>`` is the pose of the joint frame in the parent
link frame; a link's frame is the frame of the joint that has it as child. An FT sensor sits on a fixed
joint; its reading is expressed in the frame selected by ``<frame>`` (``sensor``: the child link frame
composed with the tag's ``<origin>``; ``child`` / ``parent``: that link's frame). Wrenches are ordered
``[force (N), moment (Nm)]``. :mod:`pipeline.physics.robot` builds the robot model from these parts.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

from pipeline.core.errors import RobotModelError

MOVABLE_TYPES = ("revolute", "continuous", "prismatic")


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
        return self.type in MOVABLE_TYPES


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


# --------------------------------------------------------------------------- reading
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


# Inertias are written with about six significant digits, and CAD exporters write point masses as tensors
# that are zero up to rounding (iCubGenova03's legs: eigenvalues down to -5e-20 kg m^2).
INERTIA_RTOL = 1e-6
MIN_LINK_SIZE_M = 0.01  # the least link size the rounding tolerance assumes (a link reduced to a point)


def checked_inertial(inertial: LinkInertial, size_m: float, where: str) -> LinkInertial:
    """`inertial` if physical, with rotational inertia zero or negative only by rounding clamped to the
    point mass it is; else RobotModelError naming `where` (the link) and what is wrong.

    The rounding tolerance is ``INERTIA_RTOL * max(m L^2, max |I_ij|)`` (kg m^2) with m the mass (kg) and
    L the link's size (m, at least ``MIN_LINK_SIZE_M``): the inertia a body of that mass and size could
    have, and the size of the printed values. A principal moment below 0 by at most this is set to 0
    (the tensor rebuilt from its eigen-decomposition: positive semidefinite, as Pinocchio requires of
    every diagonal entry); below it by more, or principal moments violating the triangle inequality
    (``I1 + I2 >= I3``) by more, or a negative mass, or a non-finite number, is refused.
    """
    mass, inertia = float(inertial.mass), np.asarray(inertial.inertia, float)
    if not (np.isfinite(mass) and np.all(np.isfinite(inertia)) and np.all(np.isfinite(inertial.com))):
        raise RobotModelError(f"{where}: <inertial> has a non-finite number")
    if mass < 0.0:
        raise RobotModelError(f"{where}: negative mass {mass:g} kg")
    inertia = 0.5 * (inertia + inertia.T)
    tol = INERTIA_RTOL * max(mass * max(size_m, MIN_LINK_SIZE_M) ** 2, float(np.abs(inertia).max()))
    moments, axes = np.linalg.eigh(inertia)
    if moments[0] < -tol:
        raise RobotModelError(
            f"{where}: inertia is not positive semidefinite: principal moments "
            f"{', '.join(f'{v:.3g}' for v in moments)} kg m^2 (rounding tolerance {tol:.2g})"
        )
    if moments[0] + moments[1] < moments[2] - tol:
        raise RobotModelError(
            f"{where}: inertia violates the triangle inequality: principal moments "
            f"{', '.join(f'{v:.3g}' for v in moments)} kg m^2, the two least sum below the largest"
        )
    if moments[0] >= 0.0 and np.all(np.diag(inertia) >= 0.0):
        return inertial
    clamped = (axes * np.maximum(moments, 0.0)) @ axes.T
    return LinkInertial(mass=mass, com=inertial.com, inertia=0.5 * (clamped + clamped.T))


def _link_sizes(joints: Iterable[URDFJoint], links: dict[str, LinkInertial | None]) -> dict[str, float]:
    """m: each link's size, the farthest from its frame's origin of its centre of mass and the origins
    of the joints it is the parent of."""
    sizes = {name: float(np.linalg.norm(i.com)) if i is not None else 0.0 for name, i in links.items()}
    for joint in joints:
        sizes[joint.parent] = max(sizes[joint.parent], float(np.linalg.norm(joint.origin.translation)))
    return sizes


@dataclass(frozen=True)
class URDFParts:
    """What :func:`parse_urdf_parts` reads: the robot name and its links, joints and FT sensors, each
    keyed by name in file order (links without ``<inertial>`` map to None)."""

    name: str
    links: dict[str, LinkInertial | None]
    joints: dict[str, URDFJoint]
    sensors: dict[str, FTSensor]


def _parse_joint(el: ET.Element, links: dict[str, LinkInertial | None], path: Path) -> URDFJoint:
    """One ``<joint>`` element; its links must exist in `links`."""
    name, jtype = el.get("name"), el.get("type")
    where = f"{path}: joint {name}"
    if jtype not in (*MOVABLE_TYPES, "fixed"):
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
    if jtype in MOVABLE_TYPES:
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
    joint = URDFJoint(
        name=name,
        type=jtype,
        parent=parent.get("link"),
        child=child.get("link"),
        origin=_origin(el.find("origin"), where),
        axis=axis,
        **lims,
    )
    for end in (joint.parent, joint.child):
        if end not in links:
            raise RobotModelError(f"{where}: refers to link {end!r}, which the URDF does not define")
    return joint


def _parse_sensor(el: ET.Element, joints: dict[str, URDFJoint], path: Path) -> FTSensor:
    """One top-level ``<sensor type="force_torque">`` element; it must sit on a fixed joint."""
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
    return FTSensor(name, joint_name, joint.parent, joint.child, frame, direction, child_T_sensor)


def parse_urdf_parts(path: Path) -> URDFParts:
    """Parse links, joints and top-level ``<sensor type="force_torque">`` elements of a URDF file.

    Raises RobotModelError (naming the file and element) for invalid XML, unsupported joint types,
    dangling link or joint references, links and joints that do not form one tree, or a link's
    non-physical inertial parameters (:func:`checked_inertial`, which also clamps rounding).
    """
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise RobotModelError(f"{path}: not valid XML ({exc})") from exc
    if root.tag != "robot":
        raise RobotModelError(f"{path}: root element is <{root.tag}>, expected <robot>")
    links = {
        link.get("name"): _inertial(link, f"{path}: link {link.get('name')}") for link in root.findall("link")
    }
    joints: dict[str, URDFJoint] = {}
    for el in root.findall("joint"):
        joints[el.get("name")] = _parse_joint(el, links, path)
    sensors: dict[str, FTSensor] = {}
    for el in root.findall("sensor"):  # top level only: <gazebo> copies are ignored
        if el.get("type") == "force_torque":
            sensors[el.get("name")] = _parse_sensor(el, joints, path)
    sizes = _link_sizes(joints.values(), links)
    links = {
        name: checked_inertial(i, sizes[name], f"{path}: link {name}") if i is not None else None
        for name, i in links.items()
    }
    children = [j.child for j in joints.values()]
    if len(set(children)) != len(children) or len([n for n in links if n not in set(children)]) != 1:
        raise RobotModelError(f"{path}: the links and joints do not form a tree with one root")
    return URDFParts(root.get("name", path.stem), links, joints, sensors)
