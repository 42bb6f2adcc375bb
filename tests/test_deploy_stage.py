"""Stage `deploy_test` end to end: a short deployment day from the real simulator (`ftcal simulate --deploy`),
the real export of tiny trained models (nn13 for r_leg_ft, the affine map for the r_foot pair), the stage
through the CLI; its files, and its numbers against independent references: Test A's flags against the
params' rule, Test B's raw errors against the simulator's own summary, Test C's push window against the
push schedule of the params."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from pipeline.cli import main
from pipeline.core.config import load_params, stage_section
from pipeline.deploy import checks
from pipeline.deploy.prepare import load_nominal_robot, prepare_logs
from pipeline.evaluation.params import EvaluateParams
from tests.test_export import _report
from tests.test_train import LEG, PAIR

PUSH = {"force_n": 60.0, "duration_s": 0.8, "period_s": 2.0, "direction": [1.0, 0.3, 0.0]}
LOGS = [
    {"type": "standing", "duration_s": 10},  # Test A: quasi-static runs >= 1 s, 1 s from the ends
    {"type": "walking", "duration_s": 6},
    {"type": "pole", "duration_s": 5},
]
DEPLOYED = {LEG: "nn13", PAIR: "affine"}


@pytest.fixture(scope="module")
def stage(trained_models: dict, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The deployment day simulated, the export, and the stage run once (throwaway MLflow store)."""
    root = tmp_path_factory.mktemp("deploy")
    data = yaml.safe_load(Path(trained_models["params"]).read_text())
    data["simulate"]["workers"] = 1
    data["deploy"].update(logs=LOGS, push=PUSH, real_logs=str(root / "no_real_logs"))
    params = root / "params.yaml"
    params.write_text(yaml.safe_dump(data, sort_keys=False))
    day, exported, reports = root / "later", root / "exported", root / "reports"
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")  # the export registers here
    try:
        assert main(["simulate", str(day), "--deploy", "later", "--quiet", "--params", str(params)]) == 0
        metrics = _report(root, DEPLOYED)
        args = [str(trained_models["models"]), str(metrics), str(trained_models["labelled"]), str(exported)]
        assert main(["export", *args, "--params", str(params)]) == 0
        args = [str(trained_models["models"]), str(exported), str(reports), "--later", str(day)]
        assert main(["deploy-test", *args, "--params", str(params)]) == 0
    finally:
        patch.undo()
    details = json.loads((reports / "deployment" / "details.json").read_text())
    models = trained_models["models"]
    return {
        "params": params,
        "day": day,
        "reports": reports,
        "details": details,
        "root": root,
        "models": models,
    }


def test_stage_writes_page_metrics_details_and_figures(stage: dict[str, Any]) -> None:
    reports = stage["reports"]
    assert (reports / "deployment.html").read_text().count("<h2>later</h2>") == 1
    headline = json.loads((reports / "deployment.json").read_text())
    assert set(headline) == {"later"} and isinstance(headline["later"]["fit"], bool)
    assert sorted(p.name for p in (reports / "deployment").iterdir()) == [
        "details.json",
        "later_hip_pitch.png",
        "later_walking.png",
    ]
    later = stage["details"]["details"]["later"]
    assert later["logs"] == ["00_standing_test", "01_walking_test", "02_pole_test"]
    assert {"test_a", "test_b", "test_c"} <= set(later)


def test_a_flags_exactly_the_models_above_the_params_limit(stage: dict[str, Any]) -> None:
    """Every trained model of each exported group is tested; a model is flagged iff its worst-axis ratio
    exceeds noise_threshold x (1 + noise_margin) as params.yaml states it; deployed: the export's."""
    raw = yaml.safe_load(stage["params"].read_text())["evaluate"]
    limit = raw["noise_threshold"] * (1.0 + raw["noise_margin"])
    test_a = stage["details"]["details"]["later"]["test_a"]
    assert set(test_a) == set(DEPLOYED)
    for group, entry in test_a.items():
        assert entry["deployed"] == DEPLOYED[group] and entry["quasi_static_s"] > 1.0
        assert set(entry["models"]) == {"affine", "poly1", "poly2", "nn7", "nn13"}
        for model, r in entry["models"].items():
            assert math.isfinite(r["worst"]) and r["worst"] == max(r["ratio_axes"]), (group, model)
            assert r["flagged"] == (r["worst"] > limit), (group, model, r["worst"], limit)


