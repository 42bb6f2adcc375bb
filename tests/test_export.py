"""Stage `export`: ONNX graphs of every model family against independent computations, the fused graph
against the groups' graphs, and end to end on tiny trained models (real train output, real onnxruntime,
real MLflow sqlite store): files, manifest, ONNX metadata, checks, registry; bad input."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest
import torch
import yaml

from pipeline.calib.linear import monomial_powers
from pipeline.calib.models import load_model
from pipeline.cli import main
from pipeline.core.config import load_params
from pipeline.core.errors import ConfigError, DataError
from pipeline.export import graph
from pipeline.export.check import run, session
from pipeline.export.registry import REGISTERED_MODEL
from pipeline.export.trained import read_group
from pipeline.stages import export as E
from tests.factories.labelled import LEG, PAIR
from tests.factories.reports import write_recommended

MODELS = ("raw", "affine", "poly1", "poly2", "play", "arx", "nn7", "nn13", "win")
SCALE = np.array([60.0, 60.0, 200.0, 4.0, 4.0, 1.5, 4.0, 1, 1, 1, 1, 1, 1])  # per input: N, Nm, degC, ...


def _inputs(n_sensors: int, n_inputs: int, n: int = 500, seed: int = 0) -> np.ndarray:
    """(n, S n_inputs) raw inputs around the synthetic tables' range (temperature around 30 degC)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, n_sensors, n_inputs)) * SCALE[:n_inputs]
    x[:, :, 6] += 30.0
    return x.reshape(n, -1)


def _outputs(model: Any, dtype: str, x: np.ndarray) -> np.ndarray:
    return run(session(graph.build([model], dtype, {}, "test")), x)


# --- graphs --------------------------------------------------------------------------------------


def test_monomial_index_multiplies_to_every_monomial() -> None:
    powers = monomial_powers(7, 3)
    index = graph.monomial_index(powers)
    z = np.random.default_rng(0).normal(size=(20, 7))
    z1 = np.concatenate([z, np.ones((20, 1))], axis=1)
    expected = np.prod(z[:, None, :] ** powers[None], axis=2)
    np.testing.assert_allclose(np.prod(z1[:, index], axis=2), expected, rtol=1e-12)


@pytest.mark.parametrize("name", MODELS)
def test_group_graph_equals_project_model(trained_models: dict, name: str) -> None:
    model = read_group(trained_models["models"] / PAIR, name)
    x = _inputs(2, model.n_inputs)
    reference = model.reference(x)
    np.testing.assert_allclose(_outputs(model, "float64", x), reference, rtol=0, atol=1e-9)
    if model.kind in ("network", "window"):  # float32 networks (torch's): see test_network_graph_...
        np.testing.assert_allclose(_outputs(model, "float32", x), reference, rtol=0, atol=2e-3)
    else:  # float32 in and out, float64 inside: only the output's rounding (|f| < 1000 N: < 6.1e-5 N)
        rounded = model.reference(x.astype(np.float32).astype(np.float64))
        np.testing.assert_allclose(_outputs(model, "float32", x), rounded, rtol=0, atol=6.2e-5)


def test_affine_graph_equals_hand_computation_from_baselines_json(trained_models: dict) -> None:
    entry = json.loads((trained_models["models"] / LEG / "baselines.json").read_text())["affine"]
    offset, scale, weights = (np.asarray(entry[k]) for k in ("offset", "scale", "weights"))
    x = _inputs(1, 7)
    z = (x - offset[0]) / scale[0]
    expected = x[:, :6] + np.concatenate([np.ones((len(x), 1)), z], axis=1) @ weights[0].T
    model = read_group(trained_models["models"] / LEG, "affine")
    np.testing.assert_allclose(_outputs(model, "float64", x), expected, rtol=0, atol=1e-9)


def test_network_graph_equals_torch_module(trained_models: dict) -> None:
    net, _ = load_model(trained_models["models"] / PAIR / "nn13")
    x = _inputs(2, 13)
    with torch.no_grad():
        expected32 = net(torch.tensor(x, dtype=torch.float32)).numpy()
        expected64 = net.double()(torch.tensor(x)).numpy()
    model = read_group(trained_models["models"] / PAIR, "nn13")
    np.testing.assert_allclose(_outputs(model, "float64", x), expected64, rtol=0, atol=1e-9)
    np.testing.assert_allclose(_outputs(model, "float32", x), expected32, rtol=0, atol=1e-4)


