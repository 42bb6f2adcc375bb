"""Stage `train@<group>`: params, whole-log split, bad input, and end to end on synthetic labelled tables
(real Optuna journal, real MLflow sqlite store): resume, registration, identical metrics twice."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from pipeline.calib import search as calib_search
from pipeline.calib.cuts import CutTerm, cut_sums_np
from pipeline.calib.data import LogInfo, find_logs, input_cols, load_group_data, resolve_group
from pipeline.calib.models import load_model
from pipeline.calib.params import TrainParams, select_by_folds, select_simplest
from pipeline.calib.split import split_logs
from pipeline.calib.training import train_network
from pipeline.calib.window import WindowModel
from pipeline.cli import main
from pipeline.core.config import load_params, stage_section
from pipeline.core.errors import ConfigError, DataError
from pipeline.logs import schema as S
from pipeline.logs.schema import LOG, prediction_cols
from pipeline.physics.cuts import map_wrenches, pose_wrench_transforms
from pipeline.stages.train import train_group  # the stage entry (default studies dir)
from tests.factories.labelled import (
    FRONT,
    LEG,
    PAIR,
    REAR,
    SHANK,
    TRAINED,
    TRANSFORMS,
    write_labelled_log,
    write_labelled_logs,
)
from tests.factories.params import TRAIN_PARAMS, write_params

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def labelled(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_labelled_logs(tmp_path_factory.mktemp("labelled"), n=500)


@pytest.fixture
def mlflow_uri(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> str:
    uri = f"sqlite:///{tmp_path_factory.getbasetemp() / 'train_mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    return uri


def _comparable(metrics: dict[str, Any]) -> dict[str, Any]:
    """Metrics without what legitimately differs between runs (timings, run ids, trial bookkeeping)."""
    m = {k: v for k, v in metrics.items() if k not in ("seconds", "mlflow")}
    m["networks"] = {
        name: {k: v for k, v in net.items() if k not in ("trials_run", "trials_reused")}
        for name, net in metrics["networks"].items()
    }
    return m


# --- params --------------------------------------------------------------------------------------


def test_repo_params_resolve_every_group() -> None:
    cfg = stage_section(load_params(ROOT / "params.yaml"), "train", TrainParams)
    for name in cfg.groups:
        gp = cfg.group(name)
        assert sum(v is not None for v in (gp.sensor, gp.pair, gp.sensors)) == 1
        assert gp.inputs == (7, 13) and gp.activations == ("leaky_relu", "relu") and gp.hidden == 100


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"groups": {"x": {"sensor": "a", "pair": "b"}}}, "train.groups.x must have exactly one of"),
        ({"groups": {"x": {"sensors": ["a"]}}}, r"train.groups.x.sensors must be a list of 2 or more"),
        ({"selection_margin": 1.5}, "train.selection_margin must be a number in"),
        ({"groups": {"x": {"sensor": "a", "lr": 1, "foo": 2}}}, "unknown key train.groups.x.foo"),
        ({"defaults": {"epochs": 0}}, "train.groups.r_leg_ft.epochs must be an integer >= 1, got 0"),
        ({"defaults": {"window_time_constants_s": [0.5, 0]}}, "window_time_constants_s must be a list"),
        ({"defaults": {"window_lr": 0}}, "train.groups.r_leg_ft.window_lr must be a positive number"),
        ({"defaults": {"normalisation": "batch"}}, "normalisation must be one of"),
        (
            {"defaults": {"search": {"hidden": [64, 128]}}},
            "search.hidden must include the group's own value 16",
        ),
        ({"defaults": {"search": {"dropout": [0.1]}}}, "unknown key train.groups.r_leg_ft.search.dropout"),
        ({"defaults": {"search": {"lr": {"low": 0.1, "high": 0.01}}}}, "search.lr needs low < high"),
        ({"defaults": {"inputs": [5]}}, "inputs must be a non-empty list of (6, 7, 13)"),
        ({"val_logs": 0}, "train.val_logs must be an integer >= 1"),
        ({"defaults": {"residual_slope": 0.0}}, "train.groups.r_leg_ft.residual_slope must be a number in"),
        ({"folds": 0}, "train.folds must be an integer >= 1"),
    ],
)
def test_bad_params_name_the_key(tmp_path: Path, change: dict[str, Any], message: str) -> None:
    train = copy.deepcopy(TRAIN_PARAMS)
    for key, value in change.items():
        if key == "defaults":
            train["defaults"].update(value)
        else:
            train[key] = value
    path = write_params(tmp_path, train)
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_params(path)  # every section is validated when params.yaml is loaded


# --- split and data ------------------------------------------------------------------------------


def _logs(*specs: tuple[str, str, str]) -> list[LogInfo]:
    return [LogInfo(name, Path(name), role, kind) for name, kind, role in specs]


def test_select_simplest_prefers_the_simpler_model_within_the_margin() -> None:
    errors = {"raw": 20.0, "affine": 1.0, "poly2": 0.95, "nn7": 0.85, "nn13": 0.84}
    assert select_simplest(errors, 0.1) == "nn7"  # poly2 is only 5 % better than affine; nn13 1 % than nn7
    assert select_simplest(errors, 0.2) == "affine"
    assert select_simplest(errors, 0.0) == "nn13"
    assert select_simplest({"raw": 1.0, "affine": float("nan"), "nn7": 0.5}, 0.1) == "nn7"


def test_split_is_by_whole_logs_one_per_kind_never_a_kinds_last() -> None:
    # balancing on the left and on the right foot are different kinds: neither may leave the training set
    logs = _logs(
        ("p1", "pole", "train"),
        ("p2", "pole", "train"),
        ("b1", "balancing/l_foot", "train"),
        ("b2", "balancing/r_foot", "train"),
        ("w1", "walking", "train"),
        ("w2", "walking", "train"),
        ("t1", "pole", "test"),
    )
    for seed in range(20):
        split = split_logs(logs, val_logs=5, seed=seed)
        assert split["test"] == ["t1"]
        assert len(split["val"]) == 2 and {v[0] for v in split["val"]} == {"p", "w"}  # one pole, one walking
        assert sorted(split["train"] + split["val"]) == ["b1", "b2", "p1", "p2", "w1", "w2"]
        assert split == split_logs(logs, val_logs=5, seed=seed)  # seeded
    picks = {tuple(split_logs(logs, val_logs=1, seed=s)["val"]) for s in range(20)}
    assert len(picks) > 1  # the seed does choose


def test_folds_hold_out_disjoint_logs_of_the_same_kinds() -> None:
    logs = _logs(
        ("p1", "pole", "train"),
        ("p2", "pole", "train"),
        ("p3", "pole", "train"),
        ("b1", "balancing/l_foot", "train"),
        ("w1", "walking", "train"),
        ("w2", "walking", "train"),
        ("t1", "pole", "test"),
    )
    for seed in range(10):
        split = split_logs(logs, val_logs=2, seed=seed, folds=2)
        folds = split["folds"]
        assert folds[0] == {"train": split["train"], "val": split["val"]}  # fold 0 is the split
        assert not set(folds[0]["val"]) & set(folds[1]["val"])
        for fold in folds:
            assert {v[0] for v in fold["val"]} == {"p", "w"}
            assert sorted(fold["train"] + fold["val"]) == ["b1", "p1", "p2", "p3", "w1", "w2"]
    with pytest.raises(DataError, match="kind 'walking' has only 2 training logs"):
        split_logs(logs, val_logs=2, seed=0, folds=3)


def test_selection_over_folds_needs_a_gain_beyond_the_spread() -> None:
    scores = {"raw": [20.0, 21.0], "affine": [1.0, 1.0], "poly2": [0.7, 1.05], "nn7": [0.8, 0.85]}
    assert select_by_folds(scores, 0.1) == "nn7"  # poly2 is 12 % better on average but worse on fold 2
    assert select_by_folds({**scores, "nn7": [0.5, 0.99]}, 0.1) == "nn7"  # better on both, 26 % on average
    assert select_by_folds({**scores, "nn7": [0.5, 1.01]}, 0.1) == "affine"  # 25 % better on average only
    assert select_by_folds({"raw": [1.0], "affine": [0.5]}, 0.1) == "affine"  # one fold: the margin alone


@pytest.mark.parametrize(
    ("specs", "message"),
    [
        ([("a", "pole", "test")], "no training logs"),
        ([("a", "pole", "train"), ("b", "pole", "train")], "no test logs"),
        (
            [("a", "pole", "train"), ("b", "walking", "train"), ("c", "pole", "test")],
            "cannot hold out a validation",
        ),
    ],
)
def test_split_errors(specs: list[tuple[str, str, str]], message: str) -> None:
    with pytest.raises(DataError, match=message):
        split_logs(_logs(*specs), val_logs=1, seed=0)


def test_group_data_drops_samples_with_bad_inputs_and_keeps_nan_labels(labelled: Path) -> None:
    logs = find_logs(labelled)
    params = load_params(write_params(labelled.parent))
    gp = stage_section(params, "train", TrainParams).group(PAIR)
    group = resolve_group(gp, params, logs)
    assert group.sensors == (FRONT, REAR)
    np.testing.assert_allclose(group.transforms, TRANSFORMS)
    data = load_group_data(group, logs[:1])
    assert len(data) == 500 - 6  # 3 bad wrench rows per sensor, both sensors of the pair
    assert np.isfinite(data.x).all()
    walking = load_group_data(group, [log for log in logs if log.kind == "walking"][:1])
    assert np.isnan(walking.labels[~walking.switches]).all()
    np.testing.assert_array_equal(walking.alpha_sum, walking.sum_switch & ~walking.switches.all(axis=1))


# --- bad input through the CLI -------------------------------------------------------------------


def _run_cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(["train", *args])
    err = capsys.readouterr().err
    return code, err


@pytest.mark.parametrize(
    ("group", "groups", "message"),
    [
        ("nope", None, "train.groups has no group 'nope'"),
        ("x", {"x": {"sensor": "l_knee_ft"}}, "train.groups.x.sensor: 'l_knee_ft' is not an FT sensor"),
        ("x", {"x": {"pair": "l_hand"}}, "train.groups.x.pair: 'l_hand' is not a foot pair of the robot"),
    ],
)
def test_cli_bad_group_is_one_line(
    tmp_path: Path,
    labelled: Path,
    capsys: pytest.CaptureFixture[str],
    group: str,
    groups: dict[str, Any] | None,
    message: str,
) -> None:
    train = copy.deepcopy(TRAIN_PARAMS)
    if groups:
        train["groups"] = groups
    params = write_params(tmp_path, train)
    code, err = _run_cli([group, str(labelled), str(tmp_path / "out"), "--params", str(params)], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ftcal: error:") and message in lines[0], err


def _copy_logs(src: Path, dst: Path, keep: callable) -> Path:
    dst.mkdir()
    for path in src.glob("*.parquet"):
        if keep(path.name):
            (dst / path.name).write_bytes(path.read_bytes())
    return dst


def test_cli_bad_data_is_one_line(tmp_path: Path, labelled: Path, capsys: pytest.CaptureFixture[str]) -> None:
    params = str(write_params(tmp_path))
    cases = [
        (tmp_path / "missing", "labelled directory not found"),
        (_copy_logs(labelled, tmp_path / "no_test", lambda n: "train" in n), "no test logs"),
        (_copy_logs(labelled, tmp_path / "no_train", lambda n: "test" in n), "no training logs"),
    ]
    for in_dir, message in cases:
        code, err = _run_cli([LEG, str(in_dir), str(tmp_path / "out"), "--params", params], capsys)
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and message in lines[0], err
    # a leg that never has an exact label is no error: the group is not calibrated, and says why
    no_labels = _copy_logs(labelled, tmp_path / "no_labels", lambda n: True)
    for path in no_labels.glob("*train.parquet"):
        table = pq.read_table(path)
        i = table.schema.get_field_index(S.switch_col(LEG))
        table = table.set_column(i, table.schema.field(i), pa.array(np.zeros(table.num_rows, np.uint8)))
        pq.write_table(table, path)
    code = main(["train", LEG, str(no_labels), str(tmp_path / "out"), "--params", params])
    captured = capsys.readouterr()
    why = "no exact label (one side of its cut always touches, or its wrench is not ok there)"
    assert code == 0 and captured.out == "", captured.out
    assert captured.err.splitlines() == [f"ftcal: warning: {LEG}: not calibrated: {why}"], captured.err
    record = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert record["not_calibrated"] == why and "test" not in record
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["metrics.json"]


def test_log_kind_refines_the_type_with_foot_and_part(tmp_path: Path) -> None:
    write_labelled_log(tmp_path / "a_train.parquet", "pole", "train", n=50, seed=0)
    table = pq.read_table(tmp_path / "a_train.parquet")
    meta = dict(table.schema.metadata)
    meta[S.META_EXPERIMENT] = json.dumps(
        {"type": "half_foot", "foot": "l_foot", "part": "front", "role": "train"}
    )
    pq.write_table(table.replace_schema_metadata(meta), tmp_path / "a_train.parquet")
    assert [log.kind for log in find_logs(tmp_path)] == ["half_foot/l_foot/front"]


def test_log_without_role_is_a_data_error(tmp_path: Path) -> None:
    write_labelled_log(tmp_path / "a.parquet", "pole", "", n=50, seed=0)
    with pytest.raises(DataError, match="a.parquet: experiment metadata role must be 'train' or 'test'"):
        find_logs(tmp_path)


# --- end to end ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_end_to_end_resumes_registers_and_repeats(
    tmp_path: Path, labelled: Path, mlflow_uri: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mlflow import MlflowClient

    params = load_params(write_params(tmp_path))
    out_a, out_b = tmp_path / "a", tmp_path / "b"

    # A: a fresh study.
    a = train_group(params, PAIR, labelled, out_a, tmp_path / "studies_a", progress=False)

    # B: another fresh study, interrupted in the nn7 search's second trial (the nn13 search, in another
    # worker, is ended wherever it is), then resumed.
    real = train_network
    calls = {"n": 0}  # the nn7 search's, in the worker that runs it

    def interrupted(*args: Any, **kwargs: Any) -> Any:
        if args[3].n_inputs == 7:
            calls["n"] += 1
            if calls["n"] == 2:
                raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(calib_search, "train_network", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train_group(params, PAIR, labelled, out_b, tmp_path / "studies_b", progress=False)
    monkeypatch.setattr(calib_search, "train_network", real)
    b = train_group(params, PAIR, labelled, out_b, tmp_path / "studies_b", progress=False)
    assert b.metrics["networks"]["nn7"]["trials_reused"] == 1
    assert b.metrics["networks"]["nn7"]["trials_run"] == 2
    # Same params, same data: the same metrics, whether or not the search was interrupted.
    assert _comparable(b.metrics) == _comparable(a.metrics)
    assert (
        json.loads((out_a / "metrics.json").read_text())["test"]
        == json.loads((out_b / "metrics.json").read_text())["test"]
    )

    # A again: the finished study is reused, nothing retrained.
    again = train_group(params, PAIR, labelled, out_a, tmp_path / "studies_a", progress=False)
    assert all(n["trials_run"] == 0 and n["trials_reused"] == 3 for n in again.metrics["networks"].values())
    assert _comparable(again.metrics) == _comparable(a.metrics)

    m = a.metrics
    for split in ("val", "test"):
        assert set(m[split]) == {"raw", *TRAINED}
        for errors in m[split].values():
            assert {FRONT, REAR, PAIR, "rmse", "rmse_labelled"} <= set(errors)
            assert errors["rmse"] == errors[PAIR]["rmse"]
    errors = {k: v["rmse_labelled"] for k, v in m["val"].items()}
    cv = m["cv"]
    held = [f["val"] for f in cv["folds"]]  # val_logs 1: one log of pole or walking, another per fold
    assert sorted(held) in (
        [["00_pole_train"], ["01_pole_train"]],
        [["03_walking_train"], ["04_walking_train"]],
    )
    assert set(cv["scores"]) == set(errors)
    for model, scores in cv["scores"].items():
        assert len(scores) == 2 and scores[0] == pytest.approx(errors[model], rel=1e-6)
        assert cv["mean"][model] == pytest.approx(np.mean(scores))
    assert m["best_on_validation"] == cv["chosen"] == select_by_folds(cv["scores"], 0.1)
    assert m["validation_ranking"][0] == m["best_on_validation"]
    for name in ("nn7", "nn13"):  # trained from the affine map: epoch -1 is the affine baseline
        first = m["networks"][name]["history"][0]
        assert first["epoch"] == -1 and first["val_rmse"] == pytest.approx(errors["affine"], rel=1e-3)
    first = m["windowed"]["history"][0]  # the windowed network corrects the play model
    assert first["epoch"] == -1 and first["val_rmse"] == pytest.approx(errors["play"], rel=1e-3)
    assert m["windowed"]["time_constants_s"] == [0.05, 0.5]
    assert m["windowed"]["period_s"] == pytest.approx(0.01)
    # The synthetic distortion is nearly affine: every calibration beats the raw wrench by far.
    raw = m["test"]["raw"]["rmse"]
    for name in ("affine", "poly1", "poly2", "play", "arx", "nn7", "nn13", "win"):
        assert m["test"][name]["rmse"] < raw / 3, (name, m["test"][name]["rmse"], raw)

    # Model files: weights-only, and the same predictions as in predictions.parquet.
    pred = pd.read_parquet(out_a / "predictions.parquet")
    assert set(pred[LOG]) == {"05_pole_test", "06_walking_test"}
    for name, n_inputs in (("nn7", 7), ("nn13", 13)):
        model, info = load_model(out_a / name)
        cols = [c for sensor in (FRONT, REAR) for c in input_cols(sensor, n_inputs)]
        assert info["input_columns"] == cols
        test = pd.concat([pd.read_parquet(p).assign(**{LOG: p.stem}) for p in labelled.glob("*test.parquet")])
        test = pred[[LOG, S.STAMP]].merge(test, on=[LOG, S.STAMP], how="left")
        with torch.no_grad():
            y = model(torch.tensor(test[cols].to_numpy(), dtype=torch.float32)).numpy()
        expected = pred[prediction_cols(name, FRONT) + prediction_cols(name, REAR)].to_numpy()
        np.testing.assert_allclose(y, expected, rtol=1e-5, atol=1e-4)
    win = WindowModel.from_dict(json.loads((out_a / "win.json").read_text()))
    logs = {p.stem: pd.read_parquet(p) for p in labelled.glob("*test.parquet")}
    for log, rows in pred.groupby(LOG):  # each test log from a fresh state, every reading in time order
        table = logs[log]
        x = np.stack([table[input_cols(s, 7)].to_numpy(np.float64) for s in (FRONT, REAR)], axis=1)
        y = pd.DataFrame(win.predict_log(x).reshape(len(x), -1))
        y[S.STAMP] = table[S.STAMP].to_numpy()
        y = rows[[S.STAMP]].merge(y, on=S.STAMP, how="left").drop(columns=S.STAMP).to_numpy()
        expected = rows[prediction_cols("win", FRONT) + prediction_cols("win", REAR)].to_numpy()
        np.testing.assert_allclose(y, expected, rtol=1e-6, atol=1e-5)  # stored as float32

    # MLflow: the stage's run tagged with the group, nested trial runs, registered pt2 models.
    client = MlflowClient(mlflow_uri)
    exp = client.get_experiment_by_name("ftcal")
    runs = client.search_runs([exp.experiment_id], filter_string=f"tags.`dvc.stage` = 'train@{PAIR}'")
    assert runs and all(r.data.tags["group"] == PAIR for r in runs)
    parent = runs[-1]  # the first run (A)
    children = client.search_runs(
        [exp.experiment_id], filter_string=f"tags.`mlflow.parentRunId` = '{parent.info.run_id}'"
    )
    assert len(children) == 6  # 3 trials x 2 networks
    for n_inputs in (7, 13):  # registered by A, B resumed (B interrupted registered nothing) and A again
        versions = client.search_model_versions(f"name = 'ftcal-{PAIR}-{n_inputs}'")
        assert len(versions) == 3
    # The registered pt2 model loads without allowing pickle and computes what load_model's module does.
    import mlflow.pytorch

    monkeypatch.delenv("MLFLOW_ALLOW_PICKLE_DESERIALIZATION", raising=False)
    exported = mlflow.pytorch.load_model(f"models:/ftcal-{PAIR}-7/1")
    model, _ = load_model(out_a / "nn7")
    x = torch.randn(16, 14) * 50
    np.testing.assert_allclose(exported(x).detach().numpy(), model(x).detach().numpy(), rtol=1e-5, atol=1e-4)


@pytest.mark.slow
def test_networks_searched_side_by_side_equal_those_searched_one_after_the_other(
    tmp_path: Path, labelled: Path, mlflow_uri: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stage searches nn7 and nn13 in forked processes: the same networks, bit for bit, and the same
    trials logged in MLflow, as on one core."""
    from mlflow import MlflowClient

    import pipeline.core.parallel as parallel

    params = load_params(write_params(tmp_path, n_trials=2, epochs=2))
    forked = train_group(params, LEG, labelled, tmp_path / "a", tmp_path / "studies_a", progress=False)
    monkeypatch.setattr(parallel.os, "cpu_count", lambda: 1)
    alone = train_group(params, LEG, labelled, tmp_path / "b", tmp_path / "studies_b", progress=False)
    assert _comparable(forked.metrics) == _comparable(alone.metrics)
    for name in ("nn7", "nn13"):
        a, b = (torch.load(d / f"{name}.pt", weights_only=True) for d in (tmp_path / "a", tmp_path / "b"))
        assert all(torch.equal(a[k], b[k]) for k in a), name
    client = MlflowClient(mlflow_uri)
    for result in (forked, alone):
        children = client.search_runs(
            [client.get_experiment_by_name("ftcal").experiment_id],
            filter_string=f"tags.`mlflow.parentRunId` = '{result.mlflow_run}'",
        )
        assert sorted(r.info.run_name for r in children) == sorted(
            f"{LEG} nn{n} trial {i}" for n in (7, 13) for i in (1, 2)
        )


