"""Test D from the noise level up (`pipeline.deploy.scales`) and the truth-free check at small scale
(`pipeline.calib.fidelity`).

References: the superposition through a hand-made distortion (coupling, gains, temperature, nonlinearity,
hysteresis) against a per-sample loop of the play operator and the reading model written out here; the
oracle as its own exact reference (a model equal to it reports every push at its slope exactly); hand-made
rows for the verdict's thresholds; for the virtual pushes a network that snaps small deviations from its
training relation, whose slope at each scale is known in closed form, beside an affine map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch

from pipeline.calib.fidelity import SCALES_N, group_fidelity
from pipeline.calib.pushes import PushPrior
from pipeline.deploy.scales import (
    ERROR_FLOOR,
    Tally,
    judge,
    log_tally,
    plan_pushes,
    reference_models,
    sensor_result,
)
from pipeline.evaluation.fidelity import unfaithful
from pipeline.sim.distortion import SensorDistortion

N, DT = 4000, 0.01  # a 40 s log at 100 Hz


@dataclass(frozen=True)
class Scales:  # deploy.scales, small
    force_n: tuple[float, ...] = (1.0, 5.0, 40.0)
    moment_nm: tuple[float, ...] = (0.05, 2.0)
    load_kg: tuple[float, ...] = (0.5,)
    levers: tuple[float, ...] = (0.0, 1.0)
    pulse_s: float = 0.5
    load_s: float = 2.0
    pulses: int = 12


def _distortion() -> SensorDistortion:
    rng = np.random.default_rng(3)
    coupling = np.eye(6) + rng.uniform(-0.03, 0.03, (6, 6))
    np.fill_diagonal(coupling, 1 + rng.uniform(-0.1, 0.1, 6))
    full = np.r_[np.full(3, 300.0), np.full(3, 15.0)]
    return SensorDistortion(
        coupling=coupling,
        temperature_gain=rng.uniform(-2e-3, 2e-3, 6),
        temperature_ref=25.0,
        offset=rng.uniform(-20, 20, 6),
        offset_drift=rng.uniform(-0.1, 0.1, 6),
        nonlinearity=rng.uniform(-0.02, 0.02, 6),
        full_scale=full,
        hysteresis=0.01 * full,
        hysteresis_width=[0.02 * full],
        noise_std=np.r_[np.full(3, 0.6), np.full(3, 0.03)],
    )


def _reading_by_loop(d: SensorDistortion, w: np.ndarray, temperature: np.ndarray) -> np.ndarray:
    """The noise-free reading without offsets, the model written out with the play operator as a loop."""
    v = w @ d.coupling.T
    z, out = np.zeros(6), np.empty_like(w)
    for k in range(len(w)):
        if k:
            z = np.clip(z + (v[k] - v[k - 1]) / d.hysteresis_width[0], -1, 1)
        g = 1 + d.temperature_gain * (temperature[k] - d.temperature_ref)
        out[k] = g * v[k] + d.nonlinearity * v[k] * np.abs(v[k]) / d.full_scale + d.hysteresis * z
    return out


def _log(d: SensorDistortion) -> tuple[np.ndarray, np.ndarray]:
    """(inputs (N, 13): raw wrench, temperature, accelerometer, gyroscope; true wrench (N, 6))."""
    rng = np.random.default_rng(4)
    t = np.arange(N) * DT
    true = np.stack([a * np.sin(0.3 * (k + 1) * t + k) for k, a in enumerate([20, 15, 30, 1, 2, 0.5])], 1)
    temperature = 30 + 2 * np.sin(0.05 * t)
    offsets = d.offset + d.offset_drift * (temperature[:, None] - d.temperature_ref)
    raw = _reading_by_loop(d, true, temperature) + offsets + rng.standard_normal((N, 6)) * d.noise_std
    imu = np.c_[np.tile([0.0, 0.0, 9.81], (N, 1)), np.zeros((N, 3))]
    return np.c_[raw, temperature, imu], true


@pytest.fixture(scope="module")
def sensor() -> dict:
    d = _distortion()
    x, true = _log(d)
    lever = np.array([0.0, 0.02, 0.3])
    passes = plan_pushes(Scales(), N, DT, lever, x[:, 7:10], 9.81, 1.0, np.random.default_rng(5))
    oracle = reference_models(d, lambda rows: rows[:, :6])["oracle"]
    as_oracle = log_tally(d, x, true, reference_models(d, oracle), passes)
    return {"d": d, "x": x, "true": true, "lever": lever, "passes": passes, "as_oracle": as_oracle}


def test_a_model_equal_to_the_oracle_reports_every_push_at_the_oracles_slope(sensor: dict) -> None:
    result = sensor_result(sensor["as_oracle"], Scales(), sensor["lever"])
    assert set(result) >= {"force", "moment", "random", "load", "levers"}
    for family in ("force", "moment", "random", "load"):
        for mag, row in result[family].items():
            assert row["deployed"] == row["oracle"], (family, mag)
            assert any(s is not None for s in row["deployed"]["slopes"])
    # the oracle inverts the static part: its slopes differ from 1 by the hysteresis's minor loops only
    for row in result["force"].values():
        assert all(0.9 < s < 1.5 for s in row["oracle"]["slopes"][:3])
    verdict = judge(result, 0.0, 1.0)
    assert verdict["pass"] and verdict["worst_slope_excess"] == 0.0 and verdict["worst_change_ratio"] <= 1.0


def test_raws_slope_is_the_distortions_gain_and_hysteresis_slope(sensor: dict) -> None:
    """Raw reports the change of the reading: per pass, the slope computed here with the loop reading model
    (gain, coupling, temperature, nonlinearity, hysteresis) over the same scored samples."""
    d, x, true = sensor["d"], sensor["x"], sensor["true"]
    expected = Tally()
    for batch in sensor["passes"][:3] + sensor["passes"][-1:]:  # the force passes and the load
        p = np.zeros((N, 6))
        scored = np.zeros(N, dtype=bool)
        for push in batch:
            prof = push.profile()
            p[push.start : push.start + push.length] = prof[:, None] * push.wrench
            scored[push.start : push.start + push.length] = prof > 0.3
        change = _reading_by_loop(d, true + p, x[:, 6]) - _reading_by_loop(d, true, x[:, 6])
        expected.add((batch[0].family, batch[0].magnitude), "raw", change[scored], p[scored])
    for key in {k for k, _ in expected.sums}:
        ours, ref = sensor["as_oracle"].entry(key, "raw"), expected.entry(key, "raw")
        for a in range(6):
            if ref["slopes"][a] is not None:
                assert ours["slopes"][a] == pytest.approx(ref["slopes"][a], abs=1e-4), (key, a)
        assert ours["error"] == pytest.approx(ref["error"], abs=1e-4)
        # the hysteresis makes the reading's slope differ from the static gain: measured, not assumed
        gain = np.diag(d.coupling)[:3] * (1 + d.temperature_gain[:3] * (np.mean(x[:, 6]) - 25))
        assert any(abs(s - g) > 0.01 for s, g in zip(ours["slopes"][:3], gain, strict=True) if s is not None)


def test_without_hysteresis_the_oracle_reports_every_push_exactly(sensor: dict) -> None:
    d, x, true = sensor["d"], sensor["x"], sensor["true"]
    static_only = SensorDistortion.from_dict({**d.to_dict(), "hysteresis": [0.0] * 6})
    passes = plan_pushes(Scales(), N, DT, sensor["lever"], x[:, 7:10], 9.81, 1.0, np.random.default_rng(6))
    tally = log_tally(static_only, x, true, reference_models(static_only, lambda r: r[:, :6]), passes)
    for family, rows in sensor_result(tally, Scales(), sensor["lever"]).items():
        if family in ("force", "moment", "random", "load"):
            for row in rows.values():
                # to the 4 decimals kept, and the nonlinearity's second order in the log's noise
                assert all(s is None or s == pytest.approx(1.0, abs=1e-3) for s in row["oracle"]["slopes"])


def _row(slopes: list, error: float, o_slopes: list, o_error: float) -> dict:
    def entry(s: list, e: float) -> dict:
        return {"slopes": [*s, None, None, None], "error": e, "error_torque": None}

    return {"deployed": entry(slopes, error), "oracle": entry(o_slopes, o_error), "raw": entry(slopes, error)}


def test_the_verdicts_thresholds() -> None:
    """Slope error |s - 1| at most the oracle's + tolerance on every axis at every magnitude; change error
    at most target x the oracle's (floored at ERROR_FLOOR)."""
    oracle = [1.1, 1.1, 1.05]
    ok = {"force": {"1": _row([1.15, 0.95, 1.0], 0.15, oracle, 0.1), "40": _row([1.0] * 3, 0.1, oracle, 0.1)}}
    v = judge(ok, 0.1, 1.5)
    assert v["pass"] and v["worst_slope_excess"] == pytest.approx(0.05) and v["worst_change_ratio"] == 1.5
    slope_off = {"force": {**ok["force"], "5": _row([1.0, 0.79, 1.0], 0.1, oracle, 0.1)}}
    v = judge(slope_off, 0.1, 1.5)
    assert not v["pass"] and v["at_slope"] == "5 fy" and v["worst_slope_excess"] == pytest.approx(0.11)
    change_off = {"force": {**ok["force"], "2": _row([1.0] * 3, 0.1501, oracle, 0.1)}}
    assert not judge(change_off, 0.1, 1.5)["pass"] and judge(change_off, 0.1, 1.5)["at_change"] == "2"
    tiny = {"force": {"1": _row([1.0] * 3, 1.4 * ERROR_FLOOR, [1.0] * 3, 1e-6)}}  # the oracle's floored
    assert judge(tiny, 0.1, 1.5)["pass"]
    moments = judge({"moment": ok["force"]}, 0.1, 1.5)  # moments: shown, not judged
    assert moments["worst_slope_excess"] is None


