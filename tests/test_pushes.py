"""Virtual pushes (calib.pushes), excitation (calib.excitation) and truth-free fidelity (calib.fidelity).

The synthetic sensor here is a free arm's (tests/factories/sensors.py): its true wrench lies on
torque = c x force (c = 0.15 m along z), its raw reading adds white noise to a slightly distorted copy, and
its labels are exact. Least squares can then rebuild a force from the less noisy torque channel; the checks
below show that it does without the virtual pushes and that with them every axis keeps about the factory
map's gain.
"""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch

from pipeline.calib.excitation import OUTSIDE, WEAK, excitation, lever_relation, noise_std
from pipeline.calib.fidelity import model_fidelity, worst_gap
from pipeline.calib.linear import fit_linear_baseline, monomial_powers
from pipeline.calib.models import GroupNet, NetConfig
from pipeline.calib.pushes import (
    IMU_STD,
    PushPrior,
    linear_push_gram,
    output_weights,
    push_gram,
    push_penalty,
)
from tests.factories.sensors import LEVER, NOISE, PUSH, on_relation


def affine_gains(x: np.ndarray, labels: np.ndarray, push: PushPrior | None) -> np.ndarray:
    model = fit_linear_baseline(
        "affine", x, labels, np.ones((len(x), 1), bool), order=1, ridge=0.0, lambdas=(1.0,), push=push
    )
    weight, _ = model.affine_map(0)
    return 1.0 + np.diag(weight[:, :6])


def test_least_squares_rebuilds_forces_from_torques_without_pushes() -> None:
    x, labels = on_relation(6000)
    gains = affine_gains(x, labels, None)
    # fx and fy are the torque channels' business on this relation: least squares shrinks them
    assert gains[0] < 0.5 and gains[1] < 0.5


def test_virtual_pushes_keep_the_factory_gain() -> None:
    x, labels = on_relation(6000)
    gains = affine_gains(x, labels, PUSH)
    np.testing.assert_allclose(gains, 1.0, atol=0.06)


def test_affine_push_gram_is_exact() -> None:
    x, labels = on_relation(500)
    model = fit_linear_baseline("affine", x, labels, np.ones((500, 1), bool), 1, 0.0, (1.0,))
    features = partial(model.features, s=0)
    gram = linear_push_gram(features, model.powers, model.scale[0], x[:, 0], PUSH, np.random.default_rng(0))
    expected = np.zeros(8)
    expected[1:7] = PUSH.variances() / model.scale[0][:6] ** 2 * 500
    np.testing.assert_allclose(gram, np.diag(expected), rtol=1e-12)


def test_wrench_only_affine_push_gram_is_exact_and_keeps_the_factory_gain() -> None:
    """A log without temperature: the 6-input affine map gets the same prior, checked against sampling."""
    x, labels = on_relation(6000)
    x[:, :, 6:] = np.nan  # no temperature, no IMU
    model = fit_linear_baseline(
        "affine", x, labels, np.ones((6000, 1), bool), 1, 0.0, (1.0,), n_inputs=6, push=PUSH
    )
    np.testing.assert_allclose(1.0 + np.diag(model.affine_map(0)[0][:, :6]), 1.0, atol=0.06)
    features = partial(model.features, s=0)
    exact = linear_push_gram(features, model.powers, model.scale[0], x[:, 0], PUSH, np.random.default_rng(0))
    sampled = push_gram(features, x[:, 0], PUSH, np.random.default_rng(3), rows=200_000)
    np.testing.assert_allclose(exact, sampled, rtol=0.02, atol=5e-3 * exact.max())


def test_sampled_push_gram_matches_the_exact_one_on_linear_features() -> None:
    x = np.random.default_rng(1).normal(size=(300, 13))
    powers = monomial_powers(7, 1)
    scale = np.arange(1.0, 8.0)

    def features(xs: np.ndarray) -> np.ndarray:
        z = xs[:, :7] / scale
        return np.c_[np.ones(len(z)), z][:, : len(powers)]

    sampled = push_gram(features, x, PUSH, np.random.default_rng(2), rows=200_000)
    exact = np.diag(np.r_[0.0, PUSH.variances() / scale[:6] ** 2, 0.0]) * 300
    np.testing.assert_allclose(sampled, exact, rtol=0.02, atol=2e-3 * exact.max())


