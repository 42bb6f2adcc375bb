"""Simulated sensor imperfections: the oracle inverts the static distortion exactly, the hysteresis is a
play operator, and temperature, IMU and encoder models have the statistics their parameters say."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import ConfigError
from pipeline.sim.distortion import (
    SensorDistortion,
    distort,
    draw_distortion,
    hysteresis_term,
    oracle_inverse,
    static_distortion,
)
from pipeline.sim.params import DistortionRanges, ImuNoiseParams, ThermalParams
from pipeline.sim.sensors import (
    encoder_readings,
    encoder_velocity,
    imu_readings,
    temperature_profile,
    thermal_response,
)


def leg_like_wrench(n: int, dt: float = 0.01) -> np.ndarray:
    """(n, 6) a leg sensor's load during slow motion: ~-300 N vertical, tens of N and Nm elsewhere."""
    t = np.arange(n) * dt
    return np.column_stack(
        [
            50 * np.sin(0.3 * t),
            40 * np.sin(0.5 * t + 1),
            -300 + 100 * np.sin(0.2 * t),
            15 * np.sin(0.4 * t),
            20 * np.sin(0.25 * t + 2),
            3 * np.sin(0.7 * t),
        ]
    )


# --- FT distortion -------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_oracle_inverts_static_distortion(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # Strong distortion (10x the default nonlinearity) over the whole measuring range and temperature range.
    d = draw_distortion(rng, DistortionRanges(nonlinearity=0.1, coupling=0.05, gain=0.1))
    w = rng.uniform(-1.0, 1.0, size=(2000, 6)) * d.full_scale
    temperature = rng.uniform(15.0, 60.0, size=2000)
    np.testing.assert_allclose(
        oracle_inverse(d, static_distortion(d, w, temperature), temperature), w, rtol=0, atol=1e-9
    )


def test_oracle_accepts_scalar_temperature() -> None:
    d = draw_distortion(np.random.default_rng(0), DistortionRanges())
    w = leg_like_wrench(10)
    np.testing.assert_allclose(oracle_inverse(d, static_distortion(d, w, 33.0), 33.0), w, rtol=0, atol=1e-9)


def test_static_distortion_matches_formula_per_axis() -> None:
    d = draw_distortion(np.random.default_rng(1), DistortionRanges())
    w, temperature = leg_like_wrench(50), np.linspace(28.0, 41.0, 50)
    v = np.einsum("ij,nj->ni", d.coupling, w)
    dt = (temperature - d.temperature_ref)[:, None]
    expected = (
        (1 + d.temperature_gain * dt) * v
        + d.nonlinearity * v * np.abs(v) / d.full_scale
        + d.offset
        + d.offset_drift * dt
    )
    np.testing.assert_allclose(static_distortion(d, w, temperature), expected, rtol=1e-12, atol=1e-9)


def test_oracle_error_on_raw_is_hysteresis_plus_noise() -> None:
    rng = np.random.default_rng(7)
    d = draw_distortion(rng, DistortionRanges(creep=0.0, thermal_lag_s=0.0))
    w, temperature = leg_like_wrench(20_000), np.linspace(30.0, 36.0, 20_000)
    clean, raw = distort(d, w, temperature, rng)

    # Noise-free: the oracle's error is the hysteresis mapped back through the static map's slope.
    hyst = hysteresis_term(d, w)
    np.testing.assert_allclose(clean, static_distortion(d, w, temperature) + hyst, rtol=0, atol=1e-9)
    v = w @ d.coupling.T
    slope = (
        1
        + d.temperature_gain * (temperature[:, None] - d.temperature_ref)
        + 2 * d.nonlinearity * np.abs(v) / d.full_scale
    )
    first_order = np.linalg.solve(d.coupling, (hyst / slope).T).T
    err_clean = oracle_inverse(d, clean, temperature) - w
    np.testing.assert_allclose(err_clean, first_order, rtol=0, atol=1e-3 * np.abs(first_order).max())
    assert np.abs(err_clean).max() > 0.1  # the hysteresis is really there

    # Raw: on top of that, white noise of the stated std per axis (C ~ I, slope ~ 1).
    noise_part = oracle_inverse(d, raw, temperature) - oracle_inverse(d, clean, temperature)
    np.testing.assert_allclose(noise_part.std(axis=0), d.noise_std, rtol=0.05)
    assert np.all(np.abs(noise_part.mean(axis=0)) <= 4 * d.noise_std / math.sqrt(len(w)))


