"""The FT boards' IMU checked against the kinematics: axis maps, the frame motion they are checked against
(Pinocchio's own URDF model and finite differences), the check on simulated logs with a board whose axes are
swapped (`simulate.imu.axes`), `ingest.imu_axes` mapping it back, and train refusing its 13-input network."""

from __future__ import annotations

import contextlib
import copy
import io
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pinocchio as pin
import pytest
import yaml

from pipeline.cli import main
from pipeline.core.config import load_params
from pipeline.core.errors import ConfigError
from pipeline.labels.contacts import declared_contacts
from pipeline.labels.imu_check import check_log
from pipeline.labels.imu_params import label_params
from pipeline.logs import schema as S
from pipeline.logs.imu_axes import (
    IDENTITY,
    SIGNED_PERMUTATIONS,
    axis_map,
    compose,
    matrix,
    parse_axis_map,
    to_board,
    to_sensor_frame,
)
from pipeline.logs.tables import read_table_metadata
from pipeline.physics.dynamics import ContactCase
from pipeline.physics.imu import sensor_motion
from pipeline.physics.robot import RobotModel
from tests.factories.params import TRAIN_PARAMS, repo_params

pytestmark = pytest.mark.slow  # trains the groups it checks

REPO = Path(__file__).resolve().parents[1]
SWAPPED = "l_arm_ft"  # the simulated board whose IMU has x and y swapped and inverted
SWAP = ["-y", "-x", "z"]
LOGS = [
    {"type": "pole", "duration_s": 15, "role": "train"},
    {"type": "pole", "duration_s": 10, "role": "train"},
    {"type": "balancing", "duration_s": 8, "role": "test", "foot": "l_foot"},
]
POLE, BALANCING = "00_pole_train", "02_balancing_l_foot_test"


# --- axis maps and params ------------------------------------------------------------------------


def test_axis_maps_read_literally_and_invert() -> None:
    assert len(set(SIGNED_PERMUTATIONS)) == 48 and SIGNED_PERMUTATIONS[0] == IDENTITY
    assert sum(np.linalg.det(matrix(m)) > 0 for m in SIGNED_PERMUTATIONS) == 24  # rotations; the rest mirrors
    # (x, y, z) = (-y, -x, z): the board's x reads minus the sensor frame's y (both vectors of the chip)
    v = np.array([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]])
    np.testing.assert_array_equal(to_board(v, tuple(SWAP)), [[-2, -1, 3, -5, -4, 6]])
    np.testing.assert_array_equal(to_board(v, ("z", "x", "-y")), [[3, 1, -2, 6, 4, -5]])  # the axes turned
    rng = np.random.default_rng(0)
    v = rng.normal(size=(5, 6))
    for m in SIGNED_PERMUTATIONS:
        np.testing.assert_array_equal(to_sensor_frame(to_board(v, m), m), v)
        assert axis_map(matrix(m)) == m and compose(m, axis_map(matrix(m).T)) == IDENTITY
    assert compose(("y", "x", "z"), ("z", "y", "x")) == axis_map(
        matrix(("y", "x", "z")) @ matrix(("z", "y", "x"))
    )
    assert parse_axis_map(["+x", " -z", "y"], "k") == ("x", "-z", "y")


@pytest.mark.parametrize(
    ("section", "value", "message"),
    [
        (
            "ingest",
            {"imu_axes": {"l_leg_ft": ["x", "x", "z"]}},
            r"ingest.imu_axes.l_leg_ft must name each of x, y, z once",
        ),
        (
            "ingest",
            {"imu_axes": {"l_leg_ft": ["x", "w", "z"]}},
            r"ingest.imu_axes.l_leg_ft\[1\] must be one of x, y, z",
        ),
        ("ingest", {"imu_axes": ["x", "y", "z"]}, r"ingest.imu_axes must be a mapping FT sensor"),
        (
            "simulate",
            {"imu": {"axes": {"l_leg_ft": "xyz"}}},
            r"simulate.imu.axes.l_leg_ft must be a list of three",
        ),
        (
            "label",
            {"imu_check": {"max_rms_m_s2": -1}},
            r"label.imu_check.max_rms_m_s2 must be a positive number",
        ),
    ],
)
def test_bad_params_name_the_key(tmp_path: Path, section: str, value: dict, message: str) -> None:
    data = repo_params()
    for key, v in value.items():
        if isinstance(v, dict) and isinstance(data[section].get(key), dict):
            data[section][key] = {**data[section][key], **v}
            data[section][key] = {k: x for k, x in data[section][key].items() if x is not None}
        else:
            data[section][key] = v
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError, match=rf"params.yaml: .*{message}"):
        load_params(path)


