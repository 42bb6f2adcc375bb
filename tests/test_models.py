"""calib.models: switched losses against hand computation, baselines recovering known maps, model files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.calib.linear import _monomials, fit_linear_baseline, monomial_powers
from pipeline.calib.losses import sum_in_sole, switched_loss
from pipeline.calib.models import GroupNet, NetConfig, load_model, normalisation_constants, save_model
from pipeline.calib.scores import wrench_errors
from pipeline.core.errors import DataError
from tests.factories.labelled import TRANSFORMS

NAN = float("nan")


# --- losses --------------------------------------------------------------------------------------


def test_leg_loss_eq_5_4_by_hand() -> None:
    # 3 samples, 1 sensor; sample 1 has no exact label (switch 0, NaN label): adds 0 but counts in the mean.
    pred = torch.tensor([[[1.0, 2, 3, 0, 0, 1]], [[5.0, 5, 5, 5, 5, 5]], [[0.0, 0, 0, 0, 0, 0]]])
    label = torch.tensor([[[0.0, 0, 0, 0, 0, 0]], [[NAN] * 6], [[1.0, 1, 1, 1, 1, 1]]])
    switch = torch.tensor([[True], [False], [True]])
    lam = 2.5
    loss, terms = switched_loss(pred, label, switch, torch.tensor([lam]))
    # per-sample alpha * lambda * mse over 6 components, then the batch mean
    by_hand = (lam * (1 + 4 + 9 + 0 + 0 + 1) / 6 + 0 + lam * 6 / 6) / 3
    assert math.isfinite(loss.item())
    assert loss.item() == pytest.approx(by_hand, rel=1e-6)
    assert terms["s0"].item() == pytest.approx(by_hand, rel=1e-6)


def test_nan_labels_give_finite_gradients() -> None:
    pred = torch.zeros(2, 1, 6, requires_grad=True)
    label = torch.tensor([[[NAN] * 6], [[1.0] * 6]])
    loss, _ = switched_loss(pred, label, torch.tensor([[False], [True]]), torch.tensor([1.0]))
    loss.backward()
    assert torch.isfinite(pred.grad).all()
    assert (pred.grad[0] == 0).all()  # no label: no gradient
    np.testing.assert_allclose(pred.grad[1, 0].numpy(), -2 * 1.0 / 6 / 2)  # d/dp mean((p - 1)^2 / 6) / 2


def test_foot_loss_eqs_5_6_to_5_12_by_hand() -> None:
    rng = np.random.default_rng(0)
    b = 5
    pred = rng.normal(size=(b, 2, 6))
    label = rng.normal(size=(b, 2, 6))
    sum_label = rng.normal(size=(b, 6))
    sw = np.array([[1, 1], [1, 0], [0, 0], [0, 1], [0, 0]], dtype=bool)
    sw_pair = np.array([1, 1, 1, 0, 0], dtype=bool)
    alpha_sum = sw_pair & ~(sw[:, 0] & sw[:, 1])  # eq. 5.12: sum term only where the parts are not both exact
    label[~sw] = np.nan
    sum_label[~sw_pair] = np.nan
    lf, lr, ls = 3.0, 0.5, 2.0
    loss, terms = switched_loss(
        torch.tensor(pred),
        torch.tensor(label),
        torch.tensor(sw),
        torch.tensor([lf, lr]),
        torch.tensor(sum_label),
        torch.tensor(alpha_sum),
        torch.tensor(TRANSFORMS),
        ls,
    )
    # independent reference: loop over samples, transforms applied as explicit matrix products
    total = np.zeros(b)
    for i in range(b):
        if sw[i, 0]:
            total[i] += lf * np.mean((label[i, 0] - pred[i, 0]) ** 2)
        if sw[i, 1]:
            total[i] += lr * np.mean((label[i, 1] - pred[i, 1]) ** 2)
        if alpha_sum[i]:
            nn_sum = TRANSFORMS[0] @ pred[i, 0] + TRANSFORMS[1] @ pred[i, 1]
            total[i] += ls * np.mean((sum_label[i] - nn_sum) ** 2)
    assert loss.item() == pytest.approx(total.mean(), rel=1e-10)
    assert sum(t.item() for t in terms.values()) == pytest.approx(total.mean(), rel=1e-10)
    assert set(terms) == {"s0", "s1", "sum"}


def test_sum_of_expected_wrenches_in_sole_frame_eq_5_9() -> None:
    rng = np.random.default_rng(1)
    f = rng.normal(size=(4, 2, 6))
    got = sum_in_sole(torch.tensor(f), torch.tensor(TRANSFORMS)).numpy()
    np.testing.assert_allclose(got, f[:, 0] @ TRANSFORMS[0].T + f[:, 1] @ TRANSFORMS[1].T, rtol=1e-12)


def test_all_switches_zero_contribute_nothing() -> None:
    pred = torch.randn(3, 2, 6)
    label = torch.full((3, 2, 6), NAN)
    loss, _ = switched_loss(
        pred,
        label,
        torch.zeros(3, 2, dtype=torch.bool),
        torch.ones(2),
        torch.full((3, 6), NAN),
        torch.zeros(3, dtype=torch.bool),
        torch.tensor(TRANSFORMS),
    )
    assert loss.item() == 0.0


# --- baselines -----------------------------------------------------------------------------------


def _inputs(rng: np.random.Generator, n: int, sensors: int = 1) -> np.ndarray:
    f = rng.normal(size=(n, sensors, 6)) * np.array([100, 100, 300, 5, 5, 2])
    temp = 30 + 5 * rng.random((n, sensors, 1))
    return np.concatenate([f, temp], axis=2)


def test_affine_baseline_recovers_an_affine_temperature_map() -> None:
    rng = np.random.default_rng(2)
    x = _inputs(rng, 400)
    gain = np.eye(6) + 0.03 * rng.normal(size=(6, 6))
    drift, offset = rng.normal(size=6), rng.normal(size=6) * 20
    truth = x[:, 0, :6] @ gain.T + (x[:, 0, 6:7] - 25) * drift + offset
    switches = rng.random((400, 1)) < 0.7
    labels = np.where(switches[:, :, None], truth[:, None], np.nan)
    model = fit_linear_baseline("affine", x, labels, switches, order=1, ridge=0.0, lambdas=[1.0])
    np.testing.assert_allclose(model.predict(x)[:, 0], truth, rtol=1e-8, atol=1e-8)  # also where unlabelled


def test_polynomial_baseline_recovers_its_order_and_not_a_lower_one() -> None:
    rng = np.random.default_rng(3)
    x = _inputs(rng, 2000)
    z = x[:, 0, :7] / np.array([100, 100, 300, 5, 5, 2, 30])
    truth = x[:, 0, :6] + 2 * z[:, [2]] ** 3 + z[:, [0]] * z[:, [6]] - 0.5 * z[:, [3]] ** 2 + 4
    switches = np.ones((2000, 1), dtype=bool)
    poly3 = fit_linear_baseline("poly3", x, truth[:, None], switches, order=3, ridge=0.0, lambdas=[1.0])
    np.testing.assert_allclose(poly3.predict(x)[:, 0], truth, rtol=1e-7, atol=1e-6)
    poly2 = fit_linear_baseline("poly2", x, truth[:, None], switches, order=2, ridge=0.0, lambdas=[1.0])
    assert np.abs(poly2.predict(x)[:, 0] - truth).max() > 0.1


def test_pair_baseline_uses_part_and_sum_labels_jointly() -> None:
    # Parts labelled in the first third only, sums in the rest: the coupled normal equations still
    # recover each sensor's own affine map, so the parts are right where they were never labelled.
    rng = np.random.default_rng(4)
    n = 900
    x = _inputs(rng, n, sensors=2)
    truth = np.empty((n, 2, 6))
    for s in range(2):
        gain = np.eye(6) + 0.03 * rng.normal(size=(6, 6))
        truth[:, s] = (
            x[:, s, :6] @ gain.T + (x[:, s, 6:7] - 25) * rng.normal(size=6) + rng.normal(size=6) * 20
        )
    switches = np.zeros((n, 2), dtype=bool)
    switches[: n // 3] = True
    sum_switch = ~switches.all(axis=1)
    labels = np.where(switches[:, :, None], truth, np.nan)
    sum_label = np.where(
        sum_switch[:, None], truth[:, 0] @ TRANSFORMS[0].T + truth[:, 1] @ TRANSFORMS[1].T, np.nan
    )
    model = fit_linear_baseline(
        "affine",
        x,
        labels,
        switches,
        order=1,
        ridge=0.0,
        lambdas=[1.0, 1.0],
        sum_label=sum_label,
        alpha_sum=sum_switch,
        transforms=TRANSFORMS,
    )
    np.testing.assert_allclose(model.predict(x), truth, rtol=1e-7, atol=1e-7)


def test_baseline_without_labels_is_a_data_error() -> None:
    x = _inputs(np.random.default_rng(5), 10)
    with pytest.raises(DataError, match="no training sample with an exact label"):
        fit_linear_baseline("affine", x, np.full((10, 1, 6), np.nan), np.zeros((10, 1), bool), 1, 0.0, [1.0])


def test_monomial_count() -> None:
    # C(7 + n, n) monomials of degree <= n in 7 variables
    assert [len(monomial_powers(7, n)) for n in (1, 2, 3, 4)] == [8, 36, 120, 330]


@pytest.mark.parametrize("chunk", [3, 2048])
def test_monomials_are_the_products_factor_by_factor_in_variable_order(chunk: int) -> None:
    # the features of the polynomial baselines (and of their exported graphs): every product computed as
    # 1 * z_0 ... * z_1 ..., one factor at a time in ascending variable order, bit for bit, also for
    # powers whose prefixes are not monomials of the list, and across chunks of samples
    z = np.random.default_rng(3).standard_normal((10, 7)) * 3.0
    powers = np.vstack([monomial_powers(7, 4), [[0, 2, 0, 0, 1, 0, 3]], [[5, 0, 0, 0, 0, 0, 0]]])
    expected = np.empty((len(z), len(powers)))
    for j, p in enumerate(powers):
        value = np.ones(len(z))
        for v, k in enumerate(p):
            for _ in range(k):
                value = value * z[:, v]
        expected[:, j] = value
    got = _monomials(z, powers, chunk=chunk)
    assert got.flags["C_CONTIGUOUS"]
    assert np.array_equal(got, expected)


# --- networks and files --------------------------------------------------------------------------


def test_normalisation_constants() -> None:
    x = np.array([[1.0, -4.0, 7.0], [3.0, 2.0, 7.0]])
    offset, scale = normalisation_constants(x, "max")
    np.testing.assert_allclose(offset, 0)
    np.testing.assert_allclose(scale, [3.0, 4.0, 7.0])
    offset, scale = normalisation_constants(x, "standard")
    np.testing.assert_allclose(offset, [2.0, -1.0, 7.0])
    np.testing.assert_allclose(scale, [1.0, 3.0, 1.0])  # a constant column keeps scale 1


def test_network_corrects_on_top_of_the_raw_wrench() -> None:
    model = GroupNet(NetConfig(7), 2)  # last layers zeroed: the output is the raw wrench
    for net in model.nets:
        torch.nn.init.zeros_(net.mlp[-1].weight)
        torch.nn.init.zeros_(net.mlp[-1].bias)
    x = torch.randn(4, 14)
    np.testing.assert_array_equal(model(x).detach().numpy(), torch.cat([x[:, :6], x[:, 7:13]], dim=1).numpy())


def test_untrained_network_is_its_affine_baseline() -> None:
    """The correction's output layer starts at zero: before any step the network is the affine map."""
    rng = np.random.default_rng(5)
    x = _inputs(rng, 300, sensors=2)
    gain = np.eye(6) + 0.03 * rng.normal(size=(6, 6))
    truth = x[..., :6] @ gain.T + (x[..., 6:7] - 25) * rng.normal(size=6) + rng.normal(size=6) * 20
    switches = np.ones((300, 2), dtype=bool)
    affine = fit_linear_baseline("affine", x, truth, switches, order=1, ridge=0.0, lambdas=[1.0, 1.0])
    torch.manual_seed(0)
    model = GroupNet(NetConfig(7), 2)
    model.reset_parameters()
    for s, net in enumerate(model.nets):
        net.set_affine(*affine.affine_map(s))
    with torch.no_grad():
        out = model(torch.tensor(x.reshape(300, 14), dtype=torch.float64).float()).double().numpy()
    # float32 arithmetic on wrenches of up to ~1000 N
    np.testing.assert_allclose(out.reshape(300, 2, 6), affine.predict(x), atol=2e-3)
    np.testing.assert_allclose(affine.predict(x), truth, atol=1e-8)
    poly = fit_linear_baseline("poly2", x, truth, switches, order=2, ridge=0.0, lambdas=[1.0, 1.0])
    with pytest.raises(ValueError, match="not an affine model"):
        poly.affine_map(0)