@pytest.mark.parametrize(
    ("leg", "pair_first", "per_sample"),
    [("poly2", False, False), ("nn7", False, False), ("poly2", True, False), ("nn7", False, True)],
)
def test_fused_graph_equals_groups_side_by_side(
    trained_models: dict, leg: str, pair_first: bool, per_sample: bool
) -> None:
    """With nn7 on both groups, the three networks are stacked (one MatMul per layer) across groups; stacked
    networks before another model take only their own input columns. Laid out for batches or for one
    sample per call (`per_sample`, the fused graph of the export), on several samples."""
    models = [
        read_group(trained_models["models"] / LEG, leg),
        read_group(trained_models["models"] / PAIR, "nn7"),
    ]
    x = [_inputs(1, 7, seed=1), _inputs(2, 7, seed=2)]
    if pair_first:
        models, x = models[::-1], x[::-1]
    for dtype in graph.DTYPES:
        built = graph.build(models, dtype, {}, "fused", per_sample=per_sample)
        fused = run(session(built), np.concatenate(x, axis=1))
        separate = np.concatenate([_outputs(m, dtype, xi) for m, xi in zip(models, x, strict=True)], axis=1)
        np.testing.assert_allclose(fused, separate, rtol=0, atol=1e-9 if dtype == "float64" else 2e-3)


@pytest.mark.parametrize("name", MODELS)
def test_offsets_input_is_subtracted_from_the_raw_inputs_and_defaults_to_zero(
    trained_models: dict, name: str
) -> None:
    """The graphs' ``offsets`` input (a re-zeroing's): the graph fed (x, o) is the graph fed x - o (the same
    subtraction in the graph's dtype: bit for bit), and fed x alone the graph as delivered, bit for bit."""
    models = [
        read_group(trained_models["models"] / LEG, name),
        read_group(trained_models["models"] / PAIR, "nn7"),
    ]
    x = np.concatenate([_inputs(1, models[0].n_inputs, seed=3), _inputs(2, 7, seed=4)], axis=1)
    offsets = np.zeros((1, x.shape[1]))
    offsets[0, :6] = [5.0, -3.0, 12.0, 0.4, -0.2, 0.1]  # the leg sensor's wrench columns
    offsets[0, models[0].n_inputs + 7 : models[0].n_inputs + 13] = [-8.0, 1.0, 2.0, 0.3, 0.0, -0.5]
    for dtype in graph.DTYPES:
        for per_sample in (False, True):
            sess = session(graph.build(models, dtype, {}, "fused", per_sample=per_sample))
            xd, od = x.astype(dtype), offsets.astype(dtype)
            np.testing.assert_array_equal(run(sess, xd, od), run(sess, xd - od))
            np.testing.assert_array_equal(run(sess, xd), run(sess, xd, np.zeros_like(od)))
            assert not np.array_equal(run(sess, xd, od), run(sess, xd))


def test_offsets_fill_the_wrench_columns_of_a_manifest_entry() -> None:
    from pipeline.export.offsets import WRENCH_FIELDS, Offsets

    inputs = [{"index": 7 * s + k, "sensor": name, "field": [*WRENCH_FIELDS, "temperature"][k]}
              for s, name in enumerate(("a", "b")) for k in range(7)]  # fmt: skip
    values = {"b": np.arange(1.0, 7.0)}
    vector = Offsets(values).input_vector({"inputs": inputs})
    np.testing.assert_array_equal(vector, [[0.0] * 7 + [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.0]])
    assert Offsets({"c": np.ones(6)}).input_vector({"inputs": inputs}) is None


def _numpy_network(part: Any, x: np.ndarray) -> np.ndarray:
    """One sensor's network in float64 numpy, as `pipeline.calib.models.SensorNet` writes it."""
    h = (x - part.in_offset) / part.in_scale
    for layer in part.layers:
        h = h @ layer.weight.T + layer.bias
        if layer.activation == "relu":
            h = np.maximum(h, 0.0)
        elif layer.activation == "leaky_relu":
            h = np.where(h > 0, h, layer.alpha * h)
        else:
            assert layer.activation is None, layer.activation
    return x[:, :6] + x[:, :7] @ part.affine_weight.T + part.affine_bias + part.out_scale * h


