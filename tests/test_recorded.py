"""The pipeline on recorded logs only: simulated iCub 2.x logs written as YARP dataDumper runs (no truth,
no temperature, no IMU: what a lab's archive holds) under the ingest source, one of them split by its
sidecar into two training segments and a test segment, then every stage through its own `run`: ingest ->
smooth -> label -> train (inputs: [6]) -> evaluate -> report -> export -> deploy_test. No test-segment
sample reaches training; the results are against the labels and say so; the labels of the recorded runs
agree with iDynTree's (1e-6 N/Nm); the deployment stage tests nothing on the simulated robot's logs and
says so."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import yaml

from pipeline.core.config import load_params, stage_section
from pipeline.logs.tables import read_table_metadata
from pipeline.stages import (
    deploy_prepare,
    deploy_report,
    deploy_test,
    evaluate,
    export,
    ingest,
    label,
    report,
    simulate,
    smooth,
    train,
)
from tests import dumperfile
from tests.conftest import REPO
from tests.factories.dumper import REAL_RUN
from tests.factories.params import repo_params
from tests.relabel import relabel_with_idyntree

pytestmark = pytest.mark.slow  # each test's fixture runs the pipeline's stages on recorded runs

LOGS = [
    {"type": "pole", "duration_s": 20, "role": "train"},  # split by its sidecar's segments (below)
    {"type": "walking", "duration_s": 12, "role": "train"},
    {"type": "walking", "duration_s": 10, "role": "test"},
]
SEGMENTS = [  # s of the pole run: two training segments and a test one, 1 s apart (> 61 samples, the widest
    {"start_s": 0.5, "end_s": 6.0, "role": "train"},  # smoothing window of smooth.choices)
    {"start_s": 7.0, "end_s": 12.0, "role": "train"},
    {"start_s": 13.0, "end_s": 19.5, "role": "test"},
]
GROUPS = ["r_arm_ft", "l_arm_ft", "legs"]  # the default groups: on iCub 2.x each arm, legs and feet
LEGS = ["l_leg_ft", "r_leg_ft", "l_foot_ft", "r_foot_ft"]
ARMS = ["left_arm", "right_arm"]  # dataDumper parts whose joint stream a run may lack
DAYS = ("later", "drifted")  # the simulated deployment days


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The simulated iCub 2.x logs (MCAP, with truth) every recorded run below is written from, and the
    params of a lab running its archive: robot, wrench-only models, tiny trainings, no deployment logs."""
    tmp = tmp_path_factory.mktemp("recorded")
    data = repo_params()
    data["robot"]["urdf"] = "iCubGenova02"
    data["simulate"].update(logs=LOGS, workers=1, plots=False)
    data["simulate"]["motion"]["steps_per_direction"] = 2
    data["train"]["defaults"].update(
        hidden=16, epochs=2, n_trials=1, batch_size=256, search={}, inputs=[6], poly_orders=[1, 2]
    )
    data["train"]["groups"]["legs"].update(n_trials=1, epochs=2)
    data["deploy"]["real_logs"] = str(tmp / "nothing_here")
    (tmp / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'mlflow.db'}")
    try:
        params = load_params(tmp / "params.yaml")
        simulate.run(params, tmp / "sim", progress=False)
        yield {"tmp": tmp, "params": params, "sim": tmp / "sim", "dumper": data["ingest"]["dumper"]}
    finally:
        patch.undo()