def test_cli_single_sensor_group(
    tmp_path: Path, labelled: Path, mlflow_uri: str, capsys: pytest.CaptureFixture[str]
) -> None:
    params = write_params(tmp_path, inputs=[7], n_trials=2, epochs=2)
    out = tmp_path / "out"
    code = main(
        ["train", LEG, str(labelled), str(out), "--params", str(params), "--studies", str(tmp_path / "st")]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert captured.out.startswith(f"{LEG}: test RMSE of {LEG}")
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["test"]) == {"raw", "offset", "affine", "poly1", "poly2", "play", "arx", "nn7", "win"}
    assert metrics["kind"] == "sensor" and metrics["headline"] == LEG
    assert sorted(p.name for p in out.iterdir()) == [
        "baselines.json",
        "metrics.json",
        "nn7.json",
        "nn7.pt",
        "predictions.parquet",
        "win.json",
    ]


def test_cut_sums_match_the_pose_transforms_of_the_label_stage() -> None:
    """The trainer's signed sums (torch, poses per sample) against pipeline.physics.cuts's transforms."""
    rng = np.random.default_rng(3)
    n = 50
    rot = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
    poses = np.concatenate([rot.reshape(n, 9), rng.normal(size=(n, 3))], axis=1)
    fixed = np.zeros((3, 6, 6))
    fixed[1:] = -TRANSFORMS
    cut = CutTerm("c", (2, 0, 1), fixed, ((0, 1.0),), (("unused",),))
    pred = rng.normal(size=(n, 3, 6)) * 50
    got = cut_sums_np((cut,), pred, poses[:, None])[:, 0]
    x_leg = pose_wrench_transforms(poses)
    want = (
        np.einsum("nij,nj->ni", x_leg, pred[:, 2])
        - pred[:, 0] @ TRANSFORMS[0].T
        - pred[:, 1] @ TRANSFORMS[1].T
    )
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-9)


