"""YARP dataDumper runs: written from an MCAP log they ingest to its table; the real run; bad input.

Tolerances: the dumper prints times with 6 decimals, so a stamp comes back within STAMP_TOL_NS (0.5 us
of rounding, plus the 0.12 us of a float64 second at today's epoch) of its MCAP ns value; values are
printed with 6 decimals (joint positions in degrees). A column copied from one message (q, dq_enc) is
then within half a printed unit; an interpolated one (ft) moves in addition by at most (weight change) x
(step between its two bracketing messages), the weight changing by at most 3 x STAMP_TOL_NS / (the
smallest message spacing), as in tests/test_matlog.py.
"""

from __future__ import annotations

import shutil
import tarfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.cli import main
from pipeline.core.errors import DataError
from pipeline.logs import schema as S
from pipeline.logs.dumper import DumperRunReader
from pipeline.logs.mcap_table import ingest_log
from pipeline.logs.params import DumperParams, IngestParams
from pipeline.tools.convert_dumper import write_mcap
from tests import dumperfile
from tests.factories.dumper import HALF_PRINTED, REAL_RUN, STAMP_TOL_NS, interpolated_bound
from tests.factories.logs import CFG, JOINTS, SENSORS, TOPICS, write_log
from tests.factories.params import repo_params

REPO = Path(__file__).resolve().parents[1]
EXCERPT = Path(__file__).resolve().parent / "data" / "icub02-yoga-excerpt"
FT_PORTS = {"leg": "s_one", "arm": "s_two"}
JOINT_MAP = {"leg": ["j_a", "j_b"], "torso": [None, "j_c"]}  # an axis the URDF does not have, then j_c
DUMPER = DumperParams("analog:o", ("stateExt:o", "state:o"), FT_PORTS, JOINT_MAP, ("leg", "torso"))
CFG_DUMPER = IngestParams(**{**CFG.__dict__, "dumper": DUMPER})


def ingest(path: Path, out: Path, cfg: IngestParams = CFG_DUMPER, name: str | None = None) -> pd.DataFrame:
    report = ingest_log(path, out, name or path.stem, cfg, TOPICS, JOINTS, SENSORS, ["iCubGenova09"])
    return pd.read_parquet(report.output)


@pytest.fixture(scope="module")
def mcap_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pd.DataFrame]:
    tmp = tmp_path_factory.mktemp("mcap")
    path = write_log(tmp / "log.mcap", duration=3.0)
    return path, ingest(path, tmp / "out")


def test_numbers_print_as_yarp_does() -> None:
    assert [dumperfile.yarp_number(v) for v in (0.0, 1.101, -2.5354, 23.1017764, -0.0000004)] == [
        "0.0",
        "1.101",
        "-2.5354",
        "23.101776",
        "-0.0",
    ]


@pytest.mark.parametrize("two_times", [False, True])
def test_run_ingests_like_its_mcap(tmp_path: Path, mcap_log, two_times: bool) -> None:
    """Both time-column forms; the one-time run also has a board and an FT port without data.log."""
    mcap, ref = mcap_log
    missing = [] if two_times else ["torso/stateExt:o", "arm/analog:o"]
    run = dumperfile.mcap_to_run(
        mcap, tmp_path / "run", TOPICS, FT_PORTS, JOINT_MAP, two_times=two_times, without_data=missing
    )
    got = ingest(run, tmp_path / "out", name="log")
    assert list(got.columns) == list(ref.columns) and len(got) == len(ref)
    assert np.abs(got[S.STAMP].to_numpy() - ref[S.STAMP].to_numpy()).max() <= STAMP_TOL_NS
    absent_joints = ["j_c"] if missing else []
    absent_sensors = ["s_two"] if missing else []
    for j in JOINTS:
        for quantity, scale in ((S.Q, np.pi / 180), (S.DQ_ENC, np.pi / 180)):
            c = S.joint_col(quantity, j)
            if j in absent_joints:
                assert got[c].isna().all(), c
            else:
                np.testing.assert_allclose(
                    got[c], ref[c], atol=HALF_PRINTED * scale + 1e-12, rtol=0, err_msg=c
                )
        assert got[S.joint_col(S.TAU_ENC, j)].isna().all()  # the log has no effort: status [er]
    for s in SENSORS:
        ok = S.ok_col(S.WRENCH_STREAM, s)
        if s in absent_sensors:
            assert not got[ok].any() and got[S.wrench_cols(S.FT, s)].isna().all().all()
            continue
        np.testing.assert_array_equal(got[ok], ref[ok], err_msg=ok)
        for c in S.wrench_cols(S.FT, s):
            np.testing.assert_allclose(
                got[c], ref[c], atol=interpolated_bound(ref, c, HALF_PRINTED, 0.005), rtol=0, err_msg=c
            )
        for stream in (S.IMU_STREAM, S.TEMPERATURE_STREAM):  # not in a dataDumper run of these boards
            assert not got[S.ok_col(stream, s)].any()


