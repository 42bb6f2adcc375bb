"""Steps `deploy_prepare`, `deploy_test` and `deploy_report` end to end: a short deployment day from
the real simulator (`ftcal simulate --deploy`), the real export of tiny trained models (nn13 for r_leg_ft,
the affine map for the r_foot pair), the stages through the CLI; their files, and their numbers against
independent references: Test A's flags against the params' rule, Test B's raw errors against the simulator's
own summary, Test C's push window against the push schedule of the params.

Known answers: the day's sensors have a linear hidden distortion (coupling, gains, offsets, noise; no
temperature terms, nonlinearity or hysteresis), so the exact calibration is an affine map, built from the
simulator's hidden truth (truth.json) and exported as the groups' model. That day passes, its Test B and C
ratios those of the exact inverse computed here with numpy (and the torque estimator on its wrenches); the
same day calibrated by the factory map (the raw model exported) fails, every ratio exactly 1.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.cli import main
from pipeline.core.config import load_params, stage_section
from pipeline.deploy import checks
from pipeline.deploy.prepare import read_day
from pipeline.evaluation.params import EvaluateParams
from pipeline.logs import schema as S
from tests.factories.labelled import FRONT, LEG, PAIR, REAR, TRAINED
from tests.factories.reports import write_recommended

pytestmark = pytest.mark.slow  # the deployment stages on trained groups

PUSH = {"force_n": 60.0, "duration_s": 0.8, "period_s": 2.0, "direction": [1.0, 0.3, 0.0]}
LOGS = [
    {"type": "poses", "duration_s": 9},  # on the pole, still 0-3 s and 4.5-7.5 s: the day's re-zeroing
    {"type": "standing", "duration_s": 10},  # Test A: quasi-static runs >= 1 s, 1 s from the ends
    {"type": "walking", "duration_s": 6},
    {"type": "pole", "duration_s": 5},
    {"type": "interaction", "duration_s": 12},  # Test D: pushes at every site, then a load in each hand
]
INTERACTION = {  # short: 1 s, 8 sites x 2 directions x 0.5 s, then 2 hands x (1 s + 0.5 s): 11.5 s
    "force_n": [10.0, 40.0],
    "duration_s": 0.3,
    "period_s": 0.5,
    "directions": [[1, 0, 0], [0, 1, 0]],
    "sites": {},
    "load_kg": 2.0,
    "load_s": 1.0,
}
DEPLOYED = {LEG: "nn13", PAIR: "affine"}
REZERO = {"duration_s": 2.0, "min_s": 1.5, "still_joint_rad_s": 0.02, "still_gyro_rad_s": 0.05,
          "prior_force_n": 10.0, "prior_torque_nm": 0.5, "pose_limit": 2.0, "label_mass_rel": 0.01,
          "label_com_m": 0.003, "significance": 2.0}  # fmt: skip
LINEAR = {  # the hidden distortion without its temperature terms, nonlinearity and hysteresis
    "temperature_gain": 0.0,
    "offset_drift_force": 0.0,
    "offset_drift_torque": 0.0,
    "nonlinearity": 0.0,
    "hysteresis": 0.0,
}


def _exact_affine(distortion: dict[str, Any]) -> dict[str, Any]:
    """The affine model (baselines.json's form, inputs unnormalised) inverting raw = C w + o exactly:
    w = raw + (C^-1 - I) raw - C^-1 o, temperature unused."""
    c_inv = np.linalg.inv(np.asarray(distortion["coupling"]))
    weights = np.zeros((6, 8))
    weights[:, 0] = -c_inv @ np.asarray(distortion["offset"])
    weights[:, 1:7] = c_inv - np.eye(6)
    return {"weights": weights, "offset": np.zeros(7), "scale": np.ones(7)}


def _exact_models(models: Path, out: Path, truth: dict[str, Any]) -> Path:
    """A copy of the trained groups whose affine map is the exact inverse of the day's distortions."""
    shutil.copytree(models, out)
    for group in (LEG, PAIR):
        sensors = json.loads((out / group / "metrics.json").read_text())["sensors"]
        baselines = json.loads((out / group / "baselines.json").read_text())
        exact = [_exact_affine(truth["distortions"][s]) for s in sensors]
        for key in ("weights", "offset", "scale"):
            baselines["affine"][key] = np.stack([e[key] for e in exact]).tolist()
        (out / group / "baselines.json").write_text(json.dumps(baselines))
    return out


def _deploy(root: Path, params: Path, models: Path, exported: Path, tables: Path, reports: Path) -> None:
    for group in (LEG, PAIR):
        args = [group, str(models / group), str(exported / "groups" / group), str(tables)]
        args.append(str(reports / "deployment" / "groups" / group))
        assert main(["deploy-test", *args, "--params", str(params)]) == 0
    args = [str(reports / "deployment" / "groups"), str(reports), "--params", str(params)]
    assert main(["deploy-report", *args]) == 0


FIGURES = ("interaction", "scales", "steps", "walking")  # a group's figures of a day


def _same_slopes(a: list[float | None], b: list[float | None], **tolerance: float) -> bool:
    """Slopes agree axis by axis: None (an axis the pushes did not move) on the same axes, numbers close."""
    assert len(a) == len(b) == 6
    pairs = [(x, y) for x, y in zip(a, b, strict=True) if x is not None and y is not None]
    close = [x == pytest.approx(y, **tolerance) for x, y in pairs]
    return [x is None for x in a] == [y is None for y in b] and all(close)


@pytest.fixture(scope="module")
def stage(trained_models: dict, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The deployment day simulated and prepared; the stages run once on each of three exports: the trained
    models, the exact calibration, the factory one (raw) (throwaway MLflow store)."""
    root = tmp_path_factory.mktemp("deploy")
    data = yaml.safe_load(Path(trained_models["params"]).read_text())
    data["simulate"]["workers"] = 1
    data["simulate"]["sensors"].update(LINEAR)
    (root / "real").mkdir()  # deploy.real_logs: a folder without logs yet
    data["deploy"].update(logs=LOGS, push=PUSH, interaction=INTERACTION, real_logs=str(root / "real"))
    data["deploy"]["rezero"] = REZERO
    data["simulate"]["motion"].update(pose_hold_s=3.0, pose_move_s=1.5)
    params = root / "params.yaml"
    params.write_text(yaml.safe_dump(data, sort_keys=False))
    day, tables = root / "later", root / "tables"
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")  # the export registers here
    out: dict[str, Any] = {"params": params, "day": day, "root": root, "models": trained_models["models"]}
    try:
        assert main(["simulate", str(day), "--deploy", "later", "--quiet", "--params", str(params)]) == 0
        for name, logs in (("later", day), ("real", root / "real")):
            assert main(["deploy-prepare", str(logs), str(tables / name), "--params", str(params)]) == 0
        truth = json.loads((day / "truth.json").read_text())
        exact = _exact_models(trained_models["models"], root / "exact_models", truth)
        variants = {
            "trained": (trained_models["models"], DEPLOYED),
            "exact": (exact, {LEG: "affine", PAIR: "affine"}),
        }
        variants["raw"] = (trained_models["models"], {LEG: "raw", PAIR: "raw"})
        for name, (models, deployed) in variants.items():
            exported, reports = root / f"exported_{name}", root / f"reports_{name}"
            data["export"]["models"] = deployed if name != "trained" else {}
            variant_params = root / f"params_{name}.yaml"
            variant_params.write_text(yaml.safe_dump(data, sort_keys=False))
            args = [
                str(models),
                str(write_recommended(root, DEPLOYED)),
                str(trained_models["labelled"]),
                str(exported),
            ]
            assert main(["export", *args, "--params", str(variant_params)]) == 0
            _deploy(root, variant_params, models, exported, tables, reports)
            out[name] = json.loads((reports / "deployment" / "details.json").read_text())
            out[f"{name}_reports"] = reports
    finally:
        patch.undo()
    out["truth"], out["tables"] = truth, tables
    return out


def test_stages_write_pages_metrics_details_and_figures(stage: dict[str, Any]) -> None:
    reports = stage["trained_reports"]
    page = (reports / "deployment.html").read_text()
    assert page.count("<h2 id='later'>later</h2>") == 1 and "real" not in json.loads(
        (reports / "deployment.json").read_text()
    )
    headline = json.loads((reports / "deployment.json").read_text())
    assert set(headline) == {"later"} and isinstance(headline["later"]["fit"], bool)
    # every group's figures of the day, as delivered and re-zeroed; the leg sensor's also its joint's torque
    figures = [f"later_{when}{what}.png" for when in ("", "rezeroed_") for what in FIGURES]
    groups = reports / "deployment" / "groups"
    hip = ["later_hip_pitch.png", "later_rezeroed_hip_pitch.png"]
    assert sorted(p.name for p in (groups / LEG).iterdir()) == sorted([*figures, *hip, "result.json"])
    assert sorted(p.name for p in (groups / PAIR).iterdir()) == sorted([*figures, "result.json"])
    for src in (
        "deployment/groups/r_leg_ft/later_walking.png",
        "deployment/groups/r_leg_ft/later_hip_pitch.png",
        "deployment/groups/r_leg_ft/later_steps.png",
    ):
        assert f'src="{src}"' in page and (reports / src).is_file()
    later = stage["trained"]["details"]["later"]
    assert later["logs"] == [
        "00_poses_test", "01_standing_test", "02_walking_test", "03_pole_test", "04_interaction_test"
    ]  # fmt: skip
    assert {"test_a", "test_b", "test_c", "test_d"} <= set(later)
    assert "Test D: interaction fidelity" in page
    assert read_day(stage["tables"] / "real") == []  # a recorded-logs folder without logs: nothing tested


def _verdicts(result: Any, path: str = "") -> dict[str, Any]:
    """Every flag and string (exact) and number of a deployment result, by its path in the result."""
    if isinstance(result, dict):
        return {k: v for key, item in result.items() for k, v in _verdicts(item, f"{path}.{key}").items()}
    if isinstance(result, list):
        return {k: v for j, item in enumerate(result) for k, v in _verdicts(item, f"{path}[{j}]").items()}
    return {
        path: float(result) if isinstance(result, int | float) and not isinstance(result, bool) else result
    }


def test_the_deployment_tests_judge_the_c_calibrator_alike(stage: dict[str, Any], tmp_path: Path) -> None:
    """Tests A-D of the trained export, as delivered and re-zeroed, run through its generated C calibrators
    (`--runtime c`, compiled with the system's cc): the same verdicts, and every figure within 2 %."""
    from pipeline.export.cbuild import compiler

    if compiler() is None:
        pytest.skip("no C compiler (cc) to build the C calibrator")
    root, reports = stage["root"], tmp_path / "reports"
    exported, params = root / "exported_trained", root / "params_trained.yaml"
    for group in (LEG, PAIR):
        args = [group, str(stage["models"] / group), str(exported / "groups" / group), str(stage["tables"])]
        args.append(str(reports / group))
        assert main(["deploy-test", *args, "--runtime", "c", "--params", str(params)]) == 0
        ours = _verdicts(json.loads((reports / group / "result.json").read_text()))
        theirs = _verdicts(
            json.loads(
                (stage["trained_reports"] / "deployment" / "groups" / group / "result.json").read_text()
            )
        )
        assert ours.keys() == theirs.keys()
        exact = {k: v for k, v in theirs.items() if not isinstance(v, float)}
        assert exact and {k: ours[k] for k in exact} == exact
        assert any(k.endswith("pass") for k in exact), sorted(exact)[:5]
        near = {
            k: (ours[k], v)
            for k, v in theirs.items()
            if isinstance(v, float) and abs(ours[k] - v) > 0.02 * abs(v) + 1e-3
        }
        assert not near, near


def test_pages_share_one_look_and_link_each_other(stage: dict[str, Any], tmp_path: Path) -> None:
    """The deployment page has the report page's stylesheet and frame, and each links to the other."""
    from pipeline.evaluation.html import CSS
    from pipeline.evaluation.page import render_html

    deployment = (stage["trained_reports"] / "deployment.html").read_text()
    assert f"<style>{CSS}</style>" in deployment and "href='index.html'" in deployment
    assert '<table class="num">' in deployment and "<nav>" in deployment
    index = render_html([], stage_section(load_params(stage["params"]), "evaluate", EvaluateParams), {
        "overview": "o.png", "noise": "n.png"})  # fmt: skip
    assert f"<style>{CSS}</style>" in index and "href='deployment.html'" in index


def test_a_flags_exactly_the_models_above_the_params_limit(stage: dict[str, Any]) -> None:
    """Every trained model of each exported group is tested; a model is flagged iff its worst-axis ratio
    exceeds noise_threshold x (1 + noise_margin) as params.yaml states it; deployed: the export's."""
    raw = yaml.safe_load(stage["params"].read_text())["evaluate"]
    limit = raw["noise_threshold"] * (1.0 + raw["noise_margin"])
    test_a = stage["trained"]["details"]["later"]["test_a"]
    assert set(test_a) == set(DEPLOYED)
    for group, entry in test_a.items():
        assert entry["deployed"] == DEPLOYED[group] and entry["quasi_static_s"] > 1.0
        assert set(entry["models"]) == set(TRAINED)
        for model, r in entry["models"].items():
            assert math.isfinite(r["worst"]) and r["worst"] == max(r["ratio_axes"]), (group, model)
            assert r["flagged"] == (r["worst"] > limit), (group, model, r["worst"], limit)


def test_a_margin_keeps_a_model_just_above_the_threshold(stage: dict[str, Any]) -> None:
    """Between threshold and limit a model is not flagged (evaluate's rule): the threshold placed just below
    one model's measured ratio and the limit between it and the next, whatever the ratios are."""
    params = load_params(stage["params"])
    (log,) = [g for g in read_day(stage["tables"] / "later") if g.name == "01_standing_test"]
    cfg = stage_section(params, "evaluate", EvaluateParams)
    measured = stage["trained"]["details"]["later"]["test_a"][LEG]["models"]
    ratios = sorted((r["worst"], m) for m, r in measured.items())
    k = max(range(len(ratios) - 1), key=lambda i: ratios[i + 1][0] / ratios[i][0])  # the widest gap
    (low, between), (high, above) = ratios[k], ratios[k + 1]
    assert high > low * 1.01, ratios
    threshold = low * 0.99
    margin = (low + high) / 2.0 / threshold - 1.0
    narrow = dataclasses.replace(cfg, noise_threshold=threshold, noise_margin=margin)
    result = checks.standing_noise(log, stage["models"] / LEG, narrow, DEPLOYED[LEG])["models"]
    assert {m: r["worst"] for m, r in result.items()} == pytest.approx(
        {m: r["worst"] for m, r in measured.items()}
    )
    flags = {m: r["flagged"] for m, r in result.items()}
    assert not flags[between] and flags[above]
    assert flags == {m: w > (low + high) / 2.0 for w, m in ratios}


def test_b_raw_errors_match_the_simulators_summary(stage: dict[str, Any]) -> None:
    """Test B's raw RMSE against truth (6 axes pooled, at the joint-state stamps after ingest) agrees with
    the simulator's own raw RMSE of the walking log (force and torque, at the FT board's samples)."""
    test_b = stage["trained"]["details"]["later"]["test_b"]
    assert set(test_b) == {LEG, FRONT, REAR, PAIR}
    summary = json.loads((stage["day"] / "summary.json").read_text())
    (walk,) = [log for log in summary["logs"] if log["name"] == "02_walking_test"]
    for name in (LEG, FRONT, REAR):
        sim = walk["raw_rmse"][name]
        pooled = math.sqrt((sim["force"] ** 2 + sim["torque"] ** 2) / 2.0)
        assert test_b[name]["truth"]["raw"]["rmse"] == pytest.approx(pooled, rel=0.02), name
        calibrated = test_b[name]["truth"]["calibrated"]["rmse"]
        assert test_b[name]["ratio_truth"] == pytest.approx(test_b[name]["truth"]["raw"]["rmse"] / calibrated)


def test_c_uses_the_push_window_of_the_params(stage: dict[str, Any]) -> None:
    """Only the calibrated leg sensor is tested; its window holds the pushes' samples: pushes start at
    (k + 1/2) period and last duration_s, so a 5 s log at 100 Hz has 2 pushes of 80 samples."""
    later = stage["trained"]["details"]["later"]
    (sensor,) = later["test_c"]
    assert sensor == LEG
    entry = later["test_c"][LEG]
    starts = [(k + 0.5) * PUSH["period_s"] for k in range(10)]
    n_pushes = sum(t + PUSH["duration_s"] <= LOGS[3]["duration_s"] for t in starts)
    assert n_pushes == 2
    expected = n_pushes * PUSH["duration_s"] * 100
    assert expected - 3 <= entry["samples_pushed"] <= expected + 1
    joints = ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")
    assert list(entry["joints"]) == [f"r_{j}" for j in joints]
    for v in entry["joints"].values():
        assert v["raw"]["max"] >= v["raw"]["rmse"] > 0 and np.isfinite(v["calibrated"]["max"])
        assert v["ratio_max"] == pytest.approx(v["raw"]["max"] / v["calibrated"]["max"])
        assert v["ratio_rmse"] == pytest.approx(v["raw"]["rmse"] / v["calibrated"]["rmse"])
    summary = stage["trained"]["summary"]["later"]
    assert "c.r_hip_pitch.ratio" in summary and not any(k.startswith("c.l_") for k in summary)
    # the verdict's Test C ratio is the RMSE ratio of the hip pitch joint (the max one is reported)
    assert summary["c.r_hip_pitch.ratio"] == entry["joints"]["r_hip_pitch"]["ratio_rmse"]
    assert summary["c.r_hip_pitch.ratio_max"] == entry["joints"]["r_hip_pitch"]["ratio_max"]


# --- known answers: the exact calibration passes, the factory one fails ----------------------------


def _exact_wrenches(
    stage: dict[str, Any], log: str
) -> tuple[pd.DataFrame, pd.DataFrame, dict[str, np.ndarray]]:
    """(labelled table, truth table, sensor -> the exact inverse of the distortion applied to the raw wrench
    of the table (N, 6)), computed with numpy from truth.json."""
    (day_log,) = [g for g in read_day(stage["tables"] / "later") if g.name == log]
    table, truth = pd.read_parquet(day_log.labelled), pd.read_parquet(day_log.truth)
    exact = {}
    for s in (LEG, FRONT, REAR):
        d = stage["truth"]["distortions"][s]
        raw = table[S.wrench_cols(S.FT, s)].to_numpy()
        exact[s] = (raw - np.asarray(d["offset"])) @ np.linalg.inv(np.asarray(d["coupling"])).T
    return table, truth, exact


def _rmse(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    return float(np.sqrt(np.mean((a[ok] - b[ok]) ** 2)))


def test_exact_calibration_passes_with_its_expected_ratios(stage: dict[str, Any]) -> None:
    later = stage["exact"]["details"]["later"]
    table, truth, exact = _exact_wrenches(stage, "02_walking_test")
    for s in (LEG, FRONT, REAR):
        true = truth[S.wrench_cols(S.TRUE, s)].to_numpy()
        raw = table[S.wrench_cols(S.FT, s)].to_numpy()
        b = later["test_b"][s]["truth"]
        assert b["raw"]["rmse"] == pytest.approx(_rmse(raw, true), rel=1e-3)
        assert b["calibrated"]["rmse"] == pytest.approx(_rmse(exact[s], true), rel=1e-2), s
        assert b["calibrated"]["rmse"] < 1.0 < 20.0 < b["raw"]["rmse"]  # the noise only, against the offsets
    # Test C: the torques from the exact wrench, by the estimator on the same states, during the pushes
    from pipeline.deploy.params import deploy_params
    from pipeline.deploy.prepare import load_nominal_robot
    from pipeline.physics.torques import limb_joints, sensor_joint_torques
    from pipeline.sim.push import push_profile

    params = load_params(stage["params"])
    robot, dp = load_nominal_robot(params), deploy_params(params)
    table, _, exact = _exact_wrenches(stage, "03_pole_test")
    (day_log,) = [g for g in read_day(stage["tables"] / "later") if g.name == "03_pole_test"]
    smooth = pd.read_parquet(day_log.smoothed)
    q, dq, ddq = (smooth[S.joint_cols(k, robot.joint_names)].to_numpy() for k in (S.QS, S.DQS, S.DDQS))
    joints = limb_joints(robot, "r_sole")
    true = checks.read_true_torques(
        day_log, params.topics.sim_joint_torques, table[S.STAMP].to_numpy(), joints
    )
    pushed = push_profile(table[S.TIME].to_numpy(), dp.push, len(dp.torque_limbs))[1] >= 0
    gravity = [0.0, 0.0, -params.robot.gravity]
    fixed = str(table[S.FIXED_LINK].iloc[0])
    tau = sensor_joint_torques(robot, LEG, joints, q, dq, ddq, exact[LEG], fixed, gravity)
    hip = joints.index("r_hip_pitch")
    expected = _rmse(tau[pushed][:, [hip]], true[pushed][:, [hip]])
    c = later["test_c"][LEG]["joints"]["r_hip_pitch"]
    assert c["calibrated"]["rmse"] == pytest.approx(expected, rel=1e-2)
    summary = stage["exact"]["summary"]["later"]
    assert summary["c.r_hip_pitch.ratio"] == pytest.approx(c["raw"]["rmse"] / expected, rel=1e-2)
    assert summary["c.r_hip_pitch.ratio"] >= dp.torque_target
    # Test D: the exact inverse of a distortion without hysteresis is the oracle: the same slopes (to the
    # float32 export run causally at the FT stamps, the oracle aligned from them)
    for sensor, d in later["test_d"].items():
        pushes = d["pushes"]
        assert _same_slopes(pushes["calibrated"]["slopes"], pushes["oracle"]["slopes"], abs=1e-3), sensor
        assert d["verdict"]["pass"] and d["verdict"]["change_ratio"] == pytest.approx(1.0, abs=0.01)
    assert set(later["test_d"]) == {LEG, FRONT, REAR}  # every pushed sensor of the exported groups
    # Test D from the noise level up: the same, pushes of every scale through the day's distortions
    for sensor, e in later["test_d_scales"].items():
        for row in e["force"].values():
            for s, o in zip(row["deployed"]["slopes"], row["oracle"]["slopes"], strict=True):
                assert (s is None) == (o is None) and (s is None or s == pytest.approx(o, abs=1e-3)), sensor
        assert e["verdict"]["pass"], sensor
    assert set(later["test_d_scales"]) == {LEG, FRONT, REAR}
    assert all(summary[k] for k in ("a.passed", "b.passed", "c.passed", "d.passed", "fit_to_deploy"))
    assert json.loads((stage["exact_reports"] / "deployment.json").read_text())["later"]["fit"] is True


def test_factory_calibration_fails_with_every_ratio_one(stage: dict[str, Any]) -> None:
    later, summary = stage["raw"]["details"]["later"], stage["raw"]["summary"]["later"]
    assert {later["test_a"][g]["deployed"] for g in (LEG, PAIR)} == {"raw"}
    for name in (LEG, FRONT, REAR, PAIR):
        assert later["test_b"][name]["ratio_truth"] == pytest.approx(1.0, abs=1e-9), name
    for v in later["test_c"][LEG]["joints"].values():
        assert v["ratio_rmse"] == pytest.approx(1.0, abs=1e-9)
    assert summary["a.passed"] and not summary["b.passed"] and not summary["c.passed"]
    # Test D: the factory map reports a push with its own gain and coupling errors, the day's drifted
    # offsets aside (a change): slopes near 1, and a reading whose error is the offsets'
    for d in later["test_d"].values():
        # the same numbers up to the last bit (the export's output is interpolated to the table's stamps)
        assert _same_slopes(d["pushes"]["calibrated"]["slopes"], d["pushes"]["raw"]["slopes"], rel=1e-12)
        assert d["pushes"]["calibrated"]["rmse_force"] > 10 * d["pushes"]["oracle"]["rmse_force"]
    assert summary["fit_to_deploy"] is False
    assert json.loads((stage["raw_reports"] / "deployment.json").read_text())["later"]["fit"] is False


def test_each_test_decides_the_verdict() -> None:
    """The day fails when any one test fails: a flagged or unmeasured deployed model (A), a Test B ratio
    below evaluate.target_raw_over_nn7, a Test C ratio of the judged joint below deploy.torque_target, a
    sensor failing Test D."""
    from pipeline.deploy.verdict import summarize

    dp = type("DP", (), {"torque_target": 5.0})()
    model = {"worst": 1.2, "flagged": False, "ratio_axes": []}
    passing = {
        "test_a": {LEG: {"deployed": "nn7", "models": {"nn7": model}}},
        "test_b": {LEG: {"truth": {"raw": {"rmse": 20.0}, "calibrated": {"rmse": 1.0}}, "ratio_truth": 20.0}},
        "test_c": {LEG: {"joints": {"r_hip_pitch": {"raw": {"rmse": 6.0}, "calibrated": {"rmse": 1.0},
                                                    "ratio_rmse": 6.0, "ratio_max": 2.0}}}},
        "test_d": {LEG: {"verdict": {"pass": True, "worst_slope_excess": 0.02, "change_ratio": 1.1}}},
    }  # fmt: skip
    assert summarize(passing, dp, 10.0, "hip_pitch")["fit_to_deploy"] is True
    failing = {
        "a": {**model, "flagged": True},
        "unmeasured": {**model, "worst": float("nan")},
        "b": 9.0,
        "c": 4.0,
        "d": False,
    }
    for case, value in failing.items():
        result = json.loads(json.dumps(passing))
        if case in ("a", "unmeasured"):
            result["test_a"][LEG]["models"]["nn7"] = value
        elif case == "b":
            result["test_b"][LEG]["ratio_truth"] = value
        elif case == "d":
            result["test_d"][LEG]["verdict"]["pass"] = value
        else:
            result["test_c"][LEG]["joints"]["r_hip_pitch"]["ratio_rmse"] = value
        s = summarize(result, dp, 10.0, "hip_pitch")
        assert s["fit_to_deploy"] is False and not s[f"{case[0] if case != 'unmeasured' else 'a'}.passed"], (
            case
        )


# --- after re-zeroing from the day's first still seconds ----------------------------------------


def _first_still(stage: dict[str, Any], group: str, variant: str) -> tuple[dict[str, Any], pd.DataFrame]:
    """(the group's re-zeroing on the day, the labelled rows of its stretch)."""
    result = json.loads(
        (stage[f"{variant}_reports"] / "deployment" / "groups" / group / "result.json").read_text()
    )
    rezero = result["rezeroed"]["later"]["rezero"]
    (stretch,) = rezero["stretches"]
    assert stretch["log"] == "00_poses_test" and stretch["seconds"] == pytest.approx(
        REZERO["duration_s"], abs=0.02
    )
    (day_log,) = [g for g in read_day(stage["tables"] / "later") if g.name == stretch["log"]]
    return rezero, pd.read_parquet(day_log.labelled).iloc[stretch["start"] : stretch["stop"]]


def test_rezeroed_factory_map_removes_the_mean_reading_minus_label(stage: dict[str, Any]) -> None:
    """The factory map re-zeroed from the robot still on the pole: each offset is the stretch's mean raw
    minus exact label (numpy), and the day's Test B ratios, 1 as delivered, rise above it."""
    for group, sensors in ((LEG, [LEG]), (PAIR, [FRONT, REAR])):
        rezero, rows = _first_still(stage, group, "raw")
        for s in sensors:
            expected = (
                rows[S.wrench_cols(S.FT, s)].to_numpy() - rows[S.wrench_cols(S.EXPECTED, s)].to_numpy()
            ).mean(0)
            np.testing.assert_allclose(rezero["sensors"][s]["estimate"], expected, rtol=0, atol=1e-5)
            assert rezero["sensors"][s]["status"] == "all"
            # the factory map's offsets (tens of N, Nm) are far beyond the labels' error: applied in full
            beyond = np.abs(expected) > 2.0 * np.asarray(rezero["sensors"][s]["threshold"])
            assert beyond[:3].all()
            estimate = np.asarray(rezero["sensors"][s]["estimate"])
            np.testing.assert_array_equal(np.asarray(rezero["offsets"][s])[beyond], estimate[beyond])
    after = json.loads((stage["raw_reports"] / "deployment" / "details.json").read_text())["rezeroed"][
        "later"
    ]
    for name in (LEG, FRONT, REAR, PAIR):
        assert after["details"]["test_b"][name]["ratio_truth"] > 3.0, name
    metrics = json.loads((stage["raw_reports"] / "deployment.json").read_text())["later"]
    assert metrics["fit"] is False and metrics["rezeroed"]["b_min"] > 3.0 * metrics["b_min"]


def test_rezeroed_exact_affine_map_solves_its_linear_equation(stage: dict[str, Any]) -> None:
    """The exact affine inverse w = C^-1 (x - o): re-zeroed, C^-1 (raw - delta - o) = label on average, so
    delta = mean(raw - C label) - o (numpy, truth.json): the labels' own model error, under a newton. The
    offset did not move: what is applied of that estimate is what exceeds its threshold only."""
    rezero, rows = _first_still(stage, LEG, "exact")
    d = stage["truth"]["distortions"][LEG]
    raw, label = rows[S.wrench_cols(S.FT, LEG)].to_numpy(), rows[S.wrench_cols(S.EXPECTED, LEG)].to_numpy()
    expected = (raw - label @ np.asarray(d["coupling"]).T).mean(0) - np.asarray(d["offset"])
    entry = rezero["sensors"][LEG]
    np.testing.assert_allclose(entry["estimate"], expected, rtol=0, atol=1e-5)
    assert np.abs(expected[:3]).max() < 1.5
    within = np.abs(expected) <= np.asarray(entry["threshold"])
    assert np.all(np.asarray(rezero["offsets"][LEG])[within] == 0.0)
    page = (stage["exact_reports"] / "deployment.html").read_text()
    assert "<h2 id='later-rezeroed'>later, re-zeroed</h2>" in page and "re-zeroed from 00_poses_test" in page


def test_b_gives_the_wholebodydynamics_affine_map_beside_the_deployed_model(stage: dict[str, Any]) -> None:
    """Test B scores the group's affine map (what wholeBodyDynamics runs from the export's configuration)
    on the same walking samples; with the affine map deployed (the exact export) both columns agree."""
    for name in ("trained", "exact"):
        result = json.loads(
            (stage[f"{name}_reports"] / "deployment" / "groups" / LEG / "result.json").read_text()
        )
        for b in (result["days"]["later"]["test_b"][LEG], result["rezeroed"]["later"]["test_b"][LEG]):
            assert b["fallback"]["truth"]["rmse"] > 0 and b["fallback"]["labels"]["samples"] > 100
        if name == "exact":  # the affine map deployed: its fallback is itself, run causally or on the table
            calibrated, fallback = b["truth"]["calibrated"]["rmse"], b["fallback"]["truth"]["rmse"]
            assert abs(calibrated - fallback) < 0.02 * calibrated, (calibrated, fallback)
    page = (stage["trained_reports"] / "deployment.html").read_text()
    assert "wholeBodyDynamics affine" in page
