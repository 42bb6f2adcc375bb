"""Calibrations with memory (the ``play`` family): a synthetic sensor with a known play-operator hysteresis
(the simulator's reading model) is calibrated down to its white noise, which a memoryless fit cannot do;
the fit's truth-free fidelity holds a push and takes it fresh; the exported graph carries its state from
call to call as the project's model does over a whole log; the registry names every family once."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.calib.fidelity import memory_gaps, model_fidelity
from pipeline.calib.linear import fit_linear_baseline
from pipeline.calib.pushes import PushPrior
from pipeline.calib.registry import complexity, families, family_of, has_memory, kind_of, nn_name, poly_name
from pipeline.core.errors import DataError
from pipeline.core.play import play_memory, play_operator
from pipeline.evaluation.fidelity import unfaithful
from pipeline.export import graph
from pipeline.export.check import run_logs, run_state, session
from pipeline.export.trained import read_group

WIDTH = np.r_[np.full(3, 30.0), np.full(3, 2.0)]  # the simulated sensors' play width: 2 % of full scale
HYSTERESIS = np.r_[4.0, -2.5, 3.0, 0.25, 0.2, -0.15]  # h per axis, N / Nm (up to 0.3 % of full scale)
NOISE = np.r_[np.full(3, 0.6), np.full(3, 0.03)]
WIDTHS = np.array([WIDTH / 3, WIDTH, WIDTH * 3])  # the play model's grid around it
PUSH = PushPrior(0.1, 20.0, 0.2)


def _log(seed: int, n: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """(raw inputs (n, 1, 7), true wrench (n, 1, 6)) of one log: a slow multi-sine wrench of a few 100 N
    read through gain, offset, play-operator hysteresis and white noise (`pipeline.sim.distortion`)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.01
    scale = np.r_[np.full(3, 150.0), np.full(3, 8.0)]
    phases = rng.uniform(0, 2 * np.pi, (3, 6))
    w = sum(np.sin(2 * np.pi * f * t[:, None] + phases[k]) for k, f in enumerate((0.11, 0.37, 0.83))) * scale
    raw = 1.02 * w + np.r_[30.0, -20.0, 25.0, 2.0, -1.0, 1.5] + HYSTERESIS * play_operator(w, WIDTH)
    raw += rng.normal(size=raw.shape) * NOISE
    x = np.concatenate([raw, np.full((n, 1), 30.0)], axis=1)
    return x[:, None, :], w[:, None, :]


def _fit(widths: np.ndarray | None) -> object:
    logs = [_log(seed) for seed in range(3)]
    x = np.concatenate([g[0] for g in logs])
    labels = np.concatenate([g[1] for g in logs])
    memory = None if widths is None else np.concatenate([play_memory(g[0], widths) for g in logs])
    name = "affine" if widths is None else "play"
    return fit_linear_baseline(
        name, x, labels, np.ones((len(x), 1), bool), 1, 0.0, (1.0,), push=PUSH, widths=widths, memory=memory
    )


@pytest.fixture(scope="module")
def models() -> dict:
    return {"affine": _fit(None), "play": _fit(WIDTHS)}


def _rmse(model: object, seed: int = 7) -> float:
    x, w = _log(seed)
    return float(np.sqrt(np.mean((model.predict_log(x) - w) ** 2)))


def test_play_model_calibrates_a_hysteretic_sensor_down_to_its_noise(models: dict) -> None:
    # the noise floor: the white noise's RMS over the 6 axes pooled
    floor = float(np.sqrt(np.mean(NOISE**2)))
    play, affine = _rmse(models["play"]), _rmse(models["affine"])
    assert play < 1.25 * floor, (play, floor)
    assert affine > 2.5 * play  # the hysteresis, up to 4 N, is beyond any memoryless map
    # its memory: a fresh push's slope less the held one's undoes the hysteresis's minor-loop gain, -h / width
    # where the operator is inside its loop, 0 where the push drives it further into saturation (half of the
    # pushes either way at 1 N, more at the prior's 20 N)
    x, _ = _log(8)
    entry = model_fidelity(models["play"].predict, x, PUSH, 7, play_memory(x, WIDTHS))[0]
    gaps = {(scale, a): d for scale, a, d in memory_gaps(entry)}
    for scale in ("", "1 N", "20 N"):
        gap = np.array([gaps[(scale, a)] for a in range(6)])
        assert (np.sign(gap) == -np.sign(HYSTERESIS)).all(), (scale, gap)
        assert (np.abs(gap) <= np.abs(HYSTERESIS) / WIDTH + 0.01).all(), (scale, gap)
    np.testing.assert_allclose(entry["slopes"], 1 / 1.02, atol=0.02)  # held: the static inverse
    assert unfaithful({"play": {"s": entry}}, 0.15, 0.2) == {}
    # a memory standing in for the wrench: fx reported as its smallest operator's output (a +-10 N deadband)
    deadband = copy.deepcopy(models["play"])
    deadband.weights[0, 0, 8] -= WIDTHS[0, 0]  # z = (f - y) / r: f - r z = y
    entry = model_fidelity(deadband.predict, x, PUSH, 7, play_memory(x, WIDTHS))[0]
    assert unfaithful({"play": {"s": entry}}, 0.15, 0.2)["play"].startswith("s fx memory adds -0.")


