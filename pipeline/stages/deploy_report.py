"""Step `deploy_report` (stage `report`): every group's deployment tests gathered into a page and verdict.

``ftcal deploy-report GROUPS REPORTS``: reads GROUPS/<group>/result.json of every group of
``train.groups`` (the tests of `evaluate@<group>`), gathers each day's results
(`pipeline.deploy.verdict`), and
writes ``REPORTS/deployment.html`` (the verdict per day as delivered and after re-zeroing, then each day's
tables and the groups' figures, the re-zeroing and its pose dependence; linked with the report page),
``REPORTS/metrics/deployment/<day>.json`` (one `dvc metrics show` row per day: the verdict as delivered and
re-zeroed, the smallest Test B and C ratios), ``REPORTS/deployment.json`` (per day every test's few
numbers, as delivered and under ``rezeroed``) and ``REPORTS/deployment/details.json`` (every table). A light
assembly: one group's change re-runs that group's tests and this page only. Logs one MLflow run.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option

STAGE = "deploy_report"
COMMAND = "deploy-report"
PAGE, METRICS, DETAILS = "deployment.html", "deployment.json", "deployment/details.json"
DAY_ROWS = "metrics/deployment"  # <day>.json: one `dvc metrics show` row per deployment day


def _write_day_rows(out: Path, headlines: dict[str, dict[str, Any]]) -> None:
    """One short row per day into `out`/<day>.json (the rest in deployment.json): the verdict as delivered
    and re-zeroed, and the smallest Test B and C ratios (raw / calibrated against truth)."""
    from pipeline.core.io import write_json
    from pipeline.deploy.verdict import REZEROED

    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("*.json"):
        old.unlink()
    for day, h in headlines.items():
        row = {"verdict": "fit to deploy" if h["fit"] else "recalibrate"}
        if REZEROED in h:
            row[REZEROED] = "fit to deploy" if h[REZEROED]["fit"] else "recalibrate"
        row.update({k: h[k] for k in ("b_min", "c_min") if k in h})
        write_json(out / f"{day}.json", row)


def _group_results(groups_dir: Path, groups: list[str]) -> dict[str, dict[str, Any]]:
    from pipeline.core.io import read_json
    from pipeline.deploy.verdict import RESULT_FILE

    results = {}
    for group in groups:
        missing = f"not found (run `dvc repro evaluate@{group}`)"
        results[group] = read_json(groups_dir / group / RESULT_FILE, "a deployment test result", missing)
    return results


def run(params: Any, groups_dir: str | Path, reports: str | Path) -> dict[str, Any]:
    """Gather, judge and write the deployment page and metrics (module docstring)."""
    import mlflow

    from pipeline.core.io import write_json
    from pipeline.core.tracking import stage_run
    from pipeline.deploy.page import write_page
    from pipeline.deploy.params import deploy_params
    from pipeline.deploy.verdict import REZEROED, headline, merge, summarize

    dp, groups_dir, reports = deploy_params(params), Path(groups_dir), Path(reports)
    results = _group_results(groups_dir, [str(g) for g in params.raw["train"]["groups"]])
    target_b = float(params.raw["evaluate"]["target_raw_over_nn7"])
    targets = {
        "b": target_b,
        "c": dp.torque_target,
        "joint": dp.figure_joint,
        "d_slope": dp.slope_tolerance,
        "d_change": dp.push_rmse_target,
        "pose_limit": dp.rezero.pose_limit,
    }
    days = list(dict.fromkeys(day for r in results.values() for day in r["days"]))
    details = {
        day: merge({g: r["days"][day] for g, r in results.items() if day in r["days"]}) for day in days
    }
    figures = {day: _figures(results, "figures", day, groups_dir, reports) for day in days}
    summary = {day: summarize(d, dp, target_b, dp.figure_joint) for day, d in details.items()}
    rezeroed = _rezeroed(results, days)
    for day, entry in rezeroed.items():
        entry["summary"] = summarize(entry["details"], dp, target_b, dp.figure_joint)
        entry["figures"] = _figures(results, f"figures_{REZEROED}", day, groups_dir, reports)
    if not summary:
        uncalibrated = [g for g, r in results.items() if r.get("not_calibrated")]
        targets["nothing"] = nothing_to_test(
            [g for g, r in results.items() if r.get("recorded")],
            dp.real_logs,
            {day: note for r in results.values() for day, note in r.get("not_simulated", {}).items()},
            uncalibrated,
        )
    with stage_run(STAGE, {"groups": list(results)}):
        for day, s in summary.items():
            mlflow.log_metrics({f"{day}.{k}": float(v) for k, v in s.items() if isinstance(v, int | float)})
        headlines = {day: headline(s) for day, s in summary.items()}
        for day, entry in rezeroed.items():
            headlines[day][REZEROED] = headline(entry["summary"])
            mlflow.log_metrics(
                {
                    f"{day}.{REZEROED}.{k}": float(v)
                    for k, v in headlines[day][REZEROED].items()
                    if isinstance(v, int | float)
                }
            )
        write_json(reports / METRICS, headlines or {"nothing_to_test": True})
        _write_day_rows(reports / DAY_ROWS, headlines)
        kept = {day: {k: e[k] for k in ("summary", "details", "rezero")} for day, e in rezeroed.items()}
        write_json(reports / DETAILS, {"summary": summary, "details": details, REZEROED: kept})
        write_page(reports / PAGE, details, summary, figures, targets, rezeroed)
        for name in (PAGE, METRICS, DETAILS):
            mlflow.log_artifact(str(reports / name), "deployment" if name == DETAILS else None)
    return {"summary": summary, "details": details, "nothing": targets.get("nothing"), REZEROED: rezeroed}


def _figures(results: dict[str, Any], key: str, day: str, groups_dir: Path, reports: Path) -> dict[str, str]:
    """A day's figures of every group under `key` of its result: caption -> path relative to the page."""
    return {
        f"{group}: {kind}": Path(os.path.relpath(groups_dir / group / file, reports)).as_posix()
        for group, r in results.items()
        for kind, file in r.get(key, {}).get(day, {}).items()
    }