def run_recorded(simulated: dict[str, Any], name: str, without_joints: list[str]) -> dict[str, Any]:
    """The simulated logs written as dataDumper runs without the joint streams of `without_joints` (parts),
    then every stage through its own `run`, every group of the params."""
    params, dumper = simulated["params"], simulated["dumper"]
    d = {k: simulated["tmp"] / name / k for k in ("raw", *STAGE_DIRS)}
    for mcap in sorted(simulated["sim"].glob("*.mcap")):  # what a lab's dataDumper wrote, with its sidecar
        run = dumperfile.mcap_to_run(
            mcap, d["raw"] / mcap.stem, params.topics, dumper["ft_ports"], dumper["joints"],
            without_joints=without_joints,
        )  # fmt: skip
        if "pole" in mcap.stem:
            side = run.with_name(run.name + ".yaml")
            side.write_text(yaml.safe_dump({**yaml.safe_load(side.read_text()), "segments": SEGMENTS}))
    ingest.run(params, d["raw"], d["ingested"], progress=False)
    smooth.run(params, d["ingested"], d["smoothed"], progress=False)
    labelled = label.run(params, d["smoothed"], d["labelled"], truth_dir=d["ingested"], progress=False)
    trained, results, tested = {}, {}, {}
    tables = simulated["tmp"] / "tables"
    if not tables.is_dir():
        deploy_prepare.run(params, simulated["sim"], tables / "later")  # a simulated day beside them
    groups = d["reports"] / "deployment" / "groups"
    for group in GROUPS:
        trained[group] = train.train_group(
            params, group, d["labelled"], d["models"] / group, d["studies"] / group, progress=False
        )
        results[group] = evaluate.run(
            params, group, d["models"] / group, d["labelled"], d["reports"], d["ingested"], progress=False
        )
        export.run_group(params, group, d["models"], d["reports"] / "metrics", d["labelled"], d["exported"])
        tested[group] = deploy_test.run(
            params, group, d["models"] / group, d["exported"] / "groups" / group, tables, groups / group
        )
    report.run(params, d["reports"], d["labelled"])
    exported = export.run_fused(params, d["models"], d["labelled"], d["exported"])
    deployed = deploy_report.run(params, groups, d["reports"])
    return {
        "dirs": d,
        "labelled": labelled,
        "trained": trained,
        "results": results,
        "exported": exported,
        "deployed": deployed,
        "tested": tested,
        "cfg": stage_section(params, "ingest", ingest.IngestParams),
    }


STAGE_DIRS = ("ingested", "smoothed", "labelled", "models", "studies", "reports", "exported")


@pytest.fixture(scope="module")
def recorded_run(simulated: dict[str, Any]) -> dict[str, Any]:
    """Every stream of the runs present."""
    return run_recorded(simulated, "complete", [])


@pytest.fixture(scope="module")
def without_arms(simulated: dict[str, Any]) -> dict[str, Any]:
    """The arms' joint streams absent (info.log only), as in the 2016 yoga run."""
    return run_recorded(simulated, "without_arms", ARMS)


@pytest.fixture(scope="module")
def without_left_leg(simulated: dict[str, Any]) -> dict[str, Any]:
    """The left leg's joint stream absent."""
    return run_recorded(simulated, "without_left_leg", ["left_leg"])


def test_no_test_segment_sample_is_used_in_training(simulated: dict[str, Any], recorded_run) -> None:
    import pandas as pd

    from pipeline.calib.fit import prepare
    from pipeline.logs import schema as S

    d = recorded_run["dirs"]
    prep = prepare(simulated["params"], "r_arm_ft", d["labelled"])
    pole = [f"00_pole_train__seg{k}" for k in range(3)]
    assert sorted([*prep.split["train"], *prep.split["val"]]) == [*pole[:2], "01_walking_train"]
    assert prep.split["test"] == [pole[2], "02_walking_test"]
    stamps = pd.read_parquet(d["labelled"] / f"{pole[2]}.parquet", columns=[S.STAMP])[S.STAMP]
    lo, hi = int(stamps.min()), int(stamps.max())
    for part in (prep.train, prep.val, *(x for fold in prep.folds for x in fold)):
        assert len(part) and not ((part.stamp >= lo) & (part.stamp <= hi)).any()
    assert ((prep.test.stamp >= lo) & (prep.test.stamp <= hi)).sum() > 300
    trained_on = recorded_run["trained"]["legs"].metrics["logs"]
    assert pole[2] not in [n for k in ("train", "val") for n in trained_on[k]]


