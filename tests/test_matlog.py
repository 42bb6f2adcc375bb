"""YarpRobotLoggerDevice .mat logs: an MCAP log written as a logger .mat ingests to the same table.

Tolerances: a .mat stamp is float64 seconds since the epoch, whose step at 1.7e9 s is 2**-22 s = 0.24 us,
so a stamp comes back within STAMP_TOL_NS = 120 ns of its MCAP ns value (`seconds_to_ns` loses nothing
more). Columns copied from one message (q, dq_enc) are then equal; an interpolated column moves by at
most (weight change) x (step between its two bracketing messages), the weight changing by at most
3 x 120 ns / (smallest message spacing): `interp_tol` gives that bound per column.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import yaml

from pipeline.cli import main
from pipeline.core.config import MatParams, load_params
from pipeline.core.errors import DataError
from pipeline.logs import schema as S
from pipeline.logs.matlog import MatLog, ns_to_seconds, seconds_to_ns
from pipeline.logs.mcap_table import ingest_log
from tests import matfile
from tests.factories.logs import CFG_MAT, JOINTS, MAT, SENSORS, TOPICS, write_log
from tests.factories.params import repo_params

pytestmark = pytest.mark.slow  # writes and ingests whole logger files

REPO = Path(__file__).resolve().parents[1]
STAMP_TOL_NS = 120


def ingest(path: Path, out: Path, joints=JOINTS, sensors=SENSORS) -> pd.DataFrame:
    ingest_log(path, out, path.stem, CFG_MAT, TOPICS, joints, sensors, ["iCubGenova09"])
    return pd.read_parquet(out / f"{path.stem}.parquet")


def interp_tol(ref: pd.DataFrame, column: str, spacing_s: float) -> float:
    """Largest change of an interpolated column from stamps moved by <= 120 ns (see the docstring)."""
    step = np.nanmax(np.abs(np.diff(ref[column].to_numpy()))) if len(ref) > 1 else 0.0
    return 3 * STAMP_TOL_NS * 1e-9 / spacing_s * 2 * step + 1e-12


def assert_same_table(mat: pd.DataFrame, ref: pd.DataFrame, spacing_s: float = 0.005) -> None:
    assert list(mat.columns) == list(ref.columns) and len(mat) == len(ref)
    assert np.abs(mat[S.STAMP].to_numpy() - ref[S.STAMP].to_numpy()).max() <= STAMP_TOL_NS
    np.testing.assert_allclose(mat[S.TIME], ref[S.TIME], atol=2 * STAMP_TOL_NS * 1e-9, rtol=0)
    for c in ref.columns:
        if c.startswith(S.OK + ".") or c.split(".")[0] in (S.Q, S.DQ_ENC, S.TAU_ENC):
            np.testing.assert_array_equal(mat[c], ref[c], err_msg=c)
        elif c not in (S.STAMP, S.TIME):
            np.testing.assert_allclose(mat[c], ref[c], atol=interp_tol(ref, c, spacing_s), rtol=0, err_msg=c)


# --- conversions ---


def test_stamps_round_trip_within_half_a_float_step() -> None:
    rng = np.random.default_rng(0)
    ns = 1_700_000_000 * 10**9 + rng.integers(0, 3600 * 10**9, 10_000)
    back = seconds_to_ns(ns_to_seconds(ns))
    assert np.abs(back - ns).max() <= STAMP_TOL_NS
    naive = np.round(ns_to_seconds(ns) * 1e9).astype(np.int64)  # what the split into whole seconds avoids
    assert np.abs(naive - ns).max() > STAMP_TOL_NS


# --- same table as the MCAP original ---


@pytest.fixture(scope="module")
def mcap_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pd.DataFrame]:
    tmp = tmp_path_factory.mktemp("mcap")
    path = write_log(tmp / "log.mcap", duration=3.0)
    return path, ingest(path, tmp / "out")


@pytest.mark.parametrize("compression", ["gzip", None])
def test_both_hdf5_layouts_ingest_like_the_mcap_over_several_chunks(tmp_path: Path, compression) -> None:
    """Chunked and compressed, or contiguous (the logger's default): a log read in several 30 s chunks keeps
    every channel, the slow temperature included, to its end, as its MCAP does."""
    from h5py import File

    mcap = write_log(tmp_path / "log.mcap", duration=70.0)
    ref = ingest(mcap, tmp_path / "ref")
    mat = matfile.mcap_to_mat(mcap, tmp_path / "log.mat", TOPICS, SENSORS, compression=compression)
    with File(mat, "r") as f:
        chunks = f["robot_logger_device/temperatures/s_one/data"].chunks
    assert (chunks is None) == (compression is None)
    table = ingest(mat, tmp_path / "out")
    assert_same_table(table, ref)
    assert table[S.ok_col(S.TEMPERATURE_STREAM, "s_one")].iloc[10:-10].all()


@pytest.mark.parametrize(
    ("naming", "version"), [("2022", "7.3"), ("2023", "7.3"), ("2024", "7.3"), ("2024", "5")]
)
def test_mat_ingests_like_its_mcap(tmp_path: Path, mcap_log, naming: str, version: str) -> None:
    """Every naming generation of the defaults, in both file formats, with no params change."""
    mcap, ref = mcap_log
    mat = matfile.mcap_to_mat(mcap, tmp_path / "log.mat", TOPICS, SENSORS, naming=naming, version=version)
    with MatLog(mat) as log:
        assert log.format == version and log.joints == JOINTS
    table = ingest(mat, tmp_path / "out")
    assert_same_table(table, ref)
    assert not (tmp_path / "out" / "log.truth.parquet").exists()  # no simulated truth in a logger file
    experiment = [
        S.read_metadata(pq.read_schema(p), S.META_EXPERIMENT)
        for p in (tmp_path / "out" / "log.parquet", mcap.parent / "out" / "log.parquet")
    ]
    assert experiment[0] == experiment[1] and experiment[0]["type"] == "walking"


def test_tagged_root_chunked_reading_and_empty_channels(tmp_path: Path, mcap_log) -> None:
    """A `_<tag>` root name is found; small chunks give the same table; an empty IMU channel is NaN and
    flagged like an MCAP log without that topic."""
    mcap, ref = mcap_log
    empty = ["accelerometers/s_one_imu", "gyros/s_one_imu"]
    mat = matfile.mcap_to_mat(
        mcap, tmp_path / "log.mat", TOPICS, SENSORS, root="robot_logger_device_walk", empty=empty
    )
    from pipeline.logs.matreader import MatLogReader

    with MatLogReader(mat, TOPICS, SENSORS, MAT, JOINTS, chunk_rows=37) as reader:
        assert reader.metadata["mat"]["root"] == "robot_logger_device_walk"
        assert "/ft/s_one/imu" not in reader.topics and "/ft/s_two/imu" in reader.topics
        chunks = list(reader.iter_chunks())
        assert len(chunks) == -(-len(ref) // 37)
    table = ingest(mat, tmp_path / "out")
    assert not table[S.ok_col(S.IMU_STREAM, "s_one")].any()
    assert table[S.vector_cols(S.ACC, "s_one")].isna().all().all()
    other = [
        c
        for c in ref.columns
        if ".s_one" not in c or S.IMU_STREAM not in c and S.ACC not in c and S.GYR not in c
    ]
    assert_same_table(table[other], ref[other])


def test_windows_read_in_whole_chunks_equal_the_stored_samples(tmp_path: Path) -> None:
    """Windows read forwards across HDF5 chunk boundaries, backwards and again give the stored samples."""
    n, channel = 30_000, "FTs/l_leg_ft"
    values = np.random.default_rng(0).normal(size=(n, 6))
    t = 1.7e9 + np.arange(n) * 0.01
    tree = matfile.logger_tree({channel: matfile.leaf("l_leg_ft", t, values)}, JOINTS, "iCubGenova09")
    mat = matfile.write_v73(tmp_path / "log.mat", tree)
    with h5py.File(mat, "r") as f:
        rows = f[f"{matfile.ROOT_NAME}/{channel}/data"].chunks[0]
    assert 3 * rows < n  # several chunks, so that windows cross their boundaries
    cuts = sorted({0, 1, rows - 1, rows, rows + 5, 2 * rows + 3, n - 2, n})
    windows = list(zip(cuts[:-1], cuts[1:], strict=True))
    windows += [(5, 2 * rows), (rows, rows + 1), (n - 1, n), (0, n), (n, n)]  # back, within, to the end
    with MatLog(mat) as log:
        leaf = log.leaf(channel)
        for a, b in windows:
            np.testing.assert_array_equal(leaf.read(a, b), values[a:b], err_msg=f"rows {a}:{b}")


# --- bad input: one line naming the file, nothing written ---


def _expect_error(path: Path, out: Path, match: str, joints=JOINTS) -> str:
    with pytest.raises(DataError, match=match) as info:
        ingest(path, out, joints=joints)
    message = str(info.value)
    assert "\n" not in message and str(path) in message
    assert not out.exists() or not list(out.iterdir())
    return message


def test_bad_mat_files(tmp_path: Path, mcap_log) -> None:
    mcap, _ = mcap_log
    out = tmp_path / "out"
    good = matfile.mcap_to_mat(mcap, tmp_path / "good.mat", TOPICS, SENSORS)

    junk = tmp_path / "junk.mat"
    junk.write_bytes(b"not a mat file" * 10)
    junk.with_suffix(".yaml").write_text("type: walking\n")
    _expect_error(junk, out, "not a MATLAB .mat file")

    other = matfile.write_v73(tmp_path / "other.mat", {"x": np.ones((2, 2))}, root="results")
    other.with_suffix(".yaml").write_text("type: walking\n")
    _expect_error(
        other,
        out,
        r"not a YarpRobotLoggerDevice log: no top-level struct .* \(top-level variables: results\)",
    )

    nosidecar = matfile.mcap_to_mat(mcap, tmp_path / "nosidecar.mat", TOPICS, SENSORS, sidecar=False)
    _expect_error(nosidecar, out, "missing experiment sidecar nosidecar.yaml")

    noft = matfile.mcap_to_mat(mcap, tmp_path / "noft.mat", TOPICS, SENSORS, drop=["FTs/s_two"])
    msg = _expect_error(noft, out, "FT channel of sensor s_two not found")
    assert "FTs/s_two_sensor" in msg and "FTs has: s_one" in msg

    msg = _expect_error(
        good, out, "joint names of robot_logger_device/description_list", joints=["j_a", "j_b", "j_z"]
    )
    assert "not in the URDF: j_c" in msg and "missing from the file: j_z" in msg

    truncated = tmp_path / "truncated.mat"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    good.with_suffix(".yaml").rename(truncated.with_suffix(".yaml"))
    _expect_error(truncated, out, "truncated or corrupted")


def test_cli_error_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mat = matfile.write_v73(tmp_path / "log.mat", matfile.logger_tree({}, JOINTS, "iCubGenova09"))
    assert main(["convert-mat", str(mat), str(tmp_path / "log.mcap")]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err.startswith("ftcal: error: ") and "missing experiment sidecar log.yaml" in err and "\n" not in err
    )
    assert not (tmp_path / "log.mcap").exists()


def test_mat_params_validation() -> None:
    from pipeline.core.errors import ConfigError

    good = {k: getattr(MAT, k) for k in MAT.__dataclass_fields__}
    assert MatParams.from_mapping(good) == MAT
    assert MAT.channels("ft", "l_leg_ft") == ("FTs/l_leg_ft", "FTs/l_leg_ft_sensor")
    with pytest.raises(ConfigError, match=r"ingest.mat.ft\[0\] must contain \{sensor\}"):
        MatParams.from_mapping({**good, "ft": ["FTs/left"]})
    with pytest.raises(ConfigError, match="unknown key ingest.mat.extra"):
        MatParams.from_mapping({**good, "extra": 1})
    renamed = MatParams.from_mapping({**good, "sensor_names": {"l_leg_ft": "left_leg"}})
    assert renamed.channels("gyroscope", "l_leg_ft")[0] == "gyros/left_leg_imu"


# --- the fixture against the real matio library (what the logger writes through) ---


def _matio_channel(mat: Path, channel: str) -> np.ndarray:
    """(N, k) samples of a logger channel as libmatio reads them: matdump's print of ``<channel>.data``
    (k x 1 x N, one ``data(:,:,i) =`` block of k values per sample, %g: 6 significant digits)."""
    var = "robot_logger_device." + channel.replace("/", ".") + ".data"
    run = subprocess.run(["matdump", "-d", str(mat), var], capture_output=True, text=True, check=False)
    assert run.returncode == 0 and "data(:,:,0)" in run.stdout, (var, run.stdout[-500:], run.stderr[-500:])
    blocks = re.split(r"data\(:,:,(\d+)\) = ", run.stdout)[1:]
    rows = {
        int(i): [float(v) for v in block.split("\n\n")[0].split()]
        for i, block in zip(blocks[::2], blocks[1::2], strict=True)
    }
    return np.array([rows[i] for i in range(len(rows))])


def _matdump_tool() -> None:
    if shutil.which("matdump") is None:
        reason = "matio-tools (matdump) not installed"
        if os.environ.get("CI") == "true":
            pytest.fail(f"{reason}: .ci/run installs it in CI")
        pytest.skip(reason)


@pytest.mark.parametrize("layout", ["contiguous", "chunked"])
def test_every_channel_reads_as_libmatio_reads_it(tmp_path: Path, mcap_log, layout: str) -> None:
    """The fixture's logger file (contiguous datasets, as matio writes uncompressed; or gzip-chunked) read
    by libmatio (matdump, the library under the robot logger) and by our reader: every sample of every
    channel (joint positions, velocities, wrenches, temperatures, accelerometers, gyroscopes) equal to
    matdump's 6 printed digits, the same number of samples."""
    _matdump_tool()
    mcap, _ = mcap_log
    compression = None if layout == "contiguous" else "gzip"
    mat = matfile.mcap_to_mat(mcap, tmp_path / "log.mat", TOPICS, SENSORS, compression=compression)
    channels = []
    with h5py.File(mat, "r") as f:
        f["robot_logger_device"].visititems(
            lambda name, node: (
                channels.append(name) if isinstance(node, h5py.Group) and "data" in node else None
            )
        )
        chunked = [f[f"robot_logger_device/{c}/data"].chunks is not None for c in channels]
        assert any(chunked) if layout == "chunked" else not any(chunked)
    assert len(channels) >= 2 + 4 * len(SENSORS), channels
    with MatLog(mat) as log:
        for channel in channels:
            leaf = log.leaf(channel)
            ours = leaf.read(0, len(leaf))
            matio = _matio_channel(mat, channel)
            assert matio.shape == ours.shape, channel
            np.testing.assert_allclose(ours, matio, rtol=5e-6, atol=1e-300, err_msg=channel)
            assert np.abs(np.diff(ours, axis=0)).max() > 0, channel  # a channel that changes is compared


def test_logger_struct_reads_with_matio(tmp_path: Path, mcap_log) -> None:
    """matio opens the fixture as the logger's struct: its fields, joint names, and the whos listing."""
    _matdump_tool()
    mcap, _ = mcap_log
    mat = matfile.mcap_to_mat(mcap, tmp_path / "log.mat", TOPICS, SENSORS, empty=["gyros/s_one_imu"])
    run = subprocess.run(["matdump", "-d", str(mat), "robot_logger_device"], capture_output=True, text=True)
    assert run.returncode == 0 and "HDF5 error" not in run.stderr + run.stdout, run.stderr[-2000:]
    text = run.stdout
    assert "Class Type: Structure" in text and "Fields[" in text
    for joint in JOINTS:
        assert f"\n{joint}\n" in text
    whos = subprocess.run(["matdump", "-f", "whos", str(mat)], capture_output=True, text=True).stdout
    assert "robot_logger_device" in whos and "mxSTRUCT_CLASS" in whos


# --- a simulated log of the default pipeline, through label; and `ftcal convert-mat` ---


def test_simulated_log_same_tables_and_labels(tmp_path: Path, mlflow_store: None) -> None:
    """simulate -> MCAP and its logger .mat -> ingest, smooth, label: the same rows, flags and labels
    (within the stamp tolerance); `ftcal convert-mat` of the .mat ingests exactly like the .mat."""
    from pipeline.stages import ingest as ingest_stage
    from pipeline.stages import label, simulate, smooth

    data = repo_params()
    data["simulate"].update({"logs": [{"type": "walking", "duration_s": 6, "role": "test"}], "workers": 1})
    data["simulate"]["plots"] = False
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(data))
    params = load_params(tmp_path / "params.yaml")
    simulate.run(params, tmp_path / "sim", progress=False)
    (mcap,) = sorted((tmp_path / "sim").glob("*.mcap"))
    from pipeline.physics.robot import load_robot

    sensors = list(load_robot("iCubGenova09").sensors)
    (tmp_path / "raw").mkdir()
    mat = matfile.mcap_to_mat(
        mcap, tmp_path / "raw" / f"{mcap.stem}.mat", params.topics, sensors, naming="2022"
    )
    tables = {}
    for kind, source in (("mcap", tmp_path / "sim"), ("mat", tmp_path / "raw")):
        ingest_stage.run(params, source, tmp_path / kind / "ingested", progress=False)
        smooth.run(params, tmp_path / kind / "ingested", tmp_path / kind / "smoothed", progress=False)
        label.run(params, tmp_path / kind / "smoothed", tmp_path / kind / "labelled", progress=False)
        tables[kind] = {
            stage: pd.read_parquet(tmp_path / kind / stage / f"{mcap.stem}.parquet")
            for stage in ("ingested", "labelled")
        }
    ref, got = tables["mcap"]["ingested"], tables["mat"]["ingested"]
    assert_same_table(got, ref, spacing_s=0.005)
    lab_ref, lab = tables["mcap"]["labelled"], tables["mat"]["labelled"]
    assert list(lab.columns) == list(lab_ref.columns) and len(lab) == len(lab_ref)
    for c in lab_ref.columns:
        if c.startswith((S.SWITCH + ".", S.OK + ".")) or c in (S.CONTACTS, S.FIXED_LINK, S.GUARD):
            pd.testing.assert_series_equal(lab[c], lab_ref[c], check_names=False, obj=c)
        elif c.startswith(S.EXPECTED + "."):
            # Smoothing resamples q on a uniform grid from the stamps: a 120 ns stamp error moves q by
            # |dq| x 120 ns ~ 1e-7 rad, which the second derivative (/ h^2, h = 10 ms) and link masses turn
            # into mN: 0.01 N / Nm is 60x below the simulated force noise (0.6 N), 3x below the torque noise.
            np.testing.assert_allclose(lab[c], lab_ref[c], atol=1e-2, rtol=0, err_msg=c)

    out = tmp_path / "conv" / f"{mcap.stem}.mcap"
    assert main(["convert-mat", str(mat), str(out), "--params", str(tmp_path / "params.yaml")]) == 0
    ingest_stage.run(params, out.parent, tmp_path / "conv_ingested", progress=False)
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "conv_ingested" / f"{mcap.stem}.parquet"), got)
