"""The memory models' structure from the data, and their fit on logs that start elsewhere.

A play operator wider than the training motion never saturates: its state is the reading's departure from
the log's first reading, and a least-squares fit trades it against the logs' offsets. Here two training
logs start at the same reading and their offsets differ (drift), the test log starts 40 N away: with the
simulator's widths and no ridge (the earlier fit) the play model answers the test log's start with its
weight times the 40 N (39 N off, the affine map 0.6); with the data's widths, the saturation rule and the
relative ridge it is 2 N off: what is left is the widest kept operator's near-linear state traded against
the static gain (0.95, the virtual pushes holding it), which a shift beyond the training range shows.
Also the pieces: spans, widths, the time constants a log can identify, and the offset family (the mean
residual, against numpy's).
"""

from __future__ import annotations

import numpy as np

from pipeline.calib.linear import fit_linear_baseline
from pipeline.calib.memory import (
    MIN_SATURATED,
    NOISE_WIDTHS,
    axis_spans,
    data_time_constants,
    data_widths,
    saturated,
)
from pipeline.calib.pushes import PushPrior
from pipeline.core.lowpass import memory_of
from pipeline.core.play import play_operator

NOISE = np.r_[np.full(3, 0.6), np.full(3, 0.03)]
PUSH = PushPrior(0.1, 20.0, 0.2)  # the default virtual pushes


def _log(n: int, start: float, offset: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(raw (n, 1, 7), labels (n, 1, 6)): a slow +-20 N motion on fx around `start`, an offset drift
    `offset` on fx, white noise; the sensor's gains are 1 (the labels are the true wrench)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    true = np.zeros((n, 6))
    true[:, 0] = start + 20.0 * np.sin(2 * np.pi * 0.2 * t)
    raw = true + rng.standard_normal((n, 6)) * NOISE
    raw[:, 0] += offset
    x = np.c_[raw, np.full(n, 30.0)][:, None, :]
    return x, true[:, None, :]


def _fit_and_score(widths: np.ndarray, ridge_free: bool) -> tuple[float, float]:
    """(play model's, affine map's) test RMSE on fx of the scenario of the module docstring."""
    import pipeline.calib.linear as linear

    logs = [_log(3000, 0.0, 1.0, 1), _log(3000, 0.0, -1.0, 2)]
    x = np.concatenate([g[0] for g in logs])
    labels = np.concatenate([g[1] for g in logs])
    memory = np.concatenate([memory_of(g[0], widths, None, 0.01) for g in logs])
    switches = np.ones((len(x), 1), dtype=bool)
    test_x, test_y = _log(3000, 40.0, 0.0, 3)
    saved = linear.MEMORY_RIDGE, linear.saturated
    if ridge_free:  # the earlier fit: no ridge, every operator kept
        linear.MEMORY_RIDGE, linear.saturated = 0.0, lambda states: np.ones(states.shape[1], dtype=bool)
    try:
        play = fit_linear_baseline(
            "play", x, labels, switches, 1, 0.0, (1.0,), push=PUSH, widths=widths, memory=memory
        )
    finally:
        linear.MEMORY_RIDGE, linear.saturated = saved
    affine = fit_linear_baseline("affine", x, labels, switches, 1, 0.0, (1.0,), push=PUSH)
    rmse = [
        float(np.sqrt(np.mean((m.predict_log(test_x, 0.01)[:, 0, 0] - test_y[:, 0, 0]) ** 2)))
        for m in (play, affine)
    ]
    return rmse[0], rmse[1]


def test_a_play_model_on_a_log_that_starts_elsewhere_stays_at_the_affine_maps_error() -> None:
    wide = np.array([np.r_[np.full(3, w), np.full(3, w / 20)] for w in (10.0, 30.0, 90.0)])  # the simulator's
    broken, affine = _fit_and_score(wide, ridge_free=True)
    x = np.concatenate([_log(3000, 0.0, 1.0, 1)[0], _log(3000, 0.0, -1.0, 2)[0]])
    ours = np.asarray(data_widths(x[:, :, :6], (0.02, 0.06, 0.2), NOISE))  # the default fractions
    fixed, affine_again = _fit_and_score(ours, ridge_free=False)
    assert broken > 20 * affine, (broken, affine)  # the state read the start: tens of N off
    assert fixed < broken / 10 and fixed < 4 * affine_again, (fixed, broken, affine_again)


def test_spans_widths_and_the_time_constants_a_log_identifies() -> None:
    rng = np.random.default_rng(0)
    raw = rng.uniform(-50.0, 50.0, size=(20000, 2, 6))
    raw[:, 1] *= 0.5  # a second sensor half as wide: the group's span is the wider one's
    raw[:, :, 5] = 0.0  # an axis that does not move
    spans = axis_spans(raw)
    np.testing.assert_allclose(spans[:5], np.quantile(raw[:, 0, :5], 0.995, axis=0) * 2, rtol=0.02)
    widths = np.asarray(data_widths(raw, (0.1, 0.3), NOISE))
    np.testing.assert_allclose(widths[:, :5], np.outer([0.1, 0.3], spans[:5]))
    np.testing.assert_allclose(widths[:, 5], NOISE_WIDTHS * NOISE[5])  # the noise floor of a still axis
    kept, dropped = data_time_constants((0.01, 0.1, 1.0, 10.0), [12.0, 11.0, 13.0], 0.01)
    assert kept == (0.1, 1.0) and dropped == (0.01, 10.0)  # 2 periods .. a quarter of the median log


def test_an_operator_is_kept_where_the_motion_saturates_it() -> None:
    t = np.arange(10000) * 0.01
    x = 10.0 * np.sin(2 * np.pi * 0.5 * t)[:, None]
    narrow, wide = play_operator(x, 2.0), play_operator(x, 15.0)  # reversals of 20: saturates 2, not 15
    keep = saturated(np.c_[narrow, wide])
    assert keep.tolist() == [True, False]
    assert np.mean(np.abs(narrow) > 0.999) > MIN_SATURATED


def test_the_offset_family_is_the_mean_residual() -> None:
    x, labels = _log(2000, 0.0, 3.0, 4)
    model = fit_linear_baseline("offset", x, labels, np.ones((2000, 1), dtype=bool), 0, 0.0, (1.0,))
    expected = np.mean(labels[:, 0] - x[:, 0, :6], axis=0)
    np.testing.assert_allclose(model.predict(x)[:, 0] - x[:, 0, :6], np.tile(expected, (2000, 1)), atol=1e-9)
