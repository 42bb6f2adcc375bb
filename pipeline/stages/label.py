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

Every FT board's IMU is checked against the kinematics (:mod:`pipeline.labels.imu_check`): per log and
sensor the check's record in the table's ``ftcal.label`` metadata (``imu_axes``) and the summary; a board
whose axes are not the sensor frame's is one warning line naming the axis map it follows and the
``ingest.imu_axes`` entry that maps it (train then refuses its 13-input networks).
"""

from __future__ import annotations

import argparse
import sys
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
    urdf: str | Path | None = None,
) -> list[LogSummary]:
    """Label every smoothed table of `in_dir` into `out_dir`, in one MLflow run; with the robot of `urdf`
    (a URDF file: an identified model, `pipeline.stages.identify`) instead of ``robot.urdf``."""
    import mlflow

    from pipeline.core.config import repo_root, resolve_urdf
    from pipeline.core.parallel import forked_map
    from pipeline.core.progress import progress_bar
    from pipeline.core.tracking import stage_run
    from pipeline.labels.imu_params import label_params
    from pipeline.labels.joints import merge_exact
    from pipeline.labels.table import Labeller, label_table
    from pipeline.logs.smoothing import find_tables
    from pipeline.physics.cuts import find_cut_sets
    from pipeline.physics.feet import robot_feet
    from pipeline.physics.robot import load_robot

    cfg = label_params(params)
    src, out = Path(in_dir), Path(out_dir)
    if not src.is_dir():
        raise DataError(f"{src}: input directory not found")
    tables = find_tables(src)
    if not tables:
        raise DataError(f"{src}: no smoothed *.parquet tables")
    robot = load_robot(urdf if urdf is not None else resolve_urdf(params.robot.urdf, repo_root()))
    feet = robot_feet(robot, params.robot.foot_pairs)
    pairs = [f.pair for f in feet if f.pair is not None]
    cuts = find_cut_sets(robot, pairs, cfg.cut_max_sensors)
    # one RNEA thread: the tables are labelled in forked processes, one per core
    lab = Labeller(robot, pairs, cuts, cfg, params.robot.gravity, feet, threads=1)
    summaries: list[LogSummary] = []
    start = time.perf_counter()
    run_params = {"label": asdict(cfg), "robot": asdict(params.robot), "labels_urdf": str(urdf or "")}
    with stage_run(STAGE, run_params):
        with progress_bar(progress) as bar:
            task = bar.add_task("label", total=len(tables))
            truth = Path(truth_dir) if truth_dir else None
            # the tables are independent: one forked process per core, the largest first
            jobs = [lambda t=table: label_table(t, out / t.name, lab, truth) for table in tables]
            sizes = [t.stat().st_size for t in tables]
            for summary in forked_map(jobs, costs=sizes, labels=list(map(str, tables))):
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
        metrics.update(_imu_metrics(summaries))
        # MLflow metric names cannot hold '+': cut-set names show it as ':' there
        mlflow.log_metrics({k.replace("+", ":"): v for k, v in metrics.items()})
        mlflow.log_dict({"logs": [asdict(s) for s in summaries]}, "label_summary.json")
        mlflow.log_dict({"flagged": imu_flagged(summaries)}, "imu_check.json")
    return summaries


def imu_flagged(summaries: list[LogSummary]) -> dict[str, str]:
    """FT sensor -> one line, for each board whose IMU check failed in a log (`pipeline.labels.imu_check`)."""
    from pipeline.logs.imu_axes import flagged_boards

    return flagged_boards({s.log: s.imu_axes for s in summaries})


def _imu_metrics(summaries: list[LogSummary]) -> dict[str, float]:
    """Per log and sensor the IMU check (1 passed, 0 not checked, -1 failed) and its residual RMS (m/s^2);
    the number of flagged sensors."""
    out: dict[str, float] = {"imu_flagged": len(imu_flagged(summaries))}
    for s in summaries:
        for sensor, record in s.imu_axes.items():
            out[f"{s.log}.imu_check.{sensor}"] = {"passed": 1, "failed": -1}.get(record["status"], 0)
            if record["accelerometer"].get("rms_m_s2") is not None:
                out[f"{s.log}.imu_rms.{sensor}"] = record["accelerometer"]["rms_m_s2"]
    return out


def _cmd(args: argparse.Namespace) -> int:
    import pyarrow.parquet as pq

    from pipeline.core.config import load_params
    from pipeline.labels.joints import exact_text, merge_exact
    from pipeline.labels.table import FIXED_DELTA_DEG
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
    moved = [(s.log, k, v) for s in summaries for k, v in s.fixed_sensitivity.items() if v > 0]
    if moved:  # labels that rest on joints declared still: how far they move were those off
        worst = {}
        for log, sensor, rms in moved:
            worst[sensor] = max(worst.get(sensor, (0.0, log)), (rms, log))
        text = ", ".join(f"{k} {v[0]:.3g} ({v[1]})" for k, v in worst.items())
        print(
            f"labels' change were the declared-still joints {FIXED_DELTA_DEG:g} deg off (RMS, N/Nm): {text}"
        )
    for line in imu_flagged(
        summaries
    ).values():  # a board whose IMU is not in the sensor frame: one line each
        print(f"ftcal: warning: {line}", file=sys.stderr)
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


__all__ = ["STAGE", "add_cli", "imu_flagged", "run"]
