"""`pipeline.deploy.shrink`: the labels' model error of a still stretch, and the continuous shrinkage of
an estimated offset change.

Independent references: a single body's weight and moment, its mass scaled and its centre of mass moved
along each axis in turn (numpy cross products), give the label's error per axis; the shrinkage is checked
against its defining values (nothing up to the threshold, all from twice it) and for continuity on a grid
that straddles both.
"""

from __future__ import annotations

import numpy as np

from pipeline.deploy.shrink import LabelError, reasons, shrink, weight


def test_label_floor_is_a_body_with_its_mass_scaled_and_its_com_moved() -> None:
    rng = np.random.default_rng(3)
    error = LabelError(mass_rel=0.02, com_m=0.004)
    for _ in range(5):
        mass, com, down = rng.uniform(0.5, 12.0), rng.normal(0.0, 0.2, 3), rng.normal(size=3)
        force = mass * 9.81 * down / np.linalg.norm(down)  # N, the weight in the sensor frame
        label = np.concatenate([force, np.cross(com, force)])
        scaled = np.concatenate([1.02 * force, np.cross(com, 1.02 * force)]) - label  # mass 2 % heavier
        moved = [np.cross(0.004 * np.eye(3)[j], force) for j in range(3)]  # COM 4 mm along x, y, z
        expected = np.concatenate([np.abs(scaled[:3]), np.sqrt(scaled[3:] ** 2 + sum(m**2 for m in moved))])
        np.testing.assert_allclose(error.label_floor(label), expected, rtol=1e-12, atol=1e-12)


def test_shrinkage_applies_nothing_within_the_threshold_and_all_beyond_twice_it() -> None:
    threshold = np.array([0.5, 1.0, 2.0, 0.1, 0.2, 0.3])
    for factor in (0.0, 0.3, 1.0):
        assert np.all(shrink(factor * threshold * [1, -1, 1, -1, 1, -1], threshold) == 0.0)
    for factor in (2.0, 3.0, 50.0):
        estimate = factor * threshold * [-1, 1, 1, -1, -1, 1]
        assert np.all(shrink(estimate, threshold) == estimate)
    assert weight(np.array(1.5)) == 0.5  # the smoothstep's middle
    estimate = np.array([0.5, -1.5, 6.0, 0.05, -0.35, 0.9])  # 1, 1.5, 3, 0.5, 1.75, 3 thresholds
    text = reasons(estimate, shrink(estimate, threshold), threshold)
    assert text[0].startswith("not applied (|0.5| N vs threshold 0.5 N")
    assert text[1].startswith("shrunk to 50 % (") and text[2].startswith("applied (")
    assert text[4].endswith("Nm)") and text[5].startswith("applied (|0.9| Nm")


def test_shrinkage_is_continuous_with_a_bounded_slope() -> None:
    """On a grid 1e-5 fine from 0 to 3 thresholds (both switches inside), a step of the estimate moves the
    applied change by at most 3 steps: no jump anywhere."""
    estimate = np.arange(0.0, 3.0, 1e-5) * 0.7
    applied = shrink(estimate, np.full_like(estimate, 0.7))
    slope = np.abs(np.diff(applied)) / np.diff(estimate)
    assert slope.max() < 3.0 and applied[0] == 0.0 and applied[-1] == estimate[-1]
    assert np.all(np.diff(applied) >= 0.0)  # and monotone: a larger estimate never applies less
