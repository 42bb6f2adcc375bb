"""One recording, several logs: the sidecar's window and train/test segments, for every log format (a
recording split by segments trains and tests, and no sample of its test segment reaches training:
tests/test_recorded.py)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import yaml

from pipeline.logs import schema as S
from pipeline.logs.mcap_table import ingest_log
from tests import matfile
from tests.factories.logs import CFG_MAT, JOINTS, SENSORS, TOPICS, write_log

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
    report = ingest_log(mat, tmp_path / "seg", "log", CFG_MAT, TOPICS, JOINTS, SENSORS)
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

    from tests.factories.logs import CFG, EXPERIMENT

    experiment = {**EXPERIMENT, "segments": json.dumps(SEGMENTS)}
    mcap = write_log(tmp_path / "log.mcap", duration=4.0, experiment=experiment)
    report = ingest_log(mcap, tmp_path / "out", "log", CFG, TOPICS, JOINTS, SENSORS)
    assert len(report.outputs) == 3
    for k in range(3):
        table = pd.read_parquet(tmp_path / "out" / f"log__seg{k}.parquet")
        truth = pd.read_parquet(tmp_path / "out" / f"log__seg{k}.truth.parquet")
        assert len(table) > 50 and truth[S.STAMP].tolist() == table[S.STAMP].tolist()


def test_segments_as_close_as_a_lab_writes_them_are_smoothed_apart(tmp_path: Path) -> None:
    """Segments 0.1 s apart, closer than the smoothing window (21 samples here): each is its own table,
    smoothed alone, its first and last half window not ok for labelling, so no sample of one segment's
    kinematics comes from the other's."""
    from pipeline.logs.smoothing import SmoothParams, smooth_table

    mcap = write_log(tmp_path / "log.mcap", duration=4.0)
    mat = matfile.mcap_to_mat(mcap, tmp_path / "log.mat", TOPICS, SENSORS)
    side = yaml.safe_load(mat.with_suffix(".yaml").read_text())
    close = [{"start_s": 0.2, "end_s": 1.0, "role": "train"}, {"start_s": 1.1, "end_s": 2.0, "role": "test"}]
    mat.with_suffix(".yaml").write_text(yaml.safe_dump({**side, "segments": close}))
    report = ingest_log(mat, tmp_path / "out", "log", CFG_MAT, TOPICS, JOINTS, SENSORS)
    assert len(report.outputs) == 2
    window = 21
    for k in range(2):
        src = tmp_path / "out" / f"log__seg{k}.parquet"
        smooth_table(src, tmp_path / f"s{k}.parquet", SmoothParams(window, 3, 0.05))
        ok = pd.read_parquet(tmp_path / f"s{k}.parquet")[S.ok_col(S.KINEMATICS_STREAM)].to_numpy()
        half = window // 2
        assert not ok[:half].any() and not ok[-half:].any() and ok[half:-half].all()