# --- the frame motion the boards are checked against ---------------------------------------------


def _urdf_pose(robot: RobotModel, q: np.ndarray, fixed: str, sensor: str) -> pin.SE3:
    """Pose of `sensor`'s frame in link `fixed`'s frame from Pinocchio's own URDF model (root_link fixed)."""
    model = robot.pinocchio_model
    data = model.createData()
    full = pin.neutral(model)
    for k, name in enumerate(robot.joint_names):
        full[model.idx_qs[model.getJointId(name)]] = q[k]
    pin.framesForwardKinematics(model, data, full)
    ft = robot.sensors[sensor]
    world_sensor = data.oMf[model.getFrameId(ft.child_link)] * ft.child_T_sensor
    return data.oMf[model.getFrameId(fixed)].inverse() * world_sensor


@pytest.mark.parametrize(
    ("fixed", "contacts"), [("root_link", ["root_link"]), ("l_sole", ["l_foot_front", "l_foot_rear"])]
)
def test_sensor_motion_matches_the_urdf_model_and_finite_differences(
    icub: RobotModel, fixed: str, contacts: list
) -> None:
    """Still: the accelerometer reads minus gravity in the sensor frame (rotation from Pinocchio's URDF
    model, not the contact-rooted one). Moving: the frame's acceleration and angular velocity are the
    finite differences of its pose along a smooth joint trajectory."""
    rng = np.random.default_rng(1)
    n = len(icub.joint_names)
    q0, amp, w = rng.uniform(-0.3, 0.3, n), rng.uniform(0.1, 0.4, n), rng.uniform(1.0, 3.0, n)
    gravity = np.array([0.3, -0.2, -9.7])  # a tilted fixed link, in its own frame
    case = ContactCase.make(contacts, fixed, gravity)
    q, dq, ddq = q0 + amp * np.sin(w), amp * w * np.cos(w), -amp * w**2 * np.sin(w)  # at t = 1 s
    still = sensor_motion(icub, q[None], np.zeros((1, n)), np.zeros((1, n)), case)
    moving = sensor_motion(icub, q[None], dq[None], ddq[None], case)
    h = 1e-3
    for sensor in icub.sensors:
        pose = [_urdf_pose(icub, q0 + amp * np.sin(w * (1.0 + k * h)), fixed, sensor) for k in (-1, 0, 1)]
        rot = pose[1].rotation
        np.testing.assert_allclose(still[sensor].rest[0], -rot.T @ gravity, atol=1e-9)
        np.testing.assert_allclose(still[sensor].motion[0], 0.0, atol=1e-9)
        acc = (pose[2].translation - 2 * pose[1].translation + pose[0].translation) / h**2
        np.testing.assert_allclose(moving[sensor].motion[0], rot.T @ acc, atol=2e-4)
        spin = rot.T @ (pose[2].rotation - pose[0].rotation) / (2 * h)
        np.testing.assert_allclose(moving[sensor].angular[0], [spin[2, 1], spin[0, 2], spin[1, 0]], atol=2e-5)
        np.testing.assert_allclose(moving[sensor].proper[0], rot.T @ (acc - gravity), atol=2e-4)


# --- on simulated logs ---------------------------------------------------------------------------


def _params(tmp: Path, name: str, ingest_axes: dict | None = None, **train: object) -> Path:
    """The repo's params with short logs, one board swapped in the simulator (and `ingest_axes` mapped),
    a small train section for the swapped board's group."""
    data = repo_params()
    data["simulate"].update({"logs": copy.deepcopy(LOGS), "workers": 1, "plots": False})
    data["simulate"]["imu"]["axes"] = {SWAPPED: SWAP}
    data["ingest"]["imu_axes"] = ingest_axes or {}
    data["train"] = copy.deepcopy(TRAIN_PARAMS)
    data["train"].update({"folds": 1, "groups": {SWAPPED: {"sensor": SWAPPED}}})
    data["train"]["defaults"].update({"n_trials": 1, "epochs": 1, "poly_orders": [1], **train})
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _through_label(tmp: Path, params: Path, name: str) -> str:
    """ingest, smooth and label tmp/sim into tmp/<name>/...: the label command's stderr."""
    from pipeline.stages import ingest, smooth

    p, out = load_params(params), tmp / name
    ingest.run(p, tmp / "sim", out / "ingested", progress=False)
    smooth.run(p, out / "ingested", out / "smoothed", progress=False)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main(["label", str(out / "smoothed"), str(out / "labelled"), "--params", str(params)]) == 0
    return err.getvalue()


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory: pytest.TempPathFactory, mlflow_store: None) -> dict:
    """Three short logs whose l_arm_ft board reads (x, y, z) = (-y, -x, z) of the sensor frame, labelled as
    recorded ("as_is") and with ingest.imu_axes mapping that board ("mapped"); the label stderr of each."""
    from pipeline.stages import simulate

    tmp = tmp_path_factory.mktemp("imu")
    run = {"tmp": tmp, "as_is": _params(tmp, "as_is"), "mapped": _params(tmp, "mapped", {SWAPPED: SWAP})}
    simulate.run(load_params(run["as_is"]), tmp / "sim", progress=False)
    for name in ("as_is", "mapped"):
        run[f"{name}_err"] = _through_label(tmp, run[name], name)
    return run