def test_recorded_logs_train_and_results_say_they_have_no_truth(recorded_run: dict[str, Any]) -> None:
    """Against the labels of the held-out segments and logs, said so (the models with memory too), beside the
    plain least-squares affine map fitted on the training segments (scored, never a candidate to deploy)."""
    from pipeline.calib.params import LS_AFFINE

    d = recorded_run["dirs"]
    assert not list(d["ingested"].glob("*.truth.parquet"))
    metrics = json.loads((d["models"] / "r_arm_ft" / "metrics.json").read_text())
    assert metrics["data"] == "recorded" and "nn6" in metrics["test"] and LS_AFFINE in metrics["test"]
    assert "win" in metrics["cv"]["mean"]  # the windowed network too, judged on the held-out segments' labels
    assert LS_AFFINE not in metrics["validation_ranking"] and LS_AFFINE not in metrics["cv"]["mean"]
    (headline,) = (d["reports"] / "metrics" / "r_arm_ft").glob("*.json")
    shown = json.loads(headline.read_text())
    assert shown["against"] == "held-out labels" and "oracle" not in shown and "floor" not in shown
    assert shown["raw"] > shown["rmse"] > 0 and shown["ls"] > 0
    assert shown["verdict"] in ("<= least squares", "above least squares", "worse than raw")
    page = (d["reports"] / "index.html").read_text()
    assert "<b>No truth:</b> against labels on held-out segments" in page and LS_AFFINE in page


def test_every_sensor_with_exact_labels_of_its_own_is_a_headline(recorded_run: dict[str, Any]) -> None:
    """iCub 2.x, every stream there: one metrics file (a `dvc metrics show` row) per sensor, the legs'
    four included (each has exact labels of its own on the test logs; no foot pair on iCub 2.x)."""
    d = recorded_run["dirs"]
    files = {f"{p.parent.name}/{p.stem}" for p in (d["reports"] / "metrics").glob("*/*.json")}
    assert files == {"r_arm_ft/r_arm_ft", "l_arm_ft/l_arm_ft", *(f"legs/{s}" for s in LEGS)}
    assert recorded_run["trained"]["legs"].metrics["headlines"] == LEGS
    for path in (d["reports"] / "metrics").glob("*/*.json"):
        assert json.loads(path.read_text())["rmse"] > 0, path


def test_recorded_labels_agree_with_idyntree(recorded_run: dict[str, Any]) -> None:
    d = recorded_run["dirs"]
    for table in sorted(d["labelled"].glob("*.parquet")):
        assert relabel_with_idyntree(table, d["smoothed"] / table.name, "iCubGenova02", samples=150) < 1e-6


def test_wrench_only_export_and_nothing_to_deploy_on(recorded_run: dict[str, Any]) -> None:
    d = recorded_run["dirs"]
    manifest = json.loads((d["exported"] / "manifest.json").read_text())
    for g in GROUPS:  # the raw wrench alone per sensor
        assert manifest["graphs"][g]["input_shape"] == ["N", 6 * len(manifest["graphs"][g]["sensors"])]
    for tested in recorded_run["tested"].values():
        assert tested["days"] == {} and tested["recorded"]
    assert recorded_run["deployed"]["summary"] == {}  # the simulated day was not tested
    assert json.loads((d["reports"] / "deployment.json").read_text()) == {"nothing_to_test": True}
    page = (d["reports"] / "deployment.html").read_text()
    assert f"Nothing to test: the models ({', '.join(GROUPS)}) were trained on recorded logs" in page


def _metrics_files(run: dict[str, Any]) -> dict[str, dict[str, Any]]:
    root = run["dirs"]["reports"] / "metrics"
    return {f"{p.parent.name}/{p.stem}": json.loads(p.read_text()) for p in root.glob("*/*.json")}


