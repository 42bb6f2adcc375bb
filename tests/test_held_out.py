"""Where a recorded run's held-out residual comes from (`pipeline.evaluation.residual`), on constructed
residuals whose causes are known: an offset per segment, a drift in time, an error linear in a joint's
position, one in its speed, and white noise; each share against its own mean square over the total. And
the maps' gains, the reason a faithful map may not reach the plain least squares, and the causes named for
a model worse than the affine map."""

from __future__ import annotations

import numpy as np

from pipeline.calib.linear import LinearBaseline, monomial_powers
from pipeline.evaluation.residual import decompose, excited_gains, gains, why_not_lower, worse_than_affine


def test_the_shares_recover_each_constructed_cause() -> None:
    rng = np.random.default_rng(0)
    n = 6000
    seg = np.repeat([0, 1, 2], n // 3)
    t = np.tile(np.arange(n // 3) * 0.01, 3)
    q = np.cos(2 * np.pi * 0.3 * t)[:, None]  # one joint swinging 6 cycles a segment: orthogonal to t
    dq = -2 * np.pi * 0.3 * np.sin(2 * np.pi * 0.3 * t)[:, None]
    parts = {
        "offset": np.array([0.5, -0.3, 0.1])[seg],
        "time": 0.05 * (t - t.mean()),  # the same mean time in every segment: centred within each
        "pose": 0.4 * (q[:, 0] - q[:, 0].mean()),
        "speed": 0.0 * t,
        "rest": 0.2 * rng.standard_normal(n),
    }
    r = np.zeros((n, 6))
    r[:, 0] = sum(parts.values())
    r[:, 1] = parts["rest"]  # an axis of noise alone
    shares = decompose(r, seg, t, q, dq)
    total = np.mean(r[:, 0] ** 2)
    for cause in ("offset", "time", "pose", "rest"):
        np.testing.assert_allclose(shares[cause][0], np.mean(parts[cause] ** 2) / total, atol=0.01)
    assert shares["speed"][0] < 0.01 and shares["rest"][1] > 0.98
    np.testing.assert_allclose(sum(shares[c][0] for c in shares), 1.0, atol=1e-9)


def _affine(weight: np.ndarray) -> LinearBaseline:
    """An affine map with correction ``weight`` (6, 6) of the raw wrench (no temperature, no bias)."""
    powers = monomial_powers(6, 1)
    w = np.zeros((1, 6, 7))
    w[0, :, 1:] = weight
    return LinearBaseline("affine", np.zeros((1, 6)), np.ones((1, 6)), powers, w)


def test_gains_along_the_excited_directions_and_why_a_faithful_map_stays_above() -> None:
    correction = np.zeros((6, 6))
    correction[3, 3] = -0.6  # tx read at 0.4 of its size
    model = _affine(correction)
    g = gains(model, 0)
    np.testing.assert_allclose(g, np.eye(6) + correction)
    excitation = {
        "noise": [0.1] * 3 + [0.01] * 3,
        "directions": np.eye(6)[[3, 0, 1, 2, 4, 5]].tolist(),
        "std": [200.0, 20.0, 5.0, 1.0, 0.5, 0.1],
    }
    excited = excited_gains(excitation, {"affine": g})
    assert [d["axes"][0] for d in excited] == ["+1.00 tx", "+1.00 fx"]  # std above 10 noise stds
    np.testing.assert_allclose([d["gain"]["affine"] for d in excited], [0.4, 1.0])
    ls = np.eye(6)
    ls[2, 2] = 0.05  # least squares drops fz and rebuilds it from the others
    why = why_not_lower(ls, excitation, 3.0, 1.0, excited)
    assert "contradict the factory's gain" in why and "+1.00 tx" in why and "affine 0.40" in why
    assert "fz at 0.05" in why and "fx at" not in why
    assert why_not_lower(ls, excitation, 1.0, 1.0, excited) is None  # not worse: nothing to explain
    faithful = why_not_lower(np.eye(6), excitation, 3.0, 1.0, [])
    assert faithful.startswith("no measured reason")


def test_a_model_worse_than_the_affine_is_named_with_its_measured_causes() -> None:
    axes = {m: np.full(6, v) for m, v in {"raw": 9.0, "affine": 1.0, "play": 2.0, "poly2": 1.01}.items()}
    errors = {m: float(v[0]) for m, v in axes.items()}
    cv = {"mean": {"affine": 1.0, "play": 0.8}, "spread": {"play": 0.05}}
    starts = {"play": (5.0, 1.2)}  # the memory's first seconds in a segment
    named = worse_than_affine(errors, axes, cv, starts, 0.3)
    assert set(named) == {"play"}  # poly2 within 2 %: the same error
    why = named["play"]
    assert "starts without the sensor's past" in why and "off the training span" in why
    assert "validation ranked it 0.8" in why