def _checks(run: dict, name: str) -> dict[str, dict[str, dict]]:
    """log -> sensor -> the check's record in the labelled table's metadata."""
    out = {}
    for path in sorted((run["tmp"] / name / "labelled").glob("*.parquet")):
        out[path.stem] = read_table_metadata(path)[S.META_LABEL.decode()]["imu_axes"]
    return out


def test_a_swapped_board_is_named_once_and_the_others_pass(sim_run: dict) -> None:
    """The label stage names the swapped board with its map and the params key, in one line; no other
    board fails; where a log cannot tell (a foot flat on the floor: one posture, no rotation), "not
    checked" with the reason."""
    lines = [line for line in sim_run["as_is_err"].splitlines() if line.startswith("ftcal: warning:")]
    assert len(lines) == 1, sim_run["as_is_err"]
    assert lines[0].startswith(
        f"ftcal: warning: {SWAPPED}: the IMU's axes are (x, y, z) = (-y, -x, z) of the sensor frame"
    )
    assert f"set ingest.imu_axes: {{{SWAPPED}: [-y, -x, z]}}" in lines[0]
    checks = _checks(sim_run, "as_is")
    assert {log: r[SWAPPED]["status"] for log, r in checks.items()} == dict.fromkeys(checks, "failed")
    assert all(r[SWAPPED]["axes"] == SWAP for r in checks.values())
    # the accelerometer alone, on the balancing log's quasi-static stretches, and the gyroscope agree
    arm = checks[BALANCING][SWAPPED]
    assert arm["accelerometer"]["identified"] == SWAP and arm["gyroscope"]["identified"] == SWAP
    assert arm["accelerometer"]["rms_m_s2"] < 0.3 < 3.0 < arm["accelerometer"]["rms_identity_m_s2"]
    assert arm["accelerometer"]["rotation_deg"] < 3.0
    others = [r for by in checks.values() for s, r in by.items() if s != SWAPPED]
    assert {r["status"] for r in others} == {"passed", "not checked"}
    foot = checks[BALANCING]["l_foot_front_ft"]  # the stance foot: one posture, it never turns
    assert foot["status"] == "not checked" and "gravity stays within 0 deg" in foot["reason"]
    assert "turns faster than 0.2 rad/s for 0.0 s only" in foot["reason"]


def test_ingest_maps_the_board_back_and_the_check_passes(sim_run: dict) -> None:
    """With ingest.imu_axes set, the board's columns are the sensor frame's: every check passes or is not
    checked, the swapped board passes in every log, and the tables record the map applied."""
    assert "ftcal: warning:" not in sim_run["mapped_err"], sim_run["mapped_err"]
    checks = _checks(sim_run, "mapped")
    assert {r[SWAPPED]["status"] for r in checks.values()} == {"passed"}
    # the board itself still reads in its own axes: what ingest applied is what the check finds
    assert all(r[SWAPPED]["applied"] == SWAP and r[SWAPPED]["axes"] == SWAP for r in checks.values())
    cols = S.vector_cols(S.ACC, SWAPPED) + S.vector_cols(S.GYR, SWAPPED)
    table = sim_run["tmp"] / "{}" / "ingested" / f"{POLE}.parquet"
    raw, mapped = (
        pd.read_parquet(str(table).format(k), columns=cols).to_numpy() for k in ("as_is", "mapped")
    )
    np.testing.assert_array_equal(mapped, to_sensor_frame(raw, tuple(SWAP)))
    assert read_table_metadata(str(table).format("mapped"))[S.META_INGEST.decode()]["imu_axes"] == {
        SWAPPED: SWAP
    }


