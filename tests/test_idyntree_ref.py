"""Independent checks of the iDynTree FT reference (``tests/idyntree_ref.py``).

The expected values are computed here from first principles, without iDynTree:
URDF parsing with ``xml.etree`` (tree, masses, COMs, inertias, sensor tags) and link poses / velocities /
accelerations from Pinocchio (fixed base on ``root_link``).  The wrench through a sensor whose child side
touches nothing is the sum over the child-side links of their rate of change of momentum minus gravity.

Verified conventions (see also the module docstring of ``idyntree_ref``):
* reading = ``[f, tau]`` in the sensor frame (child link frame composed with the ``<sensor>`` origin),
  moment about the sensor origin;
* ``child_to_parent`` = wrench exerted by the child side on the parent side (hanging leg: world force
  ``(0, 0, -m g)``); ``parent_to_child`` = the opposite (foot part: ``(0, 0, +m g)``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import icub_models
import numpy as np
import pinocchio as pin
import pytest

from tests.idyntree_ref import IDynTreeFT, joint_limits, movable_joints, random_in_limits

G = 9.80665
ICUB3 = Path(icub_models.get_model_file("iCubGenova09"))
ERGOCUB = Path(__file__).resolve().parent / "robots" / "ergoCubSN001" / "model.urdf"
FT8 = {
    "l_arm_ft", "r_arm_ft", "l_leg_ft", "r_leg_ft",
    "l_foot_front_ft", "l_foot_rear_ft", "r_foot_front_ft", "r_foot_rear_ft",
}  # fmt: skip
ROBOTS = [ICUB3, ERGOCUB]


# --------------------------------------------------------------------------- independent URDF model
def _origin(elem: ET.Element | None) -> pin.SE3:
    if elem is None:
        return pin.SE3.Identity()
    xyz = np.array([float(v) for v in elem.get("xyz", "0 0 0").split()])
    rpy = np.array([float(v) for v in elem.get("rpy", "0 0 0").split()])
    return pin.SE3(pin.rpy.rpyToMatrix(rpy), xyz)


@dataclass
class Inertial:
    mass: float
    com: pin.SE3  # link_H_com (inertia axes)
    inertia: np.ndarray  # 3x3 about the COM in the com axes


@dataclass
class FTTag:
    name: str
    joint: str
    child_link: str
    direction: str  # child_to_parent | parent_to_child
    origin: pin.SE3  # child_link_H_sensor


class Urdf:
    """Minimal URDF reader: tree, inertials, FT sensor tags."""

    def __init__(self, path: Path) -> None:
        root = ET.parse(path).getroot()
        self.children: dict[str, list[str]] = {}
        self.joint_child: dict[str, str] = {}
        for j in root.findall("joint"):
            parent = j.find("parent").get("link")
            child = j.find("child").get("link")
            self.children.setdefault(parent, []).append(child)
            self.joint_child[j.get("name")] = child
        self.inertials: dict[str, Inertial] = {}
        for link in root.findall("link"):
            inertial = link.find("inertial")
            if inertial is None:
                continue
            i = inertial.find("inertia")
            ixx, ixy, ixz, iyy, iyz, izz = (
                float(i.get(k)) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
            )
            self.inertials[link.get("name")] = Inertial(
                mass=float(inertial.find("mass").get("value")),
                com=_origin(inertial.find("origin")),
                inertia=np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]]),
            )
        self.ft: dict[str, FTTag] = {}
        for s in root.findall("sensor"):  # top-level tags only (not the <gazebo> copies)
            if s.get("type") != "force_torque":
                continue
            joint = s.find("parent").get("joint")
            self.ft[s.get("name")] = FTTag(
                name=s.get("name"),
                joint=joint,
                child_link=self.joint_child[joint],
                direction=s.find("force_torque").find("measure_direction").text.strip(),
                origin=_origin(s.find("origin")),
            )

    def subtree(self, link: str) -> Iterator[str]:
        yield link
        for child in self.children.get(link, []):
            yield from self.subtree(child)

    def mass(self, links: list[str]) -> float:
        return sum(self.inertials[k].mass for k in links if k in self.inertials)


class PinKin:
    """Fixed-base (root_link) kinematics with Pinocchio; per-link COM frames added for momentum rates."""

    def __init__(self, path: Path, urdf: Urdf) -> None:
        self.model = pin.buildModelFromUrdf(str(path))
        self.com_frame: dict[str, int] = {}
        for link, inertial in urdf.inertials.items():
            body = self.model.frames[self.model.getFrameId(link, pin.FrameType.BODY)]
            frame = pin.Frame(
                f"{link}__com", body.parentJoint, body.placement * inertial.com, pin.FrameType.OP_FRAME
            )
            self.com_frame[link] = self.model.addFrame(frame)
        self.data = self.model.createData()

    def set_state(self, names: list[str], q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> None:
        qp, vp, ap = pin.neutral(self.model), np.zeros(self.model.nv), np.zeros(self.model.nv)
        for k, name in enumerate(names):
            joint = self.model.joints[self.model.getJointId(name)]
            qp[joint.idx_q], vp[joint.idx_v], ap[joint.idx_v] = q[k], dq[k], ddq[k]
        pin.forwardKinematics(self.model, self.data, qp, vp, ap)
        pin.updateFramePlacements(self.model, self.data)

    def link_pose(self, link: str) -> pin.SE3:
        return self.data.oMf[self.model.getFrameId(link, pin.FrameType.BODY)]

    def frame_pose(self, name: str) -> pin.SE3:
        return self.data.oMf[self.model.getFrameId(name)]


def free_side_wrench(
    urdf: Urdf, kin: PinKin, links: list[str], point: np.ndarray, g_world: np.ndarray
) -> np.ndarray:
    """Wrench [f, tau about point] (world axes) that the rest exerts ON ``links`` (which touch nothing else).

    Newton-Euler per link: f = m (a_c - g), tau = (c - p) x m (a_c - g) + I alpha + omega x I omega.
    """
    lwa = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    f, tau = np.zeros(3), np.zeros(3)
    for link in links:
        if link not in urdf.inertials:
            continue
        inertial, fid = urdf.inertials[link], kin.com_frame[link]
        pose = kin.data.oMf[fid]
        a_c = pin.getFrameClassicalAcceleration(kin.model, kin.data, fid, lwa).linear
        omega = pin.getFrameVelocity(kin.model, kin.data, fid, lwa).angular
        alpha = pin.getFrameAcceleration(kin.model, kin.data, fid, lwa).angular
        inertia_w = pose.rotation @ inertial.inertia @ pose.rotation.T
        fi = inertial.mass * (a_c - g_world)
        f += fi
        tau += np.cross(pose.translation - point, fi) + inertia_w @ alpha + np.cross(omega, inertia_w @ omega)
    return np.concatenate([f, tau])


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module", params=ROBOTS, ids=lambda p: p.parent.name)
def ref_robot(request: pytest.FixtureRequest) -> tuple[Path, Urdf, PinKin, IDynTreeFT]:
    path: Path = request.param
    urdf = Urdf(path)
    return path, urdf, PinKin(path, urdf), IDynTreeFT(path, movable_joints(path))


def _sensor_pose(urdf: Urdf, kin: PinKin, sensor: str) -> pin.SE3:
    tag = urdf.ft[sensor]
    return kin.link_pose(tag.child_link) * tag.origin


# --------------------------------------------------------------------------- tests
def test_all_ft_sensors_survive(ref_robot: tuple[Path, Urdf, PinKin, IDynTreeFT]) -> None:
    path, urdf, _, ref = ref_robot
    assert set(ref.sensor_names) == set(urdf.ft) == FT8
    assert ref.joint_names == movable_joints(path)


def test_sensor_frame_matches_helper_link(ref_robot: tuple[Path, Urdf, PinKin, IDynTreeFT]) -> None:
    """The sensor frame (child link * <sensor><origin>) coincides with the `<name>` helper link of the URDF.

    Only up to ~1e-5 rad: ergoCubSN001's <sensor> rpy is rounded to 5-6 digits (e.g. -2.0944) while the
    helper link's joint is exact.  iDynTree uses the <sensor> tag (the dynamic test matches it to 1e-6).
    """
    path, urdf, kin, ref = ref_robot
    rng = np.random.default_rng(1)
    q, dq, ddq = random_in_limits(path, ref.joint_names, 1, rng)
    kin.set_state(ref.joint_names, q[0], dq[0], ddq[0])
    for sensor in FT8:
        if kin.model.existFrame(sensor, pin.FrameType.BODY):
            assert _sensor_pose(urdf, kin, sensor).isApprox(kin.link_pose(sensor), 1e-4)


@pytest.mark.parametrize("random_q", [False, True], ids=["q0", "qrand"])
def test_static_root_fixed_weights(ref_robot: tuple[Path, Urdf, PinKin, IDynTreeFT], random_q: bool) -> None:
    """Root clamped, static: each sensor carries the weight of its child subtree.

    child_to_parent (legs, arms): world force (0, 0, -m g); parent_to_child (feet): (0, 0, +m g).
    Also checks the moment about the sensor origin and, with a shuffled joint order, the joint mapping.
    """
    path, urdf, kin, _ = ref_robot
    rng = np.random.default_rng(2)
    names = movable_joints(path)
    names = [names[k] for k in rng.permutation(len(names))]
    ref = IDynTreeFT(path, names)
    q = random_in_limits(path, names, 1, rng)[0] if random_q else np.zeros((1, len(names)))
    zero = np.zeros_like(q)
    out = ref.expected(q, zero, zero, ["root_link"], "root_link", np.array([0.0, 0.0, -G]))
    kin.set_state(names, q[0], zero[0], zero[0])
    g_world = np.array([0.0, 0.0, -G])
    for sensor in FT8:
        tag = urdf.ft[sensor]
        links = list(urdf.subtree(tag.child_link))
        pose = _sensor_pose(urdf, kin, sensor)
        sign = -1.0 if tag.direction == "child_to_parent" else 1.0
        f_world = pose.rotation @ out[sensor][0, :3]
        m = urdf.mass(links)
        np.testing.assert_allclose(f_world, [0.0, 0.0, sign * m * G], atol=1e-6 * max(1.0, m * G))
        # Moment about the sensor origin (world axes): parent->child = -sum (c - p) x m g.
        expected = sign * free_side_wrench(urdf, kin, links, pose.translation, g_world)
        np.testing.assert_allclose(pose.rotation @ out[sensor][0, 3:], expected[3:], atol=1e-6)
    if not random_q and "iCubGenova09" in str(path):
        # Documented signs on iCub 3 (sensor frames): the leg's z axis points down.
        assert out["l_leg_ft"][0, 2] > 90.0
        assert out["l_foot_front_ft"][0, 2] > 1.0


def test_dynamic_root_fixed_newton_euler(ref_robot: tuple[Path, Urdf, PinKin, IDynTreeFT]) -> None:
    """Root clamped, random q, dq, ddq, tilted gravity: every child side is free, so the reading is the
    child subtree's momentum rate minus gravity (Newton-Euler with Pinocchio link accelerations)."""
    path, urdf, kin, ref = ref_robot
    rng = np.random.default_rng(3)
    q, dq, ddq = random_in_limits(path, ref.joint_names, 3, rng)
    g_root = G * np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    out = ref.expected(q, dq, ddq, ["root_link"], "root_link", g_root)
    for i in range(q.shape[0]):
        kin.set_state(ref.joint_names, q[i], dq[i], ddq[i])
        for sensor in FT8:
            tag = urdf.ft[sensor]
            pose = _sensor_pose(urdf, kin, sensor)
            sign = -1.0 if tag.direction == "child_to_parent" else 1.0
            w = sign * free_side_wrench(
                urdf, kin, list(urdf.subtree(tag.child_link)), pose.translation, g_root
            )
            got = np.concatenate([pose.rotation @ out[sensor][i, :3], pose.rotation @ out[sensor][i, 3:]])
            np.testing.assert_allclose(got, w, atol=1e-6 + 1e-6 * np.abs(w).max(), err_msg=sensor)