def test_a_margin_keeps_a_model_just_above_the_threshold(stage: dict[str, Any]) -> None:
    """Between threshold and limit a model is not flagged (evaluate's rule): the threshold placed just below
    one model's measured ratio and the limit between it and the next, whatever the ratios are."""
    params = load_params(stage["params"])
    day = stage["day"]
    (log,) = prepare_logs(
        params, load_nominal_robot(params), [day / "00_standing_test.mcap"], day, stage["root"] / "work"
    )
    cfg = stage_section(params, "evaluate", EvaluateParams)
    measured = stage["details"]["details"]["later"]["test_a"][LEG]["models"]
    ratios = sorted((r["worst"], m) for m, r in measured.items())
    k = max(range(len(ratios) - 1), key=lambda i: ratios[i + 1][0] / ratios[i][0])  # the widest gap
    (low, between), (high, above) = ratios[k], ratios[k + 1]
    assert high > low * 1.01, ratios
    threshold = low * 0.99
    margin = (low + high) / 2.0 / threshold - 1.0
    narrow = dataclasses.replace(cfg, noise_threshold=threshold, noise_margin=margin)
    result = checks.standing_noise(log, stage["models"], narrow, {LEG: DEPLOYED[LEG]})[LEG]["models"]
    assert {m: r["worst"] for m, r in result.items()} == pytest.approx(
        {m: r["worst"] for m, r in measured.items()}
    )
    flags = {m: r["flagged"] for m, r in result.items()}
    assert not flags[between] and flags[above]
    assert flags == {m: w > (low + high) / 2.0 for w, m in ratios}


def test_b_raw_errors_match_the_simulators_summary(stage: dict[str, Any]) -> None:
    """Test B's raw RMSE against truth (6 axes pooled, at the joint-state stamps after ingest) agrees with
    the simulator's own raw RMSE of the walking log (force and torque, at the FT board's samples)."""
    test_b = stage["details"]["details"]["later"]["test_b"]
    assert set(test_b) == {LEG, "r_foot_front_ft", "r_foot_rear_ft", PAIR}
    summary = json.loads((stage["day"] / "summary.json").read_text())
    (walk,) = [log for log in summary["logs"] if log["name"] == "01_walking_test"]
    for name in (LEG, "r_foot_front_ft", "r_foot_rear_ft"):
        sim = walk["raw_rmse"][name]
        pooled = math.sqrt((sim["force"] ** 2 + sim["torque"] ** 2) / 2.0)
        assert test_b[name]["truth"]["raw"]["rmse"] == pytest.approx(pooled, rel=0.02), name
        calibrated = test_b[name]["truth"]["calibrated"]["rmse"]
        assert test_b[name]["ratio_truth"] == pytest.approx(test_b[name]["truth"]["raw"]["rmse"] / calibrated)


def test_c_uses_the_push_window_of_the_params(stage: dict[str, Any]) -> None:
    """Only the calibrated leg sensor is tested; its window holds the pushes' samples: pushes start at
    (k + 1/2) period and last duration_s, so a 5 s log at 100 Hz has 2 pushes of 80 samples."""
    later = stage["details"]["details"]["later"]
    (sensor,) = later["test_c"]
    assert sensor == LEG
    entry = later["test_c"][LEG]
    starts = [(k + 0.5) * PUSH["period_s"] for k in range(10)]
    n_pushes = sum(t + PUSH["duration_s"] <= LOGS[2]["duration_s"] for t in starts)
    assert n_pushes == 2
    expected = n_pushes * PUSH["duration_s"] * 100
    assert expected - 3 <= entry["samples_pushed"] <= expected + 1
    joints = ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")
    assert list(entry["joints"]) == [f"r_{j}" for j in joints]
    for v in entry["joints"].values():
        assert v["raw"]["max"] >= v["raw"]["rmse"] > 0 and np.isfinite(v["calibrated"]["max"])
        assert v["ratio_max"] == pytest.approx(v["raw"]["max"] / v["calibrated"]["max"])
        assert v["ratio_rmse"] == pytest.approx(v["raw"]["rmse"] / v["calibrated"]["rmse"])
    summary = stage["details"]["summary"]["later"]
    assert "c.r_hip_pitch.ratio" in summary and not any(k.startswith("c.l_") for k in summary)
    # the verdict's Test C ratio is the RMSE ratio of the hip pitch joint (the max one is reported)
    assert summary["c.r_hip_pitch.ratio"] == entry["joints"]["r_hip_pitch"]["ratio_rmse"]
    assert summary["c.r_hip_pitch.ratio_max"] == entry["joints"]["r_hip_pitch"]["ratio_max"]


def test_unmeasured_noise_is_not_a_pass() -> None:
    """A deployed model whose output noise could not be measured (no quasi-static stretch) fails Test A."""
    from pipeline.stages.deploy_test import summarize

    dp = type("DP", (), {"torque_target": 5.0})()
    model = {"worst": float("nan"), "flagged": False, "ratio_axes": []}
    result = {"test_a": {LEG: {"deployed": "nn7", "models": {"nn7": model}}}}
    assert summarize(result, dp, 10.0, "hip_pitch")["fit_to_deploy"] is False
    result["test_a"][LEG]["models"]["nn7"] = {**model, "worst": 1.2}
    assert summarize(result, dp, 10.0, "hip_pitch")["fit_to_deploy"] is True