def _check(run: dict, robot: RobotModel, log: str, board: dict[str, tuple]) -> dict[str, dict]:
    """The check of the mapped run's smoothed table `log` whose boards `board` (sensor -> (accelerometer
    axes, gyroscope axes)) read in other axes."""
    path = run["tmp"] / "mapped" / "smoothed" / f"{log}.parquet"
    table, meta = pd.read_parquet(path), read_table_metadata(path)
    for sensor, (acc_axes, gyr_axes) in board.items():
        for quantity, axes in ((S.ACC, acc_axes), (S.GYR, gyr_axes)):
            cols = S.vector_cols(quantity, sensor)
            table[cols] = to_board(table[cols].to_numpy(), axes)
    meta.pop(S.META_INGEST.decode())  # as if ingest had mapped nothing
    kinematics = tuple(table[S.joint_cols(k, robot.joint_names)].to_numpy() for k in (S.QS, S.DQS, S.DDQS))
    ok = table[S.ok_col(S.KINEMATICS_STREAM)].to_numpy(bool)
    contacts = declared_contacts(robot, meta[S.META_EXPERIMENT.decode()], len(table))
    cfg = label_params(load_params(run["mapped"])).imu_check
    return check_log(robot, table, meta, contacts, kinematics, ok, np.array([0, 0, -9.80665]), cfg)


@pytest.mark.parametrize("axes", [("-y", "-x", "z"), ("y", "x", "z"), ("z", "x", "y"), ("-x", "-y", "z")])
def test_each_swap_is_named_with_its_map(sim_run: dict, icub: RobotModel, axes: tuple) -> None:
    """x and y swapped and inverted, swapped alone (a mirror: two fields of a driver), the axes turned, a
    half turn: on the pole (by the gyroscope: that arm is never quasi-static for long there) and on one
    foot (the accelerometer's quasi-static stretches and the gyroscope agree), the map is named, with the
    params key that maps it; every other board passes or is not checked."""
    for log, sensor, by in ((POLE, "r_arm_ft", "gyroscope"), (BALANCING, SWAPPED, "accelerometer")):
        checks = _check(sim_run, icub, log, {sensor: (axes, axes)})
        arm = checks[sensor]
        assert arm["status"] == "failed" and arm["axes"] == list(axes), arm["message"]
        assert arm[by]["identified"] == list(axes)
        assert f"set ingest.imu_axes: {{{sensor}: [{', '.join(axes)}]}}" in arm["message"]
        assert {r["status"] for s, r in checks.items() if s != sensor} <= {"passed", "not checked"}


def test_a_gyroscope_on_other_axes_fails_and_too_little_evidence_is_not_checked(
    sim_run: dict, icub: RobotModel
) -> None:
    """The accelerometer swapped, the gyroscope not: the board fails naming both maps. A board swapped on
    the stance foot (one posture, never turning) is "not checked", not a false alarm nor a pass."""
    swap = ("-y", "-x", "z")
    checks = _check(sim_run, icub, BALANCING, {SWAPPED: (swap, IDENTITY), "l_foot_front_ft": (swap, swap)})
    arm = checks[SWAPPED]
    assert arm["status"] == "failed" and arm["accelerometer"]["identified"] == list(swap)
    assert arm["gyroscope"]["identified"] == list(IDENTITY)
    assert (
        "accelerometer axes are (x, y, z) = (-y, -x, z) of the sensor frame, its gyroscope's"
        in arm["message"]
    )
    foot = checks["l_foot_front_ft"]
    assert foot["status"] == "not checked" and foot["axes"] is None
    assert foot["reason"].startswith(
        "accelerometer: gravity stays within 0 deg in the sensor frame (at least 15"
    )


def _train(run: dict, name: str) -> tuple[str, dict, Path]:
    """`ftcal train l_arm_ft` on the run's `name` labelled tables, once: (stderr, metrics.json, models/<group>
    dir)."""
    if f"trained_{name}" not in run:
        tmp = run["tmp"]
        models, err = tmp / name / "models" / SWAPPED, io.StringIO()
        args = [str(tmp / name / "labelled"), str(models), "--studies", str(tmp / name / "studies")]
        with contextlib.redirect_stderr(err):
            assert main(["train", SWAPPED, *args, "--params", str(run[name])]) == 0
        run[f"trained_{name}"] = err.getvalue(), json.loads((models / "metrics.json").read_text()), models
    return run[f"trained_{name}"]


