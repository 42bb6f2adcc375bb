"""Simulated sensor imperfections: FT distortion, FT temperature, FT-board IMU, joint encoders.

Pure numpy functions used by the simulator (`pipeline/stages/simulate.py`); everything here is hidden from the
calibration, which only ever sees the raw readings. Conventions:

- Wrenches are (N, 6) arrays ``[fx fy fz tx ty tz]`` in N and Nm, sensor frame; temperatures deg C.
- Every random quantity comes from the `numpy.random.Generator` passed in, in a fixed order, so one seed
  gives one log.
- The FT reading model (per sensor, parameters drawn once by `draw_distortion`)::

      v    = C @ w                                        coupled signal (C = I + E, gains on the diagonal)
      D    = G(T) * v + k * v * |v| / s + o + o_T * (T - T_ref)     static (memoryless) part
      read = D + h * play(v; width)                       + hysteresis (path-dependent)
      raw  = read + noise                                 white, per-axis std

  with ``G(T) = 1 + g_T * (T - T_ref)`` per axis. `oracle_inverse` inverts the static part exactly, so its
  error on the raw reading (noise + hysteresis) is the floor no per-sample calibration can beat.

The parameter dataclasses take their values from params.yaml (sections ``simulate.sensors``,
``simulate.thermal``, ``simulate.imu``) and raise `ConfigError` naming the dotted key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from scipy.signal import lfilter

from pipeline.core.errors import ConfigError

FORCE = slice(0, 3)  # force axes of a wrench (N)
TORQUE = slice(3, 6)  # torque axes of a wrench (Nm)
_SCAN_BLOCK = 32  # block length of the play-operator scan (fastest of 8..64 for 1e5 x 6 samples)


# --- validation helpers --------------------------------------------------------------------------


def _number(
    obj: Any, name: str, lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = True
) -> None:
    """Check field `name` of the params dataclass `obj` is a real number in the given interval.

    Converts ints to float in place (the dataclasses are frozen) and raises ConfigError naming
    ``<obj.SECTION>.<name>`` otherwise.
    """
    value = getattr(obj, name)
    left, right = "(" if lo_open else "[", ")" if hi_open else "]"
    key = f"{obj.SECTION}.{name}"
    interval = f"{left}{lo:g}, {'inf' if hi == math.inf else f'{hi:g}'}{right}"
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{key} must be a number in {interval}, got {value!r}")
    too_low = value <= lo if lo_open else value < lo
    too_high = value >= hi if hi_open else value > hi
    if too_low or too_high:
        raise ConfigError(f"{key} must be in {interval}, got {value!r}")
    object.__setattr__(obj, name, float(value))


def _ordered(obj: Any, low: str, high: str) -> None:
    if getattr(obj, low) > getattr(obj, high):
        raise ConfigError(
            f"{obj.SECTION}.{low} must not exceed {obj.SECTION}.{high}, "
            f"got {getattr(obj, low)!r} > {getattr(obj, high)!r}"
        )


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


# --- FT distortion -------------------------------------------------------------------------------


@dataclass(frozen=True)
class DistortionRanges:
    """Ranges from which each FT sensor's hidden distortion is drawn (section ``simulate.sensors``).

    Defaults give raw-vs-truth errors like the thesis's raw columns for loads of a few hundred N:
    ~25-50 N RMSE on the force axes and ~1.5-6 Nm on the torque axes, dominated by the offsets.
    "uniform +-x" means each entry is drawn from U(-x, x), independently per sensor and axis.
    """

    coupling: float = 0.02  # off-diagonal cross-talk of C, uniform +-: dimensionless in the force<-force
    #                         and torque<-torque blocks, 1/m in force<-torque (torque<-force is the lever)
    lever_m: float = 0.008  # force->torque lever, m: torque rows get r x f, r uniform +- per component
    gain: float = 0.03  # diagonal gain error of C, uniform +-, dimensionless
    temperature_gain: float = 5e-4  # g_T, gain change per deg C, uniform +-, 1/degC (0.05 %/degC)
    temperature_ref: float = 25.0  # T_ref, deg C: temperature of the primary calibration (zero drift)
    offset_force_min: float = 20.0  # |offset| of each force axis, N, uniform in [min, max], random sign
    offset_force_max: float = 45.0
    offset_torque_min: float = 1.0  # |offset| of each torque axis, Nm, uniform in [min, max], random sign
    offset_torque_max: float = 4.0
    offset_drift_force: float = 0.5  # o_T of force axes, N/degC, uniform +-
    offset_drift_torque: float = 0.02  # o_T of torque axes, Nm/degC, uniform +-
    nonlinearity: float = 0.01  # k, uniform +-: k * v|v|/s is k of full scale at full scale (1% rule)
    full_scale_force: float = 1500.0  # s of force axes, N
    full_scale_torque: float = 100.0  # s of torque axes, Nm
    hysteresis: float = 0.003  # h, uniform in [0, hysteresis] x full scale, per axis (0.3% of FS)
    hysteresis_width: float = 0.02  # play width = this x full scale; a reversal of 2x width saturates
    noise_force: float = 0.6  # white noise std of force axes, N
    noise_torque: float = 0.03  # white noise std of torque axes, Nm

    SECTION = "simulate.sensors"  # dotted params key, for error messages (a class attribute, not a field)

    def __post_init__(self) -> None:
        _number(self, "coupling", 0.0, 0.5)
        _number(self, "lever_m", 0.0, 0.1)
        _number(self, "gain", 0.0, 0.5)
        _number(self, "temperature_gain", 0.0, 0.005)  # keeps G(T) > 0.5 within 100 degC of T_ref
        _number(self, "temperature_ref", -50.0, 150.0, hi_open=False)
        for name in (
            "offset_force_min",
            "offset_force_max",
            "offset_torque_min",
            "offset_torque_max",
            "offset_drift_force",
            "offset_drift_torque",
            "noise_force",
            "noise_torque",
        ):
            _number(self, name, 0.0, math.inf)
        _ordered(self, "offset_force_min", "offset_force_max")
        _ordered(self, "offset_torque_min", "offset_torque_max")
        _number(self, "nonlinearity", 0.0, 0.2)  # keeps the static map monotonic far beyond full scale
        _number(self, "full_scale_force", 0.0, math.inf, lo_open=True)
        _number(self, "full_scale_torque", 0.0, math.inf, lo_open=True)
        _number(self, "hysteresis", 0.0, 0.1)
        _number(self, "hysteresis_width", 0.0, 1.0, lo_open=True, hi_open=False)


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


def play_operator(x: np.ndarray, width: np.ndarray | float, initial: np.ndarray | float = 0.0) -> np.ndarray:
    """Play (backlash) operator per column: ``z_k = clip(z_{k-1} + (x_k - x_{k-1}) / width, -1, 1)``.

    x: (N, m) input signal; width: scalar or (m,), same unit as x, > 0; initial: z_0, scalar or (m,)
    in [-1, 1]. Returns z, (N, m), dimensionless in [-1, 1].

    Method: each step is the map ``z -> clamp(z + a, lo, hi)``, and such maps are closed under
    composition, so z is a prefix scan of maps. The scan runs in blocks (a Hillis-Steele scan inside
    blocks of `_SCAN_BLOCK` samples, the same scan recursively over the block totals): ~5 vectorised
    passes over the data instead of a Python loop over samples. Equal to the loop to ~1e-15.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 2:
        raise ValueError(f"x must have shape (N, m), got {x.shape}")
    z0 = np.broadcast_to(np.asarray(initial, dtype=float), x.shape[1:])
    z = np.empty_like(x)
    if len(x) == 0:
        return z
    a = np.diff(x, axis=0) / width
    a, lo, hi = _scan_clamps(a, np.full_like(a, -1.0), np.full_like(a, 1.0))
    z[0] = z0
    z[1:] = np.minimum(np.maximum(z0 + a, lo), hi)
    return z


