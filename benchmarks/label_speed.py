"""Samples/s of our batch expected-FT function vs iDynTree's estimator on the same 5,000 samples.

Both compute the 8 FT sensors' expected wrenches of iCubGenova09 standing on its left sole, with
random in-limit (q, dq, ddq). iDynTree is used efficiently: estimator and buffers built once, values
copied into preallocated buffers (tests/idyntree_ref.py). Also printed, to show what bounds our
figure: one thread vs all cores, and a plain per-sample ``pin.rnea`` loop on the same model.
Also the cost of the cut-set sums (poses of the joint-dependent members and the signed sums of every
cut set, double support) relative to the expected wrenches themselves.
The last line is the ratio ours / iDynTree (>= 1.0 required, >= 2.0 aimed for).

    python benchmarks/label_speed.py [--samples 5000] [--repeats 3]
    python benchmarks/label_speed.py --quick    # 50 samples, once: for the test suite
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import QUICK  # noqa: E402
from pipeline.physics.cuts import cut_poses, cut_sums, find_cut_sets  # noqa: E402
from pipeline.physics.dynamics import ContactCase, expected_wrenches  # noqa: E402
from pipeline.physics.robot import load_robot  # noqa: E402
from tests.idyntree_ref import IDynTreeFT, random_in_limits  # noqa: E402

CONTACTS, FIXED, GRAVITY = ["l_foot_front", "l_foot_rear"], "l_sole", np.array([0.0, 0.0, -9.80665])


def best_of(repeats: int, fn) -> float:
    """Shortest wall time of `repeats` calls, s."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=5000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help=f"{QUICK}: 50 samples, once")
    args = parser.parse_args()
    if args.quick:
        args.samples, args.repeats = 50, 1

    robot = load_robot("iCubGenova09")
    q, dq, ddq = random_in_limits(robot.urdf_path, robot.joint_names, args.samples, np.random.default_rng(0))
    case = ContactCase.make(CONTACTS, FIXED, GRAVITY)
    oracle = IDynTreeFT(robot.urdf_path, robot.joint_names)

    # correctness first: same numbers on every sensor that has an exact label here
    ours = expected_wrenches(robot, q, dq, ddq, case)
    ref = oracle.expected(q, dq, ddq, CONTACTS, FIXED, GRAVITY)
    worst = max(np.abs(ours.wrench[s] - ref[s]).max() for s in robot.sensors if ours.switch[s][0])
    print(
        f"samples: {args.samples}, robot {robot.name}, {len(robot.sensors)} FT sensors, "
        f"max |ours - iDynTree| over exact labels: {worst:.2e}"
    )

    cores = os.cpu_count() or 1
    t_ours = best_of(args.repeats, lambda: expected_wrenches(robot, q, dq, ddq, case))
    t_ours_1 = best_of(args.repeats, lambda: expected_wrenches(robot, q, dq, ddq, case, n_threads=1))
    t_ref = best_of(args.repeats, lambda: oracle.expected(q, dq, ddq, CONTACTS, FIXED, GRAVITY))

    # what bounds us: Pinocchio's RNEA itself, one call per sample, on the same contact-rooted model
    rooted = robot.rooted("l_foot_front")
    model = rooted.model.copy()
    model.gravity = pin.Motion(robot.rigid_transform("l_foot_front", FIXED).rotation @ GRAVITY, np.zeros(3))
    data = model.createData()
    qs = rooted.neutral_batch(args.samples)
    qs[:, rooted.q_index] = q * rooted.sign
    vs, accs = np.zeros((args.samples, model.nv)), np.zeros((args.samples, model.nv))
    vs[:, rooted.v_index], accs[:, rooted.v_index] = dq * rooted.sign, ddq * rooted.sign

    def rnea_loop() -> None:
        for k in range(args.samples):
            pin.rnea(model, data, qs[k], vs[k], accs[k])

    t_rnea = best_of(args.repeats, rnea_loop)

    # cut sets in double support: every sum is exact there
    pairs = [
        robot.foot_pair("l_foot", "l_foot_front_ft", "l_foot_rear_ft", "l_sole"),
        robot.foot_pair("r_foot", "r_foot_front_ft", "r_foot_rear_ft", "r_sole"),
    ]
    cuts = [c for c in find_cut_sets(robot, pairs) if c.pair is None]
    double = ContactCase.make([*CONTACTS, "r_foot_front", "r_foot_rear"], FIXED, GRAVITY)
    t_double = best_of(args.repeats, lambda: expected_wrenches(robot, q, dq, ddq, double))
    readings = expected_wrenches(robot, q, dq, ddq, double).reading

    def sums() -> None:
        cache: dict = {}
        for cut in cuts:
            cut_sums(cut, readings, cut_poses(robot, cut, q, cache))

    t_cuts = best_of(args.repeats, sums)
    print(
        f"{len(cuts)} cut sets: sums {1e6 * t_cuts / args.samples:.2f} us/sample, "
        f"{t_cuts / t_double:.2f} x the expected wrenches of the same samples"
    )

    n = args.samples
    rows = [
        ("iDynTree estimator, 1 thread", t_ref),
        ("ours, pin.rneaInParallel, 1 thread", t_ours_1),
        (f"ours, pin.rneaInParallel, {cores} threads", t_ours),
        ("bound: pin.rnea per sample from Python", t_rnea),
    ]
    for label, seconds in rows:
        print(f"{label:40s}: {n / seconds:10.0f} samples/s  {1e6 * seconds / n:6.2f} us/sample")
    print(f"ratio ours / iDynTree, 1 thread: {t_ref / t_ours_1:.2f}")
    print(f"ratio ours / iDynTree: {t_ref / t_ours:.2f}")


if __name__ == "__main__":
    main()