def test_front_foot_contact_sole_fixed(ref_robot: tuple[Path, Urdf, PinKin, IDynTreeFT]) -> None:
    """l_sole fixed, gravity (0, 0, -g) in l_sole, contact only on l_foot_front, static random pose.

    l_foot_rear_ft (parent_to_child) carries l_foot_rear (+ massless l_sole): force in l_sole = (0, 0, +m g).
    l_foot_front_ft carries the rest of the robot pushing down on the front foot: (0, 0, -(M - m_front) g).
    """
    path, urdf, kin, ref = ref_robot
    rng = np.random.default_rng(4)
    q = random_in_limits(path, ref.joint_names, 1, rng)[0]
    zero = np.zeros_like(q)
    out = ref.expected(q, zero, zero, ["l_foot_front"], "l_sole", np.array([0.0, 0.0, -G]))
    kin.set_state(ref.joint_names, q[0], zero[0], zero[0])
    sole = kin.frame_pose("l_sole")
    rear = list(urdf.subtree(urdf.ft["l_foot_rear_ft"].child_link))
    assert "l_sole" in rear and "l_sole" not in urdf.inertials  # massless frame link
    m_rear = urdf.mass(rear)
    r_sole_rear = sole.rotation.T @ _sensor_pose(urdf, kin, "l_foot_rear_ft").rotation
    np.testing.assert_allclose(r_sole_rear @ out["l_foot_rear_ft"][0, :3], [0, 0, m_rear * G], atol=1e-6)
    m_total = urdf.mass(list(urdf.inertials))
    m_front = urdf.mass(list(urdf.subtree(urdf.ft["l_foot_front_ft"].child_link)))
    r_sole_front = sole.rotation.T @ _sensor_pose(urdf, kin, "l_foot_front_ft").rotation
    np.testing.assert_allclose(
        r_sole_front @ out["l_foot_front_ft"][0, :3], [0, 0, -(m_total - m_front) * G], atol=1e-5
    )


