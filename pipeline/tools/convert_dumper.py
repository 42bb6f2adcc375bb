"""`ftcal convert-dumper RUN OUT.mcap`: a YARP dataDumper run as a contract MCAP log.

The run's ports are read through the maps ``ingest.dumper`` of params (as ingest does, `pipeline.logs.dumper`)
for the FT sensors and joints of ``robot.urdf``, and written on the topics of ``topics``: one joint-state
topic (the time-base board's messages with every board's joints, radians), the wrenches; each message
stamped with its sender stamp, its log time the reception time where the run has one (else the stamp).
The sidecar ``<run>.yaml`` becomes the ``experiment`` record (window and segments as JSON), and what the
run lacks the ``recording`` record, so that the MCAP ingests exactly like the run. Written atomically.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import DataError

COMMAND = "convert-dumper"


def convert(run: Path, out: Path, params: Any) -> dict[str, int]:
    """Write the dataDumper run `run` as the MCAP `out`; returns messages written per topic."""
    from pipeline.core.config import repo_root, resolve_urdf, stage_section
    from pipeline.logs.dumper import DumperRunReader, is_run
    from pipeline.logs.params import IngestParams
    from pipeline.physics.robot import load_robot

    cfg = stage_section(params, "ingest", IngestParams)
    if cfg.dumper is None:
        raise DataError(f"{run}: converting a dataDumper run needs the maps ingest.dumper in params")
    if not is_run(run, cfg.dumper.sidecar_suffix):
        raise DataError(
            f"{run}: not a dataDumper run (no <robot>/<part>/<port>/data.log or info.log, nor port folders "
            f"with a sidecar {run.name}{cfg.dumper.sidecar_suffix} beside it)"
        )
    robot = load_robot(resolve_urdf(params.robot.urdf, repo_root()))
    with DumperRunReader(
        run, params.topics, list(robot.sensors), cfg.dumper, robot.joint_names, max_gap_s=cfg.max_gap_s
    ) as reader:
        return write_mcap(reader, out)


def write_mcap(reader: Any, out: Path) -> dict[str, int]:
    """Write what a `DumperRunReader` hands out, with its experiment and recording records, as the MCAP
    `out` (atomically); returns messages written per topic."""
    from pipeline.logs import rosmsg
    from pipeline.logs.sidecar import RECORDING

    counts: dict[str, int] = {}
    meta = {k: reader.metadata[k] for k in ("experiment", RECORDING)}
    with rosmsg.LogWriter(out, meta) as writer:
        for batches in reader.iter_chunks():
            for b in batches:
                _write(writer, b)
                counts[b.topic] = counts.get(b.topic, 0) + len(b)
    return counts


def _write(writer: Any, b: Any) -> None:
    from pipeline.logs import rosmsg
    from pipeline.tools.convert_mat import frame_of

    f = b.fields
    if b.msgtype == rosmsg.JOINT_STATE:
        writer.joint_states(
            b.topic,
            b.stamp_ns,
            list(b.names),
            f["position"],
            f["velocity"],
            f["effort"],
            log_times_ns=b.log_time_ns,
        )
    else:
        writer.wrenches(b.topic, b.stamp_ns, frame_of(b.topic), f["wrench"], log_times_ns=b.log_time_ns)


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    params = load_params(args.params)
    if args.mcap.resolve() == args.run.resolve():
        raise DataError(f"{args.mcap}: the output would overwrite the input")
    counts = convert(args.run, args.mcap, params)
    print(f"wrote {args.mcap}: {sum(counts.values())} messages on {len(counts)} topics")
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal convert-dumper RUN OUT.mcap`."""
    parser = subparsers.add_parser(
        COMMAND,
        help="convert a YARP dataDumper run into a contract MCAP log",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument(
        "run", type=Path, help="run folder (<robot>/<part>/<port>/data.log; <run>.yaml beside it)"
    )
    parser.add_argument("mcap", type=Path, help="MCAP file to write")
    add_params_option(parser)
    parser.set_defaults(func=_cmd)
