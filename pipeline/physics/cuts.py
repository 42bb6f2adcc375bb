"""Cut sets: groups of FT sensors whose summed wrench has an exact label where no single sensor has one.

Cutting the kinematic tree at the fixed joints of k FT sensors splits it into k + 1 connected parts. If
one part (the *isolated part*) touches every cut, the wrenches through those k sensors are all that the
rest of the robot exerts on it, so their sum, mapped into one frame, equals the part's rate of change of
momentum minus gravity: exact whenever the part touches nothing, whatever the contact forces elsewhere.
If instead every contact lies on the isolated part, each of the other parts is contact-free and each
sensor alone is exact, so the sum is exact too. The switch of a cut set is therefore
``contacts ∩ part = ∅  or  contacts ⊆ part`` (for one foot's front and rear sensors this is the foot-pair
switch of the thesis, eq. 5.12, with the part = the rest of the robot).

Which sets: every set of 2 to ``max_sensors`` FT sensors that isolates a part, such that every other part
holds a foot (a link of a foot pair: the links that can touch the floor) and no foot is split between
the isolated part and the rest. On iCub 3 and ergoCub this gives both leg sensors (the upper body), the
four foot sensors (all above the feet), a leg sensor with its foot's two sensors (thigh and shank), each
foot's pair (the rest of the robot), and a foot's pair with the other leg's sensor.

Frames and signs (the label is ``sum_s sign_s * frame_X_s(q) f_s``, f_s the reading of sensor s in its
own frame and measure direction):

- the common frame is a URDF link: the sole of a foot pair whose two sensors are in the set (the first
  such pair), else the link on the isolated part's side of the set's first sensor (URDF order);
- ``frame_X_s`` is the (6, 6) wrench transform from the sensor frame to the common frame. It is constant
  when no movable joint lies between them, else it depends on the joint positions (see
  :func:`sensor_poses`; labelled tables carry the pose per sample);
- ``sign_s`` is +1 when sensor s's reading has the same orientation with respect to the isolated part as
  the first sensor's (both the wrench exerted on the part, or both the wrench the part exerts), else -1.
  ``on_part`` says which: True if the sum is the wrench the rest exerts on the part (= its
  d(momentum)/dt - m g, in the common frame, moment about its origin).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

from pipeline.core.errors import RobotModelError
from pipeline.logs.schema import cut_set_name
from pipeline.physics.robot import FootPair, RobotModel, wrench_transform


@dataclass(frozen=True)
class CutSet:
    """A set of FT sensors that isolates a part of the robot (see the module docstring).

    sensors: sensor names, URDF order. part: links of the isolated part. others: the other parts, one
    per sensor, same order (the links beyond each sensor). frame: the common frame (a URDF link).
    signs: (k,) +1 / -1 per sensor. on_part: True if the signed sum is the wrench the rest exerts on the
    part. pair: the foot pair this set equals, if any (its sum is labelled under the pair's name).
    fixed_X: sensor -> constant (6, 6) frame_X_sensor, for the sensors rigidly attached to the frame.
    """

    name: str
    sensors: tuple[str, ...]
    part: frozenset[str] = field(repr=False)
    others: tuple[frozenset[str], ...] = field(repr=False)
    frame: str
    signs: tuple[float, ...]
    on_part: bool
    pair: str | None = None
    fixed_X: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    @property
    def label(self) -> str:
        """The name of its label columns: the foot pair's name, else the set's name."""
        return self.pair or self.name

    @property
    def moving(self) -> tuple[str, ...]:
        """Sensors whose transform to the common frame depends on joint positions."""
        return tuple(s for s in self.sensors if s not in self.fixed_X)

    def switch(self, contacts: Iterable[str]) -> bool:
        """True iff the signed sum is exact here: the part touches nothing, or it alone touches."""
        contacts = set(contacts)
        return not (contacts & self.part) or contacts <= self.part


def components(robot: RobotModel, cut_joints: set[str]) -> list[set[str]]:
    """Connected parts of the link graph without the `cut_joints`."""
    adjacency: dict[str, list[str]] = {link: [] for link in robot.links}
    for joint in robot.joints.values():
        if joint.name not in cut_joints:
            adjacency[joint.parent].append(joint.child)
            adjacency[joint.child].append(joint.parent)
    seen: set[str] = set()
    parts = []
    for start in robot.links:
        if start in seen:
            continue
        part, stack = {start}, [start]
        while stack:
            for other in adjacency[stack.pop()]:
                if other not in part:
                    part.add(other)
                    stack.append(other)
        seen |= part
        parts.append(part)
    return parts


def _isolated_part(robot: RobotModel, sensors: Sequence[str]) -> tuple[set[str], list[set[str]]] | None:
    """(isolated part, the part beyond each sensor) if some part touches every cut, else None."""
    fts = [robot.sensors[s] for s in sensors]
    parts = components(robot, {ft.joint for ft in fts})
    part_of = {link: k for k, part in enumerate(parts) for link in part}
    hubs = [
        k
        for k in range(len(parts))
        if all(k in (part_of[ft.parent_link], part_of[ft.child_link]) for ft in fts)
    ]
    if len(hubs) != 1:
        return None
    hub = hubs[0]
    beyond = [
        parts[part_of[ft.child_link] if part_of[ft.parent_link] == hub else part_of[ft.parent_link]]
        for ft in fts
    ]
    return parts[hub], beyond


def _reading_on_part(robot: RobotModel, sensor: str, part: set[str]) -> bool:
    """True if the sensor's reading is the wrench exerted on `part` (else the one `part` exerts)."""
    ft = robot.sensors[sensor]
    if ft.direction == "child_to_parent":  # Q on P
        return ft.parent_link in part
    return ft.child_link in part  # P on Q


def make_cut_set(robot: RobotModel, sensors: Sequence[str], pairs: Sequence[FootPair]) -> CutSet | None:
    """The cut set of these sensors (any order), or None if they do not isolate a part."""
    order = [s for s in robot.sensors if s in set(sensors)]
    found = _isolated_part(robot, order)
    if len(order) < 2 or found is None:
        return None
    part, beyond = found
    on = [_reading_on_part(robot, s, part) for s in order]
    signs = tuple(1.0 if o == on[0] else -1.0 for o in on)
    pair = next((p for p in pairs if {p.front, p.rear} <= set(order)), None)
    if pair is not None:
        frame = pair.sole
    else:
        first = robot.sensors[order[0]]
        frame = first.parent_link if first.parent_link in part else first.child_link
    fixed_X = {}
    for s in order:
        try:
            fixed_X[s] = wrench_transform(robot.sensor_pose_in_link(s, frame))
        except RobotModelError:  # a movable joint lies between: a per-sample transform
            continue
    same = next((p.name for p in pairs if {p.front, p.rear} == set(order)), None)
    return CutSet(
        name=cut_set_name(order),
        sensors=tuple(order),
        part=frozenset(part),
        others=tuple(frozenset(b) for b in beyond),
        frame=frame,
        signs=signs,
        on_part=on[0],
        pair=same,
        fixed_X=fixed_X,
    )


def find_cut_sets(robot: RobotModel, pairs: Sequence[FootPair], max_sensors: int = 4) -> list[CutSet]:
    """Every cut set of 2..`max_sensors` sensors whose other parts each hold a foot and that splits no
    foot (see the module docstring), in order of size then URDF sensor order. Empty without feet."""
    feet = [p.foot_links for p in pairs]
    found = []
    names = list(robot.sensors)
    for k in range(2, min(max_sensors, len(names)) + 1):
        for combo in combinations(names, k):
            cut = make_cut_set(robot, combo, pairs)
            if cut is None:
                continue
            if not all(any(other & foot for foot in feet) for other in cut.others):
                continue
            if any(foot & cut.part and not foot <= cut.part for foot in feet):
                continue
            found.append(cut)
    return found


# --------------------------------------------------------------------------- joint-dependent transforms
def _path(robot: RobotModel, a: str, b: str) -> list[tuple[str, bool]]:
    """The joints from link `a` to link `b`: (joint name, True if traversed parent -> child)."""
    parent_joint = {j.child: j for j in robot.joints.values()}

    def up(link: str) -> list[str]:
        chain = [link]
        while chain[-1] in parent_joint:
            chain.append(parent_joint[chain[-1]].parent)
        return chain

    chain_a, chain_b = up(a), up(b)
    common = next(link for link in chain_a if link in set(chain_b))
    ascend = [(parent_joint[link].name, False) for link in chain_a[: chain_a.index(common)]]
    descend = [(parent_joint[link].name, True) for link in reversed(chain_b[: chain_b.index(common)])]
    return ascend + descend


def _rotate(rot: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """``rot @ Rot(axis, angle)`` for (N, 3, 3) `rot`, unit `axis` (3,), `angle` (N,) rad. Axes along
    x, y or z (URDF's usual) rotate two columns in place of a full product."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    k = int(np.argmax(np.abs(axis)))
    if np.count_nonzero(axis) == 1:
        s = s * np.sign(axis[k])
        i, j = (k + 1) % 3, (k + 2) % 3
        out = rot.copy()
        out[:, :, i] = c * rot[:, :, i] + s * rot[:, :, j]
        out[:, :, j] = c * rot[:, :, j] - s * rot[:, :, i]
        return out
    skew = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    c, s = c[:, :, None], s[:, :, None]
    return rot @ (np.eye(3) + s * skew + (1.0 - c) * (skew @ skew))


def link_poses(robot: RobotModel, a: str, b: str, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose of link `b` in link `a` for N configurations: rotations (N, 3, 3), positions (N, 3) m.

    q: (N, n_joints) joint positions in ``robot.joint_names`` order (rad or m). Composes the joints on
    the tree path from `a` to `b`: a joint's child in its parent is ``origin * motion(q)``.
    """
    column = {name: k for k, name in enumerate(robot.joint_names)}
    n = q.shape[0]
    rot, pos = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
    for name, forward in _path(robot, a, b):
        joint = robot.joints[name]
        r0, p0 = joint.origin.rotation, joint.origin.translation
        value = q[:, column[name]] if joint.movable else None
        if forward:  # (N*3, 3) @ (3, 3) products run as one BLAS call
            pos = pos + (rot.reshape(-1, 3) @ p0).reshape(n, 3)
            rot = (rot.reshape(-1, 3) @ r0).reshape(n, 3, 3)
        if value is not None:
            sign = 1.0 if forward else -1.0
            if joint.type == "prismatic":
                pos = pos + (rot.reshape(-1, 3) @ joint.axis).reshape(n, 3) * (sign * value)[:, None]
            else:
                rot = _rotate(rot, joint.axis, sign * value)
        if not forward:  # parent in child: motion(q)^-1 * origin^-1
            pos = pos - (rot.reshape(-1, 3) @ (r0.T @ p0)).reshape(n, 3)
            rot = (rot.reshape(-1, 3) @ r0.T).reshape(n, 3, 3)
    return rot, pos


def sensor_poses(robot: RobotModel, frame: str, sensor: str, q: np.ndarray) -> np.ndarray:
    """(N, 12) pose of `sensor`'s measurement frame in link `frame`: the rotation row-major (9), then
    the position of its origin (3, m). :func:`pose_wrench_transforms` turns it into frame_X_sensor."""
    ft = robot.sensors[sensor]
    rot, pos = link_poses(robot, frame, ft.child_link, q)
    offset, n = ft.child_T_sensor, q.shape[0]
    pos = pos + (rot.reshape(-1, 3) @ offset.translation).reshape(n, 3)
    rot = (rot.reshape(-1, 3) @ offset.rotation).reshape(n, 3, 3)
    return np.concatenate([rot.reshape(-1, 9), pos], axis=1)


def pose_wrench_transforms(poses: np.ndarray) -> np.ndarray:
    """(N, 6, 6) wrench transforms a_X_b from (N, 12) poses of b in a (rotation row-major, position):
    ``[[R, 0], [p^ R, R]]``, force first (as :func:`pipeline.physics.robot.wrench_transform`)."""
    rot = poses[:, :9].reshape(-1, 3, 3)
    p = poses[:, 9:]
    skew = np.zeros_like(rot)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -p[:, 2], p[:, 1], -p[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = p[:, 2], -p[:, 1], p[:, 0]
    out = np.zeros((rot.shape[0], 6, 6))
    out[:, :3, :3] = rot
    out[:, 3:, 3:] = rot
    out[:, 3:, :3] = skew @ rot
    return out


def map_wrenches(poses: np.ndarray, wrenches: np.ndarray) -> np.ndarray:
    """(N, 6) wrenches of frame b expressed in frame a, from (N, 12) poses of b in a and (N, 6) wrenches:
    ``f_a = R f_b``, ``tau_a = R tau_b + p x f_a`` (``pose_wrench_transforms(poses) @ w``, cheaper)."""
    rot, p = poses[:, :9].reshape(-1, 3, 3), poses[:, 9:]
    force = np.einsum("nij,nj->ni", rot, wrenches[:, :3])
    moment = np.einsum("nij,nj->ni", rot, wrenches[:, 3:]) + np.cross(p, force)
    return np.concatenate([force, moment], axis=1)


def cut_poses(
    robot: RobotModel, cut: CutSet, q: np.ndarray, cache: dict[tuple[str, str], np.ndarray] | None = None
) -> dict[str, np.ndarray]:
    """Per joint-dependent sensor of `cut`, its (N, 12) pose in the common frame (:func:`sensor_poses`).
    `cache` (keyed by (frame, sensor), for one `q`) shares poses between cut sets."""
    cache = {} if cache is None else cache
    out = {}
    for s in cut.moving:
        if (cut.frame, s) not in cache:
            cache[cut.frame, s] = sensor_poses(robot, cut.frame, s, q)
        out[s] = cache[cut.frame, s].copy()
    return out


def cut_sums(cut: CutSet, readings: dict[str, np.ndarray], poses: dict[str, np.ndarray]) -> np.ndarray:
    """(N, 6) signed sum ``sum_s sign_s frame_X_s f_s`` of the readings (N, 6) in the common frame.

    poses: (N, 12) per joint-dependent sensor (:func:`cut_poses`); N, Nm (moment about the frame origin).
    """
    total = np.zeros_like(readings[cut.sensors[0]])
    for sensor, sign in zip(cut.sensors, cut.signs, strict=True):
        f = readings[sensor]
        fixed = cut.fixed_X.get(sensor)
        total += sign * (f @ fixed.T if fixed is not None else map_wrenches(poses[sensor], f))
    return total
