"""End to end on a few seconds of simulated logs: simulate -> ingest -> smooth -> label -> train -> evaluate
-> report -> export, through the stages' own `run` functions, on iCub 3 and on ergoCub (by robot.urdf
alone).

What it checks is the hand-offs: every stage reads what the previous one wrote; train's outputs are what
evaluate reads (the contract of `pipeline.calib.records`, linked to MLflow by run id); the exported ONNX
files, loaded from disk with onnxruntime's own API, compute the stored test predictions; the labels of the
simulated logs agree with iDynTree's expected FT measurements (1e-6 N/Nm) and are as close to the true
wrench as docs/labels.md says.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.core.config import load_params
from pipeline.logs import schema as S
from pipeline.stages import evaluate, export, identify, ingest, label, report, simulate, smooth, train
from tests.conftest import REPO, robot_source
from tests.factories.params import repo_params
from tests.relabel import relabel_with_idyntree

pytestmark = pytest.mark.slow  # every stage, one after the other, on both robots

LOGS = [
    {"type": "pole", "duration_s": 8, "role": "train"},
    {"type": "pole", "duration_s": 8, "role": "train"},
    {"type": "walking", "duration_s": 12, "role": "train"},
    {"type": "pole", "duration_s": 6, "role": "test"},
    {"type": "walking", "duration_s": 10, "role": "test"},
]
GROUP = "r_leg_ft"


def _params(tmp: Path, urdf: str) -> Path:
    data = repo_params()
    data["robot"]["urdf"] = urdf
    data["simulate"].update(logs=LOGS, workers=1, plots=False)
    data["simulate"]["motion"]["steps_per_direction"] = 2
    defaults = data["train"]["defaults"]
    defaults.update(hidden=16, epochs=2, n_trials=1, batch_size=256, search={}, inputs=[7, 13])
    data["train"]["groups"] = {GROUP: {"sensor": GROUP}}
    path = tmp / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope="module", params=["iCubGenova09", "ergoCubSN001"])
def pipeline_run(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    urdf = robot_source(request.param)
    tmp = tmp_path_factory.mktemp(f"e2e_{request.param}")
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'mlflow.db'}")
    try:
        params = load_params(_params(tmp, urdf))
        d = {k: tmp / k for k in ("sim", "ingested", "smoothed", "labelled", "models", "reports", "exported")}
        simulate.run(params, d["sim"], progress=False)
        ingest.run(params, d["sim"], d["ingested"], progress=False)
        smooth.run(params, d["ingested"], d["smoothed"], progress=False)
        label.run(params, d["smoothed"], d["labelled"], truth_dir=d["ingested"], progress=False)
        identified = identify.run(
            params, d["smoothed"], d["labelled"], d["models"] / "identified", d["ingested"]
        )
        trained = train.train_group(
            params, GROUP, d["labelled"], d["models"] / GROUP, tmp / "studies", progress=False
        )
        result = evaluate.run(
            params, GROUP, d["models"] / GROUP, d["labelled"], d["reports"], d["ingested"], progress=False
        )
        report.run(params, d["reports"], identified_dir=d["models"] / "identified")
        export.run(params, d["models"], d["reports"] / "metrics", d["labelled"], d["exported"])
    finally:
        patch.undo()
    return {
        "dirs": d,
        "trained": trained,
        "result": result,
        "urdf": urdf,
        "tmp": tmp,
        "identified": identified,
    }


def test_every_stage_hands_over_to_the_next(pipeline_run: dict[str, Any]) -> None:
    d, result = pipeline_run["dirs"], pipeline_run["result"]
    assert len(list(d["labelled"].glob("*.parquet"))) == len(LOGS)
    metrics = json.loads((d["models"] / GROUP / "metrics.json").read_text())
    assert metrics["mlflow"]["run_id"] == pipeline_run["trained"].mlflow_run == result.train_run
    assert set(result.model_versions) == {"nn7", "nn13"}
    assert result.recommended in result.models and result.histories["nn7"]
    raw, best = (result.headline_rmse("truth", m) for m in ("raw", result.recommended))
    assert raw > 5.0 and best < raw / 3  # the simulated leg sensor is miscalibrated; the fit corrects it
    small = json.loads((d["reports"] / "metrics" / GROUP / f"{GROUP}.json").read_text())
    assert small["deployed"] == result.recommended and small["rmse"] == pytest.approx(best, rel=1e-3)
    page = (d["reports"] / "index.html").read_text()
    assert GROUP in page and f"groups/{GROUP}/plots/loss.png" in page


def test_labels_agree_with_idyntree(pipeline_run: dict[str, Any]) -> None:
    d = pipeline_run["dirs"]
    table = sorted(d["labelled"].glob("*walking_test.parquet"))[0]
    smoothed = d["smoothed"] / table.name
    worst = relabel_with_idyntree(table, smoothed, pipeline_run["urdf"], samples=40)
    assert worst < 1e-6


def test_exported_files_compute_the_stored_predictions(pipeline_run: dict[str, Any]) -> None:
    """The export as a robot loads it: every file from disk (its sha256 the manifest's) in a plain
    onnxruntime session, fed the test samples' inputs in the manifest's column order: the group's graphs and
    the fused one compute train's stored test predictions of the exported model (float32 within float32's
    rounding at these wrenches, float64 within the stored predictions' own float32 rounding)."""
    import hashlib

    import onnxruntime as ort

    d = pipeline_run["dirs"]
    manifest = json.loads((d["exported"] / "manifest.json").read_text())
    model = manifest["graphs"][GROUP]["models"][GROUP]
    stored = pd.read_parquet(d["models"] / GROUP / "predictions.parquet")
    rows = []
    for log, part in stored.groupby(S.LOG, sort=False):
        table = pd.read_parquet(d["labelled"] / f"{log}.parquet")
        rows.append(part.merge(table, on=S.STAMP, suffixes=("", "_table")))
    frame = pd.concat(rows, ignore_index=True)
    expected = frame[S.prediction_cols(model, GROUP)].to_numpy()
    assert len(frame) > 500 and np.isfinite(expected).all()
    for name in (GROUP, "all"):
        entry = manifest["graphs"][name]
        columns = [c["column"] for c in entry["inputs"]]
        for dtype, file in entry["files"].items():
            path = d["exported"] / file
            assert hashlib.sha256(path.read_bytes()).hexdigest() == entry["sha256"][dtype]
            session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
            real = np.float32 if dtype == "float32" else np.float64
            if "state" not in entry:
                (y,) = session.run(None, {"inputs": frame[columns].to_numpy().astype(real)})
            else:  # memory: each test log from its first reading, one call (the state starts afresh)
                y = _whole_logs(session, d["labelled"], frame, columns, real)
            np.testing.assert_allclose(y, expected, rtol=0, atol=5e-4, err_msg=f"{name} {dtype}")


def _whole_logs(session: Any, labelled: Path, frame: pd.DataFrame, columns: list, real: type) -> np.ndarray:
    """A graph with memory's outputs at `frame`'s (log, stamp) rows, run over each log's readings (the rows
    whose raw wrenches are finite) in one call from a fresh state."""
    out = []
    for log, part in frame.groupby(S.LOG, sort=False):
        table = pd.read_parquet(labelled / f"{log}.parquet")
        wrench = [c for c in columns if c.startswith(f"{S.FT}.")]
        table = table[table[wrench].notna().all(axis=1)]
        y = session.run(None, {"inputs": table[columns].to_numpy().astype(real)})[0]
        where = pd.Series(np.arange(len(table)), index=table[S.STAMP].to_numpy())
        out.append(y[where.loc[part[S.STAMP].to_numpy()].to_numpy()])
    return np.concatenate(out)


def _benchmark(script: str, args: list[str]) -> subprocess.CompletedProcess[str]:
    """A benchmark script run on a pipeline's outputs; it must exit 0."""
    proc = subprocess.run(
        [sys.executable, script, *args], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


def test_calibrate_agreement_benchmark_runs_on_the_outputs(pipeline_run: dict[str, Any]) -> None:
    """`benchmarks/calibrate_agreement.py` (docs/benchmarks.md) on this run's outputs (a pipeline's, as it
    needs): the calibrated copy keeps every message, and the exported graph computes the stored test
    predictions."""
    d = pipeline_run["dirs"]
    log = sorted(d["sim"].glob("*walking_test.mcap"))[0]
    args = [str(log), "--models", str(d["exported"]), "--trained", str(d["models"])]
    args += ["--labelled", str(d["labelled"]), "--params", str(pipeline_run["tmp"] / "params.yaml")]
    proc = _benchmark("benchmarks/calibrate_agreement.py", args)
    assert "byte-identical in the copy: True" in proc.stdout, proc.stdout
    diff = re.search(r"max \|diff\| (\S+) N/Nm", proc.stdout)
    assert diff is not None and float(diff.group(1)) < 1e-3, proc.stdout


@pytest.mark.parametrize("model", ["gru", "window"])
def test_recurrent_benchmark_runs_on_the_outputs(pipeline_run: dict[str, Any], model: str) -> None:
    """`benchmarks/recurrent.py` (docs/benchmarks.md) on this run (its directory laid out as a pipeline's):
    the GRU correction of the affine map, or the windowed network's of the play model, is trained and scored
    against truth beside the group's play model, and a held push is read at three instants."""
    d = pipeline_run["dirs"]
    args = ["--params", str(pipeline_run["tmp"] / "params.yaml"), "--quick"]
    args += [f"--{n}={d[n]}" for n in ("labelled", "ingested", "models")]
    args += ["--base", "play", "--model", "window"] if model == "window" else []
    proc = _benchmark("benchmarks/recurrent.py", args)
    numbers = r"\s+(\S+)" * 4
    row = re.search(rf"^{GROUP}{numbers}\s+{model} \[(.+)\]\s+play \[(.+)\]$", proc.stdout, re.M)
    assert row is not None, proc.stdout
    affine, play, ours, oracle = (float(v) for v in row.groups()[:4])
    assert all(0 < v < 50 for v in (affine, play, ours, oracle)), proc.stdout
    for held in row.groups()[4:]:
        assert len([float(v) for v in held.split(",")]) == 3, proc.stdout
    ratio = re.search(rf"largest ratio {model} / play \(RMSE against truth\): (\S+)$", proc.stdout.strip())
    assert ratio is not None and float(ratio.group(1)) == pytest.approx(ours / play, rel=0.01), proc.stdout


def test_identify_benchmark_runs_on_the_outputs(pipeline_run: dict[str, Any]) -> None:
    """`benchmarks/identify.py` (docs/benchmarks.md) on this run's tables: labels recomputed with the true
    inertial parameters are closer to the true wrench than the URDF's for every sensor with exact samples."""
    d = pipeline_run["dirs"]
    args = ["--params", str(pipeline_run["tmp"] / "params.yaml"), "--quick"]
    args += ["--labels-urdf", str(d["models"] / "identified" / "labels.urdf")]
    args += [f"--{n}={d[n]}" for n in ("smoothed", "labelled", "ingested")]
    proc = _benchmark("benchmarks/identify.py", args)
    last = "parts of at least 1 kg identified within 1 % of the truth"
    assert re.search(rf"{last}: \d+ of \d+$", proc.stdout.strip()), proc.stdout
    rows = re.findall(r"^\s*(\w+_ft)\s+(\S+)\s+(\S+)\s+(\S+)$", proc.stdout, re.M)
    assert rows, proc.stdout
    for sensor, urdf, true, _ in rows:
        if urdf != "nan":
            assert float(true) < float(urdf), (sensor, proc.stdout)


def test_labelled_sensor_errors_against_truth_are_small(pipeline_run: dict[str, Any]) -> None:
    """Labels are within what the simulator's 3% mass errors allow of the true leg wrench: docs/labels.md's
    0.6-1.2 N (force RMSE over the test log)."""
    d = pipeline_run["dirs"]
    frame = pd.read_parquet(sorted(d["labelled"].glob("*pole_test.parquet"))[0])
    truth = pd.read_parquet(sorted(d["ingested"].glob("*pole_test.truth.parquet"))[0])
    exp = frame[[f"exp.{GROUP}.{a}" for a in ("fx", "fy", "fz")]].to_numpy()
    true = truth[[f"true.{GROUP}.{a}" for a in ("fx", "fy", "fz")]].to_numpy()
    ok = np.isfinite(exp).all(axis=1) & np.isfinite(true).all(axis=1)
    assert ok.mean() > 0.9
    rmse = np.sqrt(np.mean((exp[ok] - true[ok]) ** 2))
    print(f"label force RMSE against truth: {rmse:.3f} N")
    assert rmse < 1.2


def test_identification_without_known_loads_keeps_the_urdf(pipeline_run: dict[str, Any]) -> None:
    """These logs hang no known load: the identification says so and the labels' URDF is robot.urdf's."""
    from pipeline.physics.regressor import link_params
    from pipeline.physics.robot import load_robot

    res, out = pipeline_run["identified"], pipeline_run["dirs"]["models"] / "identified"
    assert res.status == "urdf" and "known load" in res.reason
    summary = json.loads((out / "identification.json").read_text())
    assert summary["status"] == "urdf" and summary["labels"] == "urdf" and summary["parts"]
    urdf, labels = load_robot(pipeline_run["urdf"]), load_robot(out / "labels.urdf")
    links = [lk for lk, i in urdf.links.items() if i is not None and i.mass > 0]
    np.testing.assert_array_equal(link_params(labels, links), link_params(urdf, links))
    assert (out / "parts.png").stat().st_size > 0 and (out / "parts.csv").read_text().startswith("part,")
    page = (pipeline_run["dirs"]["reports"] / "index.html").read_text()
    assert "<h2 id='identified'>Identified robot model</h2>" in page and "no training log hangs" in page
    assert (pipeline_run["dirs"]["reports"] / "plots" / "identified_parts.png").is_file()


def test_labels_from_a_written_urdf_follow_the_reading_regressor(
    pipeline_run: dict[str, Any], tmp_path: Path
) -> None:
    """A URDF written with other inertial values (`write_inertials`), labelled by the label stage, gives the
    labels ``label + Y (pi - pi_urdf)`` of the reading regressor: the identified model's two paths agree."""
    from pipeline.labels.identify import to_inertial
    from pipeline.labels.inertials import link_basis, with_change
    from pipeline.physics.dynamics import ContactCase
    from pipeline.physics.regressor import ReadingRegressor, link_params
    from pipeline.physics.robot import load_robot
    from pipeline.physics.urdf import resolve_urdf
    from pipeline.physics.urdf_write import write_inertials

    d = pipeline_run["dirs"]
    robot = load_robot(pipeline_run["urdf"])
    links = [lk for lk, i in robot.links.items() if i is not None and i.mass > 0]
    pi = link_params(robot, links)
    mass = pi[::10]  # kg: each link's mass changes by about 3 %, its centre of mass by about 3 mm
    scale = np.repeat(mass, 4) * np.tile([0.03, 0.003, 0.003, 0.003], len(links))
    change = np.random.default_rng(3).normal(size=link_basis(pi).shape[1]) * scale
    new = with_change(pi, change)
    changed = {lk: to_inertial(new[10 * k : 10 * (k + 1)]) for k, lk in enumerate(links)}
    write_inertials(resolve_urdf(pipeline_run["urdf"]), tmp_path / "model.urdf", changed)
    np.testing.assert_allclose(
        link_params(load_robot(tmp_path / "model.urdf"), links), new, rtol=0, atol=1e-12
    )
    params = load_params(pipeline_run["tmp"] / "params.yaml")
    name = sorted(d["labelled"].glob("*pole_test.parquet"))[0].name
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / name).symlink_to(d["smoothed"] / name)
    label.run(params, tmp_path / "in", tmp_path / "out", progress=False, urdf=tmp_path / "model.urdf")
    before, after = pd.read_parquet(d["labelled"] / name), pd.read_parquet(tmp_path / "out" / name)
    sm = pd.read_parquet(d["smoothed"] / name)
    rows = np.flatnonzero(before[S.CONTACTS].to_numpy() == before[S.CONTACTS].iloc[len(before) // 2])[::50][
        :20
    ]
    contacts, fixed = before[S.CONTACTS].iloc[rows[0]], before[S.FIXED_LINK].iloc[rows[0]]
    reg = ReadingRegressor(
        robot, ContactCase.make(contacts.split(","), fixed, np.array([0, 0, -params.robot.gravity])), links
    )
    q, dq, ddq = (sm[S.joint_cols(k, robot.joint_names)].to_numpy()[rows] for k in (S.QS, S.DQS, S.DDQS))
    y = reg(q, dq, ddq) @ (new - pi)  # (n, S, 6)
    for k, s in enumerate(robot.sensors):
        cols = S.wrench_cols(S.EXPECTED, s)
        expected = before[cols].to_numpy()[rows] + y[:, k]
        np.testing.assert_allclose(after[cols].to_numpy()[rows], expected, rtol=0, atol=1e-6)
