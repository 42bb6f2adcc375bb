"""Stage `label`: contacts, exact-label switches and expected wrenches of every FT sensor (thesis 4.2, 5.4).

Per log (a smoothed table): the contact set of every sample, declared by the experiment or detected from
the raw foot-sensor normal forces (:mod:`pipeline.labels.contacts`); then every sensor's expected wrench
and switch, each foot pair's sum in its sole frame, and each cut set's signed sum in its common frame
(:mod:`pipeline.labels.table`, :mod:`pipeline.physics.cuts`): a set of FT sensors that isolates a part of
the robot has an exact summed label wherever that part touches nothing (both leg sensors in double
support, the four foot sensors, a leg sensor with its foot's two sensors).

Output ``data/labelled/<log>.parquet`` (schema in :mod:`pipeline.logs.schema`) and, in the MLflow run, a
per-log summary (cut-set names with ':' for '+'): fraction of exact labels per sensor, pair and cut set,
contact phases, and for simulated
logs the contact agreement with the true contact set and the label error against the true wrenches.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import DataError

if TYPE_CHECKING:
    from pipeline.core.config import Params
    from pipeline.labels.table import LogSummary

STAGE = "label"


# --- the stage -----------------------------------------------------------------------------------


def run(
    params: Params,
    in_dir: str | Path,
    out_dir: str | Path,
    truth_dir: str | Path | None = None,
    *,
    progress: bool | None = None,
) -> list[LogSummary]:
    """Label every smoothed table of `in_dir` into `out_dir`, in one MLflow run."""
    import mlflow

    from pipeline.core.config import LabelParams, repo_root, resolve_urdf, stage_section
    from pipeline.core.parallel import forked_map
    from pipeline.core.progress import progress_bar
    from pipeline.core.tracking import stage_run
    from pipeline.labels.joints import merge_exact
    from pipeline.labels.table import Labeller, label_table
    from pipeline.logs.smoothing import find_tables
    from pipeline.physics.cuts import find_cut_sets
    from pipeline.physics.feet import robot_feet
    from pipeline.physics.robot import load_robot

    cfg = stage_section(params, STAGE, LabelParams)
    src, out = Path(in_dir), Path(out_dir)
    if not src.is_dir():
        raise DataError(f"{src}: input directory not found")
    tables = find_tables(src)
    if not tables:
        raise DataError(f"{src}: no smoothed *.parquet tables")
    robot = load_robot(resolve_urdf(params.robot.urdf, repo_root()))
    feet = robot_feet(robot, params.robot.foot_pairs)
    pairs = [f.pair for f in feet if f.pair is not None]
    cuts = find_cut_sets(robot, pairs, cfg.cut_max_sensors)
    # one RNEA thread: the tables are labelled in forked processes, one per core
    lab = Labeller(robot, pairs, cuts, cfg, params.robot.gravity, feet, threads=1)
    summaries: list[LogSummary] = []
    start = time.perf_counter()
    with stage_run(STAGE, {"label": asdict(cfg), "robot": asdict(params.robot)}):
        with progress_bar(progress) as bar:
            task = bar.add_task("label", total=len(tables))
            truth = Path(truth_dir) if truth_dir else None
            # the tables are independent: one forked process per core, the largest first
            jobs = [lambda t=table: label_table(t, out / t.name, lab, truth) for table in tables]
            for summary in forked_map(jobs, costs=[t.stat().st_size for t in tables]):
                summaries.append(summary)
                bar.advance(task)
        seconds = time.perf_counter() - start
        samples = sum(s.samples for s in summaries)
        metrics: dict[str, float] = {
            "logs": len(summaries),
            "samples": samples,
            "seconds": seconds,
            "samples_per_s": samples / seconds if seconds else 0.0,
        }
        for name, entry in merge_exact([s.exact for s in summaries]).items():
            metrics[f"exact_samples.{name}"] = entry["samples"]
            metrics[f"lost_samples.{name}"] = entry["lost"]
        for s in summaries:
            metrics[f"{s.log}.guard_fraction"] = s.guard_fraction
            if s.truth_agreement is not None:
                metrics[f"{s.log}.contact_agreement"] = s.truth_agreement
            for name, frac in s.exact_fraction.items():
                metrics[f"{s.log}.exact.{name}"] = frac
            for name, err in s.label_rmse.items():
                metrics[f"{s.log}.label_rmse_force.{name}"] = err["force"]
                metrics[f"{s.log}.label_rmse_torque.{name}"] = err["torque"]
        # MLflow metric names cannot hold '+': cut-set names show it as ':' there
        mlflow.log_metrics({k.replace("+", ":"): v for k, v in metrics.items()})
        mlflow.log_dict({"logs": [asdict(s) for s in summaries]}, "label_summary.json")
    return summaries


def _cmd(args: argparse.Namespace) -> int:
    import pyarrow.parquet as pq

    from pipeline.core.config import load_params
    from pipeline.labels.joints import exact_text, merge_exact
    from pipeline.logs import schema as S

    params = load_params(args.params)
    summaries = run(params, args.inputs, args.out, args.truth)
    samples = sum(s.samples for s in summaries)
    seconds = sum(s.seconds for s in summaries)
    sensors = S.sensors_of(pq.read_schema(Path(args.out) / f"{summaries[0].log}{S.PARQUET_SUFFIX}").names)
    exact = merge_exact([s.exact for s in summaries])
    print(
        f"labelled {len(summaries)} log(s), {samples} samples, {samples / max(seconds, 1e-9):.0f} samples/s, "
        f"into {args.out}; exact labels per sensor: {', '.join(exact_text(s, exact[s]) for s in sensors)}"
    )
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal label IN OUT [--truth DIR]`."""
    parser = subparsers.add_parser(
        STAGE, help="contacts, switches and expected wrenches", description=(__doc__ or "").split("\n\n")[0]
    )
    parser.add_argument("inputs", type=Path, metavar="IN", help="directory of smoothed <log>.parquet tables")
    parser.add_argument("out", type=Path, help="output directory for the labelled <log>.parquet tables")
    parser.add_argument(
        "--truth",
        type=Path,
        default=None,
        help="directory of simulated <log>.truth.parquet tables (optional): adds the contact "
        "agreement and label error against truth to the summary",
    )
    add_params_option(parser)
    parser.set_defaults(func=_cmd)


__all__ = ["STAGE", "add_cli", "run"]
