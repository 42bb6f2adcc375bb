"""The hidden distortion of a simulated FT sensor: what turns the true wrench into its raw reading.

Pure numpy; everything here is hidden from the calibration, which only ever sees the raw readings.
Wrenches are (N, 6) arrays ``[fx fy fz tx ty tz]`` in N and Nm, sensor frame; temperatures deg C.
Every random quantity comes from the `numpy.random.Generator` passed in, in a fixed order, so one seed
gives one log. The reading model (per sensor, parameters drawn once by `draw_distortion`)::

      v    = C @ w                                        coupled signal (C = I + E, gains on the diagonal)
      D    = G(T) * v + k * v * |v| / s + o + o_T * (T - T_ref)     static (memoryless) part
      read = D + h * play(v; width)                       + hysteresis (path-dependent)
      raw  = read + noise                                 white, per-axis std

with ``G(T) = 1 + g_T * (T - T_ref)`` per axis. `oracle_inverse` inverts the static part exactly, so its
error on the raw reading (noise + hysteresis) is the floor no per-sample calibration can beat.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from pipeline.core.play import play_operator
from pipeline.sim.params import DistortionRanges

FORCE = slice(0, 3)  # force axes of a wrench (N)
TORQUE = slice(3, 6)  # torque axes of a wrench (Nm)


def _as_samples(array: Any, width: int, name: str) -> np.ndarray:
    """`array` as float (N, width); raises ValueError naming the argument otherwise."""
    out = np.asarray(array, dtype=float)
    if out.ndim != 2 or out.shape[1] != width:
        raise ValueError(f"{name} must have shape (N, {width}), got {out.shape}")
    return out


def _temperature_column(temperature: Any, n: int) -> np.ndarray:
    """Temperature (deg C, scalar or (N,)) as an (N, 1) column."""
    t = np.asarray(temperature, dtype=float)
    if t.ndim == 0:
        return np.full((n, 1), float(t))
    if t.shape != (n,):
        raise ValueError(f"temperature must be a scalar or have shape ({n},), got {t.shape}")
    return t[:, None]


@dataclass(frozen=True, eq=False)
class SensorDistortion:
    """One FT sensor's hidden distortion parameters (read-only arrays; axes ``[fx fy fz tx ty tz]``).

    coupling: (6, 6) C, dimensionless blocks except torque<-force (m) and force<-torque (1/m); its
        diagonal holds the gains 1 + gain error.
    temperature_gain: (6,) g_T, 1/degC.        temperature_ref: T_ref, deg C.
    offset: (6,) o, N / Nm.                    offset_drift: (6,) o_T, N/degC / Nm/degC.
    nonlinearity: (6,) k, dimensionless.       full_scale: (6,) s, N / Nm.
    hysteresis: (6,) h, N / Nm.                hysteresis_width: (6,) play width, N / Nm (of v).
    noise_std: (6,) white noise std, N / Nm.
    """

    coupling: np.ndarray
    temperature_gain: np.ndarray
    temperature_ref: float
    offset: np.ndarray
    offset_drift: np.ndarray
    nonlinearity: np.ndarray
    full_scale: np.ndarray
    hysteresis: np.ndarray
    hysteresis_width: np.ndarray
    noise_std: np.ndarray

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name == "temperature_ref":
                object.__setattr__(self, f.name, float(self.temperature_ref))
                continue
            shape = (6, 6) if f.name == "coupling" else (6,)
            value = np.array(getattr(self, f.name), dtype=float)  # a private copy
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise ValueError(
                    f"SensorDistortion.{f.name} must be finite with shape {shape}, got shape {value.shape}"
                )
            value.setflags(write=False)
            object.__setattr__(self, f.name, value)
        if np.any(self.full_scale <= 0) or np.any(self.hysteresis_width <= 0):
            raise ValueError("SensorDistortion.full_scale and hysteresis_width must be positive")

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (nested lists of floats), e.g. for MCAP metadata or MLflow."""
        return {
            f.name: (getattr(self, f.name).tolist() if f.name != "temperature_ref" else self.temperature_ref)
            for f in fields(self)
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SensorDistortion:
        """Inverse of `to_dict`."""
        return cls(**data)


def _per_axis(force: float, torque: float) -> np.ndarray:
    """(6,) array with `force` on the force axes and `torque` on the torque axes."""
    return np.repeat([force, torque], 3).astype(float)


def draw_distortion(rng: np.random.Generator, ranges: DistortionRanges) -> SensorDistortion:
    """Draw one FT sensor's hidden distortion from `ranges` (fixed draw order: same seed, same sensor)."""
    r = ranges
    coupling = rng.uniform(-r.coupling, r.coupling, size=(6, 6))
    lever = rng.uniform(-r.lever_m, r.lever_m, size=3)
    # A sensor origin displaced by `lever` reads tau + lever x f: the torque<-force block is skew(lever).
    coupling[TORQUE, FORCE] = np.array(
        [[0.0, -lever[2], lever[1]], [lever[2], 0.0, -lever[0]], [-lever[1], lever[0], 0.0]]
    )
    np.fill_diagonal(coupling, 1.0 + rng.uniform(-r.gain, r.gain, size=6))

    temperature_gain = rng.uniform(-r.temperature_gain, r.temperature_gain, size=6)
    magnitude = np.concatenate(
        [
            rng.uniform(r.offset_force_min, r.offset_force_max, size=3),
            rng.uniform(r.offset_torque_min, r.offset_torque_max, size=3),
        ]
    )
    offset = magnitude * rng.choice([-1.0, 1.0], size=6)
    drift_bound = _per_axis(r.offset_drift_force, r.offset_drift_torque)
    offset_drift = rng.uniform(-1.0, 1.0, size=6) * drift_bound
    nonlinearity = rng.uniform(-r.nonlinearity, r.nonlinearity, size=6)
    full_scale = _per_axis(r.full_scale_force, r.full_scale_torque)
    hysteresis = rng.uniform(0.0, r.hysteresis, size=6) * full_scale
    return SensorDistortion(
        coupling=coupling,
        temperature_gain=temperature_gain,
        temperature_ref=r.temperature_ref,
        offset=offset,
        offset_drift=offset_drift,
        nonlinearity=nonlinearity,
        full_scale=full_scale,
        hysteresis=hysteresis,
        hysteresis_width=r.hysteresis_width * full_scale,
        noise_std=_per_axis(r.noise_force, r.noise_torque),
    )


def _gain(d: SensorDistortion, t: np.ndarray) -> np.ndarray:
    """G(T), (N, 6), from a temperature column (N, 1)."""
    return 1.0 + d.temperature_gain * (t - d.temperature_ref)


def static_distortion(d: SensorDistortion, wrench: np.ndarray, temperature: np.ndarray | float) -> np.ndarray:
    """The memoryless part D(w, T) of the reading, (N, 6) N / Nm.

    wrench: (N, 6) true wrench, N / Nm. temperature: (N,) or scalar, deg C.
    """
    w = _as_samples(wrench, 6, "wrench")
    t = _temperature_column(temperature, len(w))
    v = w @ d.coupling.T
    return (
        _gain(d, t) * v
        + d.nonlinearity * v * np.abs(v) / d.full_scale
        + d.offset
        + d.offset_drift * (t - d.temperature_ref)
    )


def hysteresis_term(d: SensorDistortion, wrench: np.ndarray) -> np.ndarray:
    """The path-dependent part of the reading, ``h * play(C @ w)``, (N, 6) N / Nm; zero at the first sample.

    wrench: (N, 6) true wrench of one continuous recording, N / Nm.
    """
    v = _as_samples(wrench, 6, "wrench") @ d.coupling.T
    return d.hysteresis * play_operator(v, d.hysteresis_width)


def distort(
    d: SensorDistortion, wrench: np.ndarray, temperature: np.ndarray | float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's readings of a true wrench: (noise-free distorted, raw), each (N, 6) N / Nm.

    wrench: (N, 6) true wrench, N / Nm, one continuous recording (the hysteresis state starts at 0).
    temperature: (N,) or scalar, deg C. The noise-free reading is D(w, T) + hysteresis; raw adds
    white noise of std `d.noise_std` drawn from `rng`.
    """
    clean = static_distortion(d, wrench, temperature) + hysteresis_term(d, wrench)
    raw = clean + rng.standard_normal(clean.shape) * d.noise_std
    return clean, raw


def oracle_inverse(d: SensorDistortion, reading: np.ndarray, temperature: np.ndarray | float) -> np.ndarray:
    """The exact inverse of the static part: w such that ``D(w, T) = reading``, (N, 6) N / Nm.

    reading: (N, 6) N / Nm; temperature: (N,) or scalar, deg C. Per axis, ``G v + (k/s) v|v| = y`` is
    solved in closed form (the root with the sign of y, in the cancellation-free form
    ``|v| = 2|y| / (G + sqrt(G^2 + 4 (k/s) |y|))``), then ``C w = v`` by a linear solve. Exact to
    rounding (~1e-13 N). Beyond the turning point of a negative k (|v| > G s / 2|k|, i.e. > 25 x full
    scale at the largest allowed k) there is no inverse; the result is then NaN.
    """
    r = _as_samples(reading, 6, "reading")
    t = _temperature_column(temperature, len(r))
    g = _gain(d, t)
    y = r - d.offset - d.offset_drift * (t - d.temperature_ref)
    c = d.nonlinearity / d.full_scale
    mag = np.abs(y)
    with np.errstate(invalid="ignore"):
        root = np.sqrt(g * g + 4.0 * c * mag)  # NaN beyond the turning point
    v = np.sign(y) * 2.0 * mag / (g + root)
    return np.linalg.solve(d.coupling, v.T).T
