"""What the training labels show of each sensor: the directions of wrench space they excite, and how far a
sample lies outside them.

A calibration is only evidence-based along the directions its labelled training samples move in; along
the others it is the factory map's (the virtual pushes' prior, `pipeline.calib.pushes`). Per sensor:

- the noise of its raw reading per axis (N, Nm), from second differences of consecutive samples (the
  motions and their wrenches lie below a few Hz, so at 100 Hz a second difference is noise);
- the excited directions: the singular value decomposition of its exact labels, centred and divided by
  that noise per axis (*noise-whitened*): each direction's standard deviation is in units of the noise, so
  a direction along which the labels move less than `WEAK` noise standard deviations carries no evidence;
- the relation the labels follow: ``torque ~ c x force`` fitted by least squares (c in m) and the share of
  the torque variance it explains; a free limb's wrenches lie on it (its own weight and inertia);
- the *outside distance* of a sample: the norm of its whitened, centred wrench along the weakly excited
  directions, in noise units (0 on the training relation; a push with another lever shows at once).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

WRENCH = 6
WEAK = 10.0  # a direction whose labels' std is below this many noise stds is weakly excited
OUTSIDE = 10.0  # a sample farther than this (noise stds) along the weak directions is off the training span
_STEP_TOLERANCE = 1.5  # consecutive samples: stamps at most this many median periods apart


def noise_std(x: np.ndarray, log: np.ndarray, stamp_ns: np.ndarray) -> np.ndarray:
    """(6,) noise std per axis of raw wrenches x (N, 6) from second differences of consecutive samples of
    each log (robust: 1.4826 MAD, so impacts and steps do not count); N and Nm."""
    rows = []
    for li in np.unique(log):
        idx = np.flatnonzero(log == li)
        if len(idx) < 3:
            continue
        step = np.diff(stamp_ns[idx])
        regular = step < _STEP_TOLERANCE * np.median(step)
        ok = regular[:-1] & regular[1:]
        w = x[idx]
        rows.append((w[2:] - 2 * w[1:-1] + w[:-2])[ok])
    if not rows or not sum(len(r) for r in rows):
        return np.full(WRENCH, np.nan)
    d2 = np.concatenate(rows)
    mad = 1.4826 * np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
    return mad / np.sqrt(6.0)  # var(second difference) = 6 var(white noise)


def lever_relation(labels: np.ndarray) -> tuple[np.ndarray, float]:
    """(c (3,) m, R^2): least-squares ``torque = c x force`` through the centred labels (N, 6)."""
    f = labels[:, :3] - labels[:, :3].mean(axis=0)
    t = labels[:, 3:] - labels[:, 3:].mean(axis=0)
    # c x f = -f x c = -[f]x c: stack the 3 rows of -[f]x for every sample
    zeros = np.zeros(len(f))
    skew = np.stack(
        [
            np.stack([zeros, f[:, 2], -f[:, 1]], axis=1),
            np.stack([-f[:, 2], zeros, f[:, 0]], axis=1),
            np.stack([f[:, 1], -f[:, 0], zeros], axis=1),
        ],
        axis=1,
    )  # (N, 3, 3)
    a = skew.reshape(-1, 3)
    c, *_ = np.linalg.lstsq(a, t.reshape(-1), rcond=None)
    resid = t.reshape(-1) - a @ c
    total = float(np.sum(t**2))
    return c, (1.0 - float(np.sum(resid**2)) / total) if total > 0 else float("nan")


@dataclass
class Excitation:
    """One sensor's excitation (module docstring). Directions are rows of `directions`, in whitened
    coordinates (axis a scaled by 1 / noise[a]), sorted by decreasing std."""

    sensor: str
    samples: int  # exact labels of the sensor in training
    noise: list[float]  # (6,) N, Nm
    mean: list[float]  # (6,) of the labels, N, Nm
    std: list[float]  # (6,) labels' std along each direction, noise units
    directions: list[list[float]]  # (6, 6) unit rows, whitened coordinates
    weak: int  # directions with std < WEAK
    lever_m: list[float]  # c of torque ~ c x force
    lever_r2: float  # share of the torque variance it explains

    def outside(self, wrench: np.ndarray) -> np.ndarray:
        """(N,) outside distance (noise units) of wrenches (N, 6) in the sensor frame."""
        if self.weak == 0:
            return np.zeros(len(wrench))
        z = (np.asarray(wrench, dtype=np.float64) - np.asarray(self.mean)) / np.asarray(self.noise)
        basis = np.asarray(self.directions)[WRENCH - self.weak :]
        return np.linalg.norm(z @ basis.T, axis=1)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Excitation:
        return cls(**data)


def excitation(sensor: str, labels: np.ndarray, noise: np.ndarray) -> Excitation | None:
    """The excitation of `sensor` from its exact training labels (N, 6) and its noise (6,); None without
    labels or noise."""
    labels = labels[np.isfinite(labels).all(axis=1)]
    if len(labels) < WRENCH or not np.all(np.isfinite(noise)) or np.any(noise <= 0):
        return None
    mean = labels.mean(axis=0)
    z = (labels - mean) / noise
    _, s, vt = np.linalg.svd(z, full_matrices=False)
    std = s / np.sqrt(len(z))
    lever, r2 = lever_relation(labels)
    return Excitation(
        sensor,
        len(labels),
        noise.tolist(),
        mean.tolist(),
        std.tolist(),
        vt.tolist(),
        int(np.sum(std < WEAK)),
        lever.tolist(),
        r2,
    )


def group_excitation(
    sensors: Sequence[str], x: np.ndarray, labels: np.ndarray, switches: np.ndarray, log: np.ndarray,
    stamp_ns: np.ndarray,
) -> dict[str, dict[str, Any]]:  # fmt: skip
    """Per sensor of a group, its `Excitation` as a dict (absent where it has no exact label).

    x (N, S, >= 6) raw inputs of the training samples (with their log ids and stamps, for the noise);
    labels (N, S, 6); switches (N, S).
    """
    out = {}
    for s, sensor in enumerate(sensors):
        e = excitation(sensor, labels[switches[:, s], s], noise_std(x[:, s, :WRENCH], log, stamp_ns))
        if e is not None:
            out[sensor] = e.to_dict()
    return out
