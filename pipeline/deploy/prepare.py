"""Deployment logs through the pipeline's own steps: ingest, smooth, label (truth kept where simulated).

The same library functions as the stages (`pipeline.logs.logfiles.ingest_one`, `smooth_table`,
`label_table`), into a day's tables directory (``ingested/``, ``smoothed/``, ``labelled/`` and
``logs.json``, the list of its logs: `write_day`, `read_day`), so a deployment log is read exactly as a
training log was. Real logs (no truth) too.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.core.config import LabelParams, Params, repo_root, resolve_urdf, stage_section
from pipeline.core.errors import DataError
from pipeline.logs import schema as S
from pipeline.logs.smoothing import SmoothParams, smooth_table
from pipeline.physics.robot import RobotModel, load_robot

if TYPE_CHECKING:
    from pipeline.labels.table import Labeller
    from pipeline.logs.logfiles import RobotLogSpec


@dataclass(frozen=True)
class DeployLog:
    """One deployment log and its tables (paths), its experiment record and whether truth exists."""

    name: str
    source: Path  # the MCAP / .mat log
    smoothed: Path
    labelled: Path
    truth: Path | None
    experiment: dict[str, str]


def load_nominal_robot(params: Params, urdf: str | Path | None = None) -> RobotModel:
    """The robot the calibration and the estimators know: that of `urdf` (the training labels' URDF,
    ``models/identified/labels.urdf``) if given, else of ``robot.urdf``."""
    return load_robot(urdf if urdf is not None else resolve_urdf(params.robot.urdf, repo_root()))


def robot_cuts(params: Params, robot: RobotModel) -> tuple[list[Any], list[Any], list[Any]]:
    """(feet, foot pairs, cut sets) of the robot as the labeller finds them (``robot.foot_pairs``,
    ``label.cut_max_sensors``): the exact sums of a labelled table."""
    from pipeline.physics.cuts import find_cut_sets
    from pipeline.physics.feet import robot_feet

    feet = robot_feet(robot, params.robot.foot_pairs)
    pairs = [f.pair for f in feet if f.pair is not None]
    label_cfg = stage_section(params, "label", LabelParams)
    return feet, pairs, find_cut_sets(robot, pairs, label_cfg.cut_max_sensors)


def prepare_logs(
    params: Params, robot: RobotModel, logs: list[Path], source_dir: Path, work: Path
) -> list[DeployLog]:
    """Ingest, smooth and label every log of `logs` (under `source_dir`) into `work`/<step>/."""
    from pipeline.core.parallel import forked_map
    from pipeline.labels.table import Labeller
    from pipeline.logs.logfiles import RobotLogSpec, log_size, output_name
    from pipeline.logs.params import IngestParams

    spec = RobotLogSpec(
        stage_section(params, "ingest", IngestParams),
        params.topics,
        robot.joint_names,
        list(robot.sensors),
        [params.robot.urdf, robot.name, Path(robot.urdf_path).stem],
    )
    smooth_cfg = stage_section(params, "smooth", SmoothParams)
    label_cfg = stage_section(params, "label", LabelParams)
    feet, pairs, cuts = robot_cuts(params, robot)
    # one RNEA thread: the logs are labelled in forked processes, one per core
    lab = Labeller(robot, pairs, cuts, label_cfg, params.robot.gravity, feet, threads=1)
    dirs = {k: work / k for k in ("ingested", "smoothed", "labelled")}
    for d in dirs.values():
        d.mkdir(parents=True, exist_ok=True)
    import scipy.signal  # noqa: F401  (smooth_table's filter: imported once, inherited by the workers)

    # the logs are independent: one forked process per core, the largest first
    jobs = [
        lambda log=log: _prepare_one(log, output_name(log, source_dir), dirs, spec, smooth_cfg, lab)
        for log in logs
    ]
    return list(forked_map(jobs, costs=[log_size(log) for log in logs], labels=list(map(str, logs))))


def _prepare_one(
    log: Path, name: str, dirs: dict[str, Path], spec: RobotLogSpec, smooth_cfg: SmoothParams, lab: Labeller
) -> DeployLog:
    """Ingest, smooth and label one log as `name` into `dirs` (``ingested``, ``smoothed``, ``labelled``)."""
    from pipeline.labels.table import label_table
    from pipeline.logs.logfiles import ingest_one

    ingest_one(log, dirs["ingested"], name, spec, None)
    table = S.PARQUET_SUFFIX
    smooth_table(dirs["ingested"] / f"{name}{table}", dirs["smoothed"] / f"{name}{table}", smooth_cfg)
    truth = dirs["ingested"] / f"{name}{S.TRUTH_SUFFIX}{table}"
    has_truth = truth.is_file()
    label_table(
        dirs["smoothed"] / f"{name}{table}",
        dirs["labelled"] / f"{name}{table}",
        lab,
        dirs["ingested"] if has_truth else None,
    )
    return DeployLog(
        name,
        log,
        dirs["smoothed"] / f"{name}{table}",
        dirs["labelled"] / f"{name}{table}",
        truth if has_truth else None,
        _experiment(dirs["ingested"] / f"{name}{table}"),
    )


def _experiment(table: Path) -> dict[str, str]:
    import pyarrow.parquet as pq

    meta = pq.read_schema(table).metadata or {}
    raw = meta.get(S.META_EXPERIMENT)
    return json.loads(raw) if raw else {}


DAY_FILE = "logs.json"  # a day's tables directory: its logs, in order (`write_day`)


def not_simulated(folder: Path) -> str | None:
    """Why a simulated day's folder (or its tables) holds no log: the first line of its
    `S.NOT_SIMULATED` note (``ftcal simulate --if-ingested`` with recorded logs only); None if it has none."""
    note = Path(folder) / S.NOT_SIMULATED
    if not note.is_file():
        return None
    lines = note.read_text(encoding="utf-8").splitlines()
    return lines[0].strip() if lines else None


def write_day(out: Path, logs: list[DeployLog]) -> None:
    """Write `out`/logs.json: each log's name, source file (as given), experiment record and whether it has
    truth; `read_day` finds its tables again under the directory the day's tables end up in."""
    from pipeline.core.io import write_json

    write_json(
        out / DAY_FILE,
        [{"name": g.name, "source": str(g.source), "truth": g.truth is not None, "experiment": g.experiment}
         for g in logs],
    )  # fmt: skip


def read_day(day: Path) -> list[DeployLog]:
    """The logs of a day's tables directory (`write_day`); DataError naming the file if it is not one."""
    file = day / DAY_FILE
    try:
        entries: list[dict[str, Any]] = json.loads(file.read_text(encoding="utf-8"))
        out = []
        for e in entries:
            table = f"{e['name']}{S.PARQUET_SUFFIX}"
            truth = day / "ingested" / f"{e['name']}{S.TRUTH_SUFFIX}{S.PARQUET_SUFFIX}"
            out.append(
                DeployLog(
                    e["name"], Path(e["source"]), day / "smoothed" / table, day / "labelled" / table,
                    truth if e["truth"] else None, dict(e["experiment"]),
                )
            )  # fmt: skip
    except FileNotFoundError:
        raise DataError(
            f"{file}: not found (a deployment day's tables: run `dvc repro deploy_days`)"
        ) from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{file}: not a deployment day's list of logs: {exc}") from None
    return out
