"""`ftcal rezero`: a calibration re-zeroed from a still stretch, on logs of the real simulator (the robot
still in three poses on the pole, standing on both feet, moving on the pole) and the real export of tiny
trained models (r_leg_ft, the r_foot pair).

Independent references: a log simulated again with one sensor's offset moved by a known amount (the same
motions and noise) re-zeroes to offsets that differ by exactly that amount; with the factory map exported
(the identity), a sensor's offset is the mean of its raw reading minus its exact label over the stretch
(numpy); after re-zeroing, `ftcal calibrate` reports the stretch's labels on average. Refusals are one line.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.cli import main
from pipeline.core.config import load_params
from pipeline.logs import schema as S
from pipeline.stages import export as E
from tests.factories.labelled import FRONT, LEG, PAIR, REAR
from tests.factories.reports import write_recommended

pytestmark = pytest.mark.slow  # trains and exports a group first

SENSORS = (LEG, FRONT, REAR)
DELTA = np.array([7.0, -4.0, 11.0, 0.3, -0.25, 0.15])  # N, Nm: the leg's offset moved by this
LOGS = [  # poses held 0-4, 5-9, 10-13 s
    {"type": "poses", "duration_s": 13, "role": "test"},
    {"type": "standing", "duration_s": 4, "role": "test"},
    {"type": "pole", "duration_s": 3, "role": "test"},
]
REZERO = {"duration_s": 3.0, "min_s": 1.5, "still_joint_rad_s": 0.02, "still_gyro_rad_s": 0.05,
          "prior_force_n": 10.0, "prior_torque_nm": 0.5, "pose_limit": 2.0, "label_mass_rel": 0.01,
          "label_com_m": 0.003, "significance": 2.0}  # fmt: skip


def _simulate_moved(params_path: Path, out: Path, serials: dict[str, str] | None = None) -> None:
    """The poses log again, same motion and noise, the leg's offset moved by DELTA (and other serials)."""
    from pipeline.sim.distortion import SensorDistortion
    from pipeline.sim.experiment import simulate_log
    from pipeline.sim.params import simulate_params
    from pipeline.sim.world import build_world

    params = load_params(params_path)
    sim = simulate_params(params)
    world = build_world(params, sim)
    moved = world.distortions[LEG].to_dict()
    moved["offset"] = (np.asarray(moved["offset"]) + DELTA).tolist()
    world = dataclasses.replace(
        world, distortions={**world.distortions, LEG: SensorDistortion.from_dict(moved)}
    )
    if serials is not None:
        robot = dataclasses.replace(params.robot, serials=serials)
        world = dataclasses.replace(world, params=dataclasses.replace(params, robot=robot))
    out.mkdir(parents=True, exist_ok=True)
    simulate_log(world, 0, sim.logs[0], out, False)


