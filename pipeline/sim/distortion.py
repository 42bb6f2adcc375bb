"""The hidden distortion of a simulated FT sensor: what turns the true wrench into its raw reading.

Pure numpy; everything here is hidden from the calibration, which only ever sees the raw readings.
Wrenches are (N, 6) arrays ``[fx fy fz tx ty tz]`` in N and Nm, sensor frame; temperatures deg C.
Every random quantity comes from the `numpy.random.Generator` passed in, in a fixed order, so one seed
gives one log. The reading model (per sensor, parameters drawn once by `draw_distortion`)::

      v    = C @ w                                        coupled signal (C = I + E, gains on the diagonal)
      T_g  = LP(T; thermal_lag)                           the gauges' temperature lags the board's
      D    = G(T_g) * v + k * v * |v| / s + o + o_T * (T_g - T_ref)   static (memoryless) part
      read = D + sum_k h_k * play(v; width_k)             + hysteresis (path-dependent, a spread of widths)
               + c * (LP(v; creep_tau) - v)               + creep and its recovery under a held load
      raw  = read + noise                                 white, per-axis std

with ``G(T) = 1 + g_T * (T - T_ref)`` per axis and LP a first-order low-pass (exact discretisation,
starting at the log's first value: the robot held its load and temperature before the log). Creep is zero
at rest and after a load step reads ``-c`` of the step, recovering with `creep_tau`: the reading creeps
towards its static value (the foil gauges' adhesive and the body relax under a held load, and back once
it is removed). `oracle_inverse` inverts the static part exactly at the board's temperature, so its error
on the raw reading (noise, hysteresis, creep, the gauges' thermal lag) is the floor no memoryless
calibration can beat; the white noise alone is the floor of any calibration.

Magnitudes (`pipeline.sim.params.DistortionRanges`): strain-gauge load cells of accuracy class C (OIML R 60)
keep hysteresis and creep (30 min) within a few 0.01 % of full scale, 6-axis FT sensors specify hysteresis
and non-linearity within 0.5-1 % of full scale (ATI, their "Hysteresis" spec), creep 0.05-0.5 % of the load
change over minutes; the sensors' aluminium and steel bodies reach the board's temperature with time
constants of about a minute.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from scipy.signal import lfilter

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
    hysteresis: (6,) h, N / Nm (the sum of the operators' amplitudes, split equally among them).
    hysteresis_width: (K, 6) the K play operators' widths, N / Nm (of v).
    noise_std: (6,) white noise std, N / Nm.
    creep: (6,) c, dimensionless.             creep_tau_s: (6,) its time constant, s.
    thermal_lag_s: the gauges' thermal time constant behind the board's thermometer, s (0: none).
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
    creep: np.ndarray = field(default_factory=lambda: np.zeros(6))
    creep_tau_s: np.ndarray = field(default_factory=lambda: np.ones(6))
    thermal_lag_s: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name in ("temperature_ref", "thermal_lag_s"):
                object.__setattr__(self, f.name, float(getattr(self, f.name)))
                continue
            value = np.array(getattr(self, f.name), dtype=float)  # a private copy
            if f.name == "hysteresis_width":
                value = value.reshape(-1, 6) if value.size and value.size % 6 == 0 else value
            shape = (6, 6) if f.name == "coupling" else value.shape if f.name == "hysteresis_width" else (6,)
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise ValueError(
                    f"SensorDistortion.{f.name} must be finite with shape {shape}, got shape {value.shape}"
                )
            value.setflags(write=False)
            object.__setattr__(self, f.name, value)
        if (
            np.any(self.full_scale <= 0)
            or np.any(self.hysteresis_width <= 0)
            or np.any(self.creep_tau_s <= 0)
        ):
            raise ValueError("SensorDistortion.full_scale, hysteresis_width and creep_tau_s must be positive")
        if self.hysteresis_width.ndim != 2 or self.thermal_lag_s < 0:
            raise ValueError("SensorDistortion.hysteresis_width must be (K, 6), thermal_lag_s >= 0")

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (nested lists of floats), e.g. for MCAP metadata or MLflow."""
        return {
            f.name: v.tolist() if isinstance(v := getattr(self, f.name), np.ndarray) else v
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
    low, high = np.log(r.hysteresis_width_min), np.log(r.hysteresis_width_max)
    widths = np.exp(rng.uniform(low, high, size=(r.hysteresis_operators, 6))) * full_scale
    creep = rng.uniform(0.0, r.creep, size=6)
    creep_tau = np.exp(rng.uniform(np.log(r.creep_tau_min_s), np.log(r.creep_tau_max_s), size=6))
    return SensorDistortion(
        coupling=coupling,
        temperature_gain=temperature_gain,
        temperature_ref=r.temperature_ref,
        offset=offset,
        offset_drift=offset_drift,
        nonlinearity=nonlinearity,
        full_scale=full_scale,
        hysteresis=hysteresis,
        hysteresis_width=widths,
        noise_std=_per_axis(r.noise_force, r.noise_torque),
        creep=creep,
        creep_tau_s=creep_tau,
        thermal_lag_s=r.thermal_lag_s,
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
    """The path-dependent part of the reading, ``sum_k (h / K) play(C @ w; width_k)``, (N, 6) N / Nm; zero
    at the first sample.

    wrench: (N, 6) true wrench of one continuous recording, N / Nm.
    """
    v = _as_samples(wrench, 6, "wrench") @ d.coupling.T
    k = len(d.hysteresis_width)
    return sum(d.hysteresis / k * play_operator(v, width) for width in d.hysteresis_width)


def lowpass(x: np.ndarray, tau_s: np.ndarray | float, dt: float) -> np.ndarray:
    """First-order low-pass of each column of x (N, m) with time constants `tau_s` (scalar or (m,), s) at
    a step of `dt` s, exact for x held over a step, starting at x[0]."""
    x = np.asarray(x, dtype=float)
    a = 1.0 - np.exp(-dt / np.broadcast_to(np.asarray(tau_s, dtype=float), x.shape[1:]))
    out = np.empty_like(x)
    for j in range(x.shape[1]):
        out[:, j] = (
            lfilter([a[j]], [1.0, a[j] - 1.0], x[:, j], zi=[(1.0 - a[j]) * x[0, j]])[0] if len(x) else 0
        )
    return out


def creep_term(d: SensorDistortion, wrench: np.ndarray, dt: float) -> np.ndarray:
    """The reading's creep, ``c (LP(C @ w; creep_tau) - C @ w)``, (N, 6) N / Nm: zero at rest, ``-c`` of a
    load step at once, recovering with `creep_tau`. wrench: (N, 6) of one recording at a step of dt s."""
    v = _as_samples(wrench, 6, "wrench") @ d.coupling.T
    if not np.any(d.creep):
        return np.zeros_like(v)
    return d.creep * (lowpass(v, d.creep_tau_s, dt) - v)


def gauge_temperature(d: SensorDistortion, temperature: np.ndarray | float, dt: float) -> np.ndarray | float:
    """The gauges' temperature, deg C: the board's (scalar or (N,)) through the thermal lag (none: as is)."""
    t = np.asarray(temperature, dtype=float)
    if t.ndim == 0 or d.thermal_lag_s <= 0:
        return temperature
    return lowpass(t[:, None], d.thermal_lag_s, dt)[:, 0]


def distort(
    d: SensorDistortion,
    wrench: np.ndarray,
    temperature: np.ndarray | float,
    rng: np.random.Generator,
    dt: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's readings of a true wrench: (noise-free distorted, raw), each (N, 6) N / Nm.

    wrench: (N, 6) true wrench, N / Nm, one continuous recording at a step of dt s (the hysteresis state
    starts at 0, the creep and the gauges' temperature at rest). temperature: the board's, (N,) or scalar,
    deg C. The noise-free reading is D(w, T_g) + hysteresis + creep; raw adds white noise of std
    `d.noise_std` drawn from `rng`.
    """
    gauges = gauge_temperature(d, temperature, dt)
    clean = static_distortion(d, wrench, gauges) + hysteresis_term(d, wrench) + creep_term(d, wrench, dt)
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
