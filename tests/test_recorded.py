"""The pipeline on recorded logs only: simulated iCub 2.x logs written as YARP dataDumper runs (no truth,
no temperature, no IMU: what a lab's archive holds) under the ingest source, one of them split by its
sidecar into two training segments and a test segment, then every stage through its own `run`: ingest ->
smooth -> label -> train (inputs: [6]) -> evaluate -> report -> export -> deploy_test. No test-segment
sample reaches training; the results are against the labels and say so; the labels of the recorded runs
agree with iDynTree's (1e-6 N/Nm); the deployment stage tests nothing on the simulated robot's logs and
says so."""

from __future__ import annotations

import json
from typing import Any

import pytest
import yaml

from pipeline.core.config import load_params, stage_section
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
from tests.relabel import relabel_with_idyntree

LOGS = [
    {"type": "pole", "duration_s": 20, "role": "train"},  # split by its sidecar's segments (below)
    {"type": "walking", "duration_s": 12, "role": "train"},
    {"type": "walking", "duration_s": 10, "role": "test"},
]
SEGMENTS = [  # s of the pole run: two training segments and a test one, 0.5 s apart (> 21 samples)
    {"start_s": 0.5, "end_s": 6.0, "role": "train"},
    {"start_s": 6.5, "end_s": 12.0, "role": "train"},
    {"start_s": 13.0, "end_s": 19.5, "role": "test"},
]
GROUP = "r_leg_ft"
DAYS = ("later", "drifted")  # the simulated deployment days


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    tmp = tmp_path_factory.mktemp("recorded")
    data = yaml.safe_load((REPO / "params.yaml").read_text())
    data["robot"]["urdf"] = "iCubGenova02"
    data["simulate"].update(logs=LOGS, workers=1, plots=False)
    data["simulate"]["motion"]["steps_per_direction"] = 2
    data["train"]["defaults"].update(hidden=16, epochs=2, n_trials=1, batch_size=256, search={}, inputs=[6])
    data["train"]["groups"] = {GROUP: {"sensor": GROUP}}
    data["deploy"]["real_logs"] = str(tmp / "nothing_here")
    (tmp / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    dumper = data["ingest"]["dumper"]
    d = {
        k: tmp / k
        for k in ("sim", "raw", "ingested", "smoothed", "labelled", "models", "reports", "exported")
    }
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'mlflow.db'}")
    try:
        params = load_params(tmp / "params.yaml")
        simulate.run(params, d["sim"], progress=False)
        for mcap in sorted(d["sim"].glob("*.mcap")):  # what a lab's dataDumper wrote, with its sidecar
            run = dumperfile.mcap_to_run(
                mcap, d["raw"] / mcap.stem, params.topics, dumper["ft_ports"], dumper["joints"]
            )
            if "pole" in mcap.stem:
                side = run.with_name(run.name + ".yaml")
                side.write_text(yaml.safe_dump({**yaml.safe_load(side.read_text()), "segments": SEGMENTS}))
        ingest.run(params, d["raw"], d["ingested"], progress=False)
        smooth.run(params, d["ingested"], d["smoothed"], progress=False)
        label.run(params, d["smoothed"], d["labelled"], truth_dir=d["ingested"], progress=False)
        trained = train.train_group(
            params, GROUP, d["labelled"], d["models"] / GROUP, tmp / "st", progress=False
        )
        result = evaluate.run(
            params, GROUP, d["models"] / GROUP, d["labelled"], d["reports"], d["ingested"], progress=False
        )
        report.run(params, d["reports"])
        exported = export.run(params, d["models"], d["reports"] / "metrics", d["labelled"], d["exported"])
        tables = tmp / "tables"
        deploy_prepare.run(params, d["sim"], tables / "later")  # a simulated day beside the recordings
        groups = d["reports"] / "deployment" / "groups"
        tested = deploy_test.run(
            params, GROUP, d["models"] / GROUP, d["exported"] / "groups" / GROUP, tables, groups / GROUP
        )
        deployed = deploy_report.run(params, groups, d["reports"])
    finally:
        patch.undo()
    cfg = stage_section(params, "ingest", ingest.IngestParams)
    return {
        "dirs": d,
        "trained": trained,
        "result": result,
        "exported": exported,
        "deployed": deployed,
        "tested": tested,
        "cfg": cfg,
    }


def test_no_test_segment_sample_is_used_in_training(recorded_run: dict[str, Any]) -> None:
    import pandas as pd

    from pipeline.calib.fit import prepare
    from pipeline.logs import schema as S

    d = recorded_run["dirs"]
    prep = prepare(load_params(d["sim"].parent / "params.yaml"), GROUP, d["labelled"])
    pole = [f"00_pole_train__seg{k}" for k in range(3)]
    assert sorted([*prep.split["train"], *prep.split["val"]]) == [*pole[:2], "01_walking_train"]
    assert prep.split["test"] == [pole[2], "02_walking_test"]
    stamps = pd.read_parquet(d["labelled"] / f"{pole[2]}.parquet", columns=[S.STAMP])[S.STAMP]
    lo, hi = int(stamps.min()), int(stamps.max())
    for part in (prep.train, prep.val, *(x for fold in prep.folds for x in fold)):
        assert len(part) and not ((part.stamp >= lo) & (part.stamp <= hi)).any()
    assert ((prep.test.stamp >= lo) & (prep.test.stamp <= hi)).sum() > 300
    trained_on = recorded_run["trained"].metrics["logs"]
    assert pole[2] not in [n for k in ("train", "val") for n in trained_on[k]]


