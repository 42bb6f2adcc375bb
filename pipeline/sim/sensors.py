"""Simulated sensor imperfections besides the FT distortion: FT temperature, FT-board IMU, encoders.

Pure numpy functions used by the simulator; everything here is hidden from the calibration. Every
random quantity comes from the `numpy.random.Generator` passed in, in a fixed order, so one seed gives
one log. The FT wrench distortion itself is :mod:`pipeline.sim.distortion`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import lfilter

from pipeline.sim.distortion import _as_samples
from pipeline.sim.params import ImuNoiseParams, ThermalParams

# --- FT temperature ------------------------------------------------------------------------------


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