@pytest.mark.parametrize("two_times, stamp_line", [(False, False), (True, False), (True, True)])
def test_recorder_folders_with_state_ports_ingest_like_the_dumper_layout(
    tmp_path: Path, mcap_log, two_times: bool, stamp_line: bool
) -> None:
    """The same run in the dumper's layout with stateExt:o ports, and in folders a recorder named
    (``legFT/``, ``joints/legPos/``) with the boards' state:o ports (positions only): info.log names each
    port. The same table, joint positions and wrenches equal to the bit; velocities and torques, which
    state:o does not carry, NaN. The reception times are told from the info.log ``Stamp:`` line, or
    without it (older dumpers) from the first line."""
    from pipeline.logs.logfiles import find_logs

    mcap, _ = mcap_log
    src = tmp_path / "raw"
    dumper = dumperfile.mcap_to_run(mcap, src / "a" / "run", TOPICS, FT_PORTS, JOINT_MAP, two_times=two_times)
    recorder = dumperfile.mcap_to_run(
        mcap,
        src / "b" / "run",
        TOPICS,
        FT_PORTS,
        JOINT_MAP,
        two_times=two_times,
        joint_port="state:o",
        folder=dumperfile.recorder_folder,
        stamp_line=stamp_line,
    )
    assert (recorder / "legFT" / "data.log").is_file() and (
        recorder / "joints" / "torsoPos" / "data.log"
    ).is_file()
    assert find_logs(src) == [dumper, recorder]
    ref = ingest(dumper, tmp_path / "a", name="log")
    got = ingest(recorder, tmp_path / "b", name="log")
    assert list(got.columns) == list(ref.columns)
    np.testing.assert_array_equal(got[S.STAMP], ref[S.STAMP])
    for j in JOINTS:
        np.testing.assert_array_equal(got[S.joint_col(S.Q, j)], ref[S.joint_col(S.Q, j)])
        assert ref[S.joint_col(S.DQ_ENC, j)].notna().all()
        for quantity in (S.DQ_ENC, S.TAU_ENC):
            assert got[S.joint_col(quantity, j)].isna().all()
    for s in SENSORS:
        for c in [*S.wrench_cols(S.FT, s), S.ok_col(S.WRENCH_STREAM, s)]:
            np.testing.assert_array_equal(got[c], ref[c], err_msg=c)


def test_converted_run_ingests_exactly_like_the_run(tmp_path: Path, mcap_log) -> None:
    mcap, _ = mcap_log
    run = dumperfile.mcap_to_run(
        mcap, tmp_path / "run", TOPICS, FT_PORTS, JOINT_MAP, without_data=["torso/stateExt:o"]
    )
    direct = ingest(run, tmp_path / "a", name="log")
    with DumperRunReader(run, TOPICS, SENSORS, DUMPER, JOINTS) as reader:
        write_mcap(reader, tmp_path / "log.mcap")
    pd.testing.assert_frame_equal(ingest(tmp_path / "log.mcap", tmp_path / "b"), direct)