def _rezeroed(results: dict[str, Any], days: list[str]) -> dict[str, dict[str, Any]]:
    """Day -> its results after re-zeroing (``details``: every group's tests with its offsets, as delivered
    where a group could not be re-zeroed; Test A is the delivered one's) and each group's re-zeroing
    (``rezero``); only the days on which some group was re-zeroed."""
    from pipeline.deploy.verdict import REZEROED, merge

    out = {}
    for day in days:
        groups = {g: r.get(REZEROED, {}).get(day) for g, r in results.items() if day in r["days"]}
        if not any(e and len(e) > 1 for e in groups.values()):
            continue
        tests = {}
        for g, entry in groups.items():
            delivered = results[g]["days"][day]
            mine = {k: v for k, v in (entry or {}).items() if k != "rezero"}
            tests[g] = {**delivered, **mine} if len(mine) else delivered
        rezero = {g: e["rezero"] for g, e in groups.items() if e and "rezero" in e}
        out[day] = {"details": merge(tests), "rezero": rezero}
    return out


def nothing_to_test(
    recorded: list[str],
    real: str,
    not_simulated: dict[str, str] | None = None,
    uncalibrated: Sequence[str] = (),
) -> str:
    """The page's sentence when no day has logs to test. not_simulated: the simulated days that were not
    simulated -> why (their note); uncalibrated: the groups nothing could be calibrated for."""
    if not_simulated:
        days, notes = ", ".join(sorted(not_simulated)), "; ".join(sorted(set(not_simulated.values())))
        why = f"there is nothing simulated to test on ({days}: {notes})"
    elif recorded:
        why = (
            f"the models ({', '.join(recorded)}) were trained on recorded logs, so the simulated deployment "
            "days would test them on another robot's logs"
        )
    else:
        why = "there are no deployment days"
    if uncalibrated and not recorded and not not_simulated:
        why = f"no model to test ({', '.join(uncalibrated)}: not calibrated, no exact label)"
    elif uncalibrated:
        why += f" ({', '.join(uncalibrated)}: not calibrated, no exact label)"
    return f"Nothing to test: {why}, and deploy.real_logs ({real}) holds no recorded deployment log."


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    out = run(load_params(args.params), args.groups, args.reports)
    for day, s in out["summary"].items():
        after = out["rezeroed"].get(day)
        verdict = "fit to deploy" if s["fit_to_deploy"] else "recalibrate"
        if after is not None:
            verdict += (
                f"; re-zeroed: {'fit to deploy' if after['summary']['fit_to_deploy'] else 'recalibrate'}"
            )
        print(f"{day}: {verdict}")
    if not out["summary"]:
        print(out["nothing"])
    return 0


def add_cli(subparsers: Any) -> None:
    p = subparsers.add_parser(
        COMMAND,
        help="the deployment page and verdict of every group's tests",
        description=__doc__.splitlines()[0],
    )
    p.add_argument(
        "groups", type=Path, help="the groups' deployment test results (reports/deployment/groups)"
    )
    p.add_argument("reports", type=Path, help="reports directory (deployment.html, deployment.json)")
    add_params_option(p)
    p.set_defaults(func=_cmd)
