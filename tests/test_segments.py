"""One recording, several logs: the sidecar's window and train/test segments, for every log format; a
recording split by segments trains and tests, and no sample of its test segment reaches training."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import yaml

from pipeline.logs import schema as S
from pipeline.logs.mcap_table import ingest_log
from tests import dumperfile, matfile
from tests.test_ingest import JOINTS, SENSORS, TOPICS, write_log
from tests.test_matlog import CFG_MAT

REPO = Path(__file__).resolve().parents[1]
SEGMENTS = [
    {"start_s": 0.2, "end_s": 1.0, "role": "train"},
    {"start_s": 2.5, "end_s": 3.5, "role": "test"},  # listed out of order: tables keep the list's index
    {"start_s": 1.3, "end_s": 2.2, "role": "train"},
]


def test_mat_sidecar_window_and_segments(tmp_path: Path) -> None:
    """A logger .mat's sidecar window keeps its samples only; segments make a table each, with its role."""
    mcap = write_log(tmp_path / "log.mcap", duration=4.0)
    mat = matfile.mcap_to_mat(mcap, tmp_path / "log.mat", TOPICS, SENSORS)
    side = yaml.safe_load(mat.with_suffix(".yaml").read_text())
    whole = pd.read_parquet(
        ingest_log(mat, tmp_path / "whole", "log", CFG_MAT, TOPICS, JOINTS, SENSORS).output
    )
    mat.with_suffix(".yaml").write_text(yaml.safe_dump({**side, "window": [0.5, 3.0]}))
    cut = pd.read_parquet(
        ingest_log(mat, tmp_path / "window", "log", CFG_MAT, TOPICS, JOINTS, SENSORS).output
    )
    inside = whole[(whole[S.TIME] >= 0.5) & (whole[S.TIME] < 3.0)].reset_index(drop=True)
    pd.testing.assert_frame_equal(cut, inside)
    mat.with_suffix(".yaml").write_text(yaml.safe_dump({**side, "segments": SEGMENTS}))
    report = ingest_log(mat, tmp_path / "seg", "log", CFG_MAT, TOPICS, JOINTS, SENSORS, (), None, 21)
    assert sorted(Path(p).name for p in report.outputs) == [f"log__seg{k}.parquet" for k in range(3)]
    for k, seg in enumerate(SEGMENTS):
        table = pd.read_parquet(tmp_path / "seg" / f"log__seg{k}.parquet")
        expected = whole[(whole[S.TIME] >= seg["start_s"]) & (whole[S.TIME] < seg["end_s"])]
        pd.testing.assert_frame_equal(table, expected.reset_index(drop=True))
        experiment = S.read_metadata(
            pq.read_schema(tmp_path / "seg" / f"log__seg{k}.parquet"), S.META_EXPERIMENT
        )
        assert (
            experiment["role"] == seg["role"]
            and experiment["run"] == "log"
            and experiment["segment"] == str(k)
        )


def test_mcap_experiment_record_segments_split_the_truth_alike(tmp_path: Path) -> None:
    """In an MCAP log the two keys are JSON strings of its experiment record; the simulated truth tables
    are split on the same rows as the tables."""
    import json

    from tests.test_ingest import CFG, EXPERIMENT

    experiment = {**EXPERIMENT, "segments": json.dumps(SEGMENTS)}
    mcap = write_log(tmp_path / "log.mcap", duration=4.0, experiment=experiment)
    report = ingest_log(mcap, tmp_path / "out", "log", CFG, TOPICS, JOINTS, SENSORS)
    assert len(report.outputs) == 3
    for k in range(3):
        table = pd.read_parquet(tmp_path / "out" / f"log__seg{k}.parquet")
        truth = pd.read_parquet(tmp_path / "out" / f"log__seg{k}.truth.parquet")
        assert len(table) > 50 and truth[S.STAMP].tolist() == table[S.STAMP].tolist()


