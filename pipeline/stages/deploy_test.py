"""Stage `deploy_test`: the thesis's deployment tests A, B, C (chapter 6) on logs no model has seen.

Each deployment day (the simulated ``later`` day, the drift check's ``drifted`` day, and the recorded logs
of ``deploy.real_logs`` if that folder holds any) is ingested, smoothed and labelled as training logs are,
calibrated with the deployed models, and tested: A on its standing log (output noise of every model vs
raw), B on its walking log (error tables vs labels and truth), C on its pushed pole log (leg joint torques
from raw vs calibrated leg sensors against the true torques). Writes ``<reports>/deployment.html``,
``deployment.json`` (per day the few numbers and the verdict, `dvc metrics`), ``deployment/details.json``
(every table) and ``deployment/*.png``; logs one MLflow run. Models trained on recorded logs (train's
``data``) are tested on ``deploy.real_logs`` only, never on the simulated days (another robot); with no
such logs the page and ``deployment.json`` say there is nothing to test.
"""

from __future__ import annotations

import argparse
import math
import shutil
import tempfile
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import DataError

STAGE = "deploy_test"
COMMAND = "deploy-test"


def _day(
    params: Any,
    dp: Any,
    robot: Any,
    trained: tuple[Path, Path],
    logs_dir: Path,
    work: Path,
    figs: Path,
    day: str,
) -> tuple:
    """Run the three tests on one day's logs; returns (results, figure paths relative to the page).

    trained: (models, exported): the train stages' outputs (every model, for Test A) and the export
    (the deployed calibration, run causally on the logs for Tests B and C).
    """
    import pandas as pd

    from pipeline.core.config import stage_section
    from pipeline.deploy import checks
    from pipeline.deploy.models import calibrated_wrenches, deployed_models
    from pipeline.deploy.page import plot_torques, plot_walking
    from pipeline.deploy.prepare import prepare_logs
    from pipeline.evaluation.params import EvaluateParams
    from pipeline.stages.ingest import find_logs

    models, exported = trained
    cfg = stage_section(params, "evaluate", EvaluateParams)
    logs = prepare_logs(params, robot, find_logs(logs_dir), logs_dir, work / day)
    deployed = deployed_models(exported)
    result: dict[str, Any] = {"logs": [log.name for log in logs]}
    figures: dict[str, str] = {}
    for log in logs:
        kind = log.experiment.get("type", "")
        if kind == "standing" and "test_a" not in result:
            result["test_a"] = checks.standing_noise(log, models, cfg, deployed)
        elif kind in ("walking", "pole") and f"test_{'b' if kind == 'walking' else 'c'}" not in result:
            table = pd.read_parquet(log.labelled)
            calibrated = calibrated_wrenches(exported, log.source, table, params.topics)
            if kind == "walking":
                result["test_b"] = checks.walking_errors(log, robot, params, calibrated)
                truth = pd.read_parquet(log.truth) if log.truth is not None else None
                shown = [s for s in dp.torque_limbs if s in calibrated]
                figures["walking"] = f"deployment/{day}_walking.png"
                plot_walking(table, truth, calibrated, shown, figs / f"{day}_walking.png")
            else:
                result["test_c"], series = checks.push_torques(log, robot, params, dp, calibrated)
                if result["test_c"]:
                    figures["torques"] = f"deployment/{day}_{dp.figure_joint}.png"
                    plot_torques(series, dp.figure_joint, figs / f"{day}_{dp.figure_joint}.png")
    return result, figures


def summarize(result: dict[str, Any], dp: Any, target_b: float, joint: str) -> dict[str, Any]:
    """The day's few numbers for `dvc metrics` and its verdict (fit to deploy, or time to recalibrate)."""
    out: dict[str, Any] = {}
    for group, a in result.get("test_a", {}).items():
        out[f"a.{group}.deployed_noise_ratio"] = a["models"][a["deployed"]]["worst"]
        out[f"a.{group}.flagged"] = sorted(m for m, r in a["models"].items() if r["flagged"])
    for name, b in result.get("test_b", {}).items():
        if "truth" in b:
            out[f"b.{name}.rmse_truth_raw"] = b["truth"]["raw"]["rmse"]
            out[f"b.{name}.rmse_truth_calibrated"] = b["truth"]["calibrated"]["rmse"]
            out[f"b.{name}.ratio"] = b["ratio_truth"]
    for c in result.get("test_c", {}).values():
        for j, v in c["joints"].items():
            if j.endswith(joint):
                out[f"c.{j}.rmse_raw"] = v["raw"]["rmse"]
                out[f"c.{j}.rmse_calibrated"] = v["calibrated"]["rmse"]
                out[f"c.{j}.ratio"] = v["ratio_rmse"]
                out[f"c.{j}.ratio_max"] = v["ratio_max"]
    # a deployed model whose noise could not be measured (no quasi-static stretch) has not passed Test A
    deployed = [a["models"][a["deployed"]] for a in result.get("test_a", {}).values()]
    ok_a = all(not r["flagged"] and math.isfinite(r["worst"]) for r in deployed)
    ok_b = all(v >= target_b for k, v in out.items() if k.startswith("b.") and k.endswith(".ratio"))
    ok_c = all(v >= dp.torque_target for k, v in out.items() if k.startswith("c.") and k.endswith(".ratio"))
    out["fit_to_deploy"] = bool(ok_a and ok_b and ok_c)
    return out


