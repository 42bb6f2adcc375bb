"""Stage `ingest` on valid logs of other recorders' layouts, and on bad inputs that must be named.

Valid layouts are written with the `mcap` package's own writer (no chunks, chunks without chunk index,
no statistics, no summary) from the messages of a log of ours, and must ingest to the same table.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.cli import main
from pipeline.core.errors import DataError
from pipeline.logs import schema as S
from pipeline.logs.mcap_read import LogReader
from pipeline.logs.rosmsg import LogWriter
from tests.factories.logs import (
    CFG,
    JOINTS,
    LAYOUTS,
    MS,
    TOPICS,
    copy_log,
    joint_position,
    run_one,
    stamps,
    write_log,
)
from tests.factories.params import write_ingest_params

TEMPERATURE_IDL = """\
// generated from rosidl_adapter/resource/msg.idl.em
#include "std_msgs/msg/Header.idl"

module sensor_msgs {
  module msg {
    @verbatim (language="comment", text=
      "Single temperature reading (a {brace}; in a comment).")
    struct Temperature {
      std_msgs::msg::Header header;

      @verbatim (language="comment", text=
        "Measurement of the Temperature in Degrees Celsius.")
      double temperature;

      double variance;
    };
  };
};

================================================================================
IDL: std_msgs/msg/Header
module std_msgs {
  module msg {
    struct Header {
      builtin_interfaces::msg::Time stamp;
      string frame_id;
    };
  };
};
"""


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pd.DataFrame]:
    """A log of our writer and its ingested table."""
    root = tmp_path_factory.mktemp("reference")
    log = write_log(root / "ref.mcap", duration=1.5)
    return log, pd.read_parquet(run_one(log, root / "out").output)


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_valid_layouts_ingest_to_the_same_table(tmp_path: Path, reference: tuple, layout: str) -> None:
    log, expected = reference
    copy = copy_log(log, tmp_path / f"{layout}.mcap", **LAYOUTS[layout])
    with LogReader(copy) as reader:
        assert reader.indexed == (layout == "no_statistics")  # the others are scanned
    pd.testing.assert_frame_equal(pd.read_parquet(run_one(copy, tmp_path / "out").output), expected)


def test_ros2idl_temperature_schema_decodes(tmp_path: Path, reference: tuple) -> None:
    log, expected = reference
    copy = copy_log(log, tmp_path / "idl.mcap", idl_temperature=TEMPERATURE_IDL)
    pd.testing.assert_frame_equal(pd.read_parquet(run_one(copy, tmp_path / "out").output), expected)
    odd = TEMPERATURE_IDL.replace("double variance;", "float variance;")
    bad = copy_log(log, tmp_path / "idl_odd.mcap", idl_temperature=odd)
    with pytest.raises(DataError) as info:
        run_one(bad, tmp_path / "out2")
    message = str(info.value)
    assert "idl_odd.mcap" in message and "/ft/s_one/temperature" in message and "'ros2idl'" in message
    assert not list((tmp_path / "out2").glob("*"))


def test_joint_name_order_changing_between_messages(tmp_path: Path, reference: tuple) -> None:
    """Per-part publishers merged: every other message lists the joints in another order."""

    def reordered(w: LogWriter) -> None:
        js = stamps(1.5, 100.0)
        t = (js - js[0]) / 1e9
        q = np.column_stack([joint_position(t, k) for k in range(len(JOINTS))])
        dq = np.gradient(q, t, axis=0)
        perm = [2, 0, 1]
        w.joint_states(TOPICS.joint_states, js[::2], JOINTS, q[::2], dq[::2])
        w.joint_states(
            TOPICS.joint_states, js[1::2], [JOINTS[p] for p in perm], q[1::2, perm], dq[1::2, perm]
        )

    log = write_log(tmp_path / "mixed.mcap", duration=1.5, skip=[TOPICS.joint_states], extra=reordered)
    pd.testing.assert_frame_equal(pd.read_parquet(run_one(log, tmp_path / "out").output), reference[1])


def _zero_stamped(tmp_path: Path) -> Path:
    def unstamped(w: LogWriter) -> None:
        ft = stamps(1.5, 200.0, offset_ns=1 * MS)
        wrench = 10.0 + np.arange(6) + 3.0 * ((ft - ft[0]) / 1e9)[:, None]
        w.wrenches(TOPICS.sensor_topic("ft_wrench", "s_two"), 0 * ft, "s_two", wrench, log_times_ns=ft)

    skip = [TOPICS.sensor_topic("ft_wrench", "s_two")]
    return write_log(tmp_path / "zero.mcap", duration=1.5, skip=skip, extra=unstamped)


def test_zero_stamps_are_an_error_or_fall_back_to_log_time(tmp_path: Path, reference: tuple) -> None:
    log = _zero_stamped(tmp_path)
    with pytest.raises(DataError, match=r"zero\.mcap: /ft/s_two/wrench: no usable sample \(every header"):
        run_one(log, tmp_path / "out")
    assert not list((tmp_path / "out").glob("*"))
    report = run_one(log, tmp_path / "out", dataclasses.replace(CFG, unstamped_fallback=True))
    assert any("every header stamp is zero" in w for w in report.warnings)
    df = pd.read_parquet(report.output)
    ok = df[S.ok_col(S.WRENCH_STREAM, "s_two")]
    assert ok.mean() > 0.95
    # log time = stamp (joint states' delay 0): the wrench of s_two at a sample stamped t is 10 + i + 3 t
    t = (df[S.STAMP] - df[S.STAMP].iloc[0] - 1 * MS) / 1e9
    cols = S.wrench_cols(S.FT, "s_two")
    np.testing.assert_allclose(
        df.loc[ok, cols].to_numpy(), (10.0 + np.arange(6) + 3.0 * t[ok].to_numpy()[:, None])
    )


def _run_cli(src: Path, out: Path, params: Path) -> int:
    return main(["ingest", str(src), str(out), "--params", str(params)])


def _one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("ftcal: error:")]
    assert len(lines) == 1 and "Traceback" not in err
    return lines[0]


@pytest.mark.slow
def test_bad_output_paths_are_one_line_errors(
    tmp_path: Path,
    request: pytest.FixtureRequest,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", request.getfixturevalue("mlflow_db"))
    logs = request.getfixturevalue("icub_logs")
    src, params = logs[0], write_ingest_params(tmp_path, skip_bad_logs=True)
    a_file = tmp_path / "file"
    a_file.write_text("not a directory")
    assert _run_cli(src, a_file, params) == 2
    assert "file: output path exists and is not a directory" in _one_error_line(capsys.readouterr().err)
    assert _run_cli(src, a_file / "out", params) == 2
    assert "cannot create the output directory" in _one_error_line(capsys.readouterr().err)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    cmd = [
        sys.executable,
        "-m",
        "pipeline.cli",
        "ingest",
        str(src),
        str(locked / "out"),
        "--params",
        str(params),
    ]
    if os.geteuid() == 0:  # root writes into read-only directories: run it without that privilege
        cmd = ["setpriv", "--bounding-set=-dac_override,-dac_read_search", "--", *cmd]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "locked: output directory is not writable" in _one_error_line(proc.stderr)


def test_one_bad_log_among_several_is_all_or_nothing(
    tmp_path: Path,
    request: pytest.FixtureRequest,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", request.getfixturevalue("mlflow_db"))
    logs = request.getfixturevalue("icub_logs")
    src = logs[0]
    out = tmp_path / "ingested"
    out.mkdir()
    (out / "previous.parquet").write_text("the previous run's output")
    dead = tmp_path / ".ingested.999999999.ingest-tmp"  # a killed run's staging directory
    dead.mkdir()
    (dead / "half.parquet").write_text("half")
    assert _run_cli(src, out, write_ingest_params(tmp_path)) == 2
    assert "c_truncated.mcap" in _one_error_line(capsys.readouterr().err)
    assert [p.name for p in out.iterdir()] == ["previous.parquet"]  # untouched: no half-made output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ingested", "params.yaml"]
    assert _run_cli(src, out, write_ingest_params(tmp_path, skip_bad_logs=True)) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "sub__a.parquet",
        "sub__a.truth.parquet",
        "sub__b.parquet",
        "sub__b.truth.parquet",
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ingested", "params.yaml"]
