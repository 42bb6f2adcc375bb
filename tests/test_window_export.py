"""The windowed network's export (family ``win``): its graph against `WindowModel.predict_log` over a long
log in float64 and float32, its play and filter state carried from call to call, fused beside groups of
other families, causal; its manifest state entry (the filters' columns, the sample period); a bad win.json
named."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import onnx
import pytest

from pipeline.calib.linear import LinearBaseline, monomial_powers
from pipeline.calib.window import Layer, WindowModel, WindowNet
from pipeline.core.errors import DataError
from pipeline.export import graph, manifest
from pipeline.export.check import max_ulps, run_logs, run_state, session
from pipeline.export.linear import state_layout, state_period
from pipeline.export.trained import GroupModel, read_group

TAUS = [0.02, 0.1, 0.5]
PERIOD = 0.01
SCALE = np.r_[np.full(3, 60.0), np.full(3, 4.0)]  # the random walks' step per sample: N, Nm (x 0.02)


def window_model(
    n_sensors: int,
    taus: list[float] = TAUS,
    hidden: int = 16,
    depth: int = 2,
    seed: int = 0,
    temperature: bool = True,
    activations: tuple[str, ...] = ("leaky_relu", "tanh"),
) -> WindowModel:
    """A windowed network of random weights over a random play model (3 play widths) of `n_sensors`."""
    rng = np.random.default_rng(seed)
    k = 7 if temperature else 6
    widths = np.array([SCALE / 6, SCALE / 2, SCALE * 1.5])
    offset = np.tile(np.r_[np.zeros(6), 30.0][:k], (n_sensors, 1))
    scale = np.tile(np.r_[SCALE * 5, 3.0][:k], (n_sensors, 1))
    base = LinearBaseline("play", offset, scale, monomial_powers(k, 1), np.zeros(0), widths)
    base.weights = rng.normal(size=(n_sensors, 6, k + 1 + widths.size)) * 0.3
    n_features = 6 * (len(taus) + 1) + k - 6
    nets = []
    for _ in range(n_sensors):
        layers, width = [], n_features
        for j in range(depth):
            out = 6 if j == depth - 1 else hidden
            act = None if j == depth - 1 else activations[j % len(activations)]
            layers.append(
                Layer(rng.normal(size=(out, width)) / np.sqrt(width), rng.normal(size=out) * 0.1, act, 0.1)
            )
            width = out
        in_offset = np.r_[rng.normal(size=6 * (len(taus) + 1)), 30.0][:n_features]
        in_scale = np.r_[np.tile(SCALE * 3, len(taus) + 1), 2.0][:n_features]
        nets.append(WindowNet(in_offset, in_scale, np.r_[np.full(3, 2.0), np.full(3, 0.1)], layers))
    return WindowModel(base, np.asarray(taus, dtype=np.float64), PERIOD, nets)


def write_window(model_dir: Path, group: str, sensors: list[str], model: WindowModel) -> GroupModel:
    """models/<group>/win.json and the metrics.json `read_group` needs; the export's view of it."""
    model_dir.mkdir(parents=True, exist_ok=True)
    (model_dir / "win.json").write_text(json.dumps(model.to_dict()))
    (model_dir / "metrics.json").write_text(json.dumps({"group": group, "sensors": sensors, "test": {}}))
    return read_group(model_dir, "win", group)


def walk(n: int, n_sensors: int, seed: int = 1, temperature: bool = True) -> np.ndarray:
    """(n, S, 7 or 6) one log's raw inputs: a random walk of the wrench, a slow temperature."""
    rng = np.random.default_rng(seed)
    wrench = np.cumsum(rng.normal(size=(n, n_sensors, 6)) * SCALE * 0.02, axis=0) * 5
    t = 30.0 + np.cumsum(rng.normal(size=(n, n_sensors, 1)) * 0.01, axis=0)
    return np.concatenate([wrench, t], axis=2) if temperature else wrench


@pytest.fixture(scope="module")
def group(tmp_path_factory: pytest.TempPathFactory) -> tuple[GroupModel, WindowModel]:
    model = window_model(2)
    return write_window(tmp_path_factory.mktemp("models") / "pair", "pair", ["a", "b"], model), model