@pytest.mark.parametrize("per_sample", [False, True])
def test_fused_networks_of_different_widths_equal_numpy(trained_models: dict, per_sample: bool) -> None:
    """Networks of different hidden widths are stacked with zero units (an exact extension): a group whose
    networks keep 7 and 5 of their hidden units, fused with the full-width group; one sample and four."""
    full = read_group(trained_models["models"] / PAIR, "nn13")

    def narrow(part: Any, keep: int) -> Any:
        w = [layer.weight for layer in part.layers]
        w = [w[0][:keep], *(wk[:keep, :keep] for wk in w[1:-1]), w[-1][:, :keep]]
        layers = tuple(
            dataclasses.replace(layer, weight=wk, bias=layer.bias[: len(wk)])
            for layer, wk in zip(part.layers, w, strict=True)
        )
        return dataclasses.replace(part, layers=layers)

    small = dataclasses.replace(
        full, group="small", parts=(narrow(full.parts[0], 7), narrow(full.parts[1], 5))
    )
    assert small.parts[1].layers[1].weight.shape == (5, 5)
    x = _inputs(4, 13, seed=3)
    expected = np.concatenate(
        [
            _numpy_network(part, x[:, 13 * s : 13 * (s + 1)])
            for s, part in enumerate((*full.parts, *small.parts))
        ],
        axis=1,
    )
    for dtype, atol in (("float64", 1e-9), ("float32", 2e-3)):
        fused = graph.build([full, small], dtype, {}, "fused", per_sample=per_sample)
        assert sum(node.op_type in ("Conv", "MatMul") for node in fused.graph.node) == 3  # one stack
        sess = session(fused)
        np.testing.assert_allclose(run(sess, x), expected, rtol=0, atol=atol)
        np.testing.assert_allclose(run(sess, x[:1]), expected[:1], rtol=0, atol=atol)


def test_leaky_relu_stays_apart_from_its_convolution(trained_models: dict, tmp_path: Path) -> None:
    """onnxruntime fuses an activation into the convolution before it; for LeakyReLU the fused kernel is
    slower a call than the two apart (`pipeline.export.graph`), so after onnxruntime's own optimisations
    the first layer's LeakyReLU still runs on its own while the second layer's ReLU is fused."""
    import onnxruntime as ort

    model = read_group(trained_models["models"] / PAIR, "nn13")
    assert [layer.activation for layer in model.parts[0].layers] == ["leaky_relu", "relu", None]
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    options.optimized_model_filepath = str(tmp_path / "optimized.onnx")
    built = graph.build([model], "float32", {}, "test", per_sample=True)
    ort.InferenceSession(built.SerializeToString(), options, providers=["CPUExecutionProvider"])
    nodes = onnx.load(tmp_path / "optimized.onnx").graph.node
    fused = [
        onnx.helper.get_attribute_value(a).decode()
        for n in nodes
        if n.op_type == "FusedConv"
        for a in n.attribute
        if a.name == "activation"
    ]
    assert fused == ["Relu"]
    assert [n.op_type for n in nodes].count("LeakyRelu") == 1


@pytest.mark.parametrize("name", ["affine", "nn7"])
def test_float32_check_is_relative_to_float32_resolution(trained_models: dict, name: str) -> None:
    """A heavier robot's wrenches (forces above 2 kN, where a float32 step is 2.4e-4 N): the float32 graph
    differs from the project's float32 prediction by more than 1e-4 N on rounding alone, and by a few
    float32 steps, which the check measures and passes."""
    from pipeline.export import check

    model = read_group(trained_models["models"] / LEG, name)
    x = _inputs(1, model.n_inputs, n=4000, seed=5)
    x[:, :3] = np.sign(x[:, :3]) * (2000.0 + np.abs(x[:, :3]) * 20.0)  # |force| from 2 kN up, N
    if model.kind == "network":  # the stored predictions: torch in float32
        net, _ = load_model(trained_models["models"] / LEG / name)
        with torch.no_grad():
            reference32 = net(torch.tensor(x, dtype=torch.float32)).numpy().astype(np.float64)
    else:  # float64 inside the float32 graph: the model on the float32 inputs
        reference32 = model.reference(x.astype(np.float32).astype(np.float64))
    samples = check.Samples(x, reference32, reference32, model.reference(x))
    result = check.check_group({d: graph.build([model], d, {}, "heavy") for d in graph.DTYPES}, samples)
    assert np.abs(reference32).max() > 2048.0
    assert result["float32"]["max_abs_diff"] > 1e-4  # an absolute 1e-4 N/Nm check fails on rounding alone
    assert 0 < result["float32"]["max_ulps"] <= 8
    check.assert_within(LEG, result, {"float32": 8.0, "float64": 1e-9})
    steps = result["float32"]["max_ulps"]
    with pytest.raises(DataError, match=f"float32 differs .* {steps:.3g} float32 steps"):
        check.assert_within(LEG, result, {"float32": steps * 0.99, "float64": 1e-9})


