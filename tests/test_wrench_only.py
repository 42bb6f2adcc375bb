"""Logs without temperature (FT boards of iCub 2.x, dataDumper archives): `inputs: [6]` networks and
wrench-only baselines train, are exported (graphs of 6 inputs per sensor, checked with onnxruntime) and
calibrate a log with no temperature topic; 7- and 13-input models keep their clear error."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from pipeline.core.config import load_params
from pipeline.core.errors import DataError
from pipeline.logs import schema as S
from pipeline.stages.train import train_group
from tests.factories.labelled import LEG, LOGS, SENSORS, write_labelled_log
from tests.factories.params import write_params

pytestmark = pytest.mark.slow  # trains networks


@pytest.fixture(scope="module")
def no_temperature(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Labelled tables whose boards have no thermometer: temp.* NaN, ok.temperature.* false everywhere."""
    out = tmp_path_factory.mktemp("no_temperature")
    for i, (name, kind, role) in enumerate(LOGS):
        path = out / f"{name}_{role}.parquet"
        write_labelled_log(path, kind, role, n=500, seed=i)
        table = pq.read_table(path)
        for s in SENSORS:
            c, flag = S.temperature_col(s), S.ok_col(S.TEMPERATURE_STREAM, s)
            table = table.set_column(table.schema.get_field_index(c), c, pc.multiply(table[c], float("nan")))
            table = table.set_column(table.schema.get_field_index(flag), flag, pa.array([False] * len(table)))
        pq.write_table(table, path)
    return out


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory, no_temperature: Path) -> tuple[Path, dict]:
    tmp = tmp_path_factory.mktemp("wrench_only")
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'mlflow.db'}")
    try:
        params = load_params(write_params(tmp, inputs=[6], n_trials=1, epochs=2, poly_orders=[1, 2]))
        result = train_group(
            params, LEG, no_temperature, tmp / "models" / LEG, tmp / "studies", progress=False
        )
    finally:
        patch.undo()
    return tmp / "models" / LEG, result.metrics


def test_7_and_13_inputs_say_what_is_missing(tmp_path: Path, no_temperature: Path, monkeypatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    for inputs in ([7], [7, 13]):
        params = load_params(write_params(tmp_path, inputs=inputs, n_trials=1, epochs=1))
        with pytest.raises(DataError, match=rf"no temperature for {LEG} .*\[6\] uses the wrench alone"):
            train_group(params, LEG, no_temperature, tmp_path / "out", tmp_path / "st", progress=False)


def test_wrench_only_networks_and_baselines_train(trained: tuple[Path, dict]) -> None:
    model_dir, metrics = trained
    assert math.isfinite(metrics["test"]["nn6"]["rmse"]) and "nn7" not in metrics["test"]
    baselines = json.loads((model_dir / "baselines.json").read_text())
    assert {np.shape(b["offset"])[-1] for b in baselines.values()} == {6}  # no temperature column
    raw, affine = metrics["test"]["raw"]["rmse"], metrics["test"]["affine"]["rmse"]
    assert affine < 0.5 * raw  # the fixture's offsets and gains are an affine map of the wrench


def test_wrench_only_models_export_and_match_onnxruntime(trained: tuple[Path, dict]) -> None:
    from pipeline.export.check import run, session
    from pipeline.export.graph import build
    from pipeline.export.trained import read_group

    model_dir, _ = trained
    rng = np.random.default_rng(0)
    for name in ("nn6", "affine", "poly2", "raw"):
        model = read_group(model_dir, name)
        assert model.n_inputs == 6 and model.input_columns == S.wrench_cols(S.FT, LEG), name
        x = rng.normal(0.0, 200.0, (64, 6))
        got = run(session(build([model], "float64", {}, name).SerializeToString()), x)
        np.testing.assert_allclose(got, model.reference(x), rtol=0, atol=1e-9, err_msg=name)


def test_a_log_without_temperature_is_calibrated_by_a_wrench_only_export(
    tmp_path: Path, trained: tuple[Path, dict]
) -> None:
    """The export's manifest and plans of a 6-input model need no temperature topic; `ftcal calibrate`'s
    machinery adds the calibrated wrench of every raw message, equal to the model on that message."""
    from pipeline.core.io import write_json
    from pipeline.export import manifest
    from pipeline.export.trained import read_group
    from pipeline.logs.rosmsg import LogReader
    from pipeline.tools.calibrate import run
    from tests.factories.logs import TOPICS, write_log

    model_dir, _ = trained
    model = read_group(model_dir, "nn6")
    (tmp_path / "exported").mkdir()
    trainings = {LEG: manifest.training(model, "0" * 64, None)}
    entry, graphs = manifest.build_graph(LEG, [model], TOPICS, "", trainings)
    entry = manifest.write_graphs(tmp_path / "exported", LEG, entry, graphs)
    doc = manifest.document("", {LEG: entry}, fused=None)
    write_json(tmp_path / "exported" / manifest.MANIFEST_FILE, doc)
    assert [c["field"] for c in entry["inputs"]] == [
        f"wrench.{a}.{x}" for a in ("force", "torque") for x in "xyz"
    ]
    log = write_log(
        tmp_path / "log.mcap", ["j_a"], [LEG], truth=False, skip=[f"/ft/{LEG}/temperature", f"/ft/{LEG}/imu"]
    )
    params = load_params(write_params(tmp_path))
    (result,) = run(params, log, tmp_path / "calibrated.mcap", tmp_path / "exported")
    with LogReader(tmp_path / "calibrated.mcap") as reader:
        data = reader.read()
    raw = np.concatenate([b.fields["wrench"] for b in data[f"/ft/{LEG}/wrench"]])
    calibrated = np.concatenate([b.fields["wrench"] for b in data[f"/ft/{LEG}/wrench_calibrated"]])
    assert result.added == len(raw) == len(calibrated) and not result.uncalibrated.get(LEG)
    np.testing.assert_allclose(calibrated, model.reference(raw), rtol=0, atol=1e-9)