def test_graph_equals_the_model_over_a_long_log(group: tuple[GroupModel, WindowModel]) -> None:
    exported, model = group
    x = walk(3000, 2)
    reference = model.predict_log(x).reshape(len(x), -1)
    assert np.abs(reference - model.base.predict_log(x).reshape(len(x), -1)).max() > 0.1  # a correction
    np.testing.assert_allclose(exported.reference(x.reshape(len(x), -1)), reference, rtol=0, atol=0)
    y64 = run_logs(session(graph.build([exported], "float64", {}, "g")), x.reshape(len(x), -1), None)
    np.testing.assert_allclose(y64, reference, rtol=0, atol=1e-9)
    rounded = x.astype(np.float32).astype(np.float64)
    target = model.predict_log(rounded).reshape(len(x), -1)
    y32 = run_logs(session(graph.build([exported], "float32", {}, "g")), x.reshape(len(x), -1), None)
    np.testing.assert_allclose(y32, target, rtol=0, atol=2e-3)
    assert max_ulps(y32, target) <= 8  # the export check's tolerance (params export.tolerance_float32_ulps)


@pytest.mark.parametrize("dtype", graph.DTYPES)
def test_state_is_carried_from_call_to_call(group: tuple[GroupModel, WindowModel], dtype: str) -> None:
    exported, _ = group
    x = walk(700, 2, seed=2).reshape(700, -1)
    sess = session(graph.build([exported], dtype, {}, "g", per_sample=dtype == "float32"))
    whole, last = run_state(sess, x)
    first, state = run_state(sess, x[:333])
    second, again = run_state(sess, x[333:], state=state)
    atol = 1e-12 if dtype == "float64" else 1e-5
    np.testing.assert_allclose(np.concatenate([first, second]), whole, rtol=0, atol=atol)
    np.testing.assert_array_equal(again, last)
    one_by_one, state = [], None  # a control loop: one sample per call
    for row in x[:60]:
        y, state = run_state(sess, row[None], state=state)
        one_by_one.append(y[0])
    np.testing.assert_allclose(np.array(one_by_one), whole[:60], rtol=0, atol=atol)
    fresh = np.concatenate([run_state(sess, x[k : k + 7])[0] for k in range(0, 700, 7)])
    assert np.abs(fresh - whole).max() > 0.1  # without the state each call forgets the windows


def test_graph_is_causal(group: tuple[GroupModel, WindowModel]) -> None:
    exported, _ = group
    x = walk(400, 2, seed=3)
    sess = session(graph.build([exported], "float64", {}, "g"))
    y = run_logs(sess, x.reshape(400, -1), None)
    changed = x.copy()
    changed[250, 0, 1] += 40.0
    z = run_logs(sess, changed.reshape(400, -1), None)
    np.testing.assert_array_equal(z[:250], y[:250])
    assert np.abs(z[251:, :6] - y[251:, :6]).max() > 1e-3 and np.abs(z[251:, 6:] - y[251:, 6:]).max() == 0


def test_fused_graph_equals_each_group_alone(group: tuple[GroupModel, WindowModel], tmp_path: Path) -> None:
    from benchmarks.export_fixture import synthetic_linear, synthetic_models

    exported, _ = group
    affine = synthetic_linear(tmp_path / "affine", "affine")[0]
    play = synthetic_linear(tmp_path / "play", "play")[2]
    network = synthetic_models(tmp_path / "nn", n_inputs=7, hidden=8)[0][4]
    single = write_window(tmp_path / "win1", "w1", ["c"], window_model(1, [0.05], seed=5, temperature=False))
    models = [affine, exported, play, network, single]
    n = 300
    xs = [walk(n, len(m.sensors), 10 + k, m.n_inputs == 7).reshape(n, -1) for k, m in enumerate(models)]
    for dtype in graph.DTYPES:
        for per_sample in (False, True):
            fused = session(graph.build(models, dtype, {}, "fused", per_sample=per_sample))
            y, state = run_state(fused, np.concatenate(xs, axis=1))
            alone = [
                run_state(session(graph.build([m], dtype, {}, m.group)), xi)[0]
                for m, xi in zip(models, xs, strict=True)
            ]
            atol = 1e-9 if dtype == "float64" else 2e-3
            np.testing.assert_allclose(y, np.concatenate(alone, axis=1), rtol=0, atol=atol)
    layout = state_layout(models)
    assert len(layout) == len(state) and [c["index"] for c in layout] == list(range(len(state)))
    filters = [c for c in layout if "time_constant_s" in c]  # the windows' filters, among the operators
    assert len(filters) == 6 * (3 + 3 + 1) and {c["sensor"] for c in filters} == {"a", "b", "c"}