def test_without_hysteresis_and_noise_the_oracle_is_exact() -> None:
    rng = np.random.default_rng(3)
    d = draw_distortion(
        rng, DistortionRanges(hysteresis=0.0, noise_force=0.0, noise_torque=0.0, creep=0.0, thermal_lag_s=0.0)
    )
    w, temperature = leg_like_wrench(1000), np.full(1000, 42.0)
    clean, raw = distort(d, w, temperature, rng)
    np.testing.assert_array_equal(clean, raw)
    np.testing.assert_allclose(oracle_inverse(d, raw, temperature), w, rtol=0, atol=1e-9)


def test_hysteresis_opens_a_loop_of_height_2h() -> None:
    """A slow triangle sweep of fz, far wider than the play, reads 2h higher going up than going down."""
    d = draw_distortion(np.random.default_rng(4), DistortionRanges(coupling=0.0, lever_m=0.0))
    fz = np.concatenate([np.linspace(-800, 0, 401), np.linspace(0, -800, 401)[1:]])
    w = np.zeros((len(fz), 6))
    w[:, 2] = fz
    h = hysteresis_term(d, w)[:, 2]
    up, down = h[200], h[-201]  # both at fz = -400, far from the turning point
    assert up == pytest.approx(d.hysteresis[2])
    assert down == pytest.approx(-d.hysteresis[2])


def test_default_raw_error_matches_thesis_raw_columns() -> None:
    """Defaults: leg sensors under a few hundred N read ~25-50 N and ~1.5-6 Nm off (RMSE, axes pooled)."""
    rng = np.random.default_rng(11)
    w, temperature = leg_like_wrench(5000), np.linspace(30.0, 38.0, 5000)
    force, torque = [], []
    for _ in range(20):
        _, raw = distort(draw_distortion(rng, DistortionRanges()), w, temperature, rng)
        err = raw - w
        force.append(np.sqrt(np.mean(err[:, :3] ** 2)))
        torque.append(np.sqrt(np.mean(err[:, 3:] ** 2)))
    assert 25.0 <= np.median(force) <= 50.0
    assert 1.5 <= np.median(torque) <= 6.0


def test_draw_is_seeded_and_json_serialisable() -> None:
    ranges = DistortionRanges()
    a = draw_distortion(np.random.default_rng(5), ranges)
    b = draw_distortion(np.random.default_rng(5), ranges)
    c = draw_distortion(np.random.default_rng(6), ranges)
    assert a.to_dict() == b.to_dict()
    assert a.to_dict() != c.to_dict()
    back = SensorDistortion.from_dict(json.loads(json.dumps(a.to_dict())))
    assert back.to_dict() == a.to_dict()
    with pytest.raises(ValueError, match="read-only"):
        a.offset[0] = 0.0


