"""Stage `ingest`: robot logs -> one aligned Parquet table per log (plus the simulated truth apart).

Every log under the source directory (``*.mcap``, recursively) becomes ``<out>/<log>.parquet``: its
topics decoded and aligned on the joint-state stamps (`pipeline.logs.mcap_table`, rules in
`pipeline.logs.align`). The output directory is all or nothing: the tables are written into a hidden
staging directory beside it, which replaces the output only when every log is done (with
``ingest.skip_bad_logs``, every good log); a failed or killed run leaves the previous output as it was,
and the next run removes the dead run's staging directory.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import ConfigError, DataError
from pipeline.logs.logfiles import LOG_SUFFIXES, RobotLogSpec, find_logs, ingest_one, log_size, output_name
from pipeline.logs.params import IngestParams

if TYPE_CHECKING:
    from pipeline.core.config import Params
    from pipeline.logs.tables import LogReport

STAGE = "ingest"
_STAGING = ".{name}.{pid}.ingest-tmp"  # staging directory beside the output, per process


# --- the output directory ------------------------------------------------------------------------


def _prepare_output(out: Path) -> Path:
    """Check `out`, remove dead runs' staging directories, and make this run's (empty) staging one."""
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: output path exists and is not a directory")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"{out}: cannot create the output directory: {exc.strerror or exc}") from None
    for old in out.parent.glob(_STAGING.format(name=out.name, pid="*")):
        pid = old.name.rsplit(".", 2)[-2]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    for path in (out.parent, out):
        if path.exists() and not os.access(path, os.W_OK | os.X_OK):
            raise DataError(f"{path}: output directory is not writable")
    staging = out.parent / _STAGING.format(name=out.name, pid=os.getpid())
    shutil.rmtree(staging, ignore_errors=True)
    try:
        staging.mkdir()
    except OSError as exc:
        raise DataError(f"{out}: cannot write the output directory: {exc.strerror or exc}") from None
    return staging


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _publish(staging: Path, out: Path) -> None:
    """Replace `out` by the complete `staging` directory (the old output is removed)."""
    old = out.parent / f"{staging.name}.old"
    try:
        if out.exists():
            os.replace(out, old)
        os.replace(staging, out)
    except OSError as exc:
        raise DataError(f"{out}: cannot replace the output directory: {exc.strerror or exc}") from None
    shutil.rmtree(old, ignore_errors=True)


# --- the stage -----------------------------------------------------------------------------------


@dataclass
class IngestSummary:
    """What one execution of the stage did."""

    reports: list[LogReport]
    skipped: list[LogReport]
    seconds: float

    @property
    def warnings(self) -> list[str]:
        out = [w for r in self.reports for w in r.warnings]
        return out + [f"skipped {r.source}: {r.error}" for r in self.skipped]


def run(
    params: Params, source_dir: str | Path, out_dir: str | Path, *, progress: bool | None = None
) -> IngestSummary:
    """Ingest every log under `source_dir` into `out_dir` (all or nothing), in one MLflow run."""
    import mlflow

    from pipeline.core.config import repo_root, resolve_urdf, stage_section
    from pipeline.core.tracking import stage_run
    from pipeline.logs.imu_axes import check_sensors
    from pipeline.physics.robot import load_robot

    cfg = stage_section(params, STAGE, IngestParams)
    source, out = Path(source_dir), Path(out_dir)
    if not source.is_dir():
        raise DataError(f"{source}: source directory not found")
    logs = find_logs(source, cfg.dumper.sidecar_suffix if cfg.dumper is not None else ".yaml")
    if not logs:
        raise DataError(f"{source}: no logs found ({', '.join('*' + s for s in LOG_SUFFIXES)})")
    names = [output_name(log, source) for log in logs]
    if len(set(names)) != len(names):
        raise DataError(f"{source}: two logs map to the same table name")
    urdf = resolve_urdf(params.robot.urdf, repo_root())
    robot = load_robot(urdf)
    check_sensors(cfg.imu_axes, robot.sensors, "ingest.imu_axes")
    unknown = sorted(set(cfg.fixed_joints) - set(robot.joint_names))
    if unknown:
        raise ConfigError(f"ingest.fixed_joints.{unknown[0]}: not a joint of {params.robot.urdf}")
    spec = RobotLogSpec(
        cfg,
        params.topics,
        robot.joint_names,
        list(robot.sensors),
        [params.robot.urdf, robot.name, Path(urdf).stem],
    )
    run_params = {
        "ingest": asdict(cfg),
        "topics": asdict(params.topics),
        "robot": {"urdf": params.robot.urdf},
    }
    staging = _prepare_output(out)
    try:
        with stage_run(STAGE, run_params) as active:
            mlflow.set_tags({"source_dir": str(source), "out_dir": str(out)})
            summary = _ingest_all(logs, names, staging, spec, progress)
            _log_mlflow(active, summary)
        if not summary.reports:
            raise DataError(f"{source}: no usable log ({len(summary.skipped)} skipped as bad)")
        _publish(staging, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    for report in summary.reports:
        report.output = str(out / Path(report.output or "").name)
        if report.truth_output:
            report.truth_output = str(out / Path(report.truth_output).name)
    for warning in summary.warnings:
        if not warning.startswith("skipped "):
            print(f"ftcal: warning: {warning}", file=sys.stderr)
    return summary


def _ingest_all(
    logs: Sequence[Path], names: Sequence[str], staging: Path, spec: RobotLogSpec, progress: bool | None
) -> IngestSummary:
    """Ingest the logs into `staging`, one forked process per core, the largest first; their reports in
    the logs' order. A bad log raises, or is skipped with skip_bad_logs; the bar advances by whole logs."""
    import mlflow

    from pipeline.core.parallel import forked_map
    from pipeline.core.progress import progress_bar
    from pipeline.logs.tables import LogReport

    t0 = time.perf_counter()
    reports: list[LogReport] = []
    skipped: list[LogReport] = []
    mlflow.set_tags({"logs": str(len(logs))})
    sizes = [log_size(log) for log in logs]
    jobs = [
        lambda log=log, name=name: _ingest_job(log, staging, name, spec)
        for log, name in zip(logs, names, strict=True)
    ]
    with progress_bar(progress, bytes_=True) as bar:
        task = bar.add_task(f"{len(logs)} log(s)", total=sum(sizes))
        done = forked_map(jobs, costs=sizes, labels=[str(log) for log in logs])
        for log, size, result in zip(logs, sizes, done, strict=True):
            bar.advance(task, size)
            if isinstance(result, LogReport):
                reports.append(result)
                continue
            if not spec.cfg.skip_bad_logs:
                mlflow.set_tag("error", str(result)[:5000])
                raise result
            skipped.append(LogReport(source=str(log), error=str(result)))
            print(f"ftcal: warning: skipping {result}", file=sys.stderr)
    return IngestSummary(reports, skipped, time.perf_counter() - t0)


