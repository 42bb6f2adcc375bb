"""`ftcal calibrate IN OUT [--models DIR]`: a log's copy with the exported calibration's wrenches added.

IN is an MCAP log with the contract topics (or a directory: every ``*.mcap`` under it, written to the same
relative paths under OUT). OUT is a copy in which every original record is kept byte for byte (schemas,
channels, chunks, log and publish times, sequence numbers, metadata) plus, per raw wrench message of a
sensor the export models, one ``<wrench topic>_calibrated`` geometry_msgs/msg/WrenchStamped with the same
header (stamp, frame_id), log time and publish time: the export's float64 graph on the raw wrench and the
latest temperature (and IMU) stamped at or before it (`pipeline.export.runtime`, `pipeline.export.logcopy`),
with the offsets of the export's latest re-zeroing (``offsets.json`` beside it, `ftcal rezero`; another
file with ``--offsets``, none with ``--no-offsets``).
The file is streamed chunk by chunk (memory flat in the log length) and written atomically; it opens in
Foxglove as any log. A log without chunk indexes (a recorder that died before writing its summary, a writer
without chunking) is read by scanning its data section, as `ftcal ingest` reads it, and copied the same way.

Sensors with wrench messages but no model pass through uncalibrated (a warning). A log the models cannot
calibrate (another robot's, a modelled sensor recorded with another board than its calibration's: its
serial, `pipeline.export.identity`; a modelled sensor's temperature or IMU topic missing, a truncated
file) is a one-line error and nothing is written; an existing OUT is refused unless ``--force``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.core.cliargs import add_models_option, add_params_option, add_runtime_option, models_dir
from pipeline.core.errors import DataError

COMMAND = "calibrate"
MCAP_SUFFIX = ".mcap"

if TYPE_CHECKING:
    from pipeline.export.logcopy import CalibrateResult


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
    params: Any, source: str | Path, out: str | Path, models: str | Path, *, force: bool = False,
    offsets: Path | bool = True,
) -> list[CalibrateResult]:  # fmt: skip
    """Calibrate one log or a directory of logs (module docstring); every input is checked first.
    `offsets`: True, the re-zeroing beside the export if any; False, none; a path, that file's."""
    from pipeline.export.logcopy import calibrate_log
    from pipeline.export.offsets import summary
    from pipeline.export.runtime import Deployment, plan_log
    from pipeline.logs.rosmsg import LogReader

    pairs = _pairs(Path(source), Path(out))
    for src, dst in pairs:
        if dst.exists() and not force:
            raise DataError(f"{dst}: exists (use --force to replace it)")
        if dst.resolve() == src.resolve():
            raise DataError(f"{dst}: is the input log (write the copy elsewhere)")
    deployment = Deployment.load(models, offsets=offsets)
    planned = []
    for src, dst in pairs:
        with LogReader(src) as reader:
            planned.append((src, dst, *plan_log(reader, deployment, params.topics)))
    results = []
    for src, dst, plans, warnings in planned:
        with LogReader(src) as reader:
            result = calibrate_log(reader, dst, deployment, plans)
        result.offsets = summary(deployment.offsets)
        result.warnings = warnings + [
            f"{src}: {n} wrench messages of {s} precede its first temperature/IMU message: not calibrated"
            for s, n in result.uncalibrated.items()
        ]
        results.append(result)
    return results


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    params = load_params(args.params)
    models = models_dir(args.models)
    offsets = False if args.no_offsets else (args.offsets if args.offsets is not None else True)
    from pipeline.export.cbuild import using

    with using(args.runtime):
        results = run(params, args.source, args.out, models, force=args.force, offsets=offsets)
    if results:
        print(results[0].offsets)
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
    add_models_option(parser)
    parser.add_argument("--force", action="store_true", help="replace existing output logs")
    which = parser.add_mutually_exclusive_group()
    which.add_argument(
        "--offsets", type=Path, default=None, metavar="FILE",
        help="a re-zeroing's offsets (default: DIR/offsets.json if it exists; `ftcal rezero`)",
    )  # fmt: skip
    which.add_argument("--no-offsets", action="store_true", help="the calibration as delivered")
    add_runtime_option(parser)
    add_params_option(parser, "topic names")
    parser.set_defaults(func=_cmd)