def test_manifest_lists_the_filters_and_the_period(group: tuple[GroupModel, WindowModel]) -> None:
    exported, model = group
    state = manifest._state([exported])["state"]
    n_play = model.base.widths.size
    assert state["shape"] == [2 * (n_play + 6 * len(TAUS))] and state["period_s"] == PERIOD
    assert "0.01 s apart" in state["carry"]
    columns = state["columns"]
    assert [c["index"] for c in columns] == list(range(len(columns)))
    a = [c for c in columns if c["sensor"] == "a"]  # per sensor: its play operators, then its filters
    assert [c.get("width") is not None for c in a] == [True] * n_play + [False] * 6 * len(TAUS)
    assert [(c["time_constant_s"], c["axis"], c["unit"]) for c in a[n_play : n_play + 7]] == [
        (TAUS[0], ax, u)
        for ax, u in zip(("fx", "fy", "fz", "tx", "ty", "tz"), ["N"] * 3 + ["Nm"] * 3, strict=True)
    ] + [(TAUS[1], "fx", "N")]
    assert exported.memory and exported.kind == "window" and exported.info["time_constants_s"] == TAUS
    assert state_period([exported]) == PERIOD


def test_sensor_carried_alone_equals_the_group_call(group: tuple[GroupModel, WindowModel]) -> None:
    """A runtime carries one sensor's state columns (by the manifest's sensor) and NaN elsewhere."""
    exported, _ = group
    sess = session(graph.build([exported], "float64", {}, "g"))
    x = walk(200, 2, seed=4).reshape(200, -1)
    whole, _ = run_state(sess, x)
    columns = [c["index"] for c in state_layout([exported]) if c["sensor"] == "b"]
    _, state = run_state(sess, x[:120])
    carried = np.full(len(state), np.nan)
    carried[columns] = state[columns]
    y, _ = run_state(sess, x[120:], state=carried)
    np.testing.assert_allclose(y[:, 6:], whole[120:, 6:], rtol=0, atol=1e-12)


def test_bad_win_json_is_a_data_error_naming_it(tmp_path: Path) -> None:
    (tmp_path / "metrics.json").write_text(json.dumps({"group": "g", "sensors": ["s"], "test": {}}))
    with pytest.raises(DataError, match=r"win\.json: not found"):
        read_group(tmp_path, "win", "g")
    (tmp_path / "win.json").write_text("{}")
    with pytest.raises(DataError, match=r"win\.json: not a windowed network"):
        read_group(tmp_path, "win", "g")
    entry = window_model(2).to_dict()
    (tmp_path / "win.json").write_text(json.dumps(entry))
    with pytest.raises(DataError, match=r"win\.json: 2 play sensors, 2 networks; metrics.json 1"):
        read_group(tmp_path, "win", "g")
    entry = window_model(1).to_dict()
    entry["time_constants"] = [0.5, -1.0]
    (tmp_path / "win.json").write_text(json.dumps(entry))
    with pytest.raises(DataError, match=r"win\.json: time constants \[0.5, -1.0\] s are not positive"):
        read_group(tmp_path, "win", "g")


def test_export_check_runs_the_logs_in_time_order(group: tuple[GroupModel, WindowModel]) -> None:
    """The export stage's check of a model with memory (`check_group` on two logs, each from a fresh state,
    and in chunks carrying the state) is within the stage's tolerances in both float types."""
    from pipeline.export.check import CHUNK, Samples, _references, check_group

    exported, _ = group
    x = np.concatenate([walk(1500, 2, seed=20), walk(900, 2, seed=21)]).reshape(2400, -1)
    bounds = np.array([0, 1500])
    reference32, reference = _references(exported, x, bounds)
    samples = Samples(x, reference, reference32, reference, bounds, np.zeros((len(x), 2), np.int64))
    graphs = {d: graph.build([exported], d, {}, "g") for d in graph.DTYPES}
    result = check_group(graphs, samples)
    assert result["float64"]["max_abs_diff"] <= 1e-9 and result["float32"]["max_ulps"] <= 8, result
    assert result["float64"]["state_carry"] <= 1e-9 and len(x) > 2 * CHUNK


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler")
def test_c_api_harness_carries_the_window(group: tuple[GroupModel, WindowModel], tmp_path: Path) -> None:
    from benchmarks.infer_speed import c_api_latency

    exported, _ = group
    path = tmp_path / "win.float32.onnx"
    onnx.save_model(graph.build([exported], "float32", {}, "fused", per_sample=True), path)
    pool = walk(16, 2, seed=5).reshape(16, -1).astype(np.float32)
    size = {i.name: i.shape[0] for i in session(path).get_overridable_initializers()}["state"]
    result = c_api_latency(path, pool, 12, calls=13, work=tmp_path, warmup=3, state=size)
    assert isinstance(result, dict), result
    y, _ = run_state(session(path), pool)  # the harness's 16 calls carry the state: one call of 16 rows
    assert result["checksum"] == pytest.approx(float(y[:, 0].sum()), rel=1e-6, abs=1e-6)
