"""Virtual pushes: the prior that keeps a calibration faithful where its training data give no evidence.

An FT sensor exists to measure what the robot meets: a push at a hand, a load carried, a foot stepping on
something. The training logs of a limb move along a narrow relation (a free arm's wrench is its own weight
and inertia: torque ~ c x force), and a least-squares fit exploits it. It rebuilds a force from a less
noisy torque channel, or from the FT board's accelerometer, because on the relation that cancels part of
the reading's noise and hysteresis; off it (a push with another lever) the same coefficients misreport the
push by tens of %. Nothing in the labels tells the two apart.

The prior: a calibration is the factory map (raw) plus a correction, and the correction must not respond
to an external wrench the factory map reports well. A *virtual push* is a random wrench added to a
sample's raw reading, ``delta = [F; tau]`` in the sensor frame, with F ~ N(0, force^2 I3) N and
tau ~ N(0, (force * lever)^2 I3) Nm (a force of about `force` at a lever of about `lever` m). The fit
minimises, besides its labelled loss,

    weight * mean over samples of E_delta |c(x + delta) - c(x)|^2      (N^2 and Nm^2, as the loss)

where c is the correction (the calibrated wrench minus the raw one). For a linear model this is a ridge
on its wrench coefficients in the metric of pushes, in closed form (`push_gram`); for a network the
expectation is sampled, one push per sample and step (`push_penalty`), and a network that reads the FT
board's IMU also gets virtual changes of it, the wrench unchanged. A correction that cancels the
reading along a direction pays about ``weight * force^2`` per sample there; a real coupling or gain
correction of a few % pays ``weight * (0.03 force)^2``, far below what the labels gain from it. So the
labels decide where they have evidence, and elsewhere the calibration stays the factory's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # torch only where a network trains (params import this module)
    import torch

WRENCH = 6
IMU_INPUTS = 13  # a sensor's inputs with its FT board's accelerometer and gyroscope (columns 7-9, 10-12)
# a virtual change of the IMU: accelerations and turn rates a moving limb's board sees (m/s^2, rad/s)
IMU_STD = np.r_[np.full(3, 2.0), np.full(3, 0.5)]


# the units in which a network's residual is Lipschitz-bounded (`pipeline.calib.models.SensorNet`), per input
# beyond the wrench: temperature (deg C), accelerometer (m/s^2), gyroscope (rad/s)
TEMPERATURE_UNIT = 1.0
IMU_UNITS = np.r_[np.full(3, 10.0), np.full(3, 2.5)]


def residual_units(force_n: float, lever_m: float, n_inputs: int) -> np.ndarray:
    """(n_inputs,) the unit of each input (and, first 6, of each output) of a network's bounded residual:
    a push of `force_n` on force axes, `force_n * lever_m` on torque axes, then `TEMPERATURE_UNIT` and
    `IMU_UNITS`."""
    units = np.r_[np.full(3, force_n), np.full(3, force_n * lever_m), TEMPERATURE_UNIT, IMU_UNITS]
    return units[:n_inputs]


@dataclass(frozen=True)
class PushPrior:
    """The virtual pushes of a fit: weight of the term, force std (N) and lever (m)."""

    weight: float
    force_n: float
    lever_m: float
    free_lever: bool = False  # the linear fits leave the sensor's torque reference point to the labels

    @property
    def active(self) -> bool:
        return self.weight > 0 and self.force_n > 0

    def variances(self) -> np.ndarray:
        """(6,) variances of a virtual push's components: force (N^2) then torque (Nm^2)."""
        torque = self.force_n * self.lever_m
        return np.r_[np.full(3, self.force_n**2), np.full(3, torque**2)]

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """(n, 6) virtual pushes."""
        return rng.standard_normal((n, WRENCH)) * np.sqrt(self.variances())