def test_draw_respects_ranges() -> None:
    r = DistortionRanges()
    for seed in range(20):
        d = draw_distortion(np.random.default_rng(seed), r)
        off_diagonal = d.coupling - np.diag(np.diag(d.coupling))
        assert np.all(np.abs(off_diagonal[:3]) <= r.coupling)
        assert np.all(np.abs(off_diagonal[3:, 3:]) <= r.coupling)
        lever_block = d.coupling[3:, :3]
        np.testing.assert_array_equal(lever_block, -lever_block.T)  # skew: tau += lever x f
        assert np.all(np.abs(lever_block) <= r.lever_m)
        assert np.all(np.abs(np.diag(d.coupling) - 1) <= r.gain)
        assert np.all(
            (r.offset_force_min <= np.abs(d.offset[:3])) & (np.abs(d.offset[:3]) <= r.offset_force_max)
        )
        assert np.all(
            (r.offset_torque_min <= np.abs(d.offset[3:])) & (np.abs(d.offset[3:]) <= r.offset_torque_max)
        )
        assert np.all((d.hysteresis >= 0) & (d.hysteresis <= r.hysteresis * d.full_scale))


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("coupling", 2, r"simulate\.sensors\.coupling must be in \[0, 0\.5\), got 2"),
        ("gain", -0.1, r"simulate\.sensors\.gain must be in \[0, 0\.5\), got -0\.1"),
        (
            "noise_force",
            "a lot",
            r"simulate\.sensors\.noise_force must be a number in \[0, inf\), got 'a lot'",
        ),
        ("full_scale_torque", 0, r"simulate\.sensors\.full_scale_torque must be in \(0, inf\), got 0"),
        ("hysteresis_width_min", True, r"simulate\.sensors\.hysteresis_width_min must be a number"),
        (
            "offset_force_min",
            50.0,
            r"simulate\.sensors\.offset_force_min must not exceed "
            r"simulate\.sensors\.offset_force_max",
        ),
    ],
)
def test_distortion_ranges_reject_bad_values(field: str, value: object, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        DistortionRanges(**{field: value})


def test_params_keep_ints_as_floats() -> None:
    assert isinstance(DistortionRanges(full_scale_force=1500).full_scale_force, float)


# --- temperature ---------------------------------------------------------------------------------


def test_thermal_response_is_the_first_order_solution() -> None:
    dt, tau = 0.01, 300.0
    t = np.arange(30_000) * dt
    temperature = thermal_response(np.full(len(t), 0.5), dt, tau, baseline=30.0, heat_gain=16.0, initial=28.0)
    np.testing.assert_allclose(temperature, 38.0 + (28.0 - 38.0) * np.exp(-t / tau), rtol=0, atol=1e-9)


def test_temperature_rises_with_activity_and_stays_in_range() -> None:
    p = ThermalParams()
    dt, n = 0.01, 15_000  # a 2.5 minute log
    idle = temperature_profile(np.random.default_rng(0), np.zeros(n), dt, p)
    busy = temperature_profile(np.random.default_rng(0), np.full(n, 0.7), dt, p)
    assert abs(idle[:100].mean() - p.baseline) <= p.baseline_spread + 0.1
    assert abs(idle[-100:].mean() - idle[:100].mean()) < 0.1
    assert busy[-100:].mean() - busy[:100].mean() > 2.0  # a few degrees over a short log
    assert np.all(np.diff(busy[::1000]) > 0)
    # A long active session approaches baseline + heat_gain, clipped to [t_min, t_max].
    long = temperature_profile(np.random.default_rng(1), np.ones(2_000_000), 0.01, p)
    assert 42.0 < long[-1000:].mean() < 47.0
    hot = temperature_profile(np.random.default_rng(1), np.ones(200_000), 0.01, replace(p, heat_gain=80.0))
    assert hot.min() >= p.t_min and hot.max() <= p.t_max
    assert hot[-1] == pytest.approx(p.t_max)


def test_temperature_is_quantised_and_continues_from_initial() -> None:
    p = ThermalParams()
    temperature = temperature_profile(np.random.default_rng(2), np.full(5000, 0.3), 0.01, p, initial=41.23)
    steps = temperature / p.resolution
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
    assert abs(temperature[0] - 41.23) < 0.3
    assert np.std(temperature[:200] - np.mean(temperature[:200])) < 0.1


def test_thermal_params_reject_bad_values() -> None:
    with pytest.raises(ConfigError, match=r"simulate\.thermal\.tau_s must be in \(0, inf\), got -1"):
        ThermalParams(tau_s=-1)
    with pytest.raises(ConfigError, match=r"simulate\.thermal\.t_min must not exceed simulate\.thermal\.t_"):
        ThermalParams(t_min=50.0, t_max=40.0)
    with pytest.raises(ValueError, match="activity"):
        temperature_profile(np.random.default_rng(0), np.full(3, 1.5), 0.01, ThermalParams())


# --- IMU -----------------------------------------------------------------------------------------


def test_imu_bias_and_noise_statistics() -> None:
    p = ImuNoiseParams(burst_rate=0.0)
    n = 50_000
    rng = np.random.default_rng(8)
    acc_true = np.tile([0.0, 0.0, 9.80665], (n, 1)) + rng.normal(size=(n, 3))
    gyro_true = rng.normal(size=(n, 3)) * 0.3
    acc, gyro = imu_readings(np.random.default_rng(9), acc_true, gyro_true, 0.01, p)
    for err, bias, noise in (
        (acc - acc_true, p.acc_bias, p.acc_noise),
        (gyro - gyro_true, p.gyro_bias, p.gyro_noise),
    ):
        mean = err.mean(axis=0)
        assert np.all(np.abs(mean) <= bias + 4 * noise / math.sqrt(n))
        np.testing.assert_allclose(err.std(axis=0), noise, rtol=0.03)
        # constant bias: both halves of the log agree
        np.testing.assert_allclose(
            err[: n // 2].mean(axis=0), err[n // 2 :].mean(axis=0), atol=6 * noise / math.sqrt(n / 2)
        )
    # different logs (generator states) draw different biases
    acc2, _ = imu_readings(np.random.default_rng(10), acc_true, gyro_true, 0.01, p)
    assert not np.allclose((acc2 - acc_true).mean(axis=0), (acc - acc_true).mean(axis=0), atol=1e-3)


def test_imu_vibration_bursts_are_bounded_and_in_band() -> None:
    p = ImuNoiseParams(acc_bias=0.0, gyro_bias=0.0, acc_noise=0.0, gyro_noise=0.0, burst_rate=0.3)
    n, dt = 60_000, 0.001  # 60 s at 1 kHz: ~18 bursts (this seed: none overlap)
    acc, gyro = imu_readings(np.random.default_rng(12), np.zeros((n, 3)), np.zeros((n, 3)), dt, p)
    active = np.linalg.norm(acc, axis=1) > 0
    assert 0.02 < active.mean() < 0.8
    assert np.linalg.norm(acc, axis=1).max() <= p.burst_acc + 1e-12
    assert np.linalg.norm(gyro, axis=1).max() <= p.burst_gyro + 1e-12
    spectrum = np.abs(np.fft.rfft(acc, axis=0)) ** 2
    freq = np.fft.rfftfreq(n, dt)
    in_band = spectrum[(freq >= 15) & (freq <= 45)].sum()
    assert in_band > 0.9 * spectrum.sum()


def test_imu_inputs_are_not_modified() -> None:
    acc_true, gyro_true = np.ones((100, 3)), np.zeros((100, 3))
    imu_readings(np.random.default_rng(0), acc_true, gyro_true, 0.01, ImuNoiseParams(burst_rate=50.0))
    np.testing.assert_array_equal(acc_true, 1.0)
    np.testing.assert_array_equal(gyro_true, 0.0)


def test_imu_params_reject_bad_values() -> None:
    with pytest.raises(ConfigError, match=r"simulate\.imu\.burst_freq_min must not exceed"):
        ImuNoiseParams(burst_freq_min=50.0, burst_freq_max=40.0)
    with pytest.raises(ConfigError, match=r"simulate\.imu\.acc_noise must be in \[0, inf\), got -1"):
        ImuNoiseParams(acc_noise=-1)


# --- encoders ------------------------------------------------------------------------------------


def test_encoder_readings_are_exact_multiples_of_the_resolution() -> None:
    rng = np.random.default_rng(13)
    q = rng.uniform(-2.0, 2.0, size=(1000, 5))
    resolution = 2 * np.pi / 4096 / 100  # 12-bit encoder behind a 100:1 gearbox
    q_meas = encoder_readings(rng, q, resolution, noise_rad=0.0)
    counts = np.round(q_meas / resolution)
    np.testing.assert_array_equal(q_meas, counts * resolution)
    assert np.abs(q_meas - q).max() <= resolution / 2 + 1e-15
    noisy = encoder_readings(rng, q, resolution, noise_rad=1e-3)
    np.testing.assert_array_equal(noisy, np.round(noisy / resolution) * resolution)
    assert (noisy - q).std() == pytest.approx(1e-3, rel=0.05)


def test_encoder_velocity_is_the_backward_difference() -> None:
    dt = 0.01
    q = np.outer(np.arange(100) * dt, [1.0, -2.0])  # constant velocities 1 and -2 rad/s
    v = encoder_velocity(q, dt)
    np.testing.assert_array_equal(v[0], 0.0)
    np.testing.assert_allclose(v[1:], np.tile([1.0, -2.0], (99, 1)), atol=1e-12)
    quantised = encoder_readings(np.random.default_rng(0), q, 3e-3, 0.0)  # steps of 3-4 counts
    assert encoder_velocity(quantised, dt)[1:].std(axis=0).min() > 0.01  # quantisation makes it noisy


def test_creep_and_the_gauges_thermal_lag_follow_their_first_order_step_responses() -> None:
    """A load step held: the reading first lacks c of the step, then creeps back as exp(-t / tau); the
    gauges' temperature follows a step of the board's as 1 - exp(-t / lag). Against the analytic
    responses (a sample's filter output includes that sample: the step is seen from its own sample on)."""
    from pipeline.sim.distortion import creep_term, gauge_temperature

    ranges = DistortionRanges(creep=0.01, creep_tau_min_s=5.0, creep_tau_max_s=5.0, thermal_lag_s=30.0)
    d = draw_distortion(np.random.default_rng(3), ranges)
    dt, n = 0.01, 3000
    t = np.arange(n) * dt
    w = np.zeros((n, 6))
    w[100:, 2] = 200.0  # a 200 N load on fz from t = 1 s
    step = (w @ d.coupling.T)[-1]  # the coupled signal's step
    expected = -d.creep * step * np.exp(-(t[:, None] - t[100] + dt) / 5.0) * (t[:, None] >= t[100])
    np.testing.assert_allclose(
        creep_term(d, w, dt), expected, rtol=0, atol=1e-9 + 1e-3 * np.abs(expected).max()
    )
    assert 0.5 * 0.01 * 200 > abs(creep_term(d, w, dt)[100, 2]) > 0.0  # c drawn in [0, 0.01]
    board = np.where(t >= 1.0, 35.0, 30.0)
    lagged = np.asarray(gauge_temperature(d, board, dt))
    want = 30.0 + 5.0 * (1 - np.exp(-(t - t[100] + dt) / 30.0)) * (t >= t[100])
    np.testing.assert_allclose(lagged, want, rtol=0, atol=2e-3)


def test_the_memory_variants_change_only_the_sensors_memory_physics() -> None:
    """benchmarks/variant.py --memory wide|slow: params.yaml with the preset's simulate.sensors keys, valid
    ranges, every other key and the seed as the default's."""
    import sys

    import yaml

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import variant

    from pipeline.core.defaults import resolve

    text = (Path(__file__).resolve().parents[1] / "params.yaml").read_text()
    default = resolve(yaml.safe_load(text))[0]
    for name, preset in variant.MEMORY.items():
        changed = resolve(yaml.safe_load(variant.variant_params(text, default["seed"], 1.0, False, preset)))[
            0
        ]
        sensors = changed["simulate"].pop("sensors")
        assert {k: sensors[k] for k in preset} == preset, name
        assert {k: v for k, v in sensors.items() if k not in preset} == {
            k: v for k, v in default["simulate"]["sensors"].items() if k not in preset
        }
        rest = dict(default["simulate"])
        rest.pop("sensors")
        assert changed["simulate"] == rest and changed["seed"] == default["seed"]
        DistortionRanges(**sensors)  # valid