def _ingest_job(log: Path, staging: Path, name: str, spec: RobotLogSpec) -> LogReport | DataError:
    """`ingest_one` as a job of `_ingest_all`: a bad log's DataError is returned, for the caller to skip
    or raise in the logs' order; a failed write raises a DataError at once."""
    try:
        return ingest_one(log, staging, name, spec, None)
    except DataError as exc:
        return exc
    except OSError as exc:
        raise DataError(f"{staging.parent}: cannot write {name}: {exc.strerror or exc}") from None


def _log_mlflow(active: Any, summary: IngestSummary) -> None:
    import mlflow

    messages = sum(r.messages for r in summary.reports)
    samples = sum(r.samples for r in summary.reports)
    metrics = {
        "logs_ingested": len(summary.reports),
        "logs_skipped": len(summary.skipped),
        "messages": messages,
        "samples": samples,
        "seconds": summary.seconds,
        "warnings": len(summary.warnings),
        "messages_per_s": messages / summary.seconds if summary.seconds > 0 else 0.0,
    }
    flags = {"duplicates": 0, "reordered": 0, "nonfinite": 0, "late": 0}
    for report in summary.reports:
        for st in report.streams.values():
            for key in flags:
                flags[key] += getattr(st, key)
    metrics.update({f"messages_{k}": v for k, v in flags.items()})
    metrics["samples_frozen"] = sum(n for r in summary.reports for n in r.frozen.values())
    mlflow.log_metrics({k: float(v) for k, v in metrics.items()})
    mlflow.log_text("\n".join(summary.warnings) + ("\n" if summary.warnings else ""), "warnings.txt")
    mlflow.log_dict(
        {
            "logs": [
                {
                    "source": r.source,
                    "output": r.output,
                    "truth": r.truth_output,
                    "samples": r.samples,
                    "messages": r.messages,
                    "seconds": r.seconds,
                    "streams": {k: asdict(v) for k, v in r.streams.items()},
                    "absent": r.absent,
                    "not_read": r.not_read,
                    "fixed_joints": r.fixed,
                    "frozen_samples": r.frozen,
                    "tables": r.outputs,
                }
                for r in summary.reports
            ],
            "skipped": [{"source": r.source, "error": r.error} for r in summary.skipped],
        },
        "ingest_summary.json",
    )