def test_memory_is_causal_and_starts_afresh_at_each_log(models: dict) -> None:
    x, _ = _log(9, n=800)
    y = models["play"].predict_log(x)
    changed = x.copy()
    changed[500, 0, 0] += 80.0  # a spike at sample 500
    z = models["play"].predict_log(changed)
    np.testing.assert_array_equal(z[:500], y[:500])
    assert np.abs(z[501:, 0, 0] - y[501:, 0, 0]).max() > 1.0  # remembered after the spike
    # the memory of a log's samples concatenated after another log's restarts where it starts
    both = play_memory(np.concatenate([x, x]), WIDTHS)
    np.testing.assert_array_equal(np.isnan(play_memory(x, WIDTHS)[:, 0, 0]).nonzero()[0], [0])
    assert not np.isnan(both[800]).any()  # one sequence: no restart unless asked (`play_memory` per log)


def _exported(tmp: Path, model: object) -> object:
    """The play model as the export reads it from a train output directory."""
    tmp.mkdir(parents=True, exist_ok=True)
    (tmp / "baselines.json").write_text(json.dumps({"play": model.to_dict()}))
    (tmp / "metrics.json").write_text(json.dumps({"group": "g", "sensors": ["s"], "test": {}}))
    return read_group(tmp, "play", "g")


def test_graph_carries_the_state_from_call_to_call(models: dict, tmp_path: Path) -> None:
    group = _exported(tmp_path / "g", models["play"])
    x = _log(10, n=1200)[0][:, 0]
    reference = models["play"].predict_log(x[:, None, :])[:, 0]
    for dtype, atol in (("float64", 1e-9), ("float32", 1e-3)):
        sess = session(graph.build([group], dtype, {}, "g"))
        whole = run_logs(sess, x, None)
        np.testing.assert_allclose(whole, reference, rtol=0, atol=atol)
        np.testing.assert_allclose(run_logs(sess, x, None, chunk=97), whole, rtol=0, atol=atol)
        one_by_one, state = [], None  # a control loop: one sample per call, the state carried
        for row in x[:300]:
            y, state = run_state(sess, row[None], state=state)
            one_by_one.append(y[0])
        np.testing.assert_allclose(np.array(one_by_one), whole[:300], rtol=0, atol=atol)
    fresh = np.concatenate([run_state(sess, x[k : k + 97])[0] for k in range(0, len(x), 97)])
    assert np.abs(fresh - whole).max() > 0.1  # without the state each call forgets the path


def test_registry_names_every_family_once() -> None:
    names = ["raw", "affine", poly_name(1), poly_name(4), "play", "arx", nn_name(7), nn_name(13), "win"]
    assert sorted(names, key=complexity) == names
    keys = ["raw", "affine", "poly", "poly", "play", "arx", "nn", "nn", "win"]
    assert [family_of(n).key for n in names] == keys
    assert [kind_of(n) for n in names] == ["identity"] + ["linear"] * 5 + ["network"] * 2 + ["window"]
    assert [n for n in names if has_memory(n)] == ["play", "arx", "win"]
    assert family_of("oracle") is None and family_of("poly") is None and family_of("nnx") is None
    assert len({f.key for f in families()}) == len(families())
    assert len({f.rank for f in families()}) == len(families())


def test_export_of_an_unknown_model_names_the_families(tmp_path: Path) -> None:
    (tmp_path / "metrics.json").write_text(json.dumps({"group": "g", "sensors": ["s"], "test": {}}))
    with pytest.raises(
        DataError, match=r"unknown model 'gru' \(raw, offset, affine, poly<n>, play, arx, nn<n>, win\)"
    ):
        read_group(tmp_path, "gru", "g")


def test_each_axis_remembers_its_own_raw_axis_only(models: dict) -> None:
    # a past excursion of the raw fx (beyond every play width), fx back to the same readings after it: the
    # fx play states differ from there on, the other axes' outputs do not (their memory is their own axis's)
    x, _ = _log(12, n=900)
    changed = x.copy()
    changed[300:340, 0, 0] += 250.0
    y, z = models["play"].predict_log(x)[:, 0], models["play"].predict_log(changed)[:, 0]
    assert np.abs(z[340:, 0] - y[340:, 0]).max() > 0.5  # fx remembers the excursion
    np.testing.assert_allclose(z[340:, 1:], y[340:, 1:], rtol=0, atol=1e-12)