def test_the_c_calibrator_computes_the_float32_graph_on_every_test_sample(
    recorded_run: dict[str, Any],
) -> None:
    """Every graph's generated C calibrator (exported/.../c), compiled with the system's cc by the export's
    check, computes the float32 graph's outputs on every test sample of the recorded runs within
    export.tolerance_float32_ulps, its state carried across calls."""
    from pipeline.export.cbuild import compiler

    if compiler() is None:
        pytest.skip("no C compiler (cc) to build the C calibrator")
    for name, entry in recorded_run["exported"].manifest["graphs"].items():
        c = entry["check"]["c"]
        assert c["max_ulps"] <= 8 and c["samples"] == entry["check"]["float32"]["samples"] > 100, (name, c)


def test_a_run_without_the_arms_joints_calibrates_the_legs_and_names_what_the_arms_lack(
    without_arms: dict[str, Any],
) -> None:
    """The arms' joint streams absent: the legs' labels need none of their joints (on the pole, walking,
    in double support), so the legs and feet are labelled, trained, scored, exported; each arm is not
    calibrated, and every stage says it lacks its stateExt:o; the labels agree with iDynTree."""
    run, d = without_arms, without_arms["dirs"]
    exact = {s: sum(log.exact[s]["samples"] for log in run["labelled"]) for s in (*LEGS, "r_arm_ft")}
    assert all(exact[s] > 300 for s in LEGS) and exact["r_arm_ft"] == 0
    lacks = {log.exact["r_arm_ft"]["lacks"][0] for log in run["labelled"]}
    assert lacks == {"right_arm/stateExt:o"}
    for table in d["labelled"].glob("*.parquet"):  # the table's own record of it
        exact = read_table_metadata(table)["ftcal.label"]["exact"]
        assert exact["r_arm_ft"]["samples"] == 0 and exact["r_arm_ft"]["lacks"] == ["right_arm/stateExt:o"]
        # standing on the left sole, the left leg's free side is the upper body: then it needs the arms
        arms = {f"{a}/stateExt:o" for a in ARMS}
        assert exact["l_leg_ft"]["samples"] > 0 and set(exact["l_leg_ft"]["lacks"]) <= arms
    why = {"r_arm_ft": "right_arm/stateExt:o", "l_arm_ft": "left_arm/stateExt:o"}
    files = _metrics_files(run)
    assert set(files) == {"r_arm_ft/r_arm_ft", "l_arm_ft/l_arm_ft", *(f"legs/{s}" for s in LEGS)}
    for arm, stream in why.items():
        reason = f"no exact label (lacks {stream})"
        assert run["trained"][arm].metrics["not_calibrated"] == reason
        assert files[f"{arm}/{arm}"] == {"deployed": "not calibrated", "verdict": "not calibrated"}
        assert run["results"][arm].not_calibrated == reason and run["tested"][arm]["days"] == {}
        assert not list((d["exported"] / "groups" / arm).glob("*.onnx"))
    assert all(files[f"legs/{s}"]["rmse"] > 0 for s in LEGS)
    manifest = run["exported"].manifest
    assert list(manifest["graphs"]) == ["legs", "all"] and manifest["graphs"]["all"]["sensors"] == LEGS
    assert manifest["not_calibrated"] == {a: f"no exact label (lacks {s})" for a, s in why.items()}
    page = (d["reports"] / "index.html").read_text()
    line = page.split("<b>Not calibrated:</b> ", 1)[1].split("</summary>", 1)[0]
    assert sorted(line.split(", ")) == ["l_arm_ft", "r_arm_ft"], line
    assert "<b>r_arm_ft</b>: no exact label (lacks right_arm/stateExt:o)" in page
    for table in sorted(d["labelled"].glob("*.parquet")):
        assert relabel_with_idyntree(table, d["smoothed"] / table.name, "iCubGenova02", samples=150) < 1e-6


