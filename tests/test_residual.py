"""The networks' structure: the factory map, the fitted affine map, and a correction whose slope is bounded.

A network (`pipeline.calib.models.SensorNet`) may not answer a small change of the wrench otherwise than a
large one: its correction of the affine map is Lipschitz with bound ``train.defaults.residual_slope`` in push
units. The data here are a free arm's whose force has a constant magnitude (a mass turning with the arm)
and whose torque channel is almost noise-free: the best memoryless predictor of its exact labels projects
each noisy force reading onto what the torque and the magnitude allow, i.e. it reads small changes of the
force off the other channels. An unbounded network learns that and reports a 1 N push far from 1 N; a
bounded one reports it as the affine map does, at every scale.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from pipeline.calib.data import Group, GroupData
from pipeline.calib.fidelity import model_fidelity
from pipeline.calib.linear import fit_linear_baseline
from pipeline.calib.models import GroupNet, LipschitzLinear, NetConfig
from pipeline.calib.pushes import PushPrior, push_penalty, residual_units
from pipeline.calib.training import (
    PUSHED_SHARE,
    NetSetting,
    _batch_loss,
    predict_inputs,
    to_tensors,
    train_network,
)

pytestmark = pytest.mark.slow  # trains networks

LEVER = np.array([0.1, 0.03, 0.0])  # m
NOISE = np.array([2.0, 2.0, 2.0, 0.01, 0.01, 0.01])  # N, Nm: the force channels are the noisy ones
PUSH = PushPrior(0.1, 20.0, 0.2)


def turning_mass(n: int, seed: int) -> GroupData:
    """A free arm's samples: force of constant magnitude (20 N) turning, torque = LEVER x force, raw =
    true + white noise (NOISE), temperature constant, exact labels; 4 logs of n / 4 samples."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    angles = np.stack([0.9 * np.sin(0.31 * t + 1.0), 1.3 * np.sin(0.17 * t) + 0.4 * np.sin(0.53 * t)], 1)
    force = 20.0 * np.stack(
        [np.cos(angles[:, 0]) * np.cos(angles[:, 1]), np.cos(angles[:, 0]) * np.sin(angles[:, 1]),
         np.sin(angles[:, 0])], 1
    )  # fmt: skip
    true = np.c_[force, np.cross(LEVER, force)]
    x = np.zeros((n, 1, 13))
    x[:, 0, :6] = true + rng.standard_normal((n, 6)) * NOISE
    x[:, 0, 6] = 30.0
    return GroupData(
        log=np.repeat(np.arange(4), n // 4),
        stamp=np.arange(n, dtype=np.int64) * 10_000_000,
        time=t,
        x=x,
        labels=true[:, None, :],
        switches=np.ones((n, 1), bool),
    )


def setting(slope: float, epochs: int = 25) -> NetSetting:
    return NetSetting(
        n_inputs=7,
        hidden=64,
        activations=("leaky_relu", "relu"),
        normalisation="standard",
        batch_size=200,
        epochs=epochs,
        lr=0.01,
        weight_decay=0.0,
        average_epochs=0.0,
        lambdas=(1.0,),
        lambda_sum=1.0,
        lambda_cut=1.0,
        lambda_prior=0.0,
        push=PUSH,
        slope=slope,
    )


@pytest.fixture(scope="module")
def trained() -> dict[float, tuple[GroupNet, GroupData]]:
    group = Group("arm", ("arm",), n_inputs=7)
    train, val = turning_mass(8000, 0), turning_mass(2000, 1)
    start = fit_linear_baseline(
        "affine", train.x, train.labels, train.switches, 1, 0.0, (1.0,), n_inputs=7, push=PUSH
    )
    torch.set_num_threads(1)
    out = {"affine": (start.predict, val)}
    for slope in (0.05, 0.0):  # the default bound, and none (the control)
        model, _ = train_network(group, train, val, setting(slope), seed=3, start=start)
        out[slope] = (lambda x, m=model: predict_inputs(m, x), val)
    return out


def push_slopes(predict, val: GroupData, force_n: float) -> np.ndarray:
    """(3,) force slopes of a model under a virtual push of `force_n` N per axis (calib.fidelity)."""
    entry = model_fidelity(predict, val.x, PushPrior(1.0, force_n, 0.2), n_inputs=7)
    return np.array(entry[0]["slopes"][:3])


def test_an_unbounded_network_reads_small_pushes_off_the_other_channels(trained) -> None:
    affine = push_slopes(*trained["affine"], 1.0)
    worst = np.abs(push_slopes(*trained[0.0], 1.0) - affine).max()
    assert worst > 0.2, f"the control network learnt no shortcut (worst 1 N slope gap {worst:.3f})"


@pytest.mark.parametrize("force_n", [1.0, 5.0, 20.0])
def test_a_bounded_network_reports_pushes_at_every_scale_as_the_affine_map(trained, force_n) -> None:
    affine = push_slopes(*trained["affine"], force_n)
    slopes = push_slopes(*trained[0.05], force_n)
    assert np.abs(slopes - affine).max() <= 0.05 * (1 + 1e-3), (slopes, affine)


def test_the_correction_is_lipschitz_with_the_bound_in_push_units() -> None:
    torch.manual_seed(0)
    config = NetConfig(n_inputs=13, hidden=32, slope=0.05)
    model = GroupNet(config, 1)
    model.reset_parameters()
    net = model.nets[0]
    with torch.no_grad():  # large weights: the bound must hold whatever training did
        for layer in net.mlp:
            if isinstance(layer, LipschitzLinear):
                layer.weight.mul_(50.0)
    units = residual_units(20.0, 0.2, 13)
    net.set_constants(np.zeros(13), units, 0.05 * units[:6])
    rng = np.random.default_rng(0)
    x = rng.standard_normal((500, 13)) * units * 5
    delta = rng.standard_normal((500, 13)) * units * rng.uniform(0.01, 3.0, (500, 1))
    with torch.no_grad():
        change = net.correction(torch.as_tensor(x + delta, dtype=torch.float32)) - net.correction(
            torch.as_tensor(x, dtype=torch.float32)
        )
    ratio = np.linalg.norm(change.numpy() / units[:6], axis=1) / np.linalg.norm(delta / units, axis=1)
    assert ratio.max() <= 0.05 * (1 + 1e-4)


def test_baking_keeps_the_outputs_and_leaves_plain_layers() -> None:
    fresh = GroupNet(NetConfig(7, 16, ("leaky_relu", "relu"), 0.05), 1)
    torch.manual_seed(2)
    fresh.reset_parameters()
    with torch.no_grad():
        for layer in fresh.nets[0].mlp:
            if isinstance(layer, torch.nn.Linear):
                layer.weight.normal_(0.0, 1.0)
    x = torch.as_tensor(turning_mass(200, 4).x[:50, 0, :7], dtype=torch.float32)
    before = fresh(x).detach()
    fresh.bake()
    assert torch.equal(fresh(x).detach(), before)
    assert not any(isinstance(m, LipschitzLinear) for m in fresh.nets[0].mlp)
    for layer in fresh.nets[0].mlp:
        if isinstance(layer, torch.nn.Linear):
            assert torch.linalg.matrix_norm(layer.weight, ord=2) <= 1.0 + 1e-6


def test_the_training_loss_holds_the_virtual_push_term() -> None:
    group = Group("arm", ("arm",), n_inputs=7)
    data = turning_mass(400, 2)
    s = setting(0.05)
    model = GroupNet(NetConfig(7, 16, ("leaky_relu", "relu"), 0.05), 1)
    torch.manual_seed(1)
    model.reset_parameters()
    with torch.no_grad():  # a correction that answers pushes
        model.nets[0].mlp[-1].weight.normal_(0.0, 0.5)
    units = residual_units(20.0, 0.2, 7)
    model.nets[0].set_constants(np.zeros(7), units, 0.05 * units[:6])
    t = to_tensors(data, 7, group)
    idx = torch.arange(len(data))
    lambdas = torch.ones(1)
    torch.set_grad_enabled(False)
    plain = _batch_loss(group, model, t, idx, lambdas, None, s, None)
    pushed = _batch_loss(group, model, t, idx, lambdas, None, s, torch.Generator().manual_seed(5))
    without = _batch_loss(group, model, t, idx, lambdas, None, replace(s, push=replace(PUSH, weight=0.0)),
                          torch.Generator().manual_seed(5))  # fmt: skip
    some = t.x[idx[: len(idx) // PUSHED_SHARE]]
    term = push_penalty(model.correction, some, 7, 1, PUSH, torch.Generator().manual_seed(5), t.push_weights)
    torch.set_grad_enabled(True)
    assert float(without) == pytest.approx(float(plain))
    assert float(term) > 0
    assert float(pushed - plain) == pytest.approx(PUSH.weight * float(term), abs=2e-6)  # float32 losses