# --- CLI -----------------------------------------------------------------------------------------


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    params = load_params(args.params)
    summary = run(params, args.source, args.out)
    print(summary_line(summary, args.out))
    return 0


def summary_line(summary: IngestSummary, out: str | Path) -> str:
    """One line: logs, samples, where; what the logs lack (absent streams), what they hold that is not
    read (each name once, with the number of logs holding it) and what was frozen."""
    from pipeline.logs import schema as S

    rows = sum(r.samples for r in summary.reports)
    kept = sum(r.samples if r.kept is None else r.kept for r in summary.reports)
    tables = sum(max(len(r.outputs), 1) for r in summary.reports)
    parts = [f"ingested {len(summary.reports)} log(s), {kept} samples, into {out}"]
    if kept != rows:
        parts[0] += f" ({rows} read, kept in the experiments' windows and segments)"
    if tables != len(summary.reports):
        parts[0] += f" as {tables} tables (segments)"
    by_lack: dict[tuple[str, ...], list[str]] = {}  # logs lacking the same streams, named once
    for r in summary.reports:
        if r.absent:
            by_lack.setdefault(tuple(r.absent), []).append(Path(r.source).name)
    absent = [
        f"{', '.join(logs) if len(logs) <= 3 else f'{len(logs)} logs'}: {', '.join(lack)}"
        for lack, logs in by_lack.items()
    ]
    if absent:
        parts.append("absent: " + "; ".join(absent))
    many = len(summary.reports) > 1
    for what, names in (
        ("not read", [r.not_read for r in summary.reports]),
        ("declared still", [r.fixed for r in summary.reports]),
    ):
        counts: dict[str, int] = {}
        for name in (n for each in names for n in each):
            counts[name] = counts.get(name, 0) + 1
        if counts:
            parts.append(f"{what}: " + ", ".join(f"{k} ({n} logs)" if many else k for k, n in counts.items()))
    frozen = []
    for r in summary.reports:
        rate = r.streams[S.JOINTS_STREAM].rate_hz if S.JOINTS_STREAM in r.streams else float("nan")
        for sensor, n in r.frozen.items():
            seconds = f"{n / rate:.1f} s, " if rate > 0 else ""
            frozen.append(f"{Path(r.source).name}: {sensor} {seconds}{n / max(r.samples, 1):.1%} of samples")
    if frozen:
        parts.append("frozen: " + "; ".join(frozen))
    if summary.skipped:
        parts.append(f"skipped {len(summary.skipped)} bad log(s)")
    return "; ".join(parts) + f" ({summary.seconds:.1f} s)"


def add_cli(subparsers: Any) -> None:
    """Add `ftcal ingest SOURCE OUT`."""
    parser = subparsers.add_parser(
        STAGE,
        help="decode MCAP logs into aligned Parquet tables",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument("source", type=Path, help="directory searched recursively for *.mcap and *.mat logs")
    parser.add_argument("out", type=Path, help="output directory for <log>.parquet (+ <log>.truth.parquet)")
    add_params_option(parser)
    parser.set_defaults(func=_cmd)
