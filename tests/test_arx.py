"""The arx family (a lagged linear map of the raw wrench's history through first-order filters): the filters
against their analytic step response; a synthetic sensor whose reading creeps (it overshoots a change of
load and relaxes to it with a known time constant) calibrated down to its white noise, which neither a
memoryless fit nor the rate-independent play model can do; causality and fresh starts; the exported graph
carrying the filters' state as the project's model does, and its manifest saying the rate."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.calib.fidelity import model_fidelity
from pipeline.calib.linear import LinearBaseline, fit_linear_baseline
from pipeline.core.lowpass import (
    alphas,
    lowpass_memory,
    lowpass_outputs,
    memory_of,
    memory_step,
    nominal_period,
    operator_columns,
)
from pipeline.core.play import play_memory, play_step
from pipeline.export import graph, manifest
from pipeline.export.check import run_logs, run_state, session
from pipeline.export.linear import state_layout
from pipeline.export.trained import read_group
from tests.factories.sensors import CREEP, DT, NOISE, PUSH, TAU, creep_log

TIME_CONSTANTS = np.array([0.5, 1.5, 5.0])


def test_filter_follows_its_analytic_step_response() -> None:
    k = np.arange(400)
    x = np.r_[0.0, np.ones(399)][:, None]  # a unit step after the first sample
    y = lowpass_outputs(x, alphas(np.array([TAU]), DT))[:, 0]
    np.testing.assert_allclose(y, np.where(k == 0, 0.0, 1.0 - np.exp(-k * DT / TAU)), rtol=0, atol=1e-12)
    # one step of memory_step is the same recursion; alpha 0 is the play operator's step
    prev, now = np.array([0.3, np.nan]), np.array([1.0, 2.0])
    gain = alphas(np.array([TAU]), DT)[0]
    np.testing.assert_allclose(memory_step(prev, now, np.inf, gain), [0.3 + gain * 0.7, 2.0])
    np.testing.assert_array_equal(play_step(prev, now, 0.5), [0.5, 2.0])  # clip(0.3, 1 - 0.5, 1 + 0.5)
    assert nominal_period(np.r_[0.0, 0.01, 0.02, 0.05, 0.06]) == pytest.approx(0.01)


def test_filter_memory_skips_missing_readings_and_starts_afresh() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 1, 6)) * 10
    x[20, 0, 2] = np.nan  # a missing reading
    mem = lowpass_memory(x, TIME_CONSTANTS, DT)
    assert np.isnan(mem[0]).all() and np.isnan(mem[20]).all() and np.isfinite(mem[21]).all()
    # the explicit loop: outputs after each finite sample, before the next
    gains = np.repeat(alphas(TIME_CONSTANTS, DT), 6)
    y, expected = np.full(18, np.nan), np.full((50, 18), np.nan)
    for k in range(50):
        if not np.isfinite(x[k, 0]).all():
            continue
        expected[k] = y
        y = memory_step(y, np.tile(x[k, 0], 3), np.inf, gains)
    expected[0] = np.nan
    np.testing.assert_allclose(mem[:, 0], expected, rtol=0, atol=1e-12)
    both = memory_of(x, np.ones((1, 6)), TIME_CONSTANTS, DT)  # play first, then the filters
    np.testing.assert_array_equal(both[:, :, :6], play_memory(x, np.ones((1, 6))))
    np.testing.assert_array_equal(both[:, :, 6:], mem)
    radius, alpha, scale = operator_columns(np.ones((1, 6)), TIME_CONSTANTS, DT)
    assert radius.shape == (24,) and np.isinf(radius[6:]).all() and (alpha[:6] == 0).all()
    np.testing.assert_array_equal(scale, np.r_[np.ones(6), np.ones(18)])


def _fit(name: str) -> LinearBaseline:
    logs = [creep_log(seed) for seed in range(3)]
    x = np.concatenate([g[0] for g in logs])
    labels = np.concatenate([g[1] for g in logs])
    spec = {
        "affine": {},
        "play": {"widths": np.array([np.r_[np.full(3, w), np.full(3, w / 20)] for w in (10.0, 30.0, 90.0)])},
        "arx": {"time_constants": TIME_CONSTANTS, "period": DT},
    }[name]
    memory = np.concatenate(
        [memory_of(g[0], spec.get("widths"), spec.get("time_constants"), DT) for g in logs]
    ) if spec else None  # fmt: skip
    switches = np.ones((len(x), 1), bool)
    return fit_linear_baseline(name, x, labels, switches, 1, 0.0, (1.0,), push=PUSH, memory=memory, **spec)


@pytest.fixture(scope="module")
def models() -> dict[str, LinearBaseline]:
    return {name: _fit(name) for name in ("affine", "play", "arx")}


def _rmse(model: LinearBaseline, seed: int = 7) -> float:
    x, w = creep_log(seed)
    return float(np.sqrt(np.mean((model.predict_log(x) - w) ** 2)))


def test_arx_model_calibrates_a_creeping_sensor_down_to_its_noise(models: dict[str, LinearBaseline]) -> None:
    floor = float(np.sqrt(np.mean(NOISE**2)))
    arx, play, affine = (_rmse(models[n]) for n in ("arx", "play", "affine"))
    assert arx < 1.15 * floor, (arx, floor)
    assert affine > 2.0 * arx and play > 1.5 * arx, (affine, play, arx)  # the creep is rate-dependent
    # held long after its onset, a push is read through the static inverse alone
    x, _ = creep_log(8)
    entry = model_fidelity(models["arx"].predict, x, PUSH, 7, memory_of(x, None, TIME_CONSTANTS, DT))[0]
    np.testing.assert_allclose(entry["slopes"], 1 / 1.02, atol=0.02)
    # at its onset the reading overshoots by the creep, which the model takes off
    instant = np.array(entry["instant"]["slopes"])
    np.testing.assert_allclose(instant, 1 / (1.02 + CREEP * (1 - alphas(np.array([TAU]), DT)[0])), atol=0.02)


def test_arx_memory_is_causal_and_reads_the_period(models: dict[str, LinearBaseline]) -> None:
    x, _ = creep_log(9, n=800)
    y = models["arx"].predict_log(x)
    changed = x.copy()
    changed[500, 0, 0] += 80.0
    z = models["arx"].predict_log(changed)
    np.testing.assert_array_equal(z[:500], y[:500])
    assert np.abs(z[501:, 0, 0] - y[501:, 0, 0]).max() > 1e-3  # remembered after the spike (0.01 N)
    assert not np.allclose(models["arx"].predict_log(x, period=10 * DT), y)  # another rate, other filters
    again = LinearBaseline.from_dict(json.loads(json.dumps(models["arx"].to_dict())))
    np.testing.assert_array_equal(again.predict_log(x), y)


def test_graph_carries_the_filters_state_and_says_the_rate(
    models: dict[str, LinearBaseline], tmp_path: Path
) -> None:
    (tmp_path / "baselines.json").write_text(json.dumps({"arx": models["arx"].to_dict()}))
    (tmp_path / "metrics.json").write_text(json.dumps({"group": "g", "sensors": ["s"], "test": {}}))
    group = read_group(tmp_path, "arx", "g")
    assert group.memory and group.parts[0].state_size == 18
    x = creep_log(10, n=1200)[0][:, 0]
    reference = models["arx"].predict_log(x[:, None, :])[:, 0]
    for dtype, atol in (("float64", 1e-9), ("float32", 1e-3)):
        sess = session(graph.build([group], dtype, {}, "g"))
        whole = run_logs(sess, x, None)
        np.testing.assert_allclose(whole, reference, rtol=0, atol=atol)
        np.testing.assert_allclose(run_logs(sess, x, None, chunk=97), whole, rtol=0, atol=atol)
        one_by_one, state = [], None
        for row in x[:200]:
            y, state = run_state(sess, row[None], state=state)
            one_by_one.append(y[0])
        np.testing.assert_allclose(np.array(one_by_one), whole[:200], rtol=0, atol=atol)
    layout = state_layout([group])
    assert [c["time_constant_s"] for c in layout[::6]] == TIME_CONSTANTS.tolist()
    assert [c["axis"] for c in layout[:6]] == ["fx", "fy", "fz", "tx", "ty", "tz"]
    state = manifest._state([group])["state"]  # the manifest's state entry of this graph
    assert state["period_s"] == DT and "0.01 s apart" in state["carry"] and state["shape"] == [18]
