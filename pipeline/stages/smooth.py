"""Stage `smooth`: Savitzky-Golay on joint positions -> smoothed positions, velocities, accelerations.

The method (segments at stamp gaps, uniform resampling, one-sided edges flagged, each joint on the samples
where its position exists) is in `pipeline.logs.smoothing`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import DataError

STAGE = "smooth"


def run(params: Any, in_dir: str | Path, out_dir: str | Path, *, progress: bool | None = None) -> list[Any]:
    """Smooth every ingested table of `in_dir` into `out_dir`, in one MLflow run."""
    from dataclasses import asdict

    import mlflow

    from pipeline.core.config import stage_section
    from pipeline.core.parallel import forked_map
    from pipeline.core.progress import progress_bar
    from pipeline.core.tracking import stage_run
    from pipeline.logs.smoothing import SmoothParams, find_tables, smooth_table

    cfg = stage_section(params, STAGE, SmoothParams)
    src, out = Path(in_dir), Path(out_dir)
    if not src.is_dir():
        raise DataError(f"{src}: input directory not found")
    tables = find_tables(src)
    if not tables:
        raise DataError(f"{src}: no ingested *.parquet tables")
    reports: list[Any] = []
    t0 = time.perf_counter()
    with stage_run(STAGE, {"smooth": asdict(cfg)}), progress_bar(progress) as bar:
        task = bar.add_task(STAGE, total=len(tables))
        mlflow.set_tags({"in_dir": str(src), "out_dir": str(out), "logs": str(len(tables))})
        import scipy.signal  # noqa: F401  (smooth_table's filter: imported once, inherited by the workers)

        # the tables are independent: one forked process per core, the largest first
        jobs = [lambda t=table: smooth_table(t, out / t.name, cfg) for table in tables]
        sizes = [t.stat().st_size for t in tables]
        for report in forked_map(jobs, costs=sizes, labels=list(map(str, tables))):
            reports.append(report)
            bar.advance(task)
        warnings = [
            f"{Path(r.source).name}: {r.short_segments} segment(s) shorter than the narrowest window "
            f"({cfg.narrowest} samples): {r.samples_not_ok} samples not smoothed"
            for r in reports
            if r.short_segments
        ]
        seconds = time.perf_counter() - t0
        mlflow.log_metrics(
            {
                "logs": float(len(reports)),
                "samples": float(sum(r.samples for r in reports)),
                "segments": float(sum(r.segments for r in reports)),
                "short_segments": float(sum(r.short_segments for r in reports)),
                "samples_not_ok": float(sum(r.samples_not_ok for r in reports)),
                "seconds": seconds,
                "warnings": float(len(warnings)),
            }
        )
        mlflow.log_text("\n".join(warnings) + ("\n" if warnings else ""), "warnings.txt")
        mlflow.log_dict({"logs": [asdict(r) for r in reports]}, "smooth_summary.json")
    for warning in warnings:
        print(f"ftcal: warning: {warning}", file=sys.stderr)
    return reports


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    params = load_params(args.params)
    reports = run(params, args.inputs, args.out)
    line = f"smoothed {len(reports)} log(s), {sum(r.samples for r in reports)} samples, into {args.out}"
    lacking = [
        f"{Path(r.source).stem}: {len(r.joints_never_ok)} joints ({', '.join(r.joints_never_ok[:3])}"
        f"{', ...' if len(r.joints_never_ok) > 3 else ''})"
        for r in reports
        if r.joints_never_ok
    ]
    if lacking:  # absent joint streams: those joints' columns stay NaN, the others are smoothed
        line += "; without positions (NaN, not ok): " + "; ".join(lacking)
    print(line)
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal smooth IN OUT`."""
    parser = subparsers.add_parser(
        STAGE,
        help="Savitzky-Golay joint velocities and accelerations",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument("inputs", type=Path, metavar="IN", help="directory of ingested <log>.parquet tables")
    parser.add_argument("out", type=Path, help="output directory for the smoothed <log>.parquet tables")
    add_params_option(parser)
    parser.set_defaults(func=_cmd)
