"""Training one group network: Adam on the switched losses, the epoch of lowest validation error kept."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from pipeline.calib.cuts import cut_sums
from pipeline.calib.data import Group, GroupData, group_errors
from pipeline.calib.excitation import noise_std
from pipeline.calib.linear import LinearBaseline
from pipeline.calib.losses import switched_loss
from pipeline.calib.models import WRENCH, GroupNet, NetConfig, normalisation_constants
from pipeline.calib.params import GroupParams
from pipeline.calib.pushes import PushPrior, output_weights, push_penalty, residual_units

PUSHED_SHARE = 4  # one sample of a batch in this many gets a virtual push (pipeline.calib.pushes)


@dataclass(frozen=True)
class NetSetting:
    """Everything one network training depends on (a group's params with one trial's values)."""

    n_inputs: int
    hidden: int
    activations: tuple[str, ...]
    normalisation: str
    batch_size: int
    epochs: int
    lr: float
    weight_decay: float
    average_epochs: float  # EMA horizon of the weights, epochs (0: none)
    lambdas: tuple[float, ...]  # per sensor
    lambda_sum: float
    lambda_cut: float  # each cut set's sum term (groups of several sensors)
    lambda_prior: float  # pull towards the affine map where a sensor has no exact label of its own
    push: PushPrior  # virtual pushes: the correction's response to them is penalised
    slope: float = 0.0  # the residual's Lipschitz bound in push units (0: unbounded)

    @classmethod
    def of(cls, gp: GroupParams, n_inputs: int, values: Mapping[str, Any] | None = None) -> NetSetting:
        v = {**gp.hyperparameters(), **(values or {})}
        if gp.sensors is not None:
            lambdas = (gp.lambda_expected,) * len(gp.sensors)
        elif gp.sensor is not None:
            lambdas = (gp.lambda_expected,)
        else:
            lambdas = (v["lambda_front"], v["lambda_rear"])
        return cls(
            n_inputs,
            int(v["hidden"]),
            gp.activations,
            str(v["normalisation"]),
            int(v["batch_size"]),
            int(v["epochs"]),
            float(v["lr"]),
            float(v["weight_decay"]),
            float(gp.average_epochs),
            tuple(map(float, lambdas)),
            float(v["lambda_sum"]),
            float(gp.lambda_cut),
            float(gp.lambda_prior),
            gp.push,
            float(gp.residual_slope),
        )


@dataclass
class Tensors:
    x: torch.Tensor  # (N, S * n_inputs) float32
    labels: torch.Tensor  # (N, S, 6)
    switches: torch.Tensor  # (N, S) bool
    sum_label: torch.Tensor | None
    alpha_sum: torch.Tensor | None
    cut_labels: torch.Tensor | None = None  # (N, C, 6)
    cut_alpha: torch.Tensor | None = None  # (N, C) bool
    poses: torch.Tensor | None = None  # (N, P, 12)
    prior: torch.Tensor | None = None  # (N, S, 6) the affine map's output, N and Nm
    push_weights: torch.Tensor | None = None  # (S, 6) the push response's weight per output axis


def one_thread() -> None:
    """One torch CPU thread in this process, deterministic algorithms only: where a network trains.

    MKL splits a matrix product between its threads and rounds by the split, in every mode of its
    conditional reproducibility on AMD CPUs (measured on an EPYC with AVX-512: (6 x 128) @ (128 x 16) ends
    in other last bits on 2 threads than on 1, with MKL_CBWR AVX2,STRICT and COMPATIBLE alike), and so does
    ATen above 32768 elements of a reduction; a network that is the same on any machine therefore trains
    on one thread, and the stages run their parallel work in processes (`pipeline.core.parallel`). The
    networks are small enough that more threads would not make them faster. One thread is also what lets a
    process fork: GNU OpenMP's threads do not survive a fork, and a child of a parent that computed with
    several waits for them forever."""
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)


def flat_inputs(data: GroupData, n_inputs: int) -> np.ndarray:
    return data.x[:, :, :n_inputs].reshape(len(data), -1)


def to_tensors(
    data: GroupData, n_inputs: int, group: Group | None = None, prior: np.ndarray | None = None
) -> Tensors:
    """The tensors of `data` for training; `prior` (N, S, 6): the affine map's output on it, or None."""
    f32 = torch.float32
    cuts = group is not None and bool(group.cuts)
    return Tensors(
        x=torch.as_tensor(flat_inputs(data, n_inputs), dtype=f32),
        labels=torch.as_tensor(data.labels, dtype=f32),
        switches=torch.as_tensor(data.switches),
        sum_label=None if data.sum_label is None else torch.as_tensor(data.sum_label, dtype=f32),
        alpha_sum=None if data.sum_switch is None else torch.as_tensor(data.alpha_sum),
        cut_labels=torch.as_tensor(data.cut_labels, dtype=f32) if cuts else None,
        cut_alpha=torch.as_tensor(data.cut_alpha(group.cuts)) if cuts else None,
        poses=torch.as_tensor(data.poses, dtype=f32) if cuts else None,
        prior=None if prior is None else torch.as_tensor(prior, dtype=f32),
    )


