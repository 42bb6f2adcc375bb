"""One robot log, read: the log formats ingest reads, where a run's logs are, their tables' names, and
`ingest_one`, the one place that turns a log into its aligned table. A library: the stage `ingest` and the
deployment days (`pipeline.deploy.prepare`) read their logs through it alike.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.logs.params import IngestParams

if TYPE_CHECKING:
    from pipeline.core.config import TopicParams
    from pipeline.logs.tables import LogReport

LOG_SUFFIXES = (".mcap", ".mat")  # log formats read by `ingest_one` (.mat: YarpRobotLoggerDevice)


@dataclass(frozen=True)
class RobotLogSpec:
    """What every log of a run is read against: params and the robot's joints and FT sensors."""

    cfg: IngestParams
    topics: TopicParams
    joints: Sequence[str]  # URDF joint order
    sensors: Sequence[str]  # URDF FT sensor names
    robot_names: Sequence[str]  # names the logs' `experiment.robot` may use for this robot


def find_logs(source_dir: Path, sidecar_suffix: str = ".yaml") -> list[Path]:
    """Every log under `source_dir` (recursively), sorted: files (`LOG_SUFFIXES`) and dataDumper run
    directories (`pipeline.logs.dumper.is_run`, with their sidecars' `sidecar_suffix`), none inside a run."""
    from pipeline.logs.dumper import is_run

    logs: list[Path] = []
    for p in sorted(source_dir.rglob("*")):
        if logs and logs[-1].is_dir() and logs[-1] in p.parents:
            continue  # inside a run
        if (p.suffix in LOG_SUFFIXES and p.is_file()) or is_run(p, sidecar_suffix):
            logs.append(p)
    return logs


def output_name(log: Path, source_dir: Path) -> str:
    """Table name of a log: its path under the source directory, without suffix, '/' -> '__'."""
    rel = log.relative_to(source_dir)
    return "__".join((rel if log.is_dir() else rel.with_suffix("")).parts)


def log_size(log: Path) -> int:
    """Bytes of a log file, or of the files of a run directory."""
    if log.is_dir():
        return sum(p.stat().st_size for p in log.rglob("*") if p.is_file())
    return log.stat().st_size


def ingest_one(
    log: Path, out_dir: Path, name: str, spec: RobotLogSpec, progress: Callable[[int], None] | None
) -> LogReport:
    """Turn one log file into ``<out_dir>/<name>.parquet`` (+ truth): the one place that reads a log.

    Raises DataError naming the file for a log that cannot be used; then nothing of it is left.
    """
    from pipeline.logs.mcap_table import ingest_log

    return ingest_log(
        log,
        out_dir,
        name,
        spec.cfg,
        spec.topics,
        spec.joints,
        spec.sensors,
        spec.robot_names,
        progress,
    )
