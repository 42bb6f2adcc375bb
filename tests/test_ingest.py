"""Stage `ingest`: alignment functions, messy-but-valid logs, bad logs, metadata, MLflow, CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from pipeline.cli import main
from pipeline.core.config import load_params, stage_section
from pipeline.core.errors import ConfigError, DataError
from pipeline.logs import mcap_table, tables
from pipeline.logs import schema as S
from pipeline.logs.align import align_continuous, align_latest, sort_unique, stamp_steps_back
from pipeline.logs.params import IngestParams
from pipeline.logs.rosmsg import LogWriter
from pipeline.logs.tables import read_table_metadata
from tests.factories.logs import (
    CFG,
    EXPERIMENT,
    JOINTS,
    MS,
    SENSORS,
    T0,
    joint_position,
    linear_wrench,
    run_one,
    stamps,
    write_log,
)
from tests.factories.params import write_ingest_params

ROOT = Path(__file__).resolve().parent.parent


# --- pure functions ---


def test_align_continuous_interpolates_within_the_gap_only() -> None:
    src = np.array([0, 10, 20, 60, 70]) * MS
    values = np.column_stack([np.array([0.0, 1, 2, 6, 7]), np.array([0.0, -1, -2, -6, -7])])
    target = np.array([-5, 0, 5, 15, 30, 45, 60, 65, 70, 75]) * MS
    out, ok = align_continuous(target, src, values, 25 * MS)  # the 40 ms hole is not bridged
    np.testing.assert_array_equal(ok, [False, True, True, True, False, False, True, True, True, False])
    np.testing.assert_allclose(out[ok, 0], [0, 0.5, 1.5, 6, 6.5, 7])
    np.testing.assert_allclose(out[ok, 1], -out[ok, 0])
    assert np.isnan(out[~ok]).all()
    empty, none_ok = align_continuous(target, np.empty(0, dtype=np.int64), np.empty((0, 2)), 25 * MS)
    assert np.isnan(empty).all() and not none_ok.any()


def test_align_latest_never_interpolates() -> None:
    src = np.array([10, 20, 30])
    values = np.array(["a", "b", "c"], dtype=object)
    out = align_latest(np.array([5, 10, 15, 29, 30, 99]), src, values)
    assert out.tolist() == [None, "a", "a", "b", "c", "c"]


def test_reorder_and_duplicate_helpers() -> None:
    np.testing.assert_array_equal(stamp_steps_back(np.array([1, 3, 2, 5, 4, 6]), None), [0, 0, 1, 0, 1, 0])
    np.testing.assert_array_equal(stamp_steps_back(np.array([1, 2]), 10), [9, 8])
    s, v, dropped = sort_unique(np.array([3, 1, 2, 1]), np.array([[30.0], [10], [20], [11]]))
    np.testing.assert_array_equal(s, [1, 2, 3])
    np.testing.assert_array_equal(v[:, 0], [10, 20, 30])  # the first arrival of stamp 1 is kept
    assert dropped == 1


def test_params_validation_names_the_key() -> None:
    with pytest.raises(ConfigError, match="ingest.max_gap_s"):
        IngestParams(
            source="x",
            max_gap_s=0,
            max_gap_temperature_s=1,
            max_reorder_s=1,
            max_nonfinite_fraction=0,
            skip_bad_logs=False,
        )
    with pytest.raises(ConfigError, match="ingest.skip_bad_logs"):
        IngestParams(
            source="x",
            max_gap_s=1,
            max_gap_temperature_s=1,
            max_reorder_s=1,
            max_nonfinite_fraction=0,
            skip_bad_logs="no",
        )  # type: ignore[arg-type]
    params = load_params(ROOT / "params.yaml")
    assert stage_section(params, "ingest", IngestParams).source == "data/sim"


# --- a valid but messy log ---


def test_aligned_table_values_flags_and_truth(tmp_path: Path) -> None:
    def messy(w: LogWriter) -> None:
        # s_two's wrench: 200 Hz with a 100 ms hole, duplicates and late (out-of-order) arrivals.
        ft = stamps(2.0, 200.0, offset_ns=1 * MS)
        hole = (ft > T0 + 1000 * MS) & (ft < T0 + 1100 * MS)
        ft = ft[~hole]
        values = linear_wrench((ft - T0) / 1e9, 1)
        log = ft + 3 * MS
        log[100:110] += 100 * MS  # arrive 100 ms late: after newer messages
        ft = np.concatenate([ft, ft[200:205]])  # duplicates, each arriving just after its original
        values = np.concatenate([values, values[200:205] + 1e6])  # (different values: the first is kept)
        log = np.concatenate([log, log[200:205] + 1])
        w.wrenches("/ft/s_two/wrench", ft, "s_two", values, log_times_ns=log)

    path = write_log(tmp_path / "messy.mcap", skip=["/ft/s_two/wrench", "/ft/s_two/imu"], extra=messy)
    report = run_one(path, tmp_path / "out")
    df = pd.read_parquet(report.output)
    assert list(df.columns) == S.ingested_columns(JOINTS, SENSORS)
    assert len(df) == 200 == report.samples
    t = (df[S.STAMP].to_numpy() - T0) / 1e9
    np.testing.assert_allclose(df[S.TIME], t - t[0])
    for k, j in enumerate(JOINTS):
        np.testing.assert_allclose(df[S.joint_col(S.Q, j)], joint_position(t, k))
    # Wrenches: exact linear interpolation between the 200 Hz messages (1 ms offset from the time base).
    for k, s in enumerate(SENSORS):
        ok = df[S.ok_col(S.WRENCH_STREAM, s)].to_numpy()
        got = df[S.wrench_cols(S.FT, s)].to_numpy()
        np.testing.assert_allclose(got[ok], linear_wrench(t, k)[ok], atol=1e-9)
        assert np.isnan(got[~ok]).all()
    ok_two = df[S.ok_col(S.WRENCH_STREAM, "s_two")].to_numpy()
    in_hole = (t > 0.996) & (t < 1.101)  # the messages around the hole: 0.996 s and 1.101 s
    assert not ok_two[in_hole].any()  # the 100 ms hole is wider than max_gap_s: flagged
    assert ok_two[~in_hole & (t > 0.01) & (t < 1.98)].all()
    # A missing optional stream: NaN, flagged, and a warning.
    assert not df[S.ok_col(S.IMU_STREAM, "s_two")].any()
    assert df[S.vector_cols(S.ACC, "s_two")].isna().all().all()
    assert any("/ft/s_two/imu" in w for w in report.warnings)
    np.testing.assert_allclose(df[S.vector_cols(S.ACC, "s_one")].to_numpy()[:, 0], t)
    # Temperature at 10 Hz is bridged (max_gap_temperature_s), except after its last message.
    ok_temp = df[S.ok_col(S.TEMPERATURE_STREAM, "s_one")].to_numpy()
    assert ok_temp[t <= 1.9].all() and not ok_temp[t > 1.9].any()
    np.testing.assert_allclose(df[S.temperature_col("s_one")][ok_temp], 30.0 + t[ok_temp])
    stats = report.streams["wrench.s_two"]
    assert (stats.duplicates, stats.reordered) == (5, 10)
    # Truth apart, on the same time base; contacts are the latest message, never interpolated.
    truth = pd.read_parquet(report.truth_output)
    assert list(truth.columns) == S.truth_columns(SENSORS)
    np.testing.assert_array_equal(truth[S.STAMP], df[S.STAMP])
    np.testing.assert_allclose(truth[S.wrench_cols(S.ORACLE, "s_one")].to_numpy(), linear_wrench(t, 0) + 200)
    assert truth[S.CONTACTS].tolist() == [
        ("l_sole" if (i // 50) % 2 else "l_sole,r_sole") for i in range(200)
    ]


def test_streamed_writing_equals_one_pass(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write_log(tmp_path / "long.mcap", duration=6.0, chunk_size=20_000)  # ~60 chunks
    whole = pd.read_parquet(run_one(path, tmp_path / "a").output)
    monkeypatch.setattr(mcap_table, "_EMIT_ROWS", 37)
    monkeypatch.setattr(tables, "ROW_GROUP_ROWS", 100)
    report = run_one(path, tmp_path / "b")
    assert pq.ParquetFile(report.output).metadata.num_row_groups > 3
    pd.testing.assert_frame_equal(pd.read_parquet(report.output), whole)
    pd.testing.assert_frame_equal(
        pd.read_parquet(report.truth_output), pd.read_parquet(tmp_path / "a" / "long.truth.parquet")
    )


def test_rare_discrete_messages_do_not_stall_or_go_stale(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Contacts published only on change (t = 0 s and 4.5 s): they neither hold back the streamed writing
    # nor arrive after rows that needed them were written.
    def contacts(w: LogWriter) -> None:
        w.strings("/sim/contacts", np.array([T0, T0 + 4_500 * MS]), ["l_sole,r_sole", "r_sole"])

    path = write_log(
        tmp_path / "rare.mcap", duration=6.0, chunk_size=20_000, skip=["/sim/contacts"], extra=contacts
    )
    monkeypatch.setattr(mcap_table, "_EMIT_ROWS", 37)
    report = run_one(path, tmp_path / "out")
    truth = pd.read_parquet(report.truth_output)
    t = (truth[S.STAMP].to_numpy() - T0) / 1e9
    assert truth[S.CONTACTS].tolist() == ["l_sole,r_sole" if x < 4.5 else "r_sole" for x in t]
    assert report.streams[S.CONTACTS].late == 0
    assert pq.ParquetFile(report.output).metadata.num_rows == 600


def test_joint_order_follows_the_urdf_whatever_the_message_order(tmp_path: Path) -> None:
    def reversed_names(w: LogWriter) -> None:
        js = stamps(2.0, 100.0)
        q = np.column_stack([joint_position((js - T0) / 1e9, k) for k in range(len(JOINTS))])
        w.joint_states("/joint_states", js, JOINTS[::-1], q[:, ::-1], np.empty((len(js), 0)))  # no velocities

    report = run_one(
        write_log(tmp_path / "rev.mcap", skip=["/joint_states"], extra=reversed_names), tmp_path / "out"
    )
    df = pd.read_parquet(report.output)
    t = (df[S.STAMP].to_numpy() - T0) / 1e9
    for k, j in enumerate(JOINTS):
        np.testing.assert_allclose(df[S.joint_col(S.Q, j)], joint_position(t, k))
    assert df[S.joint_cols(S.DQ_ENC, JOINTS) + S.joint_cols(S.TAU_ENC, JOINTS)].isna().all().all()


def test_parquet_metadata_and_units(tmp_path: Path) -> None:
    report = run_one(write_log(tmp_path / "m.mcap"), tmp_path / "out")
    meta = read_table_metadata(report.output)
    assert meta["ftcal.experiment"] == EXPERIMENT
    assert meta["ftcal.source"]["file"] == str(tmp_path / "m.mcap")
    assert meta["ftcal.source"]["topics"]["/ft/s_one/wrench"] == {
        "type": "geometry_msgs/msg/WrenchStamped",
        "messages": 400,
    }
    streams = meta["ftcal.ingest"]["streams"]
    assert streams["/joint_states"]["rate_hz"] == pytest.approx(100.0)
    assert streams["/ft/s_one/wrench"]["rate_hz"] == pytest.approx(200.0)
    assert meta["ftcal.schema"] == {"kind": "ingested", "version": S.SCHEMA_VERSION}
    schema = pq.read_schema(report.output)
    assert schema.field("ft.s_one.tz").metadata[b"unit"] == b"Nm"
    assert schema.field(S.STAMP).type == "int64"
    # A real log (no /sim/ topics) has no truth table.
    real = write_log(
        tmp_path / "real.mcap", truth=False, experiment={"type": "pole", "robot": "iCubGenova09"}
    )
    report = run_one(real, tmp_path / "out")
    assert report.truth_output is None
    assert not (tmp_path / "out" / "real.truth.parquet").exists()


# --- bad logs: each a one-line error naming the file and the problem, and no output ---


def _nan_wrench(w: LogWriter) -> None:
    ft = stamps(2.0, 200.0, offset_ns=1 * MS)
    values = linear_wrench((ft - T0) / 1e9, 0)
    values[10, 2] = np.nan
    values[11, 4] = np.inf
    w.wrenches("/ft/s_one/wrench", ft, "s_one", values)


def _clock_jump(w: LogWriter) -> None:
    received = stamps(2.0, 100.0)  # the recorder's clock runs on
    js = received.copy()
    js[120:] -= 2 * 10**9  # the robot's clock steps back 2 s
    q = np.zeros((len(js), 3))
    w.joint_states("/joint_states", js, JOINTS, q, q, log_times_ns=received)


def _wrong_type(w: LogWriter) -> None:
    js = stamps(2.0, 100.0)
    w.temperatures("/ft/s_one/wrench", js, "s_one", np.zeros(len(js)))


def _foreign_joint(w: LogWriter) -> None:
    js = stamps(2.0, 100.0)
    w.joint_states("/joint_states", js, [*JOINTS, "tail_wag"], np.zeros((len(js), 4)), np.zeros((len(js), 4)))


BAD_WRITERS = {
    "missing_topic": ({"skip": ["/ft/s_two/wrench"]}, "missing required topic(s) /ft/s_two/wrench"),
    "nan_values": ({"skip": ["/ft/s_one/wrench"], "extra": _nan_wrench}, "NaN/inf values in 2 of 400"),
    "clock_jump": (
        {"skip": ["/joint_states"], "extra": _clock_jump},
        "non-monotonic stamps on /joint_states",
    ),
    "wrong_type": (
        {"skip": ["/ft/s_one/wrench"], "extra": _wrong_type},
        "topic /ft/s_one/wrench has type sensor_msgs/msg/Temperature, expected",
    ),
    "foreign_joint": (
        {"skip": ["/joint_states"], "extra": _foreign_joint},
        "joints not in the URDF: tail_wag",
    ),
}


def _bad_bytes(tmp_path: Path) -> dict[str, tuple[bytes, str]]:
    good = write_log(tmp_path / "good_src.mcap").read_bytes()
    from mcap.reader import make_reader

    with open(tmp_path / "good_src.mcap", "rb") as f:
        chunk = make_reader(f).get_summary().chunk_indexes[0]
    corrupted = bytearray(good)
    corrupted[chunk.chunk_start_offset + chunk.chunk_length - 100] ^= 0x55
    return {
        "empty": (b"", "empty file"),
        "truncated": (good[: len(good) * 2 // 3], "truncated MCAP"),
        "corrupted": (bytes(corrupted), "corrupted chunk"),
    }


@pytest.mark.parametrize("case", [*BAD_WRITERS, "empty", "truncated", "corrupted"])
def test_bad_log_is_a_data_error_and_leaves_nothing(tmp_path: Path, case: str) -> None:
    path = tmp_path / f"{case}.mcap"
    if case in BAD_WRITERS:
        kwargs, problem = BAD_WRITERS[case]
        write_log(path, **kwargs)
    else:
        content, problem = _bad_bytes(tmp_path)[case]
        path.write_bytes(content)
    out = tmp_path / "out"
    with pytest.raises(DataError) as info:
        run_one(path, out)
    message = str(info.value)
    assert message.startswith(str(path)), message
    assert problem in message
    assert "\n" not in message
    assert not out.exists() or list(out.iterdir()) == []


def test_small_reorders_are_fine_but_joint_names_must_cover_the_urdf(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="lacks URDF joints: j_d"):
        run_one(write_log(tmp_path / "few.mcap"), tmp_path / "out", joints=[*JOINTS, "j_d"])
    tolerant = IngestParams(**{**CFG.__dict__, "max_nonfinite_fraction": 0.01})
    report = run_one(
        write_log(tmp_path / "nan.mcap", skip=["/ft/s_one/wrench"], extra=_nan_wrench),
        tmp_path / "out",
        cfg=tolerant,
    )
    assert report.streams["wrench.s_one"].nonfinite == 2
    assert any("NaN/inf" in w for w in report.warnings)


# --- the stage through the CLI: exit codes, skip_bad_logs, MLflow ---


def test_cli_bad_log_exits_2_with_one_line(
    tmp_path: Path,
    icub_logs: tuple,
    mlflow_db: str,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", mlflow_db)
    src = icub_logs[0]
    out = tmp_path / "out"
    assert main(["ingest", str(src), str(out), "--params", str(write_ingest_params(tmp_path))]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("ftcal: error:")]
    assert len(lines) == 1
    assert "c_truncated.mcap" in lines[0] and "truncated MCAP" in lines[0]
    assert not list(out.glob("*c_truncated*")) and not list(out.glob(".*tmp"))


def test_cli_skip_bad_logs_processes_the_others(
    tmp_path: Path,
    icub_logs: tuple,
    mlflow_db: str,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from mlflow import MlflowClient

    monkeypatch.setenv("MLFLOW_TRACKING_URI", mlflow_db)
    src, joints, sensors = icub_logs
    out = tmp_path / "out"
    params = write_ingest_params(tmp_path, skip_bad_logs=True)
    assert main(["ingest", str(src), str(out), "--params", str(params)]) == 0
    captured = capsys.readouterr()
    assert "warning: skipping" in captured.err and "c_truncated.mcap" in captured.err
    assert sorted(p.name for p in out.iterdir()) == [
        "sub__a.parquet",
        "sub__a.truth.parquet",
        "sub__b.parquet",
        "sub__b.truth.parquet",
    ]
    df = pd.read_parquet(out / "sub__a.parquet")
    assert list(df.columns) == S.ingested_columns(joints, sensors)
    run = MlflowClient(mlflow_db).search_runs(
        [MlflowClient(mlflow_db).get_experiment_by_name("ftcal").experiment_id],
        filter_string="tags.`dvc.stage` = 'ingest'",
        order_by=["attributes.start_time DESC"],
    )[0]
    assert run.data.metrics["logs_ingested"] == 2 and run.data.metrics["logs_skipped"] == 1
    assert run.data.params["ingest.max_gap_s"] == "0.025"
    assert run.info.status == "FINISHED"


def test_cli_config_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    params = write_ingest_params(tmp_path, max_gap_s=-1)
    assert main(["ingest", str(tmp_path), str(tmp_path / "out"), "--params", str(params)]) == 2
    assert "ingest.max_gap_s must be a positive number" in capsys.readouterr().err