def test_a_run_without_one_legs_joints_leaves_that_leg_out_and_trains_the_rest(
    without_left_leg: dict[str, Any],
) -> None:
    """The left leg's joint stream absent: its leg and foot sensors never have an exact label (every path
    to them, or their free side, crosses its joints), so they are left out of the legs group, named with
    the stream; the right leg and foot train on the pole logs, the arms on every log."""
    run, d = without_left_leg, without_left_leg["dirs"]
    reason = "no exact label (lacks left_leg/stateExt:o)"
    legs = run["trained"]["legs"].metrics
    assert legs["sensors"] == ["r_leg_ft", "r_foot_ft"]
    assert legs["left_out"] == {"l_leg_ft": reason, "l_foot_ft": reason}
    files = _metrics_files(run)
    assert (
        files["legs/l_leg_ft"]
        == files["legs/l_foot_ft"]
        == {"deployed": "not calibrated", "verdict": "not calibrated"}
    )
    assert files["legs/r_leg_ft"]["rmse"] > 0 and files["legs/r_foot_ft"]["rmse"] > 0
    assert files["r_arm_ft/r_arm_ft"]["rmse"] > 0 and files["l_arm_ft/l_arm_ft"]["rmse"] > 0
    manifest = run["exported"].manifest
    assert manifest["graphs"]["all"]["sensors"] == ["r_arm_ft", "l_arm_ft", "r_leg_ft", "r_foot_ft"]
    assert manifest["not_calibrated"] == {"l_leg_ft": reason, "l_foot_ft": reason}
    page = (d["reports"] / "index.html").read_text()
    assert f"<b>legs/l_leg_ft</b>: {reason}" in page


def test_a_simulated_log_written_as_a_run_ingests_like_its_mcap(simulated, recorded_run) -> None:
    """The simulator's walking test log, ingested from its MCAP and from its dataDumper run: the same rows,
    joint positions and velocities within half a printed unit (1e-6 deg, deg/s), the same wrench flags and
    wrenches within the printed unit plus what 1.2 us of stamp rounding moves an interpolation by (the
    bound of tests/test_dumper.py); the run has no temperature or IMU (flagged)."""
    import numpy as np
    import pandas as pd

    from pipeline.logs import schema as S
    from pipeline.logs.logfiles import RobotLogSpec, ingest_one
    from pipeline.physics.robot import load_robot
    from tests.factories.dumper import HALF_PRINTED, STAMP_TOL_NS, interpolated_bound

    d, sim, params = recorded_run["dirs"], simulated["sim"], simulated["params"]
    robot = load_robot("iCubGenova02")
    spec = RobotLogSpec(recorded_run["cfg"], params.topics, robot.joint_names, list(robot.sensors), [])
    name = "02_walking_test"
    ref = pd.read_parquet(ingest_one(sim / f"{name}.mcap", sim.parent / "mcap", name, spec, None).output)
    got = pd.read_parquet(d["ingested"] / f"{name}.parquet")
    assert (
        len(got) == len(ref)
        and np.abs(got[S.STAMP].to_numpy() - ref[S.STAMP].to_numpy()).max() <= STAMP_TOL_NS
    )
    for j in robot.joint_names:
        for quantity in (S.Q, S.DQ_ENC):
            c = S.joint_col(quantity, j)
            np.testing.assert_allclose(
                got[c], ref[c], atol=HALF_PRINTED * np.pi / 180 + 1e-12, rtol=0, err_msg=c
            )
    for s in robot.sensors:
        np.testing.assert_array_equal(got[S.ok_col(S.WRENCH_STREAM, s)], ref[S.ok_col(S.WRENCH_STREAM, s)])
        for c in S.wrench_cols(S.FT, s):
            np.testing.assert_allclose(
                got[c], ref[c], atol=interpolated_bound(ref, c, HALF_PRINTED, 0.005), rtol=0, err_msg=c
            )
        assert not got[S.ok_col(S.TEMPERATURE_STREAM, s)].any() and not got[S.ok_col(S.IMU_STREAM, s)].any()