def test_train_refuses_the_swapped_boards_13_input_network_until_ingest_maps_it(sim_run: dict) -> None:
    """As recorded: no 13-input network for the group, one warning line naming the sensor, the map and the
    params key, the same note in metrics.json; the baselines and the 7-input network train. With
    ingest.imu_axes: the 13-input network trains too."""
    err, metrics, models = _train(sim_run, "as_is")
    lines = [line for line in err.splitlines() if line.startswith("ftcal: warning:")]
    assert len(lines) == 1, err
    assert lines[0].startswith(
        f"ftcal: warning: {SWAPPED}: no 13-input network: {SWAPPED}: the IMU's axes are "
    )
    assert (
        "(x, y, z) = (-y, -x, z)" in lines[0]
        and f"set ingest.imu_axes: {{{SWAPPED}: [-y, -x, z]}}" in lines[0]
    )
    assert metrics["notes"] == [lines[0].removeprefix("ftcal: warning: ")]
    assert "nn13" not in metrics["test"] and {"nn7", "affine", "raw"} <= set(metrics["test"])
    assert (models / "nn7.json").is_file() and not (models / "nn13.json").exists()
    err, metrics, models = _train(sim_run, "mapped")
    assert "ftcal: warning:" not in err and metrics["notes"] == []
    assert {"nn7", "nn13"} <= set(metrics["test"]) and (models / "nn13.json").is_file()


def test_a_map_of_a_sensor_the_robot_lacks_is_a_one_line_error(sim_run: dict, tmp_path: Path) -> None:
    data = yaml.safe_load(sim_run["as_is"].read_text())
    data["ingest"]["imu_axes"] = {"l_leg_fts": SWAP}
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert (
            main(["ingest", str(sim_run["tmp"] / "sim"), str(tmp_path / "out"), "--params", str(path)]) == 2
        )
    (line,) = err.getvalue().splitlines()
    assert line.startswith("ftcal: error: ingest.imu_axes.l_leg_fts: no FT sensor of that name in the URDF")
    assert line.endswith(
        "l_leg_ft, l_foot_front_ft, l_foot_rear_ft, r_leg_ft, r_foot_front_ft, r_foot_rear_ft)"
    )
    assert not (tmp_path / "out").exists()


def test_the_export_carries_the_map_and_calibrate_applies_it_to_the_board(sim_run: dict) -> None:
    """The 13-input network trained on the mapped run, exported: the manifest records the board's map, and
    `ftcal calibrate`'s runtime reads the log's raw board readings through it (the sensor frame, as training
    saw them); an export without the map feeds them as they are."""
    from pipeline.export.runtime import CausalCalibrator, Deployment, plan_log
    from pipeline.logs.rosmsg import LogReader
    from pipeline.stages import export

    tmp = sim_run["tmp"]
    _train(sim_run, "mapped")
    d = tmp / "mapped"
    data = yaml.safe_load(sim_run["mapped"].read_text())
    data["export"]["models"] = {SWAPPED: "nn13"}
    (tmp / "export.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    params = load_params(tmp / "export.yaml")
    result = export.run_group(params, SWAPPED, d / "models", d / "reports", d / "labelled", d / "exp")
    assert result.manifest["graphs"][SWAPPED]["imu_axes"] == {SWAPPED: SWAP}
    imu_topic = params.topics.sensor_topic("ft_imu", SWAPPED)
    fed = {}
    for name, axes in (("mapped", SWAP), ("unmapped", None)):
        deployment = Deployment.load(result.out_dir)
        deployment.manifest["graphs"][SWAPPED]["imu_axes"] = {SWAPPED: axes}
        with LogReader(tmp / "sim" / f"{POLE}.mcap") as reader:
            plans, _ = plan_log(reader, deployment, params.topics)
            calibrator, last = CausalCalibrator(deployment, plans), None
            for batches in reader.iter_chunks(calibrator.topics()):
                calibrator.feed(batches)
                for b in batches:
                    if b.topic == imu_topic:
                        last = (b.stamp_ns, b.fields["linear_acceleration"], b.fields["angular_velocity"])
        board = np.concatenate(last[1:], axis=1)[np.argsort(last[0], kind="stable")][-1:]
        fed[name] = (calibrator._imu[SWAPPED].value[-1:], board)
    stream, board = fed["mapped"]
    np.testing.assert_array_equal(stream, to_sensor_frame(board, tuple(SWAP)))
    stream, board = fed["unmapped"]
    np.testing.assert_array_equal(stream, board)