def _params(tmp_path: Path, **changes: object) -> Path:
    data = repo_params()
    data["robot"]["urdf"] = "iCubGenova02"
    for key, value in changes.items():
        section, field = key.split(".", 1)
        data[section][field] = value
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


# --- the real run: its excerpt (committed) and the whole run (../shared, beside developer checkouts) ---


@pytest.fixture(scope="module")
def icub2():
    from pipeline.physics.robot import load_robot

    return load_robot("iCubGenova02")


def _real_cfg() -> IngestParams:
    from pipeline.core.config import load_params, stage_section

    return stage_section(load_params(REPO / "params.yaml"), "ingest", IngestParams)


def _copy_run(source: Path, dest: Path, sidecar: dict | None = None) -> Path:
    shutil.copytree(source / "icub", dest / "icub")
    side = {"type": "balancing", "robot": "iCubGenova02", "role": "train", "contacts": ["r_sole"]}
    dest.with_name(dest.name + ".yaml").write_text(yaml.safe_dump(sidecar if sidecar is not None else side))
    return dest


@pytest.fixture(scope="module")
def excerpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The committed excerpt of the real run (1.6 s of every port, bytes as recorded), unpacked."""
    tmp = tmp_path_factory.mktemp("excerpt")
    with tarfile.open(EXCERPT.with_suffix(".tar.xz")) as tar:
        tar.extractall(tmp, filter="data")
    return tmp / EXCERPT.name


def frozen_reference(
    analog: Path, stamps_ns: np.ndarray, max_frozen_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """((N,) bool frozen, (N,) bool inside the stream), independently of the reader: the latest message
    of `analog` at or before each stamp repeats the 6 values of a run of identical lines spanning more
    than `max_frozen_s`; the stamp lies between the stream's first and last message."""
    rows = [line.split(" ") for line in analog.read_text().splitlines()]
    t = np.array([round(float(r[1]) * 1e6) * 1000 for r in rows], dtype=np.int64)
    frozen = np.zeros(len(rows), dtype=bool)
    start = 0
    for k in range(1, len(rows) + 1):
        if k == len(rows) or rows[k][2:] != rows[start][2:]:
            if t[k - 1] - t[start] > max_frozen_s * 1e9:
                frozen[start:k] = True
            start = k
    latest = np.searchsorted(t, stamps_ns, side="right") - 1
    return (latest >= 0) & frozen[np.maximum(latest, 0)], (stamps_ns >= t[0]) & (stamps_ns <= t[-1])


def _check_real_table(df: pd.DataFrame, run: Path, max_frozen_s: float) -> None:
    ok = df[S.ok_col(S.WRENCH_STREAM, "r_leg_ft")].to_numpy()
    expected, inside = frozen_reference(
        run / "icub/right_leg/analog:o/data.log", df[S.STAMP].to_numpy(), max_frozen_s
    )
    assert expected.any() and (~expected).any()
    np.testing.assert_array_equal(~ok & expected, expected)  # every frozen sample is flagged ...
    assert ok[~expected & inside].all()  # ... and no other one inside the stream
    for part, s in (("left_leg", "l_leg_ft"), ("left_foot", "l_foot_ft"), ("right_arm", "r_arm_ft")):
        _, inside = frozen_reference(run / f"icub/{part}/analog:o/data.log", df[S.STAMP].to_numpy(), 1.0)
        assert df[S.ok_col(S.WRENCH_STREAM, s)][inside].all()
    for j in ("l_knee", "l_hip_pitch", "r_elbow", "l_wrist_yaw"):  # boards whose data.log was not kept
        assert df[S.joint_col(S.Q, j)].isna().all()
    for j in ("r_knee", "torso_yaw", "neck_pitch"):
        assert df[S.joint_col(S.Q, j)].notna().all() and df[S.joint_col(S.Q, j)].abs().max() < np.pi