def test_recorded_logs_only_simulate_nothing_and_deployment_says_so(
    simulated: dict[str, Any], recorded_run: dict[str, Any], tmp_path, capfd: pytest.CaptureFixture[str]
) -> None:
    """With ingest.source on the recorded runs, the steps of stages `simulate` and `deploy_days` (as dvc.yaml
    runs them, `--if-ingested` the simulated data's folder) simulate nothing and never load the URDF (an
    absent file here), each printing one line; the prepared days pass the note on, and the group's
    deployment tests and page say there is nothing simulated to test on."""
    from pipeline.cli import main

    d, group, tested = recorded_run["dirs"], "legs", None
    data = yaml.safe_load((simulated["tmp"] / "params.yaml").read_text())
    data["ingest"]["source"] = str(d["raw"])
    recorded = tmp_path / "params.yaml"
    recorded.write_text(yaml.safe_dump(data, sort_keys=False))
    data["robot"]["urdf"] = str(tmp_path / "absent" / "robot.urdf")
    unloadable = tmp_path / "unloadable.yaml"
    unloadable.write_text(yaml.safe_dump(data, sort_keys=False))
    sim, days, tables = tmp_path / "sim", tmp_path / "days", tmp_path / "tables"
    steps = [
        ["simulate", str(sim), "--if-ingested", str(sim)],
        *(["simulate", str(days / v), "--deploy", v, "--quiet", "--if-ingested", str(sim)] for v in DAYS),
        *(["deploy-prepare", str(days / v), str(tables / v)] for v in DAYS),
    ]
    assert main([a for step in steps for a in ["+", *step, "--params", str(unloadable)]][1:]) == 0
    out, err = capfd.readouterr()
    note = f"nothing simulated: ingest.source is {d['raw']}, not {sim} (recorded logs only)"
    assert out.splitlines() == [
        f"simulate: {sim}: {note}",
        *(f"simulate: {days / v}: {note}" for v in DAYS),
        *(f"{tables / v}: {note}" for v in DAYS),
    ]
    assert not err
    for folder in (sim, *(days / v for v in DAYS)):
        assert [p.name for p in folder.iterdir()] == ["not_simulated.txt"]
    groups = tmp_path / "groups"
    for other in GROUPS:  # the page reads every group's tests
        exported = d["exported"] / "groups" / other
        run = deploy_test.run(
            load_params(recorded), other, d["models"] / other, exported, tables, groups / other
        )
        tested = run if other == group else tested
    assert tested["days"] == {} and tested["not_simulated"] == dict.fromkeys(DAYS, note)
    deployed = deploy_report.run(load_params(recorded), groups, tmp_path / "reports")
    assert deployed["nothing"].startswith(
        f"Nothing to test: there is nothing simulated to test on ({DAYS[1]}"
    )
    assert note in (tmp_path / "reports" / "deployment.html").read_text()


