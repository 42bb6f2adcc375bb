"""`ftcal convert-mat IN.mat OUT.mcap`: a YarpRobotLoggerDevice .mat log as a contract MCAP log.

The channels are found through the name map ``ingest.mat`` of params (as ingest does) for the FT sensors
of ``robot.urdf``, and written on the topics of ``topics``: joint states (positions, and the logger's
velocities and torques where it has them, joint names from the file's description_list), wrenches,
FT-board IMUs and temperatures, each message stamped with its logger timestamp (log time = stamp). The
sidecar YAML becomes the ``experiment`` metadata record. The MCAP is written atomically.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import DataError

COMMAND = "convert-mat"


def convert(mat: Path, out: Path, params: Any) -> dict[str, int]:
    """Write `mat` as the MCAP `out`; returns messages written per topic."""
    from pipeline.core.config import mat_section, repo_root, resolve_urdf
    from pipeline.logs import rosmsg
    from pipeline.logs.matreader import MatLogReader
    from pipeline.physics.robot import load_robot

    cfg = mat_section(params)
    robot = load_robot(resolve_urdf(params.robot.urdf, repo_root()))
    if out.resolve() == mat.resolve():
        raise DataError(f"{out}: the output would overwrite the input")
    counts: dict[str, int] = {}
    with MatLogReader(mat, params.topics, list(robot.sensors), cfg) as reader:
        meta = {"experiment": reader.metadata["experiment"]}
        with rosmsg.LogWriter(out, meta) as writer:
            for batches in reader.iter_chunks():
                for b in batches:
                    write_batch(writer, b)
                    counts[b.topic] = counts.get(b.topic, 0) + len(b)
    return counts


def write_batch(writer: Any, b: Any) -> None:
    """Write a contract `rosmsg.Batch` (joint states, wrenches, IMU, temperatures) with `writer`, each
    message's log time = its stamp."""
    from pipeline.logs import rosmsg

    f, t = b.fields, b.stamp_ns
    if b.msgtype == rosmsg.JOINT_STATE:
        effort = f["effort"] if f["effort"].shape[1] else None
        writer.joint_states(b.topic, t, list(b.names), f["position"], f["velocity"], effort, log_times_ns=t)
    elif b.msgtype == rosmsg.WRENCH_STAMPED:
        writer.wrenches(b.topic, t, frame_of(b.topic), f["wrench"], log_times_ns=t)
    elif b.msgtype == rosmsg.IMU:
        imu = (f["linear_acceleration"], f["angular_velocity"])
        writer.imus(b.topic, t, frame_of(b.topic), *imu, log_times_ns=t)
    elif b.msgtype == rosmsg.TEMPERATURE:
        writer.temperatures(b.topic, t, frame_of(b.topic), f["temperature"], log_times_ns=t)


def frame_of(topic: str) -> str:
    """frame_id of a per-sensor message: the sensor name (the topic's second-to-last level)."""
    parts = [p for p in topic.split("/") if p]
    return parts[-2] if len(parts) >= 2 else ""


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    params = load_params(args.params)
    counts = convert(args.mat, args.mcap, params)
    print(f"wrote {args.mcap}: {sum(counts.values())} messages on {len(counts)} topics")
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal convert-mat IN.mat OUT.mcap`."""
    parser = subparsers.add_parser(
        COMMAND,
        help="convert a YarpRobotLoggerDevice .mat log into a contract MCAP log",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument(
        "mat", type=Path, help="logger .mat file (its experiment sidecar <stem>.yaml beside it)"
    )
    parser.add_argument("mcap", type=Path, help="MCAP file to write")
    add_params_option(parser)
    parser.set_defaults(func=_cmd)