def push_gram(
    features: Callable[..., np.ndarray],
    x: np.ndarray,
    prior: PushPrior,
    rng: np.random.Generator,
    rows: int = 4000,
    memory: np.ndarray | None = None,
) -> np.ndarray:
    """(P, P) ``sum over samples of E_delta [d d^T]`` with ``d = features(x + delta) - features(x)``.

    features: maps raw inputs (M, >= 7) to (M, P) features (with `memory`, (N, ...) a state per sample
    such as a model with memory reads, also that state, held: ``features(x, memory=...)``). x: (N, >= 7)
    one sensor's raw inputs. Exact for features linear in the wrench (the expectation of d d^T is then the
    same at every sample); otherwise estimated on `rows` (sample, push) draws and scaled to N samples.
    """
    n = len(x)
    if n == 0:
        return np.zeros((0, 0))
    pick = rng.integers(0, n, size=rows)
    base = x[pick].copy()
    pushed = base.copy()
    pushed[:, :WRENCH] += prior.draw(rng, rows)
    held = {} if memory is None else {"memory": memory[pick]}
    d = features(pushed, **held) - features(base, **held)
    return (d.T @ d) * (n / rows)


def linear_push_gram(
    features: Callable[[np.ndarray], np.ndarray],
    powers: np.ndarray,
    scale: np.ndarray,
    x: np.ndarray,
    prior: PushPrior,
    rng: np.random.Generator,
) -> np.ndarray:
    """`push_gram` of a linear-in-parameters model with monomial `powers` (P, I) of the inputs over `scale`
    (I,), I = 7 (wrench, temperature) or 6 (wrench alone): exact for the affine model (d is the push over
    the scales on the wrench features, the same at every sample), sampled for higher orders."""
    if powers.sum(axis=1).max() > 1:
        return push_gram(features, x, prior, rng)
    scale = np.asarray(scale)
    pushed = np.zeros(len(scale))  # no temperature change
    pushed[:WRENCH] = prior.variances()
    variances = pushed / scale**2
    linear = np.argmax(powers[1:], axis=1)  # the input of each linear feature (constant first)
    return np.diag(np.r_[0.0, variances[linear]]) * len(x)


def push_penalty(
    correction: Callable[[torch.Tensor], torch.Tensor],
    x: torch.Tensor,
    n_inputs: int,
    n_sensors: int,
    prior: PushPrior,
    generator: torch.Generator,
    axis_weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """The network's term: ``mean over the batch of sum_s mean_axes w_sa (c_sa(x + delta) - c_sa(x))^2``,
    `axis_weights` w (S, 6) (`output_weights`; ones if None).

    correction: maps flat inputs (B, S * n_inputs) to the corrections (B, S * 6) (N, Nm). One virtual
    push per sample and sensor, drawn from `generator`, on each sensor's raw wrench columns; with 13 inputs
    also a virtual change of the FT board's IMU (`IMU_STD`), the wrench unchanged: the accelerometer and
    gyroscope must not stand in for the wrench the sensor measures.
    """
    import torch

    std = np.sqrt(prior.variances())
    if n_inputs == IMU_INPUTS:
        std = np.r_[std, 0.0, IMU_STD]  # no temperature change
    width = len(std)
    scale = torch.as_tensor(std, dtype=x.dtype)
    delta = torch.zeros_like(x)
    noise = torch.randn((len(x), n_sensors, width), generator=generator, dtype=x.dtype) * scale
    delta.view(len(x), n_sensors, n_inputs)[:, :, :width] = noise
    change = (correction(x + delta) - correction(x)).view(len(x), n_sensors, WRENCH).square()
    if axis_weights is not None:
        change = change * axis_weights
    return change.mean(dim=2).sum(dim=1).mean()


def output_weights(noise: np.ndarray) -> np.ndarray:
    """(S, 6) weights of a network's push response per output axis, from the raw readings' noise std
    (S, 6): each axis in units of its own noise, scaled so that the force axes weigh about 1 (N^2).

    A network's correction models what the affine map cannot (temperature-dependent gains, nonlinearity,
    hysteresis): effects a push barely moves. In N^2 and Nm^2 a torque's change would count for
    nothing beside a force's (0.03 Nm of noise against 0.6 N); measured in each axis's noise a network
    cannot answer a sideways push at a sole with a torque it never saw. Axes without a noise estimate
    weigh 1.
    """
    noise = np.asarray(noise, dtype=np.float64)
    ok = np.isfinite(noise) & (noise > 0)
    count = ok[:, :3].sum(axis=1, keepdims=True)
    force = np.where(ok[:, :3], noise[:, :3], 0.0).sum(axis=1, keepdims=True) / np.maximum(count, 1)
    weights = (force / np.where(ok, noise, 1.0)) ** 2
    return np.where(ok & (count > 0), weights, 1.0)
