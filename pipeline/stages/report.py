"""Stage `report`: the page a researcher opens, assembled from every group's evaluation.

``ftcal report REPORTS [--labelled DIR]`` reads ``REPORTS/groups/<group>/report.json`` of every group of
``train.groups`` (written by evaluate@<group>) and writes ``REPORTS/index.html`` (summary with the model to
deploy per group and headline, noise check, one section per group with every table and figure) and the
two overview figures in ``REPORTS/plots/``. Nothing is recomputed: a change to one group re-runs its train
and evaluate stages and this light assembly only. With ``--labelled``, the page also shows how often each
label (sensor, foot pair, cut set) is exact per experiment type, over every labelled log: only the switch,
contact and guard columns are read (`pipeline.evaluation.availability`).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import DataError

STAGE = "report"


def read_reports(reports_dir: Path, groups: list[str]) -> list[Any]:
    """The `GroupReport` of each group, in `groups` order.

    Raises:
        DataError: a group's report.json is missing or not a group report.
    """
    import json

    from pipeline.evaluation.params import GROUP_REPORT, GROUPS_DIR
    from pipeline.evaluation.results import GroupReport

    out = []
    for group in groups:
        path = reports_dir / GROUPS_DIR / group / GROUP_REPORT
        try:
            out.append(GroupReport.from_dict(json.loads(path.read_text(encoding="utf-8"))))
        except FileNotFoundError:
            raise DataError(f"{path}: missing (run `dvc repro evaluate@{group}`)") from None
        except (OSError, ValueError, TypeError, KeyError) as exc:
            raise DataError(f"{path}: not a group report ({exc}); rerun evaluate@{group}") from None
    return out


def run(
    params: Any,
    reports_dir: str | Path,
    labelled_dir: str | Path | None = None,
    identified_dir: str | Path | None = None,
) -> tuple[list[Any], list[str], float]:
    """Assemble the page (module docstring) in one MLflow run ``report``; returns (reports, files, s).

    Raises:
        DataError: a group's report is missing or unusable, `labelled_dir` holds no labelled table, or
            `identified_dir` no identification.json.
    """
    import mlflow

    from pipeline.calib.params import TrainParams
    from pipeline.core.config import stage_section
    from pipeline.core.tracking import stage_run
    from pipeline.evaluation.availability import label_availability
    from pipeline.evaluation.page import write_page
    from pipeline.evaluation.params import REPORT_FILE, EvaluateParams

    t0 = time.perf_counter()
    cfg = stage_section(params, "evaluate", EvaluateParams)
    groups = list(stage_section(params, "train", TrainParams).groups)
    out = Path(reports_dir)
    reports = read_reports(out, groups)
    availability = label_availability(Path(labelled_dir)) if labelled_dir is not None else None
    identification = _identification(Path(identified_dir), out) if identified_dir is not None else None
    with stage_run(STAGE, {"groups": ",".join(groups)}):
        files = write_page(out, reports, cfg, availability, identification)
        if availability is not None:
            mlflow.log_dict(availability, "label_availability.json")
        mlflow.set_tags({f"recommended.{r.group}": r.recommended or "none" for r in reports})
        mlflow.log_artifact(str(out / REPORT_FILE))
        mlflow.log_metric("seconds", time.perf_counter() - t0)
    return reports, files, time.perf_counter() - t0


def _identification(identified: Path, out: Path) -> Any:
    """The label stage's identification.json of `identified`, its figure copied beside the page's."""
    import shutil

    from pipeline.core.io import read_json
    from pipeline.evaluation.params import IDENTIFIED_FIGURE
    from pipeline.stages.identify import SUMMARY

    summary = read_json(identified / SUMMARY, "identified robot model", "missing (run `dvc repro label`)")
    if (identified / "parts.png").is_file():
        (out / IDENTIFIED_FIGURE).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(identified / "parts.png", out / IDENTIFIED_FIGURE)
    return summary


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    reports, _, seconds = run(load_params(args.params), args.reports, args.labelled, args.identified)
    for r in reports:
        if r.not_calibrated is not None:
            print(f"{r.group}: not calibrated: {r.not_calibrated}")
            continue
        left = "".join(f"; {s} not calibrated: {why}" for s, why in r.left_out.items())
        print(f"{r.group}: deploy {r.recommended}{left}")
    print(f"report: {Path(args.reports) / 'index.html'} ({seconds:.1f} s)")
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal report REPORTS [--labelled DIR]`."""
    parser = subparsers.add_parser(
        STAGE,
        help="assemble the report page of every group's evaluation",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument("reports", type=Path, help="reports directory (groups/<group>/report.json inside)")
    parser.add_argument(
        "--labelled",
        type=Path,
        default=None,
        help="directory of labelled <log>.parquet tables (optional): adds the exact-label availability",
    )
    parser.add_argument(
        "--identified",
        type=Path,
        default=None,
        help="the label stage's identified robot model (models/identified, optional): adds its section",
    )
    add_params_option(parser)
    parser.set_defaults(func=_cmd)