class Snapper(torch.nn.Module):
    """A 'network' that learned to cancel what looks like noise: it pulls the raw wrench back towards its
    training relation (here wrench = M acc) by ``exp(-(|r| / rho)^2)`` of the deviation r (torques in units
    of the lever). A push of size d either way moves it by d (1 - exp(-(d / rho)^2))."""

    def __init__(self, mass: np.ndarray, rho_n: float, lever_m: float) -> None:
        super().__init__()
        self.mass = torch.as_tensor(mass)
        self.rho = torch.as_tensor(np.r_[np.full(3, rho_n), np.full(3, rho_n * lever_m)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r = x[..., :6] - x[..., 7:10] @ self.mass.T
        pull = torch.exp(-(((r / self.rho) ** 2).sum(-1, keepdim=True)))
        return x[..., :6] - pull * r


def test_the_small_scale_check_flags_a_network_that_snaps_small_pushes() -> None:
    rng = np.random.default_rng(7)
    mass = rng.normal(0, 2.0, (6, 3))
    acc = rng.normal(0, 3.0, (500, 1, 3))
    x = np.concatenate([acc @ mass.T, np.full((500, 1, 1), 30.0), acc, np.zeros((500, 1, 3))], axis=2)
    push, rho = PushPrior(0.1, 20.0, 0.2), 3.0
    net = Snapper(mass, rho, push.lever_m)
    affine = np.diag([0.97, 1.02, 0.99, 1.01, 0.98, 1.0])
    predictors = {
        "nn13": (lambda v: net(torch.as_tensor(v)).numpy(), 13),
        "affine": (lambda v: v[:, :, :6] @ affine.T + 0.5, 7),
    }
    fid = group_fidelity(predictors, x, ["s"], push)
    snap = fid["nn13"]["s"]
    for scale in SCALES_N:
        expected = 1 - np.exp(-((scale / rho) ** 2))
        np.testing.assert_allclose(snap["scales"][f"{scale:g}"], expected, atol=1e-9)
    assert min(snap["slopes"]) > 1 - 0.15  # at the prior's size (20 N) it looks faithful
    np.testing.assert_allclose(fid["affine"]["s"]["scales"]["1"], np.diag(affine), atol=1e-12)
    flags = unfaithful(fid, 0.15)
    assert set(flags) == {"nn13"} and flags["nn13"].endswith("at 1 N")


class _Report:
    """The few fields of a GroupReport the floors read: RMSE against the truth per model, the noise floor."""

    def __init__(self, truth: dict, floor: float) -> None:
        self.group, self.headline, self.headlines, self.recommended = "arm", "arm", [], "nn7"
        self.truth, self.floor = truth, {"arm": floor}

    def headline_rmse(self, ref: str, model: str | None, name: str | None = None) -> float | None:
        return self.truth.get(model) if ref == "truth" else None


def test_below_the_oracle_the_page_says_which_floor() -> None:
    import pandas as pd

    from pipeline.evaluation.floors import noise_columns, noise_floor, prior_notes
    from pipeline.logs import schema as S

    rng = np.random.default_rng(8)
    noise = rng.standard_normal((5000, 6)) * np.r_[np.full(3, 0.6), np.full(3, 0.03)]
    clean = rng.normal(0, 20, (5000, 6))
    cols = [c for q in (S.FT, S.DISTORTED, S.TRUE) for c in S.wrench_cols(q, "arm")]
    frame = pd.DataFrame(np.c_[clean + noise, clean, clean], columns=cols)
    frame = pd.concat([frame, pd.DataFrame(noise_columns(frame, ["arm"], {}, ["arm"], {}))], axis=1)
    floor = noise_floor(frame, ["arm"])["arm"]
    assert floor == pytest.approx(np.sqrt(np.mean(noise**2)), rel=1e-12)
    assert floor == pytest.approx(np.sqrt((3 * 0.36 + 3 * 0.0009) / 6), rel=0.03)  # the noise std pooled
    report = _Report({"oracle": 0.74, "affine": 0.54, "nn7": 0.30, "nn13": 0.9, "play": 0.45}, floor)
    notes = prior_notes([report], ["affine", "nn13", "play"])
    assert len(notes) == 3  # nn13 is above the oracle: nothing said
    (look_a, _, affine), (look_p, _, play), (look_n, _, nn7) = notes
    assert "<b>affine</b>" in affine and "hysteresis absorbed as gain" in affine and look_a
    # memory: between the oracle and the noise floor is where it belongs (no look asked)
    assert "<b>play</b>" in play and "memory undoes the sensor's hysteresis" in play and not look_p
    assert "<b>nn7</b>" in nn7 and "below the noise floor" in nn7 and "prior" in nn7 and look_n


def test_step_response_of_a_held_load() -> None:
    """A held load's step response (`pipeline.deploy.steps`): a model reporting the push as it is stays at 1
    on the plateau; one reading a fresh load 20 % larger than a held one shows it as a decay."""
    from pipeline.deploy.scales import Push
    from pipeline.deploy.steps import Steps

    push = Push("load", 2.0, None, np.r_[3.0, 0.0, -19.6, 0.5, 0.2, 0.0], 0, 200, ramp=0.15)
    p = push.profile()[:, None] * push.wrench
    steps = Steps()
    steps.add("deployed", p.copy(), p, push.wrench)
    steps.add("oracle", p * np.linspace(1.2, 1.0, 200)[:, None], p, push.wrench)
    entry = steps.entry()
    assert entry["holds"] == 1 and max(entry["truth"]) == pytest.approx(1.0, abs=1e-3)
    np.testing.assert_allclose(entry["models"]["deployed"], entry["truth"], atol=1e-12)
    flat, decaying = entry["plateau"]["deployed"], entry["plateau"]["oracle"]
    assert flat["first"] == flat["last"] == pytest.approx(1.0, abs=1e-3)
    assert decaying["first"] - decaying["last"] > 0.08 and decaying["max"] > 1.1
