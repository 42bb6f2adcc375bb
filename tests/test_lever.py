"""The free lever of the linear fits (calib.linear `_free_lever`, ``train.defaults.free_lever``).

A sensor whose torque reference point is displaced by d reads ``tau + d x f``. The synthetic sensor here is
a foot's below its ankle: large vertical forces (the robot's weight), small sideways ones, torques of their
own; its only distortion is such a lever (and white noise). The virtual pushes penalise every torque<-force
coefficient alike, so with few sideways forces they hold back the lever's terms in those forces; with the
lever free the labels fix it. Off the lever (the symmetric part of the block) the pushes still decide, and on
a free arm's relation a free lever neither rebuilds forces nor cancels the torques' noise.
"""

from __future__ import annotations

import numpy as np

from pipeline.calib.linear import fit_linear_baseline
from pipeline.calib.pushes import PushPrior
from pipeline.core.play import play_memory
from tests.factories.sensors import NOISE, on_relation

D = np.array([0.004, -0.006, 0.003])  # m: the displaced torque reference point
HELD = PushPrior(0.1, 20.0, 0.2, free_lever=False)
FREE = PushPrior(0.1, 20.0, 0.2, free_lever=True)


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x: skew(v) @ f = v x f."""
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def foot(n: int = 8000, sideways_n: float = 6.0, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(raw inputs (n, 1, 7), exact labels (n, 1, 6)) of a foot sensor with lever D."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    force = np.c_[
        sideways_n * np.sin(0.9 * t), sideways_n * np.sin(1.3 * t + 1), -300 + 100 * np.sin(0.4 * t)
    ]
    torque = np.stack([8 * np.sin((0.5 + 0.3 * k) * t + k) for k in range(3)], 1)
    true = np.c_[force, torque]
    raw = true.copy()
    raw[:, 3:] += np.cross(D, force)
    raw += np.r_[25.0, -30, 40, 2, -1, 3] + rng.standard_normal((n, 6)) * NOISE
    x = np.zeros((n, 1, 7))
    x[:, 0, :6], x[:, 0, 6] = raw, 30.0
    return x, true[:, None, :]


def torque_force_block(x: np.ndarray, labels: np.ndarray, push: PushPrior, widths=None) -> np.ndarray:
    """(3, 3) the fitted correction's torque<-force coefficients, m (calibrated tau = raw tau + T f + ...)."""
    memory = None if widths is None else play_memory(x, widths)
    model = fit_linear_baseline(
        "m",
        x,
        labels,
        np.ones((len(x), 1), bool),
        order=1,
        ridge=0.0,
        lambdas=(1.0,),
        push=push,
        widths=widths,
        memory=memory,
    )
    w = model.weights[0][:, 1:7] / model.scale[0][:6]  # the linear (static) features, physical units
    return w[3:, :3]


def test_a_free_lever_is_learned_where_the_pushes_held_it_back() -> None:
    x, labels = foot()
    expected = -skew(D)  # the correction undoes tau += d x f
    free = torque_force_block(x, labels, FREE)
    held = torque_force_block(x, labels, HELD)
    np.testing.assert_allclose(free, expected, atol=3e-4)  # m: 0.3 mm
    # held back: the terms in the sideways forces (columns fx, fy of the tz row) lose most of the lever
    assert abs(held[2, 0] - expected[2, 0]) > 0.5 * abs(expected[2, 0])
    assert abs(held[2, 1] - expected[2, 1]) > 0.5 * abs(expected[2, 1])


def test_the_play_model_learns_the_free_lever_too() -> None:
    x, labels = foot()
    widths = np.array([[10.0, 10, 10, 0.5, 0.5, 0.5]])
    np.testing.assert_allclose(torque_force_block(x, labels, FREE, widths), -skew(D), atol=3e-4)


def test_off_the_lever_the_pushes_still_decide() -> None:
    # a symmetric torque<-force distortion (no lever): with few sideways forces it stays mostly unlearned,
    # as every coefficient the labels barely see
    x, labels = foot(seed=2)
    sym = np.array([[0.0, 0.005, 0.0], [0.005, 0.0, 0.0], [0.0, 0.0, 0.0]])
    x[:, 0, 3:6] += labels[:, 0, :3] @ sym.T - np.cross(D, labels[:, 0, :3])  # replace the lever by sym
    block = torque_force_block(x, labels, FREE)
    assert abs(block[0, 1] + 0.005) > 0.0025 and abs(block[1, 0] + 0.005) > 0.0025


def test_a_free_lever_on_a_free_arms_relation_keeps_the_factory_gains() -> None:
    x, labels = on_relation(6000)
    model = fit_linear_baseline(
        "affine", x, labels, np.ones((len(x), 1), bool), order=1, ridge=0.0, lambdas=(1.0,), push=FREE
    )
    weight, _ = model.affine_map(0)
    np.testing.assert_allclose(1.0 + np.diag(weight[:, :6]), 1.0, atol=0.06)
