"""Step `deploy_test@<group>` (stage `evaluate@<group>`): the thesis's deployment tests (chapter 6) of one
sensor group, on logs no model has seen.

``ftcal deploy-test GROUP MODELS EXPORTED TABLES OUT``: on every deployment day under TABLES (the tables of
`deploy_prepare`, stage `deploy_days`: the simulated ``later`` day, the drift check's ``drifted`` day, the
recorded logs of ``deploy.real_logs`` if it holds any), the group's tests of `pipeline.deploy.group`: A on
the standing log (output noise of every model in MODELS vs raw), B on the walking log (error tables vs
labels and truth), C on the pushed pole log (leg joint torques from raw vs calibrated leg sensors against
the true torques), D on the interaction log. The calibration is the group's export (EXPORTED, an export
directory) run causally on each log's raw messages, as on the robot: as delivered, and re-zeroed from the
day's first still seconds (`ftcal rezero`'s library, `pipeline.deploy.rezeroing`: the first still stretch
of the day's logs, ``deploy.rezero``), tests B, C, D again with those offsets (Test A, every trained
model's output noise, is the same). A group trained on recorded logs (train's ``data``) is tested on
``deploy.real_logs`` only, never on the simulated days (another robot); simulated days that were not
simulated (recorded logs only) are named with why in ``not_simulated``. Writes OUT/result.json (per day
the results and figures, and under ``rezeroed`` the re-zeroing and the results after it) and
OUT/<day>_*.png; logs one MLflow run. `deploy_report` gathers every group's into the deployment page and
verdict.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option, add_runtime_option
from pipeline.core.errors import DataError

STAGE = "deploy_test"
COMMAND = "deploy-test"
DAY_ORDER = ("later", "drifted")  # the simulated days first, then the others (recorded logs) by name


def days_of(tables: Path) -> list[Path]:
    """The prepared days under `tables` that hold logs, in DAY_ORDER then by name."""
    from pipeline.deploy.prepare import DAY_FILE, read_day

    if not tables.is_dir():
        raise DataError(f"{tables}: deployment tables not found (run `dvc repro deploy_days`)")
    found = [d for d in tables.iterdir() if (d / DAY_FILE).is_file() and read_day(d)]
    rank = {name: k for k, name in enumerate(DAY_ORDER)}
    return sorted(found, key=lambda d: (rank.get(d.name, len(rank)), d.name))


def run(
    params: Any,
    group: str,
    models: str | Path,
    exported: str | Path,
    tables: str | Path,
    out: str | Path,
    urdf: str | Path | None = None,
) -> dict[str, Any]:
    """The group's tests on every prepared day (module docstring); what OUT/result.json holds. `urdf`: the
    robot model of the estimators (the training labels', ``models/identified/labels.urdf``), else
    ``robot.urdf``."""
    from dataclasses import replace

    import mlflow
    import numpy as np

    from pipeline.calib.exact import NOT_CALIBRATED
    from pipeline.core.config import stage_section
    from pipeline.core.io import atomic_dir, write_json
    from pipeline.core.tracking import stage_run
    from pipeline.deploy.group import GroupDay, run_days
    from pipeline.deploy.models import deployed_models, group_models
    from pipeline.deploy.params import deploy_params
    from pipeline.deploy.prepare import load_nominal_robot, not_simulated, read_day
    from pipeline.deploy.verdict import RESULT_FILE, REZEROED
    from pipeline.evaluation.params import EvaluateParams
    from pipeline.export.manifest import read_manifest
    from pipeline.export.offsets import Offsets
    from pipeline.export.trained import read_metrics

    dp, cfg = deploy_params(params), stage_section(params, "evaluate", EvaluateParams)
    models, exported, out = Path(models), Path(exported), Path(out)
    if not models.is_dir():
        raise DataError(f"{models}: models directory not found")
    why = (read_manifest(exported).get(NOT_CALIBRATED) or {}).get(group) if exported.is_dir() else None
    if why is not None:  # nothing calibrated, nothing exported: nothing to test
        result = {"group": group, NOT_CALIBRATED: why, "days": {}, "figures": {}, "recorded": False}
        with atomic_dir(out) as tmp:
            write_json(tmp / RESULT_FILE, result)
        return result
    deployed = deployed_models(exported)
    if group not in deployed:
        raise DataError(f"{exported}: the export has no graph of {group} ({', '.join(deployed)})")
    days = days_of(Path(tables))
    metrics = read_metrics(models)
    # trained on recorded logs (train's ``data``: not simulated)
    recorded = metrics.get("data", "simulated") != "simulated"
    if recorded:  # a real robot's calibration is not tested on the simulated robot's logs
        days = [d for d in days if d.name not in DAY_ORDER]
    sensors, robot = group_models(models)[0], load_nominal_robot(params, urdf)
    result: dict[str, Any] = {"group": group, "deployed": deployed[group], "days": {}, "figures": {}}
    result |= {"recorded": recorded, REZEROED: {}, f"figures_{REZEROED}": {}}
    # the simulated days that were not simulated (recorded logs only), and why
    notes = {d.name: not_simulated(d) for d in sorted(Path(tables).iterdir()) if d.is_dir()}
    result["not_simulated"] = {day: note for day, note in notes.items() if note is not None}
    with stage_run(f"{STAGE}@{group}", {"group": group, "deployed": deployed[group]}), atomic_dir(out) as tmp:
        logs = {day.name: read_day(day) for day in days}
        rezeros = _rezero_days(params, dp, exported, logs, sensors, robot)
        planned, keys = [], []
        for day in days:
            args = (group, sensors, models, exported, deployed[group], params, dp, cfg, robot, day.name, tmp)
            ctx = GroupDay(*args, excitation=metrics.get("excitation"))
            planned.append((ctx, logs[day.name]))
            keys.append((day.name, ""))
            if "offsets" in rezeros[day.name]:
                values = {s: np.asarray(v) for s, v in rezeros[day.name]["offsets"].items()}
                planned.append((replace(ctx, offsets=Offsets(values), variant=REZEROED), logs[day.name]))
                keys.append((day.name, REZEROED))
        for (name, variant), (tested, drawn) in zip(keys, run_days(planned), strict=True):  # in parallel
            if variant:
                result[REZEROED][name] = {"rezero": rezeros[name], **tested}
                result[f"figures_{REZEROED}"][name] = drawn
            else:
                result["days"][name], result["figures"][name] = tested, drawn
        for name, rezero in rezeros.items():
            result[REZEROED].setdefault(name, {"rezero": rezero})
        write_json(tmp / RESULT_FILE, result)
        mlflow.log_artifacts(str(tmp), f"deployment/{group}")
    return result


def _rezero_days(
    params: Any, dp: Any, exported: Path, logs: dict[str, list[Any]], sensors: list[str], robot: Any
) -> dict[str, dict[str, Any]]:
    """Day -> the group re-zeroed from its first still seconds (`pipeline.deploy.rezeroing.rezero_day`),
    the days in forked processes."""
    from pipeline.core.parallel import forked_map
    from pipeline.deploy.prepare import robot_cuts
    from pipeline.deploy.rezeroing import rezero_day

    _, _, cuts = robot_cuts(params, robot)
    jobs = [lambda d=d: rezero_day(exported, d, sensors, robot, cuts, dp.rezero) for d in logs.values()]
    return dict(zip(logs, forked_map(jobs), strict=True))


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params
    from pipeline.export.cbuild import using

    with using(args.runtime):
        result = run(
            load_params(args.params), args.group, args.models, args.exported, args.tables, args.out, args.urdf
        )
    if "not_calibrated" in result:
        print(f"{args.group}: not calibrated, nothing to test: {result['not_calibrated']}")
        return 0
    tested = ", ".join(
        f"{day}: {', '.join(k for k in r if k.startswith('test_'))}" for day, r in result["days"].items()
    )
    untested = "; ".join(f"{day}: {note}" for day, note in result["not_simulated"].items())
    nothing = f"no deployment logs{f' ({untested})' if untested else ''}"
    print(f"{args.group}: deployment tests of {result['deployed']} ({tested or nothing})")
    return 0


def add_cli(subparsers: Any) -> None:
    p = subparsers.add_parser(
        COMMAND, help="deployment tests A, B, C of one sensor group", description=__doc__.splitlines()[0]
    )
    p.add_argument("group", help="sensor group: a key of train.groups in params.yaml")
    p.add_argument(
        "models", type=Path, help="the group's trained models (models/<group>): every model, Test A"
    )
    p.add_argument(
        "exported", type=Path, help="the group's export (exported/groups/<group>): the calibration"
    )
    p.add_argument("tables", type=Path, help="the prepared deployment days (data/deploy/tables)")
    p.add_argument(
        "out", type=Path, help="the group's results and figures (reports/deployment/groups/<group>)"
    )
    add_runtime_option(p)
    p.add_argument(
        "--urdf",
        type=Path,
        default=None,
        help="the estimators' robot model (models/identified/labels.urdf), else robot.urdf",
    )
    add_params_option(p)
    p.set_defaults(func=_cmd)