@pytest.mark.slow
def test_several_sensors_group_trains_with_its_cut_sets(
    tmp_path: Path, labelled: Path, mlflow_uri: str
) -> None:
    """A leg and its foot's two sensors as one group: the shank and foot cut sets read from the labelled
    metadata, scored and written; the leg is labelled through the shank where it has no label itself."""
    train = copy.deepcopy(TRAIN_PARAMS)
    train["groups"] = {"shank": {"sensors": [LEG, FRONT, REAR], "inputs": [7], "n_trials": 1, "epochs": 3}}
    params = load_params(write_params(tmp_path, train))
    r = train_group(params, "shank", labelled, tmp_path / "out", tmp_path / "st", progress=False)
    m = r.metrics
    assert m["kind"] == "sensors" and m["headlines"] == [LEG, PAIR]
    assert m["pairs"] == {PAIR: [FRONT, REAR]} and sorted(m["cut_sets"]) == sorted([PAIR, SHANK])
    for name in ("affine", "nn7"):
        errors = m["test"][name]
        assert {LEG, FRONT, REAR, PAIR, SHANK} <= set(errors)
        assert errors[SHANK]["rmse"] < m["test"]["raw"][SHANK]["rmse"] / 3
    # epoch -1 of the network is the affine map, fitted part by part (the leg alone, the foot pair)
    assert m["networks"]["nn7"]["history"][0]["epoch"] == -1
    pred = pd.read_parquet(tmp_path / "out" / "predictions.parquet")
    test = pd.concat([pd.read_parquet(p).assign(**{LOG: p.stem}) for p in labelled.glob("*test.parquet")])
    test = pred[[LOG, S.STAMP]].merge(test, on=[LOG, S.STAMP], how="left")
    poses = test[S.cut_pose_cols(SHANK, LEG)].to_numpy().astype(np.float32)  # as the stage reads them
    leg, front, rear = (pred[prediction_cols("nn7", s)].to_numpy() for s in (LEG, FRONT, REAR))
    want = map_wrenches(poses, leg) - front @ TRANSFORMS[0].T - rear @ TRANSFORMS[1].T
    # the shank's score is the cut-set sum of the sensors' predictions written, against its label
    on = pred[S.switch_col(SHANK)].to_numpy() == 1
    label = pred[S.wrench_cols(S.EXPECTED, SHANK)].to_numpy()[on]
    assert on.sum() > 100
    rmse = np.sqrt(np.mean((want[on] - label) ** 2))
    assert rmse == pytest.approx(m["test"]["nn7"][SHANK]["rmse"], rel=1e-9)
    # a foot pair's predicted sum is written (a headline evaluate scores), the shank's is not
    pair = front @ TRANSFORMS[0].T + rear @ TRANSFORMS[1].T
    np.testing.assert_allclose(pred[prediction_cols("nn7", PAIR)].to_numpy(), pair, rtol=1e-9, atol=1e-9)
    assert not set(prediction_cols("nn7", SHANK)) & set(pred.columns)


