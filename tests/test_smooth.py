"""Stage `smooth`: against scipy's savgol_filter, against analytic derivatives, gaps, the stage itself."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from scipy.signal import savgol_filter

from pipeline.cli import main
from pipeline.core.errors import ConfigError
from pipeline.logs import schema as S
from pipeline.logs.smoothing import STILL_WINDOW_S, SmoothParams, segments, smooth_kinematics
from pipeline.logs.tables import read_table_metadata
from tests.factories.logs import JOINTS, SENSORS, T0, joint_position, run_one, write_log
from tests.factories.params import repo_params

ROOT = Path(__file__).resolve().parents[1]
RATE = 100.0  # Hz


def uniform_stamps(n: int, rate: float = RATE) -> np.ndarray:
    return T0 + np.round(np.arange(n) * 1e9 / rate).astype(np.int64)


@pytest.mark.parametrize(("window", "polyorder"), [(21, 3), (7, 2), (31, 5)])
def test_equals_scipy_savgol_on_uniform_samples(window: int, polyorder: int) -> None:
    rng = np.random.default_rng(window)
    q = np.cumsum(rng.standard_normal((500, 4)), axis=0) * 0.01
    stamps = uniform_stamps(500)
    res = smooth_kinematics(stamps, q, window, polyorder, max_gap_s=0.05)
    dt = 1 / RATE
    for got, deriv in ((res.q, 0), (res.dq, 1), (res.ddq, 2)):
        expected = savgol_filter(q, window, polyorder, deriv=deriv, delta=dt, axis=0)
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
    half = window // 2  # one-sided fits at the ends: values kept, not ok
    assert res.ok[half:-half].all() and not res.ok[:half].any() and not res.ok[-half:].any()
    assert res.segments == 1


# Stated bounds for a sine of amplitude A and angular frequency w = 2 pi rad/s (1 Hz, faster than the joint
# motions here) sampled at 100 Hz, window 21 (0.2 s), order 3, relative to A, A w, A w^2. SG attenuates a
# sine (the fit is exact only for cubics): measured interior errors 6.5e-4 / 3.6e-4 / 3.0e-2; the edge
# windows (mode "interp") extrapolate the fit: 6.5e-4 / 1.2e-2 / 8.3e-2 over the whole segment.
SINE_A, SINE_W = 0.7, 2 * np.pi * 1.0  # rad, rad/s (1 Hz: faster than any humanoid joint motion here)


def _sine(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a, w = SINE_A, SINE_W
    return a * np.sin(w * t), a * w * np.cos(w * t), -a * w * w * np.sin(w * t)


def _errors(res: object, t: np.ndarray, sl: slice) -> tuple[float, float, float]:
    q, dq, ddq = _sine(t)
    a, w = SINE_A, SINE_W
    return (
        np.abs(res.q[sl, 0] - q[sl]).max() / a,
        np.abs(res.dq[sl, 0] - dq[sl]).max() / (a * w),
        np.abs(res.ddq[sl, 0] - ddq[sl]).max() / (a * w * w),
    )


def test_sine_derivatives_within_stated_bounds() -> None:
    stamps = uniform_stamps(400)
    t = (stamps - T0) / 1e9
    res = smooth_kinematics(stamps, _sine(t)[0][:, None], 21, 3, max_gap_s=0.05)
    e_in = _errors(res, t, slice(10, -10))
    e_all = _errors(res, t, slice(None))
    assert e_in[0] < 1e-3 and e_in[1] < 1e-3 and e_in[2] < 5e-2, e_in
    assert e_all[0] < 1e-3 and e_all[1] < 2e-2 and e_all[2] < 0.15, e_all


def test_jitter_and_lost_samples_are_resampled_not_ignored() -> None:
    # 0.5 ms stamp jitter and 2 % lost messages: the time scaling must follow the real stamps.
    rng = np.random.default_rng(7)
    stamps = uniform_stamps(600) + rng.integers(-500_000, 500_000, 600)
    stamps = stamps[rng.random(600) > 0.02]
    t = (stamps - T0) / 1e9
    res = smooth_kinematics(stamps, _sine(t)[0][:, None], 21, 3, max_gap_s=0.05)
    e_in = _errors(res, t, slice(15, -15))
    assert e_in[0] < 3e-3 and e_in[1] < 3e-3 and e_in[2] < 5e-2, e_in  # measured 1.8e-3 / 1.7e-3 / 3.2e-2
    # Treating the samples as uniform (ignoring the stamps) is visibly worse on velocity.
    naive = savgol_filter(_sine(t)[0], 21, 3, deriv=1, delta=float(np.median(np.diff(t))))
    assert np.abs(naive - _sine(t)[1])[15:-15].max() / (SINE_A * SINE_W) > 3 * e_in[1]


def test_no_smoothing_across_gaps_and_short_segments_flagged() -> None:
    first = uniform_stamps(300)
    second = first[-1] + 10**9 + uniform_stamps(200) - T0  # 1 s gap
    short = second[-1] + 10**9 + uniform_stamps(10) - T0  # shorter than the window
    stamps = np.concatenate([first, second, short])
    t = (stamps - T0) / 1e9
    q = np.column_stack([np.where(t < 4, np.sin(t), 5.0 + t), np.cos(3 * t)])  # a step inside the gap
    assert segments(stamps, 50_000_000) == [(0, 300), (300, 500), (500, 510)]
    res = smooth_kinematics(stamps, q, 21, 3, max_gap_s=0.05)
    assert (res.segments, res.short_segments) == (3, 1)
    for start, stop in ((0, 300), (300, 500)):
        alone = smooth_kinematics(stamps[start:stop], q[start:stop], 21, 3, max_gap_s=0.05)
        np.testing.assert_allclose(res.dq[start:stop], alone.dq, rtol=1e-12, atol=1e-12)
    assert res.ok[10:290].all() and res.ok[310:490].all() and not res.ok[500:].any()
    assert not res.ok[[0, 9, 290, 299, 300, 309, 490, 499]].any()  # half a window at segment ends
    assert np.isnan(res.q[500:]).all()


def test_a_joint_absent_for_a_stretch_or_the_whole_log_touches_only_its_own_columns() -> None:
    """Joint 0 always there, joint 1 absent (NaN) for 0.6 s, joint 2 absent from the log (a recording
    without its board): joint 0 is smoothed bit for bit as alone, joint 1 on either side of its stretch
    as two logs of its own, joint 2 is NaN; each flag is its own, and ``ok`` is every joint's."""
    stamps = uniform_stamps(500)
    t = (stamps - T0) / 1e9
    q = np.column_stack([np.sin(t), np.cos(2 * t), t])
    q[200:260, 1] = np.nan
    q[:, 2] = np.nan
    res = smooth_kinematics(stamps, q, 21, 3, max_gap_s=0.05)
    alone = smooth_kinematics(stamps, q[:, :1], 21, 3, max_gap_s=0.05)
    for got, ref in ((res.q, alone.q), (res.dq, alone.dq), (res.ddq, alone.ddq)):
        np.testing.assert_array_equal(got[:, 0], ref[:, 0])
    np.testing.assert_array_equal(res.joint_ok[:, 0], alone.ok)
    for start, stop in ((0, 200), (260, 500)):
        side = smooth_kinematics(stamps[start:stop], q[start:stop, 1:2], 21, 3, max_gap_s=0.05)
        np.testing.assert_allclose(res.dq[start:stop, 1], side.dq[:, 0], rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(res.joint_ok[start:stop, 1], side.ok)
    assert np.isnan(res.dq[200:260, 1]).all() and not res.joint_ok[190:270, 1].any()
    assert res.joint_ok[10:190, 1].all() and res.joint_ok[270:490, 1].all()
    assert np.isnan(res.q[:, 2]).all() and not res.joint_ok[:, 2].any() and not res.ok.any()
    np.testing.assert_array_equal(
        smooth_kinematics(stamps, q[:, :2], 21, 3, 0.05).ok, res.joint_ok[:, :2].all(axis=1)
    )


def test_params_validation() -> None:
    with pytest.raises(ConfigError, match="smooth.window must be an odd integer"):
        SmoothParams(window=20, polyorder=3, max_gap_s=0.05)
    with pytest.raises(ConfigError, match="smooth.polyorder"):
        SmoothParams(window=5, polyorder=5, max_gap_s=0.05)
    with pytest.raises(ConfigError, match="smooth.max_gap_s"):
        SmoothParams(window=5, polyorder=3, max_gap_s=0)
    with pytest.raises(ConfigError, match=r"smooth.choices\[1\] window must be an odd"):
        SmoothParams(window=5, polyorder=3, max_gap_s=0.05, choices=[[21, 5], [20, 3]])
    with pytest.raises(ConfigError, match=r"smooth.choices\[0\] must be a \[window, polyorder\] pair"):
        SmoothParams(window=5, polyorder=3, max_gap_s=0.05, choices=[21])
    with pytest.raises(ConfigError, match="lists a setting twice"):
        SmoothParams(window=5, polyorder=3, max_gap_s=0.05, choices=[[21, 5], [21, 5]])
    cfg = SmoothParams(window=41, polyorder=5, max_gap_s=0.05, choices=[[61, 7], [21, 5]])
    assert (cfg.widest, cfg.narrowest, cfg.settings) == (61, 21, ((61, 7), (21, 5)))


# --- the setting chosen per joint -----------------------------------------------------------------

CHOICES = ((61, 7), (51, 5), (41, 5), (31, 5), (31, 7), (21, 5))  # params.yaml's kind of list
NOISE = 6e-5  # rad: the simulator's encoder noise with its quantum


def _motion(t: np.ndarray, fast: bool) -> tuple[np.ndarray, np.ndarray]:
    """(q, ddq) rad, rad/s^2: a slow swing (a known load's posture change), with a 3 Hz ripple of 3 mrad
    (a gait's steps: 1 rad/s^2) if `fast`."""
    w, v, ripple = 2 * np.pi * 0.2, 2 * np.pi * 3.0, 0.003 if fast else 0.0
    q = 0.3 * np.sin(w * t) + ripple * np.sin(v * t)
    return q, -0.3 * w * w * np.sin(w * t) - ripple * v * v * np.sin(v * t)


def _acceleration_errors(fast: bool, seed: int) -> tuple[np.ndarray, float, tuple[int, int]]:
    """The true RMS acceleration error of every setting of CHOICES, the chosen one's, and the choice."""
    n = 3000
    t = np.arange(n) / RATE
    q, ddq = _motion(t, fast)
    noisy = (q + np.random.default_rng(seed).standard_normal(n) * NOISE)[:, None]
    inner = slice(40, n - 40)
    fits = [savgol_filter(noisy[:, 0], w, p, deriv=2, delta=1 / RATE)[inner] for w, p in CHOICES]
    each = np.array([np.sqrt(np.mean((fit - ddq[inner]) ** 2)) for fit in fits])
    res = smooth_kinematics(uniform_stamps(n), noisy, 41, 5, 0.05, CHOICES)
    (setting,) = res.chosen  # one segment
    return each, float(np.sqrt(np.mean((res.ddq[inner, 0] - ddq[inner]) ** 2))), setting


@pytest.mark.parametrize("fast", [False, True])
@pytest.mark.parametrize("seed", [1, 2])
def test_chosen_setting_is_near_the_best_against_the_true_acceleration(fast: bool, seed: int) -> None:
    each, chosen, setting = _acceleration_errors(fast, seed)
    assert chosen <= 1.1 * each.min(), (setting, chosen, dict(zip(CHOICES, each.round(4), strict=True)))
    assert chosen < 0.25 * each.max()  # the settings differ by far: a wrong choice would show
    if fast:  # bias rules: a narrow window
        assert setting[0] <= 31
    else:  # noise rules: a wide one
        assert setting[0] >= 51


def test_the_joints_of_a_segment_share_one_setting_the_least_summed_error() -> None:
    """A slow joint beside a fast one: one setting for both (a link's motion composes theirs), the one whose
    acceleration error summed over both is least against the truth, and its own ok margin."""
    n = 3000
    t = np.arange(n) / RATE
    rng = np.random.default_rng(5)
    (q0, a0), (q1, a1) = _motion(t, False), _motion(t, True)
    q = np.column_stack([q0, q1]) + rng.standard_normal((n, 2)) * NOISE
    res = smooth_kinematics(uniform_stamps(n), q, 41, 5, 0.05, CHOICES)
    (setting,) = res.chosen
    assert res.chosen == {setting: 1}
    inner = slice(40, n - 40)
    truth = np.column_stack([a0, a1])[inner]
    errors = [
        np.sum((savgol_filter(q, w, p, deriv=2, delta=1 / RATE, axis=0)[inner] - truth) ** 2)
        for w, p in CHOICES
    ]
    assert errors[CHOICES.index(setting)] <= 1.2 * min(errors)
    expected = savgol_filter(q, *setting, deriv=2, delta=1 / RATE, axis=0)
    np.testing.assert_allclose(res.ddq, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
    half = setting[0] // 2
    assert res.ok[half : n - half].all() and not res.ok[:half].any() and not res.ok[n - half :].any()


def test_a_still_quantised_joint_takes_the_first_listed_setting() -> None:
    q = np.full((500, 1), 0.25)  # an encoder that never moves: every setting is exact
    res = smooth_kinematics(uniform_stamps(500), q, 41, 5, 0.05, CHOICES)
    assert res.chosen == {CHOICES[0]: 1}
    np.testing.assert_allclose(res.ddq[:, 0], 0.0, atol=1e-6)  # order 7's coefficients: 1e-7 rad/s^2


def test_stage_adds_kinematics_and_keeps_everything(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    ingested = tmp_path / "ingested"
    run_one(write_log(tmp_path / "log.mcap", duration=3.0), ingested)
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(repo_params()))
    out = tmp_path / "smoothed"
    assert main(["smooth", str(ingested), str(out), "--params", str(params)]) == 0
    assert [p.name for p in out.iterdir()] == ["log.parquet"]  # truth tables stay in ingested/
    before = pd.read_parquet(ingested / "log.parquet")
    after = pd.read_parquet(out / "log.parquet")
    assert list(after.columns) == [*before.columns, *S.smoothed_extra_columns(JOINTS)]
    pd.testing.assert_frame_equal(after[before.columns], before)
    t = (after[S.STAMP].to_numpy() - T0) / 1e9
    w = 2 * np.pi * 0.5
    cfg = yaml.safe_load(params.read_text())["smooth"]
    meta = read_table_metadata(out / "log.parquet")
    chosen = meta["ftcal.smooth"]["chosen"]  # joint segments per "window/order" setting
    assert sum(chosen.values()) == 1 and {tuple(c) for c in cfg["choices"]} >= {
        tuple(map(int, key.split("/"))) for key in chosen
    }
    h = max(int(key.split("/")[0]) for key in chosen) // 2  # samples at each end where a fit is one-sided
    for k, j in enumerate(JOINTS):
        np.testing.assert_allclose(after[S.joint_col(S.QS, j)], joint_position(t, k), atol=1e-4)
        np.testing.assert_allclose(
            after[S.joint_col(S.DQS, j)][h:-h], 0.5 * w * np.cos(w * t[h:-h] + k), atol=1e-3
        )
    ok = after[S.ok_col(S.KINEMATICS_STREAM)].to_numpy()
    assert ok[h:-h].all() and not ok[:h].any() and not ok[-h:].any()
    assert meta["ftcal.smooth"]["window"] == cfg["window"] and meta["ftcal.smooth"]["segments"] == 1
    assert meta["ftcal.experiment"]["type"] == "walking"
    assert meta["ftcal.schema"]["kind"] == "smoothed"
    assert set(SENSORS) == set(S.sensors_of(after.columns))


def test_a_noise_free_encoder_gets_the_least_biased_setting() -> None:
    """Without noise the reference's residual is its bias: taken for noise, it would make a wide window look
    best (a gait's steps smoothed away); bounded by the 6th differences, the narrowest setting is kept."""
    n = 3000
    q, ddq = _motion(np.arange(n) / RATE, True)
    res = smooth_kinematics(uniform_stamps(n), q[:, None], 41, 5, 0.05, CHOICES)
    assert res.chosen == {(21, 5): 1}
    inner = slice(40, n - 40)
    assert np.sqrt(np.mean((res.ddq[inner, 0] - ddq[inner]) ** 2)) < 0.02  # rad/s^2; 61/7: 0.12


ICUB_STEP = np.radians(360 / 4096)  # iCub 2.x encoders: 0.088 deg


def _quantised(q: np.ndarray, step: float = ICUB_STEP) -> np.ndarray:
    """Readings as a dataDumper run has them: whole steps, printed in degrees to 6 decimals, in rad."""
    return np.radians(np.round(np.degrees(np.round(q / step) * step), 6))


def test_an_encoders_step_is_found_on_its_lattice_and_nowhere_else() -> None:
    from pipeline.logs.smoothing import quantisation_step

    t = np.arange(3000) / RATE
    swing = 0.2 * np.sin(2 * np.pi * 0.3 * t)
    assert quantisation_step(_quantised(swing)) == pytest.approx(ICUB_STEP, rel=1e-5)
    noisy = swing + np.random.default_rng(0).standard_normal(len(t)) * 1e-4
    assert quantisation_step(noisy) == 0.0  # off any lattice: smoothed as it is
    assert quantisation_step(np.full(3000, 0.25)) == 0.0  # never changes: nothing to decide from


def test_a_still_joint_flickering_by_one_step_has_no_velocity_or_acceleration() -> None:
    """A joint at rest whose reading flickers between two adjacent steps (iCub's still joints) beside a
    moving one: the still joint's velocity and acceleration are exactly 0 and its position the flicker's
    running mean over `STILL_WINDOW_S`, where SG of the flicker alone reads accelerations of rad/s^2; the
    moving joint's are as good as when it is smoothed alone."""
    n = 3000
    t = np.arange(n) / RATE
    rng = np.random.default_rng(3)
    level = 0.1 + 0.5 * ICUB_STEP  # halfway between two steps
    flicker = _quantised(
        level + (rng.random(n) - 0.5) * 0.4 * ICUB_STEP + 0.45 * ICUB_STEP * np.sign(np.sin(7 * t))
    )
    assert len(np.unique(flicker)) == 2
    moving, ddq_true = _motion(t, False)
    q = np.column_stack([flicker, _quantised(moving)])
    res = smooth_kinematics(uniform_stamps(n), q, 41, 5, 0.05, CHOICES)
    assert res.still[:, 0].all() and not res.still[:, 1].any()
    assert np.all(res.dq[:, 0] == 0.0) and np.all(res.ddq[:, 0] == 0.0)
    w = max(max(x for x, _ in CHOICES), int(round(STILL_WINDOW_S * RATE)) | 1)
    inner_mean = np.convolve(flicker, np.ones(w) / w, mode="valid")  # the flicker's running mean
    np.testing.assert_allclose(res.q[w // 2 : n - w // 2, 0], inner_mean, rtol=0, atol=1e-12)
    assert np.max(np.abs(res.q[:, 0] - level)) < 0.5 * ICUB_STEP  # where it rests, within half a step
    (setting,) = res.chosen
    plain = savgol_filter(flicker, *setting, deriv=2, delta=1 / RATE)
    assert np.sqrt(np.mean(plain**2)) > 0.05  # rad/s^2 of a joint that does not move: what is avoided
    alone = smooth_kinematics(uniform_stamps(n), q[:, 1:], 41, 5, 0.05, CHOICES)
    inner = slice(40, n - 40)
    rms = [np.sqrt(np.mean((r.ddq[inner, -1] - ddq_true[inner]) ** 2)) for r in (res, alone)]
    assert rms[0] <= 1.05 * rms[1], rms


def test_a_step_known_from_the_joints_own_board_holds_it_still_after_interpolation() -> None:
    """A board interpolated at another board's stamps leaves the lattice (its readings are blends of two
    steps): the step its own readings had (ingest's `encoders` record) still finds it at rest."""
    n = 2000
    stamps = uniform_stamps(n)
    flicker = _quantised(0.3 + ICUB_STEP * (np.random.default_rng(4).random(n) > 0.5))
    blended = np.interp(stamps + 3_000_000, stamps, flicker)  # read 3 ms later, interpolated
    found = smooth_kinematics(stamps, blended[:, None], 41, 5, 0.05, CHOICES)
    assert found.steps[0] == 0.0 and not found.still.any()
    known = smooth_kinematics(stamps, blended[:, None], 41, 5, 0.05, CHOICES, steps=[ICUB_STEP])
    assert known.still.all() and np.all(known.ddq == 0.0)
