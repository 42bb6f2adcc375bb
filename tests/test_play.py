"""The play operator (pipeline/core/play.py) against its defining recursion, one sample at a time."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.play import play_operator, play_outputs, play_step


def play_reference(x: np.ndarray, width: np.ndarray, z0: float = 0.0) -> np.ndarray:
    """The play operator's defining recursion, one sample at a time."""
    z = np.empty_like(x)
    z[0] = z0
    for k in range(1, len(x)):
        z[k] = np.clip(z[k - 1] + (x[k] - x[k - 1]) / width, -1.0, 1.0)
    return z


def test_play_operator_hand_example() -> None:
    # width 2: steps +1, +2, -1, -4, +1 move z by half of that, clipped to [-1, 1].
    x = np.array([0.0, 1.0, 3.0, 2.0, -2.0, -1.0])[:, None]
    np.testing.assert_allclose(play_operator(x, 2.0)[:, 0], [0.0, 0.5, 1.0, 0.5, -1.0, -0.5], atol=1e-15)
    np.testing.assert_allclose(
        play_operator(x, 2.0, initial=-1.0)[:, 0], [-1.0, -0.5, 0.5, 0.0, -1.0, -0.5], atol=1e-15
    )


@pytest.mark.parametrize("n", [0, 1, 2, 31, 32, 33, 64, 1025, 5000])
def test_play_operator_matches_recursion(n: int) -> None:
    rng = np.random.default_rng(n)
    x = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    width = np.array([0.5, 3.0, 20.0])
    np.testing.assert_allclose(play_operator(x, width), play_reference(x, width) if n else x, atol=1e-12)
    if n:
        np.testing.assert_allclose(play_operator(x, width, 0.3), play_reference(x, width, 0.3), atol=1e-12)


def test_play_step_from_a_fresh_start_is_the_scan() -> None:
    # the backlash form y_k = clip(y_{k-1}, x_k - w, x_k + w), started from NaN, one sample at a time, is
    # the output x - w z of the z recursion started at 0
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.normal(size=(700, 4)) * 3.0, axis=0)
    width = np.array([1.0, 4.0, 9.0, 30.0])
    y = np.full(4, np.nan)
    stepped = []
    for row in x:
        y = play_step(y, row, width)
        stepped.append(y)
    np.testing.assert_allclose(np.array(stepped), x - width * play_reference(x, width), atol=1e-10)
    np.testing.assert_allclose(play_outputs(x, width), np.array(stepped), atol=1e-10)
    # a constant shift of the whole input shifts the output and leaves z as it is
    np.testing.assert_allclose(play_outputs(x + 5.0, width), play_outputs(x, width) + 5.0, atol=1e-10)