def test_without_imu_a_7_input_network_trains_and_a_13_input_one_says_why(
    tmp_path: Path, labelled: Path, mlflow_uri: str
) -> None:
    """Logs whose FT board has no IMU stream (ingest: NaN columns, ok.imu false everywhere)."""
    import pyarrow.compute as pc

    no_imu = tmp_path / "labelled"
    no_imu.mkdir()
    for path in sorted(labelled.glob("*.parquet")):
        table = pq.read_table(path)
        for c in S.vector_cols(S.ACC, LEG) + S.vector_cols(S.GYR, LEG):
            table = table.set_column(table.schema.get_field_index(c), c, pc.multiply(table[c], float("nan")))
        flag = S.ok_col(S.IMU_STREAM, LEG)
        table = table.set_column(table.schema.get_field_index(flag), flag, pa.array([False] * len(table)))
        pq.write_table(table, no_imu / path.name)
    params = load_params(write_params(tmp_path, inputs=[7, 13], n_trials=1, epochs=1))
    with pytest.raises(DataError, match=rf"no IMU .* for {LEG} .*a 13-input network needs it"):
        train_group(params, LEG, no_imu, tmp_path / "out13", tmp_path / "st13", progress=False)
    params = load_params(write_params(tmp_path, inputs=[7], n_trials=1, epochs=1))
    result = train_group(params, LEG, no_imu, tmp_path / "out7", tmp_path / "st7", progress=False)
    assert math.isfinite(result.metrics["test"]["nn7"]["rmse"])