def test_segments_closer_than_the_smoothing_window_are_an_error(tmp_path: Path) -> None:
    from pipeline.core.errors import DataError

    mcap = write_log(tmp_path / "log.mcap", duration=4.0)
    mat = matfile.mcap_to_mat(mcap, tmp_path / "log.mat", TOPICS, SENSORS)
    side = yaml.safe_load(mat.with_suffix(".yaml").read_text())
    close = [{"start_s": 0.2, "end_s": 1.0, "role": "train"}, {"start_s": 1.1, "end_s": 2.0, "role": "test"}]
    mat.with_suffix(".yaml").write_text(yaml.safe_dump({**side, "segments": close}))
    with pytest.raises(
        DataError, match=r"segments\[1\] starts 0.100 s after segments\[0\] ends: .* 21 samples"
    ):
        ingest_log(mat, tmp_path / "out", "log", CFG_MAT, TOPICS, JOINTS, SENSORS, (), None, 21)
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())


def test_one_recording_split_by_segments_trains_and_tests(tmp_path: Path, mlflow_store: None) -> None:
    """A simulated iCub 2.x recording written as a dataDumper run, its sidecar splitting it into two
    training segments and a test segment: ingest -> smooth -> label -> train@r_arm_ft (wrench only); the
    training and validation samples all lie outside the test segment, the test samples all inside."""
    from pipeline.calib.fit import prepare
    from pipeline.core.config import load_params
    from pipeline.stages import ingest, label, simulate, smooth
    from pipeline.stages.train import train_group

    data = yaml.safe_load((REPO / "params.yaml").read_text())
    data["robot"]["urdf"] = "iCubGenova02"
    data["simulate"].update({"logs": [{"type": "pole", "duration_s": 24, "role": "train"}], "workers": 1})
    data["simulate"]["plots"] = False
    data["train"].update({"val_logs": 1, "folds": 1})
    data["train"]["defaults"].update(
        {"inputs": [6], "n_trials": 1, "epochs": 2, "hidden": 64, "poly_orders": [1]}
    )
    data["train"]["groups"] = {"r_arm_ft": {"sensor": "r_arm_ft"}}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    params = load_params(tmp_path / "params.yaml")
    simulate.run(params, tmp_path / "sim", progress=False)
    (mcap,) = sorted((tmp_path / "sim").glob("*.mcap"))
    dumper = data["ingest"]["dumper"]
    segments = [
        {"start_s": 0.5, "end_s": 7.5, "role": "train"},
        {"start_s": 8.0, "end_s": 15.0, "role": "train"},
        {"start_s": 16.0, "end_s": 23.0, "role": "test"},
    ]
    side = {"type": "pole", "robot": "iCubGenova02", "contacts": "root_link", "segments": segments}
    dumperfile.mcap_to_run(
        mcap, tmp_path / "raw" / "yoga", TOPICS, dumper["ft_ports"], dumper["joints"], sidecar=side
    )
    ingest.run(params, tmp_path / "raw", tmp_path / "ingested", progress=False)
    smooth.run(params, tmp_path / "ingested", tmp_path / "smoothed", progress=False)
    label.run(params, tmp_path / "smoothed", tmp_path / "labelled", progress=False)
    prep = prepare(params, "r_arm_ft", tmp_path / "labelled")
    assert sorted([*prep.split["train"], *prep.split["val"]]) == ["yoga__seg0", "yoga__seg1"]
    assert prep.split["test"] == ["yoga__seg2"]
    test_stamps = pd.read_parquet(tmp_path / "labelled" / "yoga__seg2.parquet", columns=[S.STAMP])[S.STAMP]
    lo, hi = int(test_stamps.min()), int(test_stamps.max())
    for part in (prep.train, prep.val):
        assert len(part) and not ((part.stamp >= lo) & (part.stamp <= hi)).any()
    assert len(prep.test) and ((prep.test.stamp >= lo) & (prep.test.stamp <= hi)).all()
    result = train_group(
        params, "r_arm_ft", tmp_path / "labelled", tmp_path / "models", tmp_path / "st", progress=False
    )
    assert np.isfinite(result.metrics["test"]["nn6"]["rmse"])
    assert result.metrics["test"]["affine"]["rmse"] < 0.2 * result.metrics["test"]["raw"]["rmse"]