def _headline(summary: dict[str, Any]) -> dict[str, Any]:
    """A day's few numbers for `dvc metrics show`: the verdict (``fit``), the smallest Test B and Test C
    ratios (raw / calibrated against truth: ``b_min``, ``c_min``), the largest output noise ratio of a
    deployed model (``a_max``); every number is in deployment/details.json."""

    def pick(prefix: str, suffix: str) -> list[float]:
        return [v for k, v in summary.items() if k.startswith(prefix) and k.endswith(suffix)]

    out: dict[str, Any] = {"fit": summary["fit_to_deploy"]}
    for key, values, best in (
        ("b_min", pick("b.", ".ratio"), min),
        ("c_min", pick("c.", ".ratio"), min),
        ("a_max", pick("a.", ".deployed_noise_ratio"), max),
    ):
        if values:
            out[key] = round(float(best(values)), 4)
    return out


def run(params: Any, models: Path, exported: Path, days: dict[str, Path], reports: Path) -> dict[str, Any]:
    """Run the tests on every day of `days` (name -> folder of logs) and the real logs; write the reports."""
    import mlflow

    from pipeline.core.io import write_json
    from pipeline.core.tracking import stage_run
    from pipeline.deploy.page import write_page
    from pipeline.deploy.params import deploy_params
    from pipeline.deploy.prepare import load_nominal_robot
    from pipeline.stages.ingest import find_logs

    dp = deploy_params(params)
    models = Path(models)
    if not models.is_dir():
        raise DataError(f"{models}: models directory not found")
    real = Path(dp.real_logs)
    days = {k: Path(v) for k, v in days.items()}
    recorded = trained_on_recordings(models)
    if recorded:  # a real robot's calibration is not tested on the simulated robot's logs
        days = {}
    if real.is_dir() and find_logs(real):
        days["real"] = real
    for day, path in days.items():
        if not path.is_dir():
            raise DataError(f"{path}: deployment logs of day {day!r} not found")
    robot = load_nominal_robot(params)
    target_b = float(params.raw["evaluate"]["target_raw_over_nn7"])
    figs = reports / "deployment"
    shutil.rmtree(figs, ignore_errors=True)
    figs.mkdir(parents=True)
    results, summary, figures = {}, {}, {}
    with stage_run(STAGE, {"deploy": params.raw["deploy"]}), tempfile.TemporaryDirectory() as work:
        for day, path in days.items():
            results[day], figures[day] = _day(
                params, dp, robot, (models, Path(exported)), path, Path(work), figs, day
            )
            summary[day] = summarize(results[day], dp, target_b, dp.figure_joint)
            mlflow.log_metrics(
                {f"{day}.{k}": float(v) for k, v in summary[day].items() if isinstance(v, int | float)}
            )
        verdict = "; ".join(
            f"{day}: {'fit to deploy' if s['fit_to_deploy'] else 'recalibrate'}" for day, s in summary.items()
        ) or nothing_to_test(recorded, real)
        headlines = {day: _headline(s) for day, s in summary.items()}
        write_json(reports / "deployment.json", headlines or {"nothing_to_test": True})
        write_json(figs / "details.json", {"summary": summary, "details": results})
        write_page(reports / "deployment.html", results, figures, verdict)
        mlflow.log_artifact(str(reports / "deployment.html"))
        mlflow.log_artifact(str(reports / "deployment.json"))
        mlflow.log_artifact(str(figs / "details.json"))
        mlflow.log_artifacts(str(figs), artifact_path="deployment")
    return {"summary": summary, "details": results, "verdict": verdict}


def trained_on_recordings(models: Path) -> list[str]:
    """The groups of `models` trained on recorded logs (train's metrics.json ``data``: not simulated)."""
    import json

    out = []
    for metrics in sorted(Path(models).glob("*/metrics.json")):
        try:
            data = json.loads(metrics.read_text(encoding="utf-8")).get("data", "simulated")
        except (OSError, ValueError) as exc:
            raise DataError(f"{metrics}: not a train output: {exc}") from None
        if data != "simulated":
            out.append(metrics.parent.name)
    return out


def nothing_to_test(recorded: list[str], real: Path) -> str:
    """The page's sentence when no day has logs to test."""
    why = (
        f"the models ({', '.join(recorded)}) were trained on recorded logs, so the simulated deployment days "
        "would test them on another robot's logs"
        if recorded
        else "there are no deployment days"
    )
    return f"Nothing to test: {why}, and deploy.real_logs ({real}) holds no recorded deployment log."


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    days = {"later": args.later, "drifted": args.drifted}
    days = {k: v for k, v in days.items() if v}
    out = run(load_params(args.params), args.models, args.exported, days, args.reports)
    for day, s in out["summary"].items():
        print(f"{day}: {'fit to deploy' if s['fit_to_deploy'] else 'recalibrate'}")
    if not out["summary"]:
        print(out["verdict"])
    return 0


def add_cli(subparsers: Any) -> None:
    p = subparsers.add_parser(COMMAND, help="deployment tests A, B, C", description=__doc__.splitlines()[0])
    p.add_argument("models", type=Path, help="the trained groups (models/): every model, for Test A")
    p.add_argument("exported", type=Path, help="the export (exported/): the deployed calibration")
    p.add_argument("reports", type=Path, help="reports directory (deployment.html, deployment.json)")
    p.add_argument(
        "--later", type=Path, default=None, help="deployment logs of a later day (data/deploy/later)"
    )
    p.add_argument("--drifted", type=Path, default=None, help="the drift check's logs (data/deploy/drifted)")
    add_params_option(p)
    p.set_defaults(func=_cmd)
