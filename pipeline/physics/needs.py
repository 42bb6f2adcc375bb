"""Which joints a label needs: those whose positions, velocities and accelerations enter it.

A label whose switch is 1 (a sensor's, a foot pair's sum, a cut set's sum) is the rate of change of
momentum minus gravity of a contact-free region R of the robot, computed on the tree rooted at the contact
case's root link (:func:`pipeline.physics.dynamics.choose_root`), which does not move. Every label cuts the
robot into a part (a sensor's child side, a foot's links, a cut set's isolated part) and the rest, and R is
the side without the root: a sensor's far side, the foot when the contacts are all off it and the rest of
the robot when they are all on it, a cut set's isolated part when it touches nothing and the parts beyond
it when it alone touches. A link's motion follows from the joints on the tree path from the root to it, so
the label needs exactly the movable joints on the paths from the root to R's links: the joints on the path
to its cut joint(s), and those moving R itself. Any other joint may hold any value (a recording without
that board: its positions are absent), the label is the same (`tests/test_label_joints.py` checks it).

Sets of links in, joint column indices (``robot.joint_names`` order) out; cached per root and region, a
function of the tree only (inertial parameters and loads do not change it).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from pipeline.physics.cuts import CutSet
from pipeline.physics.robot import FootPair, RobotModel


def label_parts(
    robot: RobotModel, pairs: Sequence[FootPair] = (), cuts: Iterable[CutSet] = ()
) -> dict[str, frozenset[str]]:
    """Label name -> the part its cut separates from the rest of the robot (links): a sensor's child
    side, a foot pair's foot links, a cut set's isolated part (under its label name)."""
    parts = {s: robot.sensor_sides(s)[1] for s in robot.sensors}
    parts.update({p.name: p.foot_links for p in pairs})
    parts.update({c.label: c.part for c in cuts if c.pair is None})
    return parts


class JointNeeds:
    """The joints each label needs per root link (module docstring), cached.

    `pairs` and `cuts`: the labeller's foot pairs and cut sets. A cut set's sum is expressed in its common
    frame with per-sample transforms of its moving members: it also needs the joints between that frame
    and those members.
    """

    def __init__(self, robot: RobotModel, pairs: Sequence[FootPair] = (), cuts: Iterable[CutSet] = ()):
        self.robot = robot
        self.parts = label_parts(robot, pairs, cuts)
        self._poses = {
            c.label: [(c.frame, robot.sensors[s].child_link) for s in c.moving]
            for c in cuts
            if c.pair is None
        }
        self._column = {name: k for k, name in enumerate(robot.joint_names)}
        self._all = frozenset(robot.links)
        self._trees: dict[str, dict[str, tuple[str, str]]] = {}
        self._cache: dict[tuple[str, frozenset[str]], np.ndarray] = {}
        self._labels: dict[tuple[str, str], np.ndarray] = {}

    def of_label(self, name: str, root: str) -> np.ndarray:
        """(K,) column indices of the joints label `name` needs with the tree rooted at `root`."""
        key = (name, root)
        if key not in self._labels:
            parts = [self.beyond(root, self.parts[name])]
            parts += [self.of_region(frame, frozenset({link})) for frame, link in self._poses.get(name, ())]
            self._labels[key] = np.unique(np.concatenate(parts)).astype(np.intp)
        return self._labels[key]

    def _tree(self, root: str) -> dict[str, tuple[str, str]]:
        """Link -> (joint to its parent, parent link) in the tree rooted at `root`."""
        if root not in self._trees:
            adjacency: dict[str, list[tuple[str, str]]] = {link: [] for link in self._all}
            for joint in self.robot.joints.values():
                adjacency[joint.parent].append((joint.name, joint.child))
                adjacency[joint.child].append((joint.name, joint.parent))
            tree, stack = {}, [self.robot.check_link(root)]
            while stack:
                link = stack.pop()
                for joint, other in adjacency[link]:
                    if other != root and other not in tree:
                        tree[other] = (joint, link)
                        stack.append(other)
            self._trees[root] = tree
        return self._trees[root]

    def of_region(self, root: str, region: frozenset[str]) -> np.ndarray:
        """(K,) sorted column indices of the movable joints on the paths from `root` to `region`'s links."""
        key = (root, region)
        if key not in self._cache:
            tree, seen, needed = self._tree(root), {root}, set()
            for link in region:
                while link not in seen:
                    seen.add(link)
                    joint, link = tree[link]
                    if joint in self._column:
                        needed.add(self._column[joint])
            self._cache[key] = np.array(sorted(needed), dtype=np.intp)
        return self._cache[key]

    def beyond(self, root: str, part: frozenset[str]) -> np.ndarray:
        """The joints of a label whose cut separates `part` from the rest (:func:`label_parts`): its
        region is the side without `root` (only meaningful where the label's switch is 1)."""
        return self.of_region(root, part if root not in part else self._all - part)

    def names(self, columns: Iterable[int]) -> list[str]:
        """The joint names of column indices."""
        return [self.robot.joint_names[k] for k in columns]


__all__ = ["JointNeeds", "label_parts"]