def _compose_scan_inplace(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
    """Inclusive Hillis-Steele scan along axis 1 of maps ``z -> clamp(z + a, lo, hi)``, in place.

    Arrays are (blocks, k, ...); element k of each block becomes map_k o ... o map_0 of that block.
    Composition rule: ``clamp(clamp(z + a1, l1, h1) + a2, l2, h2)
    = clamp(z + a1 + a2, clamp(l1 + a2, l2, h2), clamp(h1 + a2, l2, h2))``.
    """
    s = 1
    while s < a.shape[1]:
        a2, l2, h2 = a[:, s:], lo[:, s:], hi[:, s:]
        new_lo = lo[:, :-s] + a2
        np.minimum(np.maximum(new_lo, l2, out=new_lo), h2, out=new_lo)
        new_hi = hi[:, :-s] + a2
        np.minimum(np.maximum(new_hi, l2, out=new_hi), h2, out=new_hi)
        new_a = a[:, :-s] + a2
        a[:, s:], lo[:, s:], hi[:, s:] = new_a, new_lo, new_hi
        s *= 2


def _scan_clamps(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inclusive scan (along axis 0) of maps ``z -> clamp(z + a, lo, hi)``; returns new arrays."""
    k, rest = len(a), a.shape[1:]
    if k <= _SCAN_BLOCK:
        a, lo, hi = a[None].copy(), lo[None].copy(), hi[None].copy()
        _compose_scan_inplace(a, lo, hi)
        return a[0], lo[0], hi[0]
    nb = -(-k // _SCAN_BLOCK)
    pad = nb * _SCAN_BLOCK - k  # padded with identity maps (a = 0, no clamp)

    def blocks(y: np.ndarray, fill: float) -> np.ndarray:  # (k, ...) -> (nb, block length, ...), a copy
        return np.concatenate([y, np.full((pad, *rest), fill)]).reshape(nb, _SCAN_BLOCK, *rest)

    a, lo, hi = blocks(a, 0.0), blocks(lo, -np.inf), blocks(hi, np.inf)
    _compose_scan_inplace(a, lo, hi)
    ta, tl, th = _scan_clamps(a[:, -1], lo[:, -1], hi[:, -1])  # maps up to the end of each block
    # Exclusive prefix of each block (identity before the first), composed under the in-block maps.
    pa = np.concatenate([np.zeros((1, *rest)), ta[:-1]])[:, None]
    pl = np.concatenate([np.full((1, *rest), -np.inf), tl[:-1]])[:, None]
    ph = np.concatenate([np.full((1, *rest), np.inf), th[:-1]])[:, None]
    new_lo = np.minimum(np.maximum(pl + a, lo), hi)
    new_hi = np.minimum(np.maximum(ph + a, lo), hi)
    a += pa

    def unblock(y: np.ndarray) -> np.ndarray:
        return y.reshape(nb * _SCAN_BLOCK, *rest)[:k]

    return unblock(a), unblock(new_lo), unblock(new_hi)


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


# --- FT temperature ------------------------------------------------------------------------------


@dataclass(frozen=True)
class ThermalParams:
    """First-order thermal model of an FT sensor (section ``simulate.thermal``).

    The sensor relaxes with time constant `tau_s` towards ``baseline + heat_gain * activity``, where
    the baseline (idle temperature) is drawn per log; a 2-3 minute log drifts a few degrees, a long
    active one approaches baseline + heat_gain (~45 degC by default).
    """

    baseline: float = 30.0  # idle sensor temperature, deg C (the log starts here unless `initial` is given)
    baseline_spread: float = 1.0  # baseline drawn uniform +- this, deg C, per log
    heat_gain: float = 15.0  # temperature rise at activity 1 in steady state, deg C
    tau_s: float = 300.0  # thermal time constant, s
    t_min: float = 15.0  # clip of the temperature, deg C
    t_max: float = 60.0
    noise: float = 0.05  # white measurement noise std, deg C
    resolution: float = 0.1  # quantisation step of the published temperature, deg C (0: none)
    warmup_max: float = 0.0  # a log starts up to this much above its baseline (robot busy before), deg C

    SECTION = "simulate.thermal"  # dotted params key, for error messages (a class attribute, not a field)

    def __post_init__(self) -> None:
        _number(self, "baseline", -50.0, 150.0, hi_open=False)
        _number(self, "baseline_spread", 0.0, 50.0)
        _number(self, "heat_gain", 0.0, 100.0)
        _number(self, "tau_s", 0.0, math.inf, lo_open=True)
        _number(self, "t_min", -50.0, 150.0, hi_open=False)
        _number(self, "t_max", -50.0, 150.0, hi_open=False)
        _ordered(self, "t_min", "t_max")
        _number(self, "noise", 0.0, 10.0)
        _number(self, "resolution", 0.0, 10.0)
        _number(self, "warmup_max", 0.0, 50.0)


def thermal_response(
    activity: np.ndarray, dt: float, tau_s: float, baseline: float, heat_gain: float, initial: float
) -> np.ndarray:
    """Noise-free sensor temperature, (N,) deg C: exact discretisation of
    ``dT/dt = (baseline + heat_gain * activity - T) / tau_s`` with activity held over each step.

    activity: (N,) in [0, 1], dimensionless; dt: sample period, s; T[0] = initial, deg C.
    """
    act = np.asarray(activity, dtype=float)
    target = baseline + heat_gain * act
    if len(act) == 0:
        return target
    alpha = math.exp(-dt / tau_s)
    out = np.empty_like(target)
    out[0] = initial
    # T_k = alpha T_{k-1} + (1 - alpha) target_{k-1}, k >= 1
    out[1:], _ = lfilter([1.0 - alpha], [1.0, -alpha], target[:-1], zi=[alpha * initial])
    return out


def temperature_profile(
    rng: np.random.Generator, activity: np.ndarray, dt: float, p: ThermalParams, initial: float | None = None
) -> np.ndarray:
    """The FT sensor's published temperature over one log, (N,) deg C (see `temperature_signals`)."""
    return temperature_signals(rng, activity, dt, p, initial)[1]


def temperature_signals(
    rng: np.random.Generator, activity: np.ndarray, dt: float, p: ThermalParams, initial: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The FT sensor's (true, published) temperature over one log, each (N,) deg C.

    activity: (N,) in [0, 1], how hard the sensor's limb works (e.g. normalised joint torque), given by
    the caller; dt: sample period, s; initial: temperature at the first sample, deg C (the last value of
    the previous log of a session), or None to start at the drawn baseline. The true temperature
    (`thermal_response`, clipped to [t_min, t_max]) gets white noise of std `p.noise` and is quantised
    to `p.resolution`; the result stays in [t_min, t_max].
    """
    act = np.asarray(activity, dtype=float)
    if act.ndim != 1:
        raise ValueError(f"activity must have shape (N,), got {act.shape}")
    if act.size and not (np.all(np.isfinite(act)) and act.min() >= 0.0 and act.max() <= 1.0):
        raise ValueError("activity must lie in [0, 1]")
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt!r}")
    baseline = p.baseline + rng.uniform(-p.baseline_spread, p.baseline_spread)
    warm = rng.uniform(0.0, p.warmup_max) if p.warmup_max > 0 else 0.0
    start = baseline + warm if initial is None else float(initial)
    true = np.clip(thermal_response(act, dt, p.tau_s, baseline, p.heat_gain, start), p.t_min, p.t_max)
    measured = true + rng.standard_normal(true.shape) * p.noise
    if p.resolution > 0:
        # Quantise onto multiples of the resolution that lie inside [t_min, t_max].
        lo = math.ceil(p.t_min / p.resolution - 1e-9)  # tolerance: 15 / 0.1 = 150.00000000000003
        hi = math.floor(p.t_max / p.resolution + 1e-9)
        steps = np.clip(np.round(measured / p.resolution), lo, hi)
        return true, steps * p.resolution
    return true, np.clip(measured, p.t_min, p.t_max)


# --- FT-board IMU --------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuNoiseParams:
    """Accelerometer and gyroscope imperfections of an FT board IMU (section ``simulate.imu``).

    Biases are constant over a log; vibration bursts (e.g. foot impacts, motor cogging) arrive as a
    Poisson process and are a Hann-windowed sinusoid along a random direction.
    """

    acc_bias: float = 0.2  # accelerometer bias per axis, uniform +-, m/s^2
    gyro_bias: float = 0.01  # gyroscope bias per axis, uniform +-, rad/s
    acc_noise: float = 0.05  # accelerometer white noise std, m/s^2
    gyro_noise: float = 0.005  # gyroscope white noise std, rad/s
    burst_rate: float = 0.1  # vibration bursts per second (Poisson)
    burst_duration_min: float = 0.1  # burst length, s, uniform in [min, max]
    burst_duration_max: float = 0.5
    burst_freq_min: float = 20.0  # burst oscillation frequency, Hz, uniform in [min, max]
    burst_freq_max: float = 40.0  # (aliased if above the Nyquist frequency, as an unfiltered sensor would)
    burst_acc: float = 2.0  # peak burst amplitude on the accelerometer, uniform in [0, this], m/s^2
    burst_gyro: float = 0.05  # peak burst amplitude on the gyroscope at the same relative level, rad/s

    SECTION = "simulate.imu"  # dotted params key, for error messages (a class attribute, not a field)

    def __post_init__(self) -> None:
        for name in (
            "acc_bias",
            "gyro_bias",
            "acc_noise",
            "gyro_noise",
            "burst_rate",
            "burst_acc",
            "burst_gyro",
        ):
            _number(self, name, 0.0, math.inf)
        _number(self, "burst_duration_min", 0.0, math.inf, lo_open=True)
        _number(self, "burst_duration_max", 0.0, math.inf, lo_open=True)
        _ordered(self, "burst_duration_min", "burst_duration_max")
        _number(self, "burst_freq_min", 0.0, math.inf)
        _number(self, "burst_freq_max", 0.0, math.inf)
        _ordered(self, "burst_freq_min", "burst_freq_max")


def vibration_bursts(
    rng: np.random.Generator, n: int, dt: float, p: ImuNoiseParams
) -> tuple[np.ndarray, np.ndarray]:
    """Vibration bursts over n samples: (acc (n, 3) m/s^2, gyro (n, 3) rad/s), zero outside bursts."""
    acc, gyro = np.zeros((n, 3)), np.zeros((n, 3))
    t = np.arange(n) * dt
    for _ in range(rng.poisson(p.burst_rate * n * dt)):
        start = rng.uniform(0.0, n * dt)
        duration = rng.uniform(p.burst_duration_min, p.burst_duration_max)
        freq = rng.uniform(p.burst_freq_min, p.burst_freq_max)
        level = rng.uniform(0.0, 1.0)
        phase = rng.uniform(0.0, 2.0 * np.pi)
        acc_dir, gyro_dir = (u / np.linalg.norm(u) for u in rng.standard_normal((2, 3)))
        i0, i1 = np.searchsorted(t, [start, start + duration])
        if i1 <= i0:
            continue
        tau = (t[i0:i1] - start) / duration  # in [0, 1)
        wave = np.sin(np.pi * tau) ** 2 * np.sin(2.0 * np.pi * freq * (t[i0:i1] - start) + phase)
        acc[i0:i1] += level * p.burst_acc * wave[:, None] * acc_dir
        gyro[i0:i1] += level * p.burst_gyro * wave[:, None] * gyro_dir
    return acc, gyro


def imu_readings(
    rng: np.random.Generator, proper_acc: np.ndarray, gyro: np.ndarray, dt: float, p: ImuNoiseParams
) -> tuple[np.ndarray, np.ndarray]:
    """What the FT board IMU publishes: (accelerometer (N, 3) m/s^2, gyroscope (N, 3) rad/s).

    proper_acc: (N, 3) true proper acceleration (specific force: acceleration minus gravity, so +g up at
    rest), m/s^2, sensor frame; gyro: (N, 3) true angular velocity, rad/s; dt: sample period, s.
    Adds a constant bias per log, white noise and vibration bursts; the inputs are not modified.
    """
    acc_true = _as_samples(proper_acc, 3, "proper_acc")
    gyro_true = _as_samples(gyro, 3, "gyro")
    if len(acc_true) != len(gyro_true):
        raise ValueError(f"proper_acc and gyro differ in length: {len(acc_true)} != {len(gyro_true)}")
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt!r}")
    n = len(acc_true)
    acc_bias = rng.uniform(-p.acc_bias, p.acc_bias, size=3)
    gyro_bias = rng.uniform(-p.gyro_bias, p.gyro_bias, size=3)
    acc_burst, gyro_burst = vibration_bursts(rng, n, dt, p)
    acc = acc_true + acc_bias + acc_burst + rng.standard_normal((n, 3)) * p.acc_noise
    gyr = gyro_true + gyro_bias + gyro_burst + rng.standard_normal((n, 3)) * p.gyro_noise
    return acc, gyr


# --- encoders ------------------------------------------------------------------------------------


def encoder_readings(
    rng: np.random.Generator, q: np.ndarray, resolution_rad: float, noise_rad: float
) -> np.ndarray:
    """Measured joint positions, (N, n) rad: white noise of std `noise_rad`, then quantised to
    multiples of `resolution_rad` (rad per encoder count; 0 = no quantisation).

    q: (N, n) true joint positions, rad.
    """
    q = np.asarray(q, dtype=float)
    if q.ndim != 2:
        raise ValueError(f"q must have shape (N, n), got {q.shape}")
    if not (math.isfinite(resolution_rad) and resolution_rad >= 0):
        raise ValueError(f"resolution_rad must be >= 0, got {resolution_rad!r}")
    if not (math.isfinite(noise_rad) and noise_rad >= 0):
        raise ValueError(f"noise_rad must be >= 0, got {noise_rad!r}")
    noisy = q + rng.standard_normal(q.shape) * noise_rad
    if resolution_rad == 0:
        return noisy
    return np.round(noisy / resolution_rad) * resolution_rad


def encoder_velocity(q_meas: np.ndarray, dt: float) -> np.ndarray:
    """Joint velocities as a robot publishes them: the backward difference of the measured positions,
    (N, n) rad/s; the first sample, with no predecessor, is 0.

    q_meas: (N, n) measured joint positions, rad; dt: sample period, s.
    """
    q = np.asarray(q_meas, dtype=float)
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt!r}")
    v = np.zeros_like(q)
    v[1:] = np.diff(q, axis=0) / dt
    return v
