"""Labels from the joints they need: which joints (pipeline.physics.needs) and labelling without the others.

The joints a label needs, per contact case, are checked against an independent numerical definition: the
joints whose position, velocity and acceleration change moves the label (each joint perturbed in turn on
random states, every label of the case at once). Then a label is computed, with the same value, where
only the joints it needs are there (the others NaN and not ok), and is switched off, the sample counted
as lost and the joint named, where one it needs is missing.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.config import LabelParams
from pipeline.labels.contacts import Contacts
from pipeline.labels.joints import Lacking
from pipeline.labels.table import Labeller, label_arrays
from pipeline.logs import schema as S
from pipeline.physics.cuts import find_cut_sets
from pipeline.physics.dynamics import ContactCase, choose_root
from pipeline.physics.feet import robot_feet
from pipeline.physics.robot import load_robot
from tests.conftest import GRAVITY

CFG = LabelParams(
    contact_on=0.04,
    contact_off=0.02,
    guard_s=0.01,
    zero_quantile=0.2,
    cut_max_sensors=4,
    imu_check=None,
    inertials="urdf",
    identify=None,
)
G = np.array([0.0, 0.0, -GRAVITY])
# (contacts, fixed link): on one sole, double support, on the pole, on the front of a foot (iCub 3)
CASES = [({"r_sole"}, "r_sole"), ({"l_sole", "r_sole"}, "l_sole"), ({"root_link"}, "root_link")]
HALF_FOOT = ({"l_foot_front"}, "l_foot_front")
N = 6


@pytest.fixture(scope="module", params=["iCubGenova09", "iCubGenova02"])
def labeller(request: pytest.FixtureRequest) -> Labeller:
    robot = load_robot(request.param)
    feet = robot_feet(robot, None)
    pairs = [f.pair for f in feet if f.pair is not None]
    return Labeller(robot, pairs, find_cut_sets(robot, pairs, 4), CFG, GRAVITY, feet, threads=1)


def _cases(lab: Labeller) -> list[tuple[set[str], str]]:
    return [*CASES, HALF_FOOT] if lab.pairs else CASES


def _label(lab: Labeller, case: tuple[set[str], str], kin: list[np.ndarray], ok: np.ndarray, lacking=None):
    contacts = Contacts(
        [frozenset(case[0])], np.zeros(N, int), np.full(N, case[1], object), np.zeros(N, bool), False
    )
    return label_arrays(lab, contacts, *kin, ok, G, lacking)


def _wrench(columns: dict[str, np.ndarray], name: str) -> np.ndarray:
    return np.column_stack([columns[c] for c in S.wrench_cols(S.EXPECTED, name)])


def _state(lab: Labeller, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    j = len(lab.robot.joint_names)
    return [rng.uniform(-0.5, 0.5, (N, j)), rng.normal(0, 1, (N, j)), rng.normal(0, 3, (N, j))]


def test_a_label_needs_exactly_the_joints_that_move_it(labeller: Labeller) -> None:
    lab, every = labeller, np.ones((N, len(labeller.robot.joint_names)), bool)
    kin = _state(lab, 0)
    for case in _cases(lab):
        root = choose_root(lab.robot, ContactCase.make(*case, G))
        ref = _label(lab, case, kin, every)
        exact = [m for m in lab.names if (ref[S.switch_col(m)] == 1).all()]
        assert len(exact) >= 2, case
        moved: dict[str, set[int]] = {m: set() for m in exact}
        for j in range(len(lab.robot.joint_names)):
            changed = [a.copy() for a in kin]
            for a, step in zip(changed, (0.3, 1.0, 2.0), strict=True):
                a[:, j] += step
            out = _label(lab, case, changed, every)
            for m in exact:
                base = _wrench(ref, m)
                if np.abs(_wrench(out, m) - base).max() > 1e-9 * max(1.0, np.abs(base).max()):
                    moved[m].add(j)
        for m in exact:
            needed = set(lab.needs.of_label(m, root).tolist())
            assert needed == moved[m], (case, m, lab.needs.names(needed ^ moved[m]))


def test_labels_without_the_joints_they_do_not_need(labeller: Labeller) -> None:
    """Every joint an arm sensor's label does not need is absent (NaN, not ok): that label is the same,
    the others that need one of them are off, lost, and name the joints they lack."""
    lab, robot = labeller, labeller.robot
    names = robot.joint_names
    kin = _state(lab, 1)
    every = np.ones((N, len(names)), bool)
    case = CASES[0]
    root = choose_root(robot, ContactCase.make(*case, G))
    ref = _label(lab, case, kin, every)
    keep = lab.needs.of_label("r_arm_ft", root)
    ok = np.zeros_like(every)
    ok[:, keep] = True
    absent = [np.where(ok, a, np.nan) for a in kin]
    lacking = Lacking()
    got = _label(lab, case, absent, ok, lacking)
    np.testing.assert_array_equal(_wrench(got, "r_arm_ft"), _wrench(ref, "r_arm_ft"))
    assert (got[S.switch_col("r_arm_ft")] == 1).all()
    for m in lab.names:
        needs_absent = not set(lab.needs.of_label(m, root).tolist()) <= set(keep.tolist())
        if (ref[S.switch_col(m)] == 1).all() and needs_absent:
            assert (got[S.switch_col(m)] == 0).all() and np.isnan(_wrench(got, m)).all(), m
            assert lacking.lost[m] == N, m
            missing = set(lab.needs.of_label(m, root).tolist()) - set(keep.tolist())
            assert lacking.joints[m] == missing, m
    # an arm sensor always needs its own arm: the left arm's label is lost, naming its joints
    summary = lacking.summary({m: int(got[S.switch_col(m)].sum()) for m in lab.names}, names, {})
    assert summary["l_arm_ft"]["samples"] == 0 and "l_elbow" in summary["l_arm_ft"]["lacks"]
    assert summary["r_arm_ft"] == {"samples": N, "lost": 0, "lacks": []}