def test_fast_path_matches_get_measurement() -> None:
    """The zero-copy buffers and toVector layout give the same as setVal + getMeasurement."""
    ref = IDynTreeFT(ICUB3)
    q, dq, ddq = random_in_limits(ICUB3, ref.joint_names, 5, np.random.default_rng(5))
    g = np.array([0.0, 0.0, -G])
    fast = ref.expected(q, dq, ddq, ["l_sole", "r_sole"], "l_sole", g)
    assert ref._q.view is not None and ref._meas_view is not None
    for buf in (ref._q, ref._dq, ref._ddq, ref._gravity):
        buf.view = None
    ref._meas_view = None
    slow = ref.expected(q, dq, ddq, ["l_sole", "r_sole"], "l_sole", g)
    for name in ref.sensor_names:
        np.testing.assert_allclose(fast[name], slow[name], rtol=0, atol=1e-12)


def test_contacts_rebuilt_only_on_change() -> None:
    ref = IDynTreeFT(ICUB3)
    z = np.zeros((1, len(ref.joint_names)))
    g = np.array([0.0, 0.0, -G])
    ref.expected(z, z, z, ["l_sole"], "l_sole", g)
    unknowns = ref._unknowns
    assert ref._contacts == ("l_sole",)
    ref.expected(z, z, z, ["l_sole"], "root_link", g)
    assert ref._contacts == ("l_sole",) and ref._unknowns is unknowns
    a = ref.expected(z, z, z, ["root_link"], "root_link", g)
    assert ref._contacts == ("root_link",)
    b = ref.expected(z, z, z, ["l_foot_front", "l_foot_rear"], "l_sole", g)
    assert not np.allclose(a["l_leg_ft"], b["l_leg_ft"])


