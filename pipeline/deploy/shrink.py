"""What a re-zeroing applies: each estimated offset change, shrunk towards zero where it is not significant
against the stretch's noise and the labels' model error.

The labels' model error. The exact labels of a still stretch follow the URDF, whose link masses and centres
of mass are not the robot's (CAD masses, cables, covers): for that pose they are off by a fixed amount that
averaging over the stretch does not reduce. A re-zeroing folds it into the offsets it estimates, while the
calibration as trained averaged such errors over many poses; an estimated change of their size is no
evidence that the offset moved. Their size (1 sigma) per axis of an equation's label L (N, Nm, the mean
over the stretch), the free side of the cut taken as one body of the label's weight, its mass off by
``mass_rel`` (relative) and its centre of mass by ``com_m`` (m, per axis)::

    force axis k:   mass_rel |L_f,k|                      (the weight's error lies along the weight)
    torque axis k:  sqrt((mass_rel L_t,k)^2 + com_m^2 (|L_f|^2 - L_f,k^2))   (a moved COM: dc x weight)

A sensor with an exact label of its own takes its label's (the calibration's slope taken as one); through
sums only, the solve's own linear map from each sum's label to the offsets (`pipeline.deploy.rezero`)
carries theirs. A log held still in several poses also shows the part that differs from pose to pose
(the labels' error, and the calibration's own, which the labels cannot tell apart from an offset): the
spread of the offsets estimated from each pose alone (`pipeline.deploy.rezeroing.pose_dependence`) joins
the floor in quadrature. Measured on the default run's later day (offsets moved by temperature only): on
the pole the leg sensors' labels were off by up to 1 N and 0.4 Nm, their floor 0.2-0.8 N and 0.2-0.4 Nm;
the feet's off by under 0.05 N, their floor 0.01-0.02 N.

Shrinkage. Per axis the total uncertainty u = sqrt(std^2 + floor^2) (std: the noise's, from the stretch),
the threshold tau = ``significance`` x u, and the applied change ``estimate x w(|estimate| / tau)`` with
w = 0 up to 1, 1 from 2 and the smoothstep between: nothing of a change within the threshold, a change
beyond twice it (a knock) applied as estimated, and continuous in between (Lipschitz constant below 3):
a tiny change of the inputs gives a tiny change of the applied offsets, never a switch that flips between
machines whose inputs differ in the last bits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LabelError:
    """The URDF's inertial error the labels carry (1 sigma): the free side's mass, relative, and its
    centre of mass, m per axis."""

    mass_rel: float
    com_m: float

    def label_floor(self, label: np.ndarray) -> np.ndarray:
        """(6,) the error (1 sigma, N / Nm) of a still stretch's label `label` (6,) N / Nm (module
        docstring)."""
        force, torque = np.asarray(label[:3], float), np.asarray(label[3:], float)
        weight = float(force @ force)
        moved = self.com_m**2 * np.maximum(weight - force**2, 0.0)
        return np.concatenate([self.mass_rel * np.abs(force), np.sqrt((self.mass_rel * torque) ** 2 + moved)])


def weight(ratio: np.ndarray) -> np.ndarray:
    """The share of an estimate applied at |estimate| / threshold = `ratio` (>= 0): 0 up to 1, 1 from 2, the
    smoothstep ``3 t^2 - 2 t^3`` of ``t = ratio - 1`` between."""
    t = np.clip(np.asarray(ratio, float) - 1.0, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def shrink(estimate: np.ndarray, threshold: np.ndarray) -> np.ndarray:
    """The applied changes (same shape, N / Nm) of estimated ones given their thresholds (> 0)."""
    estimate = np.asarray(estimate, float)
    return estimate * weight(np.abs(estimate) / np.maximum(np.asarray(threshold, float), 1e-12))


def thresholds(std: np.ndarray, floor: np.ndarray, significance: float) -> np.ndarray:
    """tau = significance x sqrt(std^2 + floor^2) per axis, N / Nm."""
    return significance * np.sqrt(np.asarray(std, float) ** 2 + np.asarray(floor, float) ** 2)


def reasons(estimate: np.ndarray, applied: np.ndarray, threshold: np.ndarray) -> list[str]:
    """Per axis (6,) what was applied and why not: ``applied``, ``shrunk to <share> %`` or ``not applied``,
    with |estimate| beside the threshold (N on force axes, Nm on torque axes)."""
    out = []
    for k, (d, a, tau) in enumerate(zip(estimate, applied, threshold, strict=True)):
        unit = "N" if k < 3 else "Nm"
        size = f"|{d:.3g}| {unit} vs threshold {tau:.3g} {unit}"
        if a == d:
            out.append(f"applied ({size}: beyond twice the threshold)")
        elif a == 0.0:
            out.append(f"not applied ({size}: within the noise and label error)")
        else:
            out.append(f"shrunk to {100.0 * a / d:.0f} % ({size})")
    return out