@pytest.fixture(scope="module")
def day(trained_models: dict, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("rezero")
    data = yaml.safe_load(Path(trained_models["params"]).read_text())
    data["simulate"].update(workers=1, plots=False, logs=LOGS)
    data["simulate"]["motion"].update(pose_hold_s=4.0, pose_move_s=1.0)
    data["deploy"]["rezero"] = REZERO
    params = root / "params.yaml"
    params.write_text(yaml.safe_dump(data, sort_keys=False))
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")
    try:
        assert main(["simulate", str(root / "logs"), "--quiet", "--params", str(params)]) == 0
        _simulate_moved(params, root / "moved")
        _simulate_moved(params, root / "swapped", serials={**data["robot"]["serials"], LEG: "FT58-0999"})
        exports = {}
        for name, deployed in (("trained", {}), ("raw", {LEG: "raw", PAIR: "raw"})):
            data["export"]["models"] = deployed
            variant = root / f"params_{name}.yaml"
            variant.write_text(yaml.safe_dump(data, sort_keys=False))
            report = write_recommended(root, {LEG: "nn13", PAIR: "nn7"})
            E.run(load_params(variant), trained_models["models"], report, trained_models["labelled"],
                  root / name)  # fmt: skip
            exports[name] = root / name
    finally:
        patch.undo()
    logs = {spec["type"]: root / "logs" / f"{i:02d}_{spec['type']}_test.mcap" for i, spec in enumerate(LOGS)}
    tables = root / "tables"  # the logs ingested, smoothed and labelled as the deployment days' are
    assert main(["deploy-prepare", str(root / "logs"), str(tables), "--params", str(params)]) == 0
    labelled = pd.read_parquet(tables / "labelled" / f"{logs['poses'].stem}.parquet")
    return {"root": root, "params": params, "logs": logs, "exports": exports, "poses": labelled}


def _rezero(day: dict[str, Any], log: Path, export: str, out: Path, *extra: str) -> int:
    args = ["rezero", str(log), "--models", str(day["exports"][export]), "--out", str(out)]
    return main([*args, *extra, "--params", str(day["params"])])


def test_offsets_moved_by_a_known_amount_are_recovered(
    day: dict[str, Any], tmp_path: Path, capsys: Any
) -> None:
    """The same log with the leg's offset moved by DELTA: its re-zeroing differs by DELTA, within its
    stated uncertainty; the foot sensors' do not move. On the pole every sensor has its own exact label."""
    moved = day["root"] / "moved" / day["logs"]["poses"].name
    for log, name in ((day["logs"]["poses"], "a.json"), (moved, "b.json")):
        assert _rezero(day, log, "trained", tmp_path / name) == 0
    a, b = (json.loads((tmp_path / n).read_text()) for n in ("a.json", "b.json"))
    assert a["status"] == b["status"] == {s: "all" for s in SENSORS}
    for sensor in SENSORS:
        diff = np.subtract(b["sensors"][sensor]["estimate"], a["sensors"][sensor]["estimate"])
        std = np.asarray(a["sensors"][sensor]["std"])
        expected = DELTA if sensor == LEG else np.zeros(6)
        assert np.all(np.abs(diff - expected) <= np.maximum(std, 1e-4)), (sensor, diff, std)
        assert np.all(std[:3] < 0.6) and np.all(std[3:] < 0.03)  # under one reading's noise (0.6 N, 0.03 Nm)
    # applied: nothing of an estimate within its threshold, all of one beyond twice it
    for entry in b["sensors"].values():
        estimate, offset, threshold = (np.asarray(entry[k]) for k in ("estimate", "offset", "threshold"))
        assert np.all(offset[np.abs(estimate) <= threshold] == 0.0)
        beyond = np.abs(estimate) >= 2.0 * threshold
        np.testing.assert_array_equal(offset[beyond], estimate[beyond])
    assert b["sensors"][FRONT]["offset"] == b["sensors"][FRONT]["estimate"]  # a foot: its label is exact
    stretch = a["stretches"][0]
    assert stretch["t0"] < 1.0 and stretch["seconds"] == pytest.approx(REZERO["duration_s"], abs=0.05)
    assert (
        stretch["joint_rad_s"] < REZERO["still_joint_rad_s"]
        and stretch["gyro_rad_s"] < REZERO["still_gyro_rad_s"]
    )
    out = capsys.readouterr().out
    assert f"{LEG}: re-zeroed; offset" in out and "still (fastest joint" in out


def test_identity_calibration_offset_is_the_mean_reading_minus_label(
    day: dict[str, Any], tmp_path: Path
) -> None:
    """With the factory map deployed, f(raw - delta) = raw - delta: each offset is the stretch's mean of
    raw minus label, computed here from the labelled table of the same log (`ftcal deploy-prepare`)."""
    assert _rezero(day, day["logs"]["poses"], "raw", tmp_path / "raw.json") == 0
    doc = json.loads((tmp_path / "raw.json").read_text())
    table = day["poses"]
    stretch = doc["stretches"][0]
    rows = table[(table[S.TIME] >= stretch["t0"] - 1e-9) & (table[S.TIME] <= stretch["t1"] + 1e-9)]
    assert len(rows) == stretch["stop"] - stretch["start"] == doc["samples"]
    for sensor in SENSORS:
        expected = (
            rows[S.wrench_cols(S.FT, sensor)].to_numpy() - rows[S.wrench_cols(S.EXPECTED, sensor)].to_numpy()
        ).mean(0)
        np.testing.assert_allclose(doc["sensors"][sensor]["estimate"], expected, rtol=0, atol=1e-5)


def test_calibrate_runs_the_offsets_beside_the_export(day: dict[str, Any], tmp_path: Path) -> None:
    """Written beside the export, the offsets are what `ftcal calibrate` applies (the originals still copied
    byte for byte): over the re-zeroing's stretch the calibrated wrench of a sensor whose estimate was
    applied in full averages to the exact labels."""
    import shutil

    from pipeline.export.runtime import Deployment, calibrated_messages
    from pipeline.logs.rosmsg import LogReader

    export = tmp_path / "exported"
    shutil.copytree(day["exports"]["trained"], export)
    log = day["logs"]["poses"]
    assert main(["rezero", str(log), "--models", str(export), "--params", str(day["params"])]) == 0
    doc = json.loads((export / "offsets.json").read_text())
    out = tmp_path / "calibrated.mcap"
    assert (
        main(["calibrate", str(log), str(out), "--models", str(export), "--params", str(day["params"])]) == 0
    )
    from tests.factories.readback import mcap_records, ros2_messages, stamp_ns, xyz

    assert [m for m in mcap_records(out) if not m[0].endswith("_calibrated")] == mcap_records(log)
    params = load_params(day["params"])
    with LogReader(log) as reader:
        delivered = calibrated_messages(Deployment.load(export, offsets=False), reader, params.topics)
    decoded = ros2_messages(out)
    t0 = min(stamp_ns(m.ros_msg) for m in decoded[f"/ft/{LEG}/wrench"])
    stretch, full = doc["stretches"][0], []
    for sensor in SENSORS:
        messages = decoded[f"/ft/{sensor}/wrench_calibrated"]
        stamps = np.array([stamp_ns(m.ros_msg) for m in messages])
        got = np.array([xyz(m.ros_msg.wrench.force) + xyz(m.ros_msg.wrench.torque) for m in messages])
        assert not np.allclose(got, delivered[sensor][1])  # the offsets are applied
        keep = (stamps - t0 >= stretch["t0"] * 1e9) & (stamps - t0 <= stretch["t1"] * 1e9)
        rows = day["poses"].iloc[stretch["start"] : stretch["stop"]]
        labels = rows[S.wrench_cols(S.EXPECTED, sensor)].to_numpy().mean(axis=0)
        error = np.abs(got[keep].mean(axis=0) - labels)
        if doc["sensors"][sensor]["offset"] == doc["sensors"][sensor]["estimate"]:  # applied in full
            full.append(sensor)
            assert np.all(error[:3] < 0.3) and np.all(error[3:] < 0.02), (sensor, error)
    assert set(full) >= {FRONT, REAR}  # the feet's labels carry little model error (a foot's weight)
    # the wholeBodyDynamics configuration beside it: each sensor's FT_OFFSET moved by S delta
    from pipeline.export import wbd

    delivered_terms = json.loads((export / "manifest.json").read_text())[wbd.KEY]["sensors"]
    fragment = (export / wbd.FILE).read_text()
    assert (
        "re-zeroed by ftcal rezero" in fragment
        and fragment != (day["exports"]["trained"] / wbd.FILE).read_text()
    )
    for sensor in SENSORS:
        s_matrix = np.reshape(delivered_terms[sensor]["secondary_calibration"], (6, 6))
        moved = np.array(delivered_terms[sensor]["offset"]) - s_matrix @ np.array(
            doc["sensors"][sensor]["offset"]
        )
        line = next(x for x in fragment.split("<group")[3].split("<param")[1:] if f'name="{sensor}"' in x)
        written = [float(v) for v in line.split("(")[1].split(")")[0].split(",")]
        np.testing.assert_allclose(written, moved, rtol=0, atol=1e-12)
    # the same log through the generated C calibrator (`--runtime c`): the same calibrated wrenches
    out_c = tmp_path / "calibrated_c.mcap"
    args = [str(log), str(out_c), "--models", str(export), "--runtime", "c", "--params", str(day["params"])]
    assert main(["calibrate", *args]) == 0
    decoded_c = ros2_messages(out_c)
    for sensor in SENSORS:
        ours = np.array(
            [
                xyz(m.ros_msg.wrench.force) + xyz(m.ros_msg.wrench.torque)
                for m in decoded_c[f"/ft/{sensor}/wrench_calibrated"]
            ]
        )
        theirs = np.array(
            [
                xyz(m.ros_msg.wrench.force) + xyz(m.ros_msg.wrench.torque)
                for m in decoded[f"/ft/{sensor}/wrench_calibrated"]
            ]
        )
        assert ours.shape == theirs.shape and np.abs(ours - theirs).max() < 1e-3 * max(
            1.0, np.abs(theirs).max()
        )


def test_pose_dependence_is_each_pose_re_zeroed_alone(day: dict[str, Any], tmp_path: Path) -> None:
    """The log's three still poses: the reported spread is the std of the offsets estimated from each pose
    by itself (`--start`), beside the reading's noise; named pose-dependent above pose_limit x the noise."""
    assert _rezero(day, day["logs"]["poses"], "trained", tmp_path / "all.json") == 0
    (poses,) = json.loads((tmp_path / "all.json").read_text())["pose_dependence"]["logs"]
    assert len(poses["poses"]) == 3 and set(poses["sensors"]) == set(SENSORS)
    offsets = []
    for k, (t0, t1) in enumerate(poses["poses"]):
        window = ["--start", str(t0), "--duration", str(t1 - t0 + 0.005)]  # the pose's samples
        assert _rezero(day, day["logs"]["poses"], "trained", tmp_path / f"{k}.json", *window) == 0
        offsets.append(json.loads((tmp_path / f"{k}.json").read_text())["sensors"])
    for sensor, entry in poses["sensors"].items():
        spread = np.std([o[sensor]["estimate"] for o in offsets], axis=0, ddof=1)
        np.testing.assert_allclose(entry["spread"], spread, rtol=1e-6, atol=1e-9)
        ratio = float((spread / np.asarray(entry["noise"])).max())
        assert entry["ratio"] == pytest.approx(ratio) and entry["depends"] == (ratio > REZERO["pose_limit"])
        assert min(entry["noise"][:3]) > 0.3 and max(entry["noise"][:3]) < 1.0  # the simulated 0.6 N


def test_standing_on_both_feet_re_zeroes_through_sums_only(day: dict[str, Any], tmp_path: Path) -> None:
    """Both feet on the floor: no leg or foot sensor has an exact label of its own; the shank's sum (the
    leg sensor with its foot's two) has. Each sensor is re-zeroed through that sum, and the sum's
    residual is the noise's; asked for the leg sensor alone, the stretch has no exact label: refused."""
    assert _rezero(day, day["logs"]["standing"], "trained", tmp_path / "s.json") == 0
    doc = json.loads((tmp_path / "s.json").read_text())
    assert doc["status"] == {s: "sums" for s in SENSORS}
    shank = S.cut_set_name([LEG, FRONT, REAR])
    assert all(doc["sensors"][s]["equations"] == [shank] for s in SENSORS)
    assert max(doc["residual_rms"][shank][:3]) < 2.0
    for s in SENSORS:  # along what the sum leaves open the prior stays: uncertainty near its 10 N
        assert 1.0 < max(doc["sensors"][s]["std"][:3]) <= REZERO["prior_force_n"] + 1e-9


def _identity_solve(day: dict[str, Any], change: np.ndarray) -> Any:
    """The factory map (the raw export) re-zeroed in the library on the first still second of the poses log,
    the leg's exact label there set to its raw reading minus `change` (N, Nm) on every sample: its estimate
    is `change` exactly, its floor that of the label (`pipeline.deploy.shrink`), its noise nil."""
    from pipeline.deploy.params import deploy_params
    from pipeline.deploy.prepare import load_nominal_robot, robot_cuts
    from pipeline.deploy.rezero import solve, stretch_data
    from pipeline.deploy.rezeroing import label_error, prior
    from pipeline.export.runtime import Deployment

    params = load_params(day["params"])
    cfg = deploy_params(params).rezero
    _, _, cuts = robot_cuts(params, load_nominal_robot(params))
    rows = day["poses"].iloc[100:200].copy()
    rows[S.wrench_cols(S.EXPECTED, LEG)] = rows[S.wrench_cols(S.FT, LEG)].to_numpy() - change
    deployment = Deployment.load(day["exports"]["raw"], offsets=False)
    data = stretch_data("still", rows, deployment, [LEG], cuts)  # the leg's own label: no sum of it alone
    result = solve(deployment, [data], [LEG], prior(cfg), label_error(cfg), cfg.significance)
    np.testing.assert_allclose(result.estimated[LEG], change, rtol=0, atol=1e-6)
    return result


def test_a_change_of_the_labels_error_size_is_not_applied(day: dict[str, Any]) -> None:
    """An offset change as large as the leg label's model error (its floor: a leg weighs ~100 N on the
    pole, 1 % of it and 3 mm of lever) is estimated, and not applied; a knock of three times the threshold
    on every axis is applied as estimated."""
    floor = _identity_solve(day, np.zeros(6)).floor[LEG]
    assert np.all(floor[:3] <= 0.01 * 200.0) and floor.max() > 0.2  # N, Nm: from the label, not the noise
    small = _identity_solve(day, floor * np.array([1, -1, 1, -1, 1, -1]))
    assert np.all(small.offsets[LEG] == 0.0), small.offsets[LEG]
    assert small.record()[LEG]["applied"][0].startswith("not applied (")
    knock = 3.0 * small.threshold[LEG] * np.array([-1, 1, 1, -1, 1, 1])
    np.testing.assert_allclose(_identity_solve(day, knock).offsets[LEG], knock, rtol=0, atol=1e-6)


def test_applied_offsets_are_continuous_in_the_inputs(day: dict[str, Any]) -> None:
    """Where a hard switch would flip (an estimate at its threshold, or twice it), inputs differing by
    1e-6 of it give applied offsets differing by as little, whatever side of the threshold each falls."""
    for at in (1.0, 2.0):
        change = np.zeros(6)
        for _ in range(5):  # the threshold follows the label (raw - change) a little: its fixed point
            change = at * _identity_solve(day, change).threshold[LEG]
        below, above = (_identity_solve(day, change * f) for f in (1 - 1e-6, 1 + 1e-6))
        ratios = [np.abs(r.estimated[LEG]) / r.threshold[LEG] for r in (below, above)]
        assert np.all(ratios[0] < at) and np.all(ratios[1] > at)  # either side of the switch
        step = np.abs(above.offsets[LEG] - below.offsets[LEG])
        assert np.all(step <= 3 * 2e-6 * np.abs(change) + 1e-9), (at, step)


def _refused(capsys: Any, code: int, message: str) -> None:
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("ftcal: error: ") and err.count("\n") == 1 and message in err, err


def test_refusals_are_one_line_and_write_nothing(day: dict[str, Any], tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "offsets.json"
    _refused(capsys, _rezero(day, day["logs"]["pole"], "trained", out), "the robot is never still for 1.5 s")
    moving = _rezero(day, day["logs"]["poses"], "trained", out, "--start", "3.0")  # spans the move at 4-5 s
    _refused(capsys, moving, ": the robot moved (joint")
    alone = _rezero(day, day["logs"]["standing"], "trained", out, "--sensors", LEG)
    _refused(capsys, alone, f"no exact label of {LEG} there; their sums with other sensors")
    swapped = day["root"] / "swapped" / day["logs"]["poses"].name
    _refused(capsys, _rezero(day, swapped, "trained", out), f"{LEG} is serial 'FT58-0999' in this log")
    assert not out.exists()


def test_offsets_of_another_export_are_refused(day: dict[str, Any], tmp_path: Path, capsys: Any) -> None:
    import shutil

    export = tmp_path / "exported"
    shutil.copytree(day["exports"]["trained"], export)
    assert _rezero(day, day["logs"]["poses"], "trained", export / "offsets.json") == 0
    capsys.readouterr()
    args = ["calibrate", str(day["logs"]["poses"]), str(tmp_path / "c.mcap"), "--models", str(export)]
    assert main([*args, "--params", str(day["params"])]) == 0  # re-zeroed for this very export
    capsys.readouterr()
    manifest = json.loads((export / "manifest.json").read_text())
    manifest["robot"] = manifest["robot"] + " "  # the export changed since the re-zeroing
    (export / "manifest.json").write_text(json.dumps(manifest))
    _refused(capsys, main([*args[:2], str(tmp_path / "d.mcap"), *args[3:], "--params", str(day["params"])]),
             "offsets.json: re-zeroed for another export")  # fmt: skip