def test_prior_holds_a_sensor_without_its_own_label_near_the_affine_map(
    tmp_path: Path, labelled: Path
) -> None:
    """lambda_prior: where the leg has no exact label of its own (only the shank's sum), a strong prior
    keeps its output at the affine map's; without it the network moves freely there."""
    from dataclasses import replace

    from pipeline.calib.fit import prepare
    from pipeline.calib.fitting import fit_affine
    from pipeline.calib.training import NetSetting, predict

    train = copy.deepcopy(TRAIN_PARAMS)
    train["groups"] = {"shank": {"sensors": [LEG, FRONT, REAR], "inputs": [7], "epochs": 4, "lr": 0.03}}
    params = load_params(write_params(tmp_path, train))
    prep = prepare(params, "shank", labelled)
    affine = fit_affine(prep.gp, prep.group, prep.train, prep.seed)
    free = ~prep.train.switches[:, 0]
    assert free.sum() > 50
    gaps, models = {}, {}
    no_pushes = replace(prep.gp.push, weight=0.0)  # the prior alone (virtual pushes also hold it near)
    for lam in (0.0, 100.0):
        setting = replace(NetSetting.of(prep.gp, 7), lambda_prior=lam, average_epochs=0.0, push=no_pushes)
        models[lam], _ = train_network(prep.group, prep.train, prep.train, setting, 3, None, affine)
        gap = predict(models[lam], prep.train)[free, 0] - affine.predict(prep.train.x)[free, 0]
        gaps[lam] = float(np.sqrt(np.mean(gap**2)))
    # the free samples' inputs resemble labelled ones, where the labels pull the other way: a clear cut
    assert gaps[100.0] < 0.75 * gaps[0.0], gaps
    # the term itself: lambda_prior x the batch mean of the squared distance (mean over axes) to the prior,
    # summed over the sensors without an exact label (on the network trained without it: farther away)
    from pipeline.calib.training import _batch_loss, to_tensors

    model = models[0.0]
    prior = affine.predict(prep.train.x)
    t = to_tensors(prep.train, 7, prep.group, prior)
    idx = torch.arange(len(prep.train))
    lambdas = torch.ones(3)
    transforms = None  # a group of several sensors: its sums are cut sets
    setting = replace(NetSetting.of(prep.gp, 7), lambda_prior=2.0)
    with torch.no_grad():
        with_prior = _batch_loss(prep.group, model, t, idx, lambdas, transforms, setting)
        t.prior = None
        without = _batch_loss(prep.group, model, t, idx, lambdas, transforms, setting)
    gap = ((predict(model, prep.train) - prior) ** 2).mean(axis=2) * ~prep.train.switches
    assert float(with_prior - without) == pytest.approx(2.0 * gap.sum(axis=1).mean(), rel=1e-4)