def predict(model: GroupNet, data: GroupData) -> np.ndarray:
    """(N, S, 6) float64 calibrated wrenches of a network on `data`."""
    return predict_inputs(model, data.x)


def predict_inputs(model: GroupNet, x: np.ndarray) -> np.ndarray:
    """(N, S, 6) float64 calibrated wrenches of a network from raw inputs x (N, S, >= its inputs)."""
    flat = x[:, :, : model.config.n_inputs].reshape(len(x), -1)
    with torch.no_grad():
        out = model.eval()(torch.as_tensor(flat, dtype=torch.float32)).numpy().astype(np.float64)
    return out.reshape(len(x), model.n_sensors, WRENCH)


def _batch_loss(
    group: Group,
    model: GroupNet,
    t: Tensors,
    idx: torch.Tensor,
    lambdas: torch.Tensor,
    transforms: torch.Tensor | None,
    setting: NetSetting,
    pushes: torch.Generator | None = None,
) -> torch.Tensor:
    """The switched loss of the samples `idx` (a batch), with the virtual pushes' term when `pushes` (their
    random stream) is given and the setting has a push weight."""
    pred = model(t.x[idx]).view(len(idx), model.n_sensors, WRENCH)
    cuts = None
    if t.cut_labels is not None:
        cuts = (cut_sums(group.cuts, pred, t.poses[idx]), t.cut_labels[idx], t.cut_alpha[idx])
    loss, _ = switched_loss(
        pred,
        t.labels[idx],
        t.switches[idx],
        lambdas,
        None if t.sum_label is None else t.sum_label[idx],
        None if t.alpha_sum is None else t.alpha_sum[idx],
        transforms,
        setting.lambda_sum,
        cuts,
        setting.lambda_cut,
    )
    if t.prior is not None:
        # where a sensor has no exact label of its own (a leg in double support), the cut-set sums leave
        # some directions free (one leg's error cancelled by the other's): take the affine map's there
        free = (~t.switches[idx]).float()  # (B, S)
        gap = ((pred - t.prior[idx]) ** 2).mean(dim=2)  # (B, S)
        loss = loss + setting.lambda_prior * (free * gap).sum(dim=1).mean()
    if pushes is not None and setting.push.active:
        # on a quarter of the batch (already in random order): the expectation stays the same, and the extra
        # forward and backward pass costs a quarter of the step instead of doubling it
        some = t.x[idx[: max(1, len(idx) // PUSHED_SHARE)]]
        penalty = push_penalty(
            model.correction, some, setting.n_inputs, model.n_sensors, setting.push, pushes, t.push_weights
        )
        loss = loss + setting.push.weight * penalty
    return loss


def train_epoch(
    group: Group,
    model: torch.nn.Module,
    t: Tensors,
    lambdas: torch.Tensor,
    transforms: torch.Tensor | None,
    setting: NetSetting,
    optimiser: torch.optim.Optimizer,
    generator: torch.Generator,
    average: WeightAverage | None = None,
    pushes: torch.Generator | None = None,
) -> float:
    """One pass of Adam over every sample of `t` in batches of ``setting.batch_size``, in a random order
    drawn from `generator`, the moving average of the weights updated after each step; the mean batch loss.
    `model` maps t.x's rows to (B, S * 6) calibrated wrenches (a `GroupNet`, or any module of that form)."""
    model.train()
    n = len(t.x)
    order = torch.randperm(n, generator=generator)
    total = 0.0
    for first in range(0, n, setting.batch_size):
        batch = order[first : first + setting.batch_size]
        loss = _batch_loss(group, model, t, batch, lambdas, transforms, setting, pushes)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        if average is not None:
            average.update()
        total += float(loss.detach())
    return total / max(math.ceil(n / setting.batch_size), 1)


def _train_loss(
    group: Group,
    model: GroupNet,
    t: Tensors,
    lambdas: torch.Tensor,
    transforms: torch.Tensor | None,
    setting: NetSetting,
) -> float:
    """The switched loss over every training sample (the loss of epoch -1, before any step)."""
    with torch.no_grad():
        return float(
            _batch_loss(group, model.eval(), t, torch.arange(len(t.x)), lambdas, transforms, setting)
        )


def _val_error(group: Group, val: GroupData, model: GroupNet) -> float:
    """Validation rmse_labelled of `model`; inf for a diverged network (the worst, not NaN)."""
    err = group_errors(group, val, predict(model, val))["rmse_labelled"]
    return err if math.isfinite(err) else math.inf


EpochCallback = Callable[[int, float, float], None]  # (epoch, mean training loss, validation error)


class WeightAverage:
    """Exponential moving average of a model's parameters with a horizon of `steps` optimiser steps
    (Polyak averaging): the averaged network moves less from one step to the next than the trained one,
    so which epoch is best, and its error, depend less on the last steps' noise."""

    def __init__(self, model: GroupNet, steps: float) -> None:
        self.rate = 1.0 / max(steps, 1.0)
        self.params = list(model.parameters())
        self.average = [p.detach().clone() for p in self.params]

    def update(self) -> None:
        with torch.no_grad():
            for avg, p in zip(self.average, self.params, strict=True):
                avg.lerp_(p, self.rate)

    @contextmanager
    def applied(self) -> Iterator[None]:
        """The model holds the averaged weights inside the block, its trained ones again after it."""
        saved = [p.detach().clone() for p in self.params]
        with torch.no_grad():
            for p, avg in zip(self.params, self.average, strict=True):
                p.copy_(avg)
        try:
            yield
        finally:
            with torch.no_grad():
                for p, value in zip(self.params, saved, strict=True):
                    p.copy_(value)


def _new_network(
    group: Group, train: GroupData, setting: NetSetting, start: LinearBaseline | None
) -> GroupNet:
    """A freshly initialised network with the normalisation of `train`; equal to `start` if given."""
    config = NetConfig(setting.n_inputs, setting.hidden, setting.activations, setting.slope)
    model = GroupNet(config, len(group.sensors))
    model.reset_parameters()
    for s, net in enumerate(model.nets):
        x = train.x[:, s, : setting.n_inputs]
        offset, scale = normalisation_constants(x, setting.normalisation)
        out_scale = normalisation_constants(x[:, :WRENCH], "standard")[1]
        if setting.slope > 0:  # the residual's slope at most `slope` in push units (SensorNet)
            scale = residual_units(setting.push.force_n, setting.push.lever_m, setting.n_inputs)
            out_scale = setting.slope * scale[:WRENCH]
        net.set_constants(offset, scale, out_scale)
        if start is not None:
            net.set_affine(*start.affine_map(s))
    return model


def train_network(
    group: Group,
    train: GroupData,
    val: GroupData,
    setting: NetSetting,
    seed: int,
    on_epoch: EpochCallback | None = None,
    start: LinearBaseline | None = None,
) -> tuple[GroupNet, list[dict[str, float]]]:
    """Train one group network with Adam on the switched loss; keep the epoch of lowest validation error.

    `train` holds only samples with at least one term in the loss. Weight init and batch order come from
    `seed`. `start` is the affine baseline the networks correct (`pipeline.calib.models`); the untrained
    network equals it, scored as epoch -1 (loss NaN) and kept if no epoch beats it on validation. With
    ``setting.average_epochs`` > 0 the network scored and kept at each epoch is the moving average of the
    weights (`WeightAverage`) over that many epochs of steps.
    `on_epoch` may raise (e.g. optuna.TrialPruned) to stop. Returns the model at its best epoch (eval mode)
    and the per-epoch history [{epoch, loss, val_rmse}].
    """
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    pushes = torch.Generator().manual_seed((seed + 1) % 2**63)  # the virtual pushes' own stream
    model = _new_network(group, train, setting, start)
    optimiser = torch.optim.Adam(model.parameters(), lr=setting.lr, weight_decay=setting.weight_decay)
    history: list[dict[str, float]] = []
    best_state, best_err = None, math.inf
    prior = start.predict(train.x) if start is not None and setting.lambda_prior > 0 else None
    t = to_tensors(train, setting.n_inputs, group, prior)
    noise = np.stack(
        [noise_std(train.x[:, s, :WRENCH], train.log, train.stamp) for s in range(t.labels.shape[1])]
    )
    t.push_weights = torch.as_tensor(output_weights(noise), dtype=torch.float32)
    lambdas = torch.tensor(setting.lambdas, dtype=torch.float32)
    transforms = None if group.transforms is None else torch.as_tensor(group.transforms, dtype=torch.float32)
    if start is not None:
        best_err = _val_error(group, val, model)
        best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        loss = _train_loss(group, model, t, lambdas, transforms, setting)
        history.append({"epoch": -1, "loss": loss, "val_rmse": best_err})
    steps = math.ceil(len(train) / setting.batch_size)
    average = WeightAverage(model, setting.average_epochs * steps) if setting.average_epochs > 0 else None
    for epoch in range(setting.epochs):
        loss = train_epoch(
            group, model, t, lambdas, transforms, setting, optimiser, generator, average, pushes
        )
        with average.applied() if average is not None else nullcontext():
            err = _val_error(group, val, model)
            if err < best_err:
                best_err = err
                best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        history.append({"epoch": epoch, "loss": loss, "val_rmse": err})
        if on_epoch is not None:
            on_epoch(epoch, history[-1]["loss"], err)
    if best_state is not None:
        model.load_state_dict(best_state)
    model.bake()
    return model.eval(), history
