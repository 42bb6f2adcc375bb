"""Step `deploy_prepare` (stage `deploy_days`): a deployment day's logs ingested, smoothed and labelled.

``ftcal deploy-prepare LOGS OUT``: every log (``*.mcap``, ``*.mat``) under LOGS (a simulated deployment
day, or the recorded logs of ``deploy.real_logs``, which may hold none yet) through the pipeline's own
ingest, smooth and label (`pipeline.deploy.prepare`), into OUT: ``ingested/``, ``smoothed/``,
``labelled/`` and ``logs.json`` (the day's logs, what `deploy_test` reads); a simulated day that was not
simulated (recorded logs only) passes its note on (``not_simulated.txt``: why). OUT is replaced whole,
atomically; the run is logged to MLflow.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import DataError

STAGE = "deploy_prepare"
COMMAND = "deploy-prepare"


def run(params: Any, logs_dir: str | Path, out: str | Path, urdf: str | Path | None = None) -> list[Any]:
    """Prepare every log of `logs_dir` into `out` (module docstring); the day's `DeployLog`s. `urdf`: the
    URDF the labels are made with (the label stage's, ``models/identified/labels.urdf``), else
    ``robot.urdf``."""
    import mlflow

    from pipeline.core.io import atomic_dir, write_text
    from pipeline.core.tracking import stage_run
    from pipeline.deploy.prepare import load_nominal_robot, not_simulated, prepare_logs, read_day, write_day
    from pipeline.logs.logfiles import find_logs
    from pipeline.logs.schema import NOT_SIMULATED

    t0 = time.perf_counter()
    logs_dir, out = Path(logs_dir), Path(out)
    if not logs_dir.is_dir():
        raise DataError(f"{logs_dir}: deployment logs folder not found")
    logs = find_logs(logs_dir)
    note = None if logs else not_simulated(logs_dir)  # a simulated day not simulated: say why
    with stage_run(f"{STAGE}@{out.name}", {"logs_dir": str(logs_dir)}):
        robot = load_nominal_robot(params, urdf) if logs else None
        with atomic_dir(out) as tmp:
            write_day(tmp, prepare_logs(params, robot, logs, logs_dir, tmp) if logs else [])
            if note is not None:
                write_text(tmp / NOT_SIMULATED, note + "\n")
        mlflow.log_metrics({"logs": len(logs), "seconds": time.perf_counter() - t0})
    return read_day(out)


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params
    from pipeline.deploy.prepare import not_simulated

    logs = run(load_params(args.params), args.logs, args.out, args.urdf)
    note = None if logs else not_simulated(args.out)
    print(f"{args.out}: {note or f'{len(logs)} deployment log(s) ingested, smoothed and labelled'}")
    return 0


def add_cli(subparsers: Any) -> None:
    p = subparsers.add_parser(
        COMMAND, help="ingest, smooth and label a deployment day's logs", description=__doc__.splitlines()[0]
    )
    p.add_argument("logs", type=Path, help="folder of the day's logs (data/deploy/<day>, deploy.real_logs)")
    p.add_argument("out", type=Path, help="the day's tables (data/deploy/tables/<day>)")
    p.add_argument(
        "--urdf",
        type=Path,
        default=None,
        help="the URDF to label with (models/identified/labels.urdf, the training labels'), else robot.urdf",
    )
    add_params_option(p)
    p.set_defaults(func=_cmd)