def test_real_excerpt_ingests_with_its_frozen_board_flagged(tmp_path: Path, excerpt: Path, icub2) -> None:
    run = _copy_run(excerpt, tmp_path / "yoga")
    cfg = _real_cfg()
    report = ingest_log(run, tmp_path / "out", "yoga", cfg, TOPICS, icub2.joint_names, list(icub2.sensors))
    assert report.absent[:3] == ["left_arm/stateExt:o", "left_leg/stateExt:o", "right_arm/stateExt:o"]
    assert set(report.frozen) == {"r_leg_ft"}
    _check_real_table(pd.read_parquet(report.output), run, cfg.max_frozen_s)


@pytest.mark.skipif(
    not REAL_RUN.is_dir(), reason=f"{REAL_RUN} is absent (../shared is beside developer checkouts)"
)
@pytest.mark.slow
def test_real_run_ingests_and_the_summary_names_what_is_absent_and_frozen(
    tmp_path: Path, mlflow_store: None, capsys: pytest.CaptureFixture[str]
) -> None:
    run = _copy_run(REAL_RUN, tmp_path / "raw" / "yoga")
    assert main(["ingest", str(run.parent), str(tmp_path / "out"), "--params", str(_params(tmp_path))]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert "absent: yoga: left_arm/stateExt:o, left_leg/stateExt:o, right_arm/stateExt:o" in line
    assert "imu (all 6 sensors), temperature (all 6 sensors)" in line
    assert "frozen: yoga: r_leg_ft 11.9 s, 16.0% of samples" in line, line
    df = pd.read_parquet(tmp_path / "out" / "yoga.parquet")
    _check_real_table(df, run, _real_cfg().max_frozen_s)


# --- bad input: one line naming the file and line, or the key; nothing written ---


def _edit_line(path: Path, k: int, edit) -> None:
    lines = path.read_text().splitlines(keepends=True)
    lines[k - 1] = edit(lines[k - 1])
    path.write_text("".join(lines))


FT_LOG = "icub/right_foot/analog:o/data.log"
STATE_LOG = "icub/right_leg/stateExt:o/data.log"
SIDE = {"type": "balancing", "robot": "iCubGenova02", "role": "train"}
BAD_RUNS = {
    "field count": (
        lambda run: _edit_line(run / FT_LOG, 7, lambda line: line.replace("\n", " 1.0\n")),
        rf"{FT_LOG}:7: 9 fields, expected 8",
    ),
    "not a number": (
        lambda run: _edit_line(run / FT_LOG, 12, lambda line: line.rsplit(" ", 1)[0] + " 0.1.2\n"),
        rf"{FT_LOG}:12: wrench value '0.1.2' is not a number",
    ),
    "status": (
        lambda run: _edit_line(run / STATE_LOG, 30, lambda line: line.replace("[ok]", "[er]", 1)),
        rf"{STATE_LOG}:30: joint positions have status \[er\], not \[ok\]",
    ),
    "two folders, one port": (
        lambda run: shutil.copytree(run / "icub/right_foot/analog:o", run / "rightFootFT"),
        r"icub/right_foot/analog:o and \S+/yoga/rightFootFT both hold port right_foot/analog:o",
    ),
    "a folder with data naming no port": (
        lambda run: _port(run / "notes", "", "1 0.5 1.0 2.0\n"),
        r"yoga/notes: its info.log names no port, so what it holds is unknown",
    ),
    "segments overlap": (
        lambda run: _sidecar(run, {**SIDE, "segments": _segs((0.1, 0.8, "train"), (0.7, 1.4, "test"))}),
        r"yoga.yaml: segments\[1\] \[0.7, 1.4\] s overlaps segments\[0\] \[0.1, 0.8\] s",
    ),
    "segment leaves the run": (
        lambda run: _sidecar(run, {**SIDE, "segments": _segs((0.0, 0.5, "train"), (0.8, 9.0, "test"))}),
        r"yoga: segments\[1\] \[0.8, 9\] s leaves the recording \(its samples span 0 to 1.5",
    ),
    "empty window": (
        lambda run: _sidecar(run, {**SIDE, "window": [20, 30]}),
        r"yoga: the experiment window \[20, 30\] s holds no data",
    ),
    "no sidecar": (
        lambda run: run.with_name("yoga.yaml").unlink(),
        r"yoga: missing experiment sidecar yoga.yaml beside it",
    ),
}


def _port(folder: Path, name: str, data: str | None) -> None:
    """A port folder: info.log naming `name` ('' none), data.log holding `data` (None: no file)."""
    folder.mkdir(parents=True)
    connected = f"[1457625466.000000] {name} [connected]\n" if name else ""
    (folder / "info.log").write_text("Type: Bottle;\n" + connected)
    if data is not None:
        (folder / "data.log").write_text(data)


def _segs(*items: tuple[float, float, str]) -> list[dict]:
    return [{"start_s": a, "end_s": b, "role": r} for a, b, r in items]


def _sidecar(run: Path, data: dict) -> None:
    run.with_name(run.name + ".yaml").write_text(yaml.safe_dump(data))


@pytest.mark.parametrize("case", list(BAD_RUNS))
def test_bad_runs_are_one_line_errors_and_leave_nothing(
    tmp_path: Path, excerpt: Path, icub2, case: str
) -> None:
    run = _copy_run(excerpt, tmp_path / "yoga")
    spoil, message = BAD_RUNS[case]
    spoil(run)
    out = tmp_path / "out"
    with pytest.raises(DataError, match=message) as info:
        ingest_log(run, out, "yoga", _real_cfg(), TOPICS, icub2.joint_names, list(icub2.sensors), (), None)
    assert "\n" not in str(info.value)
    assert not out.exists() or not list(out.iterdir())


def test_cli_bad_run_and_convert_exit_2_with_one_line(
    tmp_path: Path, excerpt: Path, mlflow_store: None, capsys: pytest.CaptureFixture[str]
) -> None:
    run = _copy_run(excerpt, tmp_path / "raw" / "yoga")
    _edit_line(run / FT_LOG, 7, lambda line: line.replace("\n", " 1.0\n"))
    params = str(_params(tmp_path))
    for argv, written in (
        (["ingest", str(run.parent), str(tmp_path / "out")], tmp_path / "out"),
        (["convert-dumper", str(run), str(tmp_path / "yoga.mcap")], tmp_path / "yoga.mcap"),
    ):
        assert main([*argv, "--params", params]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("ftcal: error: ") and "\n" not in err and f"{FT_LOG}:7: 9 fields" in err
        assert not written.exists()


def test_cli_convert_dumper_writes_what_ingests_like_the_run(
    tmp_path: Path, excerpt: Path, mlflow_store: None, icub2
) -> None:
    run = _copy_run(excerpt, tmp_path / "raw" / "yoga")
    params = str(_params(tmp_path))
    out = tmp_path / "conv" / "yoga.mcap"
    out.parent.mkdir()
    assert main(["convert-dumper", str(run), str(out), "--params", params]) == 0
    cfg, joints, sensors = _real_cfg(), icub2.joint_names, list(icub2.sensors)
    direct = ingest_log(run, tmp_path / "a", "yoga", cfg, TOPICS, joints, sensors)
    converted = ingest_log(out, tmp_path / "b", "yoga", cfg, TOPICS, joints, sensors)
    assert converted.absent == direct.absent and converted.frozen == direct.frozen
    pd.testing.assert_frame_equal(pd.read_parquet(converted.output), pd.read_parquet(direct.output))


def test_dumper_params_name_the_key() -> None:
    from pipeline.core.errors import ConfigError

    good = {k: getattr(DUMPER, k) for k in DUMPER.__dataclass_fields__}
    assert DumperParams.from_mapping(good) == DUMPER
    for change, message in (
        (
            {"time_base": ["arm"]},
            r"ingest.dumper.time_base must be a non-empty list of parts of ingest.dumper.joints",
        ),
        (
            {"joints": {"leg": ["j_a"], "torso": ["j_a"]}, "time_base": ["leg"]},
            r"ingest.dumper.joints.torso\[0\]",
        ),
        ({"ft_ports": {"leg": "s_one", "arm": "s_one"}}, "ingest.dumper.ft_ports maps two parts"),
        ({"extra": 1}, "unknown key ingest.dumper.extra"),
        ({"joint_ports": []}, "ingest.dumper.joint_ports must be a non-empty list of port names"),
        (
            {"joint_ports": ["state:o", "analog:o"]},
            "ingest.dumper.joint_ports: 'analog:o' is also the ft_port",
        ),
    ):
        with pytest.raises(ConfigError, match=message):
            DumperParams.from_mapping({**good, **change})


# --- frozen boards: the same samples flagged whatever the source ---


def test_frozen_runs_of_identical_readings() -> None:
    from pipeline.logs.align import frozen_runs

    t = np.arange(10, dtype=np.int64) * 10
    v = np.array([[0], [1], [1], [1], [2], [2], [3], [3], [3], [3]], dtype=float)
    start, frozen = frozen_runs(t, v, None, 15)
    np.testing.assert_array_equal(start, [0, 10, 10, 10, 40, 40, 60, 60, 60, 60])
    np.testing.assert_array_equal(frozen, [0, 1, 1, 1, 0, 0, 1, 1, 1, 1])
    start, frozen = frozen_runs(t, v, -100, 15)  # the first run began before these messages
    assert start[0] == -100 and frozen[0]


def _frozen_wrench(w) -> None:
    """s_one's wrench (200 Hz) repeating one reading from 19.5 s to 22.5 s, and for 1.5 s from 5 s
    (shorter than the test's ingest.max_frozen_s, 2 s: not frozen)."""
    from tests.factories.logs import T0, linear_wrench, stamps

    ft = stamps(30.0, 200.0, offset_ns=1_000_000)
    t = (ft - T0) / 1e9
    wrench = linear_wrench(t, 0) + np.sin(7 * t)[:, None]
    for lo, hi in ((19.5, 22.5), (5.0, 6.5)):
        held = (t >= lo) & (t <= hi)
        wrench[held] = wrench[np.argmax(held)]
    w.wrenches("/ft/s_one/wrench", ft, "s_one", wrench, log_times_ns=ft + 3_000_000)


def test_frozen_board_flagged_alike_in_mcap_mat_and_dumper_run(tmp_path: Path, monkeypatch) -> None:
    from pipeline.logs import mcap_table
    from tests import matfile
    from tests.factories.logs import CFG_MAT

    monkeypatch.setattr(mcap_table, "_EMIT_ROWS", 37)  # rows written while the frozen run is being read

    mcap = write_log(  # small MCAP chunks: the table is written in pieces while the log is read
        tmp_path / "log.mcap",
        duration=30.0,
        skip=["/ft/s_one/wrench"],
        extra=_frozen_wrench,
        chunk_size=2**16,
    )
    # longer than the reorder window and the widest gap together (1 s): a sample is written only once
    # its run is decided
    cfg = IngestParams(**{**CFG_MAT.__dict__, "dumper": DUMPER, "max_frozen_s": 2.0})
    (tmp_path / "mat").mkdir()
    mat = matfile.mcap_to_mat(mcap, tmp_path / "mat" / "log.mat", TOPICS, SENSORS)
    run = dumperfile.mcap_to_run(mcap, tmp_path / "run", TOPICS, FT_PORTS, JOINT_MAP)
    flags = {}
    for kind, path in (("mcap", mcap), ("mat", mat), ("run", run)):
        report = ingest_log(path, tmp_path / kind, "log", cfg, TOPICS, JOINTS, SENSORS)
        df = pd.read_parquet(report.output)
        t = df[S.TIME].to_numpy()
        flags[kind] = ~df[S.ok_col(S.WRENCH_STREAM, "s_one")].to_numpy()
        assert report.frozen == {"s_one": int(flags[kind][(t > 1) & (t < 29)].sum())}, kind
        inside = (t > 19.51) & (t < 22.49)
        assert flags[kind][inside].all() and not flags[kind][(t > 1) & (t < 19.49)].any(), kind
        assert not flags[kind][(t > 22.51) & (t < 29)].any(), kind
        assert df[S.ok_col(S.WRENCH_STREAM, "s_two")][(t > 1) & (t < 29)].all()
    np.testing.assert_array_equal(flags["mat"], flags["mcap"])
    np.testing.assert_array_equal(flags["run"], flags["mcap"])


def test_what_a_run_holds_beside_the_contract_is_named_once_and_not_read(
    tmp_path: Path, excerpt: Path, icub2
) -> None:
    """A run as a lab saved it: a skin board's port, an estimator's outputs (another prefix, a module's own
    port), a part no map names and a port that never connected sit beside the contract's ports. They are
    not read: the tables are those of the run without them, and the summary names each once, with the
    number of runs holding it."""
    from pipeline.stages.ingest import IngestSummary, summary_line

    def ingest(run: Path, name: str) -> tuple[object, pd.DataFrame]:
        report = ingest_log(
            run,
            tmp_path / "out",
            name,
            _real_cfg(),
            TOPICS,
            icub2.joint_names,
            list(icub2.sensors),
        )
        return report, pd.read_parquet(tmp_path / "out" / f"{name}.parquet")

    plain = _copy_run(excerpt, tmp_path / "plain")
    _, expected = ingest(plain, "plain")
    reports = []
    for k in range(2):
        run = _copy_run(excerpt, tmp_path / f"saved{k}")
        line = "1 1457625466.1 0.1 0.2 0.3\n"
        _port(run / "icub/right_leg/inertialMTB", "/icub/right_leg/inertialMTB", line)
        _port(run / "wbd/lleg", "/wholeBodyDynamics/left_leg/cartesianEndEffectorWrench:o", line)
        _port(
            run / "QuaternionEKF/filteredOrientationEuler", "/QuaternionEKF/filteredOrientationEuler:o", line
        )
        _port(run / "icub/inertial/analog:o", "", None)  # the dumper's layout: a part no map names
        _port(run / "rightLegAcc", "", "")  # never connected: no port named, an empty data.log
        report, table = ingest(run, f"saved{k}")
        pd.testing.assert_frame_equal(table, expected)
        reports.append(report)
    assert reports[0].not_read == [
        "/QuaternionEKF/filteredOrientationEuler:o",
        "/icub/inertial/analog:o",
        "/icub/right_leg/inertialMTB",
        "rightLegAcc (never connected)",
        "/wholeBodyDynamics/left_leg/cartesianEndEffectorWrench:o",
    ]
    line = summary_line(IngestSummary(reports, [], 1.0), tmp_path / "out")
    assert line.count("/icub/right_leg/inertialMTB") == 1 and "/icub/right_leg/inertialMTB (2 logs)" in line


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ({"neck_pitch": "zero"}, r"ingest.fixed_joints.neck_pitch must be a position in degrees, got 'zero'"),
        ({"neck_pitch": float("nan")}, r"ingest.fixed_joints.neck_pitch must be a position in degrees"),
        ([0.0, 0.0], r"ingest.fixed_joints must map joint names to degrees"),
    ],
)
def test_bad_declared_still_joints_are_one_line_errors_naming_the_key(value: object, message: str) -> None:
    from pipeline.core.errors import ConfigError

    with pytest.raises(ConfigError, match=message):
        IngestParams(**{**CFG.__dict__, "fixed_joints": value})
