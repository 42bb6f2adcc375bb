"""`ftcal calibrate IN OUT [--models DIR]`: a log's copy with the exported calibration's wrenches added.

IN is an MCAP log with the contract topics (or a directory: every ``*.mcap`` under it, written to the same
relative paths under OUT). OUT is a copy in which every original record is kept byte for byte (schemas,
channels, chunks, log and publish times, sequence numbers, metadata) plus, per raw wrench message of a
sensor the export models, one ``<wrench topic>_calibrated`` geometry_msgs/msg/WrenchStamped with the same
header (stamp, frame_id), log time and publish time: the export's float64 graph on the raw wrench and the
latest temperature (and IMU) stamped at or before it (`pipeline.export.runtime`). The file is streamed
chunk by chunk (memory flat in the log length) and written atomically; it opens in Foxglove as any log.

Sensors with wrench messages but no model pass through uncalibrated (a warning). A log the models cannot
calibrate (another robot's, a modelled sensor's temperature or IMU topic missing, a truncated file) is a
one-line error and nothing is written; an existing OUT is refused unless ``--force``.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import DataError

COMMAND = "calibrate"
DEFAULT_MODELS = "exported"  # the export stage's output directory, at the repo root (dvc.yaml)
MCAP_SUFFIX = ".mcap"


@dataclass
class CalibrateResult:
    source: Path
    out: Path
    messages: int  # original messages, copied
    added: int  # calibrated messages added
    seconds: float
    uncalibrated: dict[str, int] = field(default_factory=dict)  # sensor -> wrench messages without inputs yet
    warnings: list[str] = field(default_factory=list)

    @property
    def rate(self) -> float:
        """Messages (original + added) per second of wall time."""
        return (self.messages + self.added) / self.seconds if self.seconds > 0 else float("inf")


def plan_log(reader: Any, deployment: Any, topics: Any) -> tuple[list[Any], list[str]]:
    """(the plans of the modelled sensors present in the log, warnings). DataError if the log cannot be
    calibrated by these models (module docstring)."""
    from pipeline.export.runtime import check_robot, sensors_in_topics
    from pipeline.logs.rosmsg import IMU, TEMPERATURE, WRENCH_STAMPED

    check_robot(deployment, reader.metadata, reader.path)
    present = {t: info for t, info in reader.topics.items() if info.message_count}
    plans, modelled = [], set()
    for plan in deployment.plans(topics):
        modelled.add(plan.sensor)
        if plan.wrench_topic not in present:
            continue
        for topic, msgtype in (
            (plan.wrench_topic, WRENCH_STAMPED),
            (plan.temperature_topic, TEMPERATURE),
            (plan.imu_topic, IMU),
        ):
            if topic is None:
                continue
            if topic not in present:
                need = f"its {plan.n_inputs}-input model ({plan.group})"
                raise DataError(f"{reader.path}: has {plan.wrench_topic} but no {topic}, an input of {need}")
            if present[topic].msgtype != msgtype:
                raise DataError(
                    f"{reader.path}: topic {topic} has type {present[topic].msgtype}, expected {msgtype}"
                )
        plans.append(plan)
    if not plans:
        raise DataError(
            f"{reader.path}: none of the sensors of {deployment.path} ({', '.join(sorted(modelled))}) has "
            f"messages on {topics.ft_wrench} (models of another robot, or other topic names?)"
        )
    others = sorted(set(sensors_in_topics(topics.ft_wrench, present)) - modelled)
    warnings = [f"{reader.path}: no model for {s}: its wrenches pass through uncalibrated" for s in others]
    return plans, warnings


def _records(augmenter: Any, channels: dict[str, int], calibrated: list[Any]) -> list[tuple[int, Any, Any]]:
    """MCAP Message records of calibrated wrenches, per (channel, frame_id)."""
    import numpy as np

    from pipeline.logs.cdr import WRENCH_STAMPED, fixed_records, fixed_template

    parts = []
    for c in calibrated:
        channel = channels[c.plan.sensor]
        for frame in dict.fromkeys(c.frame_id.tolist()):
            sel = c.frame_id == frame if len(set(c.frame_id.tolist())) > 1 else np.ones(len(c.stamp), bool)
            template = fixed_template(WRENCH_STAMPED, str(frame).encode())
            seq = augmenter.next_sequence(channel, int(sel.sum()))
            rec = fixed_records(
                template,
                channel,
                seq,
                c.log_time[sel],
                c.publish_time[sel],
                c.stamp[sel],
                {"wrench": c.wrench[sel]},
            )
            parts.append((channel, rec, c.log_time[sel]))
    return parts


def calibrate_log(reader: Any, out: Path, deployment: Any, plans: list[Any]) -> CalibrateResult:
    """Write `out`: the log of `reader` with calibrated wrenches added (module docstring)."""
    from pipeline.export.runtime import CausalCalibrator
    from pipeline.logs.augment import LogAugmenter
    from pipeline.logs.rosmsg import WRENCH_STAMPED

    t0 = time.perf_counter()
    calibrator = CausalCalibrator(deployment, plans)
    with LogAugmenter(reader, out) as augmenter:
        channels = {p.sensor: augmenter.add_channel(p.out_topic, WRENCH_STAMPED) for p in plans}
        for index, batches in reader.iter_indexed_chunks(calibrator.topics()):
            augmenter.copy_through(index)
            augmenter.add_chunk(_records(augmenter, channels, calibrator.feed(batches)))
        augmenter.add_chunk(_records(augmenter, channels, calibrator.flush()))
    added = sum(calibrator.calibrated.values())
    return CalibrateResult(
        reader.path,
        out,
        reader.message_count,
        added,
        time.perf_counter() - t0,
        {s: n for s, n in calibrator.uncalibrated.items() if n},
    )


def _pairs(source: Path, out: Path) -> list[tuple[Path, Path]]:
    """(input log, output log) pairs of the file or directory form."""
    if source.is_dir():
        logs = sorted(source.rglob(f"*{MCAP_SUFFIX}"))
        if not logs:
            raise DataError(f"{source}: no *{MCAP_SUFFIX} logs")
        if out.exists() and not out.is_dir():
            raise DataError(f"{out}: exists and is not a directory (IN is a directory)")
        return [(log, out / log.relative_to(source)) for log in logs]
    if not source.is_file():
        raise DataError(f"{source}: log not found")
    if out.is_dir():
        raise DataError(f"{out}: is a directory (IN is one log: give an output file)")
    return [(source, out)]


def run(
    params: Any, source: str | Path, out: str | Path, models: str | Path, *, force: bool = False
) -> list[CalibrateResult]:
    """Calibrate one log or a directory of logs (module docstring); every input is checked first."""
    from pipeline.export.runtime import Deployment
    from pipeline.logs.rosmsg import LogReader

    pairs = _pairs(Path(source), Path(out))
    for src, dst in pairs:
        if dst.exists() and not force:
            raise DataError(f"{dst}: exists (use --force to replace it)")
        if dst.resolve() == src.resolve():
            raise DataError(f"{dst}: is the input log (write the copy elsewhere)")
    deployment = Deployment.load(models)
    planned = []
    for src, dst in pairs:
        with LogReader(src) as reader:
            planned.append((src, dst, *plan_log(reader, deployment, params.topics)))
    results = []
    for src, dst, plans, warnings in planned:
        with LogReader(src) as reader:
            result = calibrate_log(reader, dst, deployment, plans)
        result.warnings = warnings + [
            f"{src}: {n} wrench messages of {s} precede its first temperature/IMU message: not calibrated"
            for s, n in result.uncalibrated.items()
        ]
        results.append(result)
    return results


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params, repo_root

    params = load_params(args.params)
    models = args.models if args.models is not None else repo_root() / DEFAULT_MODELS
    results = run(params, args.source, args.out, models, force=args.force)
    for r in results:
        for warning in r.warnings:
            print(f"ftcal: warning: {warning}", file=sys.stderr)
        print(
            f"{r.out}: {r.messages} messages copied, {r.added} calibrated wrenches added "
            f"({r.rate / 1e3:.0f} k messages/s)"
        )
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal calibrate IN OUT [--models DIR] [--force]`."""
    parser = subparsers.add_parser(
        COMMAND,
        help="copy a log adding the exported calibration's wrenches",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument("source", type=Path, metavar="IN", help="MCAP log, or a directory of *.mcap logs")
    parser.add_argument("out", type=Path, metavar="OUT", help="output log (or directory, for a directory IN)")
    parser.add_argument(
        "--models",
        type=Path,
        default=None,
        metavar="DIR",
        help=f"export directory with manifest.json (default: {DEFAULT_MODELS}/ at the repo root)",
    )
    parser.add_argument("--force", action="store_true", help="replace existing output logs")
    add_params_option(parser, "topic names")
    parser.set_defaults(func=_cmd)