def test_save_and_load_model_weights_only(tmp_path: Path) -> None:
    torch.manual_seed(0)
    model = GroupNet(NetConfig(13, hidden=16, activations=("leaky_relu", "relu", "tanh")), 2)
    model.reset_parameters()
    for net in model.nets:
        net.set_constants(np.arange(13.0), np.arange(1.0, 14.0), np.full(6, 3.0))
    save_model(tmp_path / "nn13", model, {"sensors": ["a", "b"]})
    loaded, config = load_model(tmp_path / "nn13")
    x = torch.randn(8, 26)
    np.testing.assert_array_equal(loaded(x).detach().numpy(), model.eval()(x).detach().numpy())
    assert config["sensors"] == ["a", "b"] and config["net"]["n_inputs"] == 13
    # the weights file is plain tensors: torch's weights-only unpickler reads it
    state = torch.load(tmp_path / "nn13.pt", weights_only=True)
    assert all(isinstance(v, torch.Tensor) for v in state.values())


def test_load_model_refuses_a_pickled_module(tmp_path: Path) -> None:
    model = GroupNet(NetConfig(7), 1)
    save_model(tmp_path / "nn7", model)
    torch.save(model, tmp_path / "nn7.pt")  # a whole pickled module: loading it would run code
    with pytest.raises(DataError, match="nn7.pt: holds objects other than tensors"):
        load_model(tmp_path / "nn7")


def test_wrench_errors() -> None:
    pred = np.array([[1.0, 0, 0, 0, 0, 2], [1.0, 0, 0, 0, 0, 0]])
    errors = wrench_errors(pred, np.zeros((2, 6)))
    assert errors["mse"] == pytest.approx(6 / 12)
    assert errors["rmse_force"] == pytest.approx(math.sqrt(2 / 6))
    assert errors["mae_tz"] == pytest.approx(1.0)
    assert errors["samples"] == 2