def test_push_penalty_is_zero_for_the_affine_start_and_positive_once_trained() -> None:
    net = GroupNet(NetConfig(7, 16), 1)
    torch.manual_seed(0)
    net.reset_parameters()  # output layer zero: the network is its affine map, no correction at all
    x = torch.randn(64, 7) * 10
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        assert float(push_penalty(net.correction, x, 7, 1, PUSH, gen)) == 0.0
        torch.nn.init.normal_(net.nets[0].mlp[-1].weight)
        assert float(push_penalty(net.correction, x, 7, 1, PUSH, gen)) > 0.0


def test_noise_std_from_second_differences() -> None:
    rng = np.random.default_rng(3)
    n = 20_000
    t = np.arange(n) / 100.0
    x = 50 * np.sin(0.5 * t)[:, None] + rng.standard_normal((n, 6)) * NOISE
    stamps = (t * 1e9).astype(np.int64)
    np.testing.assert_allclose(noise_std(x, np.zeros(n, int), stamps), NOISE, rtol=0.05)


def test_excitation_finds_the_relation_and_what_lies_off_it() -> None:
    _, labels = on_relation(6000)
    c, r2 = lever_relation(labels[:, 0])
    np.testing.assert_allclose(c, LEVER, atol=1e-9)
    assert r2 == pytest.approx(1.0)
    e = excitation("arm", labels[:, 0], NOISE)
    assert e is not None and e.weak == 3  # torque = c x force: 3 directions carry nothing
    assert np.all(np.asarray(e.std[:3]) > WEAK)
    assert np.max(e.outside(labels[:, 0])) < 1e-6
    push = labels[:100, 0] + np.r_[0.0, 0, 0, 2.0, 0, 0]  # a torque with no force: off the relation
    assert np.min(e.outside(push)) > OUTSIDE


def test_fidelity_of_raw_and_of_a_shortcut() -> None:
    x, _ = on_relation(1000)

    def raw(xs: np.ndarray) -> np.ndarray:
        return xs[:, :, :6].copy()

    def shortcut(xs: np.ndarray) -> np.ndarray:  # fx rebuilt from ty: fx = -ty / c_z
        out = xs[:, :, :6].copy()
        out[:, :, 0] = -xs[:, :, 4] / LEVER[2]
        return out

    np.testing.assert_allclose(model_fidelity(raw, x, PUSH, 7)[0]["slopes"], 1.0)
    entry = model_fidelity(shortcut, x, PUSH, 7)[0]
    assert entry["slopes"][0] == pytest.approx(0.0)
    assert worst_gap(entry) == pytest.approx(1.0)


def test_a_network_reading_the_imu_pays_for_it() -> None:
    """13 inputs: a correction that follows the accelerometer (the wrench unchanged) is penalised: here
    1 kg x acc_x on fx, so the term is E[(delta acc_x)^2] / 6 axes = IMU_STD[0]^2 / 6."""
    x = torch.randn(20_000, 13, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)

    def reads_acc(xs: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(len(xs), 6, dtype=xs.dtype)
        out[:, 0] = 1.0 * xs[:, 7]
        return out

    penalty = float(push_penalty(reads_acc, x, 13, 1, PUSH, gen))
    assert penalty == pytest.approx(IMU_STD[0] ** 2 / 6, rel=0.05)


def test_output_weights_measure_each_axis_in_its_noise() -> None:
    noise = np.array([NOISE, [np.nan] * 6])
    weights = output_weights(noise)
    np.testing.assert_allclose(weights[0], [1, 1, 1, 400, 400, 400])
    np.testing.assert_allclose(weights[1], 1.0)  # no estimate: unweighted
    # a correction that answers a pure force with a torque of 0.03 Nm per 20 N pays as 0.6 N would
    x = torch.zeros(1000, 7, dtype=torch.float64)

    def torque_from_force(xs: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(len(xs), 6, dtype=xs.dtype)
        out[:, 3] = xs[:, 0] * (0.03 / 20.0)
        return out

    gen = torch.Generator().manual_seed(0)
    w = torch.as_tensor(weights[:1])
    plain = float(push_penalty(torque_from_force, x, 7, 1, PUSH, gen))
    weighted = float(push_penalty(torque_from_force, x, 7, 1, PUSH, torch.Generator().manual_seed(0), w))
    assert weighted == pytest.approx(400 * plain)