@pytest.mark.skipif(
    not REAL_RUN.is_dir(), reason=f"{REAL_RUN} is absent (../shared is beside developer checkouts)"
)
def test_the_real_2016_run_goes_through_dvc_repro_and_says_why_no_sensor_is_calibrated(
    tmp_path: Path,
) -> None:
    """The yoga run of ../shared (right foot on the floor; the left leg's and the arms' joint streams not
    kept) with its sidecar, as a lab sets it up (params: iCub 2.x, recorded logs only, wrench-only models):
    `dvc repro` runs every stage to the end, exit 0, no traceback, nothing simulated; the frozen board is
    flagged; no sensor has an exact label (each needs the left leg or an arm), and every stage names, per
    sensor, the streams it lacks; the export's graphs calibrate no sensor and its manifest says why."""
    import os
    import shutil
    import subprocess
    import sys

    import numpy as np
    import onnx
    import pandas as pd

    from pipeline.logs import schema as S

    raw = tmp_path / "data" / "raw"
    shutil.copytree(REAL_RUN / "icub", raw / "yoga" / "icub")
    side = {"type": "balancing", "robot": "iCubGenova02", "role": "train", "contacts": ["r_sole"]}
    (raw / "yoga.yaml").write_text(yaml.safe_dump({**side, "window": [14.34, 68.04]}))  # params.m
    data = repo_params()
    data["robot"]["urdf"] = "iCubGenova02"
    data["ingest"]["source"] = "data/raw"
    data["train"]["defaults"]["inputs"] = [6]
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    shutil.copy(REPO / "dvc.yaml", tmp_path / "dvc.yaml")  # and the code its stages depend on
    shutil.copytree(REPO / "pipeline", tmp_path / "pipeline", ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / data["deploy"]["real_logs"]).mkdir(parents=True)  # tracked, empty, in a checkout
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}",
    }
    dvc = [sys.executable, "-m", "dvc"]
    subprocess.run([*dvc, "init", "--no-scm", "-q"], cwd=tmp_path, env=env, check=True)
    proc = subprocess.run([*dvc, "repro"], cwd=tmp_path, env=env, capture_output=True, text=True)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "Traceback" not in out
    assert not list((tmp_path / "data" / "sim").glob("*.mcap"))  # recorded logs only: nothing simulated
    assert "frozen: yoga: r_leg_ft 11.9 s, 16.0% of samples" in out
    table = pd.read_parquet(tmp_path / "data" / "labelled" / "yoga.parquet")
    assert (~table[S.ok_col(S.WRENCH_STREAM, "r_leg_ft")]).mean() >= 0.16  # its frozen 16 % flagged
    assert not np.any([table[S.switch_col(s)].any() for s in S.sensors_of(table.columns)])
    lacks = {
        "l_leg_ft": "left_leg/stateExt:o",
        "l_foot_ft": "left_leg/stateExt:o",
        "r_leg_ft": "left_arm/stateExt:o, left_leg/stateExt:o, right_arm/stateExt:o",
        "r_foot_ft": "left_arm/stateExt:o, left_leg/stateExt:o, right_arm/stateExt:o",
        "l_arm_ft": "left_arm/stateExt:o",
        "r_arm_ft": "right_arm/stateExt:o",
    }
    line = next(x for x in out.splitlines() if x.startswith("labelled "))
    assert all(f"{s} 0 (lacks {streams})" in line for s, streams in lacks.items()), line
    for arm in ("l_arm_ft", "r_arm_ft"):
        assert f"{arm}: not calibrated: no exact label (lacks {lacks[arm]})" in out
    legs = next(x for x in out.splitlines() if x.startswith("legs: not calibrated: "))
    assert all(f"{s} lacks {lacks[s]}" in legs for s in LEGS), legs
    page = (tmp_path / "reports" / "index.html").read_text()
    assert "<b>Not calibrated:</b>" in page and "<b>legs</b>: " in page
    manifest = json.loads((tmp_path / "exported" / "manifest.json").read_text())
    assert manifest["graphs"] == {} and set(manifest["not_calibrated"]) == set(GROUPS)
    assert not list((tmp_path / "exported" / "groups").rglob("*.onnx"))
    # no C calibrator and no wholeBodyDynamics group, each saying why
    assert [p.name for p in (tmp_path / "exported" / "c").iterdir()] == ["not_calibrated.txt"]
    fragment = (tmp_path / "exported" / "wholebodydynamics.xml").read_text()
    assert fragment.startswith("<!-- ftcal: nothing calibrated: ") and "<group" not in fragment
    for dtype in ("float32", "float64"):  # the fused graph: no sensor, zero columns in and out
        graph = onnx.load(tmp_path / "exported" / f"all.{dtype}.onnx").graph
        assert [d.dim_value for d in graph.output[0].type.tensor_type.shape.dim][1:] == [0]
    for group in GROUPS:  # train's own line is a warning: the other groups go on
        assert f"ftcal: warning: {group}: not calibrated: no exact label" in out, group
    shown = subprocess.run([*dvc, "metrics", "show"], cwd=tmp_path, env=env, capture_output=True, text=True)
    lines = shown.stdout.splitlines()[1:]
    rows = {line.split()[0]: line for line in lines if line.startswith("reports/metrics/")}
    assert set(rows) == {f"reports/metrics/{g}/{g}.json" for g in GROUPS}, shown.stdout
    assert all(row.split()[1:] == ["not", "calibrated"] * 2 for row in rows.values()), shown.stdout
    assert max(map(len, shown.stdout.splitlines())) <= 160, shown.stdout  # a terminal's width