# --- the stage -----------------------------------------------------------------------------------


def _params(trained: dict, tmp_path: Path, **export: Any) -> Path:
    data = yaml.safe_load(Path(trained["params"]).read_text())
    data["export"].update(export)
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def exported(trained_models: dict, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The stage run once through the CLI: nn13 recommended for the leg, poly2 for the foot."""
    tmp = tmp_path_factory.mktemp("export")
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", trained_models["mlflow_uri"])
    try:
        args = [
            "export",
            str(trained_models["models"]),
            str(write_recommended(tmp, {LEG: "nn13", PAIR: "poly2"})),
            str(trained_models["labelled"]),
            str(tmp / "exported"),
            "--params",
            str(trained_models["params"]),
        ]
        assert main(args) == 0
    finally:
        patch.undo()
    return {"dir": tmp / "exported", "manifest": json.loads((tmp / "exported" / "manifest.json").read_text())}


def test_stage_writes_checked_graphs_and_manifest(exported: dict, trained_models: dict) -> None:
    out, doc = exported["dir"], exported["manifest"]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"all.{d}.onnx" for d in graph.DTYPES] + ["c", "groups", "manifest.json", "wholebodydynamics.xml"]
    )
    for group in (LEG, PAIR):  # each group's export is an export directory of its own
        assert sorted(p.name for p in (out / "groups" / group).iterdir()) == sorted(
            [f"{group}.{d}.onnx" for d in graph.DTYPES] + ["c", "manifest.json"]
        )
        own = json.loads((out / "groups" / group / "manifest.json").read_text())
        assert set(own["graphs"]) == {group} and own["fused"] is None
        assert doc["graphs"][group]["files"] == {
            d: f"groups/{group}/{f}" for d, f in own["graphs"][group]["files"].items()
        }
    assert set(doc["graphs"]) == {LEG, PAIR, "all"} and doc["robot"] == "iCubGenova09"
    fused = doc["graphs"]["all"]
    assert fused["models"] == {LEG: "nn13", PAIR: "poly2"}
    assert fused["input_shape"] == ["N", 13 + 2 * 7] and fused["output_shape"] == ["N", 18]
    first = fused["inputs"][0]
    assert first == {
        "index": 0,
        "column": f"ft.{LEG}.fx",
        "sensor": LEG,
        "topic": f"/ft/{LEG}/wrench",
        "field": "wrench.force.x",
        "unit": "N",
    }
    assert [c["unit"] for c in fused["inputs"][6:13]] == ["degC", "m/s^2", "m/s^2", "m/s^2"] + ["rad/s"] * 3
    assert fused["outputs"][-1]["topic"] == "/ft/r_foot_rear_ft/wrench_calibrated"
    training = fused["training"][PAIR]
    assert training["family"] == "poly" and len(training["training_data_sha256"]) == 64
    assert training["mlflow_run"] and training["logs"]["test"] == ["05_pole_test", "06_walking_test"]
    assert fused["training"][LEG]["family"] == "nn"
    for name, entry in doc["graphs"].items():
        assert entry["check"]["float32"]["max_ulps"] <= 8, name
        assert entry["check"]["float64"]["max_abs_diff"] <= 1e-9, name
        assert entry["check"]["float64"]["samples"] > 500
        props = {p.key: p.value for p in onnx.load(out / entry["files"]["float32"]).metadata_props}
        assert json.loads(props["ftcal.manifest"])["inputs"] == entry["inputs"]
        assert props["ftcal.robot"] == "iCubGenova09"
        assert json.loads(props["ftcal.mlflow_runs"]) == {
            g: t["mlflow_run"] for g, t in entry["training"].items()
        }


def test_stage_registers_the_export(exported: dict, trained_models: dict) -> None:
    from mlflow import MlflowClient

    client = MlflowClient(trained_models["mlflow_uri"])
    (version,) = client.search_model_versions(f"name = '{REGISTERED_MODEL}'")
    assert version.tags[f"model.{LEG}"] == "nn13" and version.source.endswith("/onnx")
    files = client.list_artifacts(version.run_id, "onnx")
    assert {Path(f.path).name for f in files} >= {"manifest.json", "all.float32.onnx", "groups", "c"}
    assert {Path(f.path).name for f in files} >= {"wholebodydynamics.xml"}
    c_files = {Path(f.path).name for f in client.list_artifacts(version.run_id, "onnx/c")}
    assert c_files == {"ftcal_calibrator.h", "ftcal_calibrator.c"}
    # the registered training version of the exported network points at its ONNX graphs (the group's run)
    run = exported["manifest"]["graphs"][LEG]["training"][LEG]["mlflow_run"]
    (trained,) = client.search_model_versions(f"name = 'ftcal-{LEG}-13' and run_id = '{run}'")
    group_run = trained.tags["onnx.float32"].split("/")[1]
    assert trained.tags["onnx.float32"] == f"runs:/{group_run}/onnx/{LEG}.float32.onnx"
    assert client.get_run(group_run).data.tags["dvc.stage"] == f"export@{LEG}"
    assert trained.tags["onnx.registered"] == f"{REGISTERED_MODEL}/{version.version}"


def test_failed_check_writes_nothing(
    trained_models: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'm.db'}")
    out = tmp_path / "exported"
    out.mkdir()
    (out / "old.txt").write_text("previous export")
    params = load_params(_params(trained_models, tmp_path, tolerance_float32_ulps=1e-12))
    report = write_recommended(tmp_path, {LEG: "nn7", PAIR: "nn7"})
    with pytest.raises(
        DataError,
        match=r"export check failed: r_leg_ft float32 .* float32 steps .* > export.tolerance_float32_ulps",
    ):
        E.run(params, trained_models["models"], report, trained_models["labelled"], out)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    assert [p.name for p in out.iterdir()] == ["old.txt"]


@pytest.mark.parametrize(
    ("change", "recommended", "message"),
    [
        ({"models": {"nope": "nn7"}}, {LEG: "nn7", PAIR: "nn7"}, "export.models.nope: not a group"),
        (
            {"models": {LEG: 7}},
            {LEG: "nn7", PAIR: "nn7"},
            "export.models.r_leg_ft must be a non-empty string",
        ),
        ({"tolerance_float64": -1}, {LEG: "nn7", PAIR: "nn7"}, "export.tolerance_float64 must be a positive"),
        ({}, {LEG: None, PAIR: "nn7"}, "no recommended model for r_leg_ft"),
        ({"models": {LEG: "poly9"}}, {PAIR: "nn7"}, "baselines.json: no entry 'poly9'"),
    ],
)
def test_bad_input_is_one_line(
    trained_models: dict, tmp_path: Path, change: dict, recommended: dict, message: str, capsys: Any
) -> None:
    args = [
        "export",
        str(trained_models["models"]),
        str(write_recommended(tmp_path, recommended)),
        str(trained_models["labelled"]),
        str(tmp_path / "out"),
        "--params",
        str(_params(trained_models, tmp_path, **change)),
    ]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("ftcal: error: ") and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_missing_inputs_are_data_errors(trained_models: dict, tmp_path: Path) -> None:
    params = load_params(trained_models["params"])
    report = write_recommended(tmp_path, {LEG: "nn7", PAIR: "nn7"})
    with pytest.raises(DataError, match="models directory not found"):
        E.run(params, tmp_path / "none", report, trained_models["labelled"], tmp_path / "o")
    with pytest.raises(
        DataError, match=r"r_leg_ft/<headline>\.json: not found \(run `dvc repro evaluate@r_leg_ft`\)"
    ):
        E.run(
            params,
            trained_models["models"],
            tmp_path / "missing.json",
            trained_models["labelled"],
            tmp_path / "o",
        )
    with pytest.raises(ConfigError):
        E.choose_models([LEG], report, {PAIR: "nn7"})