def test_recorded_logs_train_and_results_say_they_have_no_truth(recorded_run: dict[str, Any]) -> None:
    d = recorded_run["dirs"]
    assert not list(d["ingested"].glob("*.truth.parquet"))
    metrics = json.loads((d["models"] / GROUP / "metrics.json").read_text())
    assert metrics["data"] == "recorded" and "nn6" in metrics["test"]
    (headline,) = (d["reports"] / "metrics" / GROUP).glob("*.json")
    shown = json.loads(headline.read_text())
    assert shown["truth"] == "none: recorded logs, errors against the labels only"
    assert shown["labels"]["raw"] > shown["labels"]["rec"] > 0
    page = (d["reports"] / "index.html").read_text()
    assert "<b>No truth:</b> the test logs are recordings" in page


def test_recorded_labels_agree_with_idyntree(recorded_run: dict[str, Any]) -> None:
    d = recorded_run["dirs"]
    for table in sorted(d["labelled"].glob("*.parquet")):
        assert relabel_with_idyntree(table, d["smoothed"] / table.name, "iCubGenova02", samples=150) < 1e-6


def test_wrench_only_export_and_nothing_to_deploy_on(recorded_run: dict[str, Any]) -> None:
    d = recorded_run["dirs"]
    manifest = json.loads((d["exported"] / "manifest.json").read_text())
    assert manifest["graphs"][GROUP]["input_shape"] == ["N", 6]
    assert recorded_run["tested"]["days"] == {} and recorded_run["tested"]["recorded"]
    assert recorded_run["deployed"]["summary"] == {}  # the simulated day was not tested
    assert json.loads((d["reports"] / "deployment.json").read_text()) == {"nothing_to_test": True}
    page = (d["reports"] / "deployment.html").read_text()
    assert "Nothing to test: the models (r_leg_ft) were trained on recorded logs" in page


def test_a_simulated_log_written_as_a_run_ingests_like_its_mcap(recorded_run: dict[str, Any]) -> None:
    """The simulator's walking test log, ingested from its MCAP and from its dataDumper run: the same rows,
    joint positions and velocities within half a printed unit (1e-6 deg, deg/s), the same wrench flags and
    wrenches within the printed unit plus what 1.2 us of stamp rounding moves an interpolation by (the
    bound of tests/test_dumper.py); the run has no temperature or IMU (flagged)."""
    import numpy as np
    import pandas as pd

    from pipeline.logs import schema as S
    from pipeline.physics.robot import load_robot
    from pipeline.stages.ingest import RobotLogSpec, ingest_one
    from tests.test_dumper import HALF_PRINTED, STAMP_TOL_NS, _bound

    d = recorded_run["dirs"]
    params = load_params(d["sim"].parent / "params.yaml")
    robot = load_robot("iCubGenova02")
    spec = RobotLogSpec(recorded_run["cfg"], params.topics, robot.joint_names, list(robot.sensors), [])
    name = "02_walking_test"
    ref = pd.read_parquet(
        ingest_one(d["sim"] / f"{name}.mcap", d["sim"].parent / "mcap", name, spec, None).output
    )
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
                got[c], ref[c], atol=_bound(ref, c, HALF_PRINTED, 0.005), rtol=0, err_msg=c
            )
        assert not got[S.ok_col(S.TEMPERATURE_STREAM, s)].any() and not got[S.ok_col(S.IMU_STREAM, s)].any()


def test_recorded_logs_only_simulate_nothing_and_deployment_says_so(
    recorded_run: dict[str, Any], tmp_path, capfd: pytest.CaptureFixture[str]
) -> None:
    """With ingest.source on the recorded runs, the steps of stages `simulate` and `deploy_days` (as dvc.yaml
    runs them, `--if-ingested` the simulated data's folder) simulate nothing and never load the URDF (an
    absent file here), each printing one line; the prepared days pass the note on, and the group's
    deployment tests and page say there is nothing simulated to test on."""
    from pipeline.cli import main

    d = recorded_run["dirs"]
    data = yaml.safe_load((d["sim"].parent / "params.yaml").read_text())
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
    exported = d["exported"] / "groups" / GROUP
    tested = deploy_test.run(
        load_params(recorded), GROUP, d["models"] / GROUP, exported, tables, groups / GROUP
    )
    assert tested["days"] == {} and tested["not_simulated"] == dict.fromkeys(DAYS, note)
    deployed = deploy_report.run(load_params(recorded), groups, tmp_path / "reports")
    assert deployed["nothing"].startswith(
        f"Nothing to test: there is nothing simulated to test on ({DAYS[1]}"
    )
    assert note in (tmp_path / "reports" / "deployment.html").read_text()