def test_errors_list_available_names() -> None:
    ref = IDynTreeFT(ICUB3)
    z = np.zeros((2, len(ref.joint_names)))
    g = np.array([0.0, 0.0, -G])
    with pytest.raises(ValueError, match="available frames.*l_sole"):
        ref.expected(z, z, z, ["no_such_link"], "l_sole", g)
    with pytest.raises(ValueError, match="available frames.*root_link"):
        ref.expected(z, z, z, ["l_sole"], "no_such_frame", g)
    with pytest.raises(ValueError, match="available movable joints.*l_knee"):
        IDynTreeFT(ICUB3, ["l_knee", "no_such_joint"])
    with pytest.raises(ValueError, match="available movable joints"):
        IDynTreeFT(ICUB3, ["l_knee", "l_leg_ft_sensor"])  # fixed joint
    with pytest.raises(ValueError):
        ref.expected(z[:, :-1], z, z, ["l_sole"], "l_sole", g)


def test_random_in_limits_and_movable_joints() -> None:
    names = movable_joints(ICUB3)
    assert len(names) == 32 and names[0] == "r_hip_pitch" and "l_leg_ft_sensor" not in names
    lo, hi = joint_limits(ICUB3, names)
    q, dq, ddq = random_in_limits(ICUB3, names, 2000, np.random.default_rng(6))
    assert q.shape == dq.shape == ddq.shape == (2000, 32)
    assert np.all(q >= lo) and np.all(q <= hi) and np.all(hi > lo)
    assert np.abs(dq).max() <= 1.0 and np.abs(ddq).max() <= 5.0 and np.abs(ddq).max() > 4.9
