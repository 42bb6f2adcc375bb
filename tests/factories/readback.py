"""MCAP logs read back independently of the project: every record by mcap's own reader (CRCs checked),
every message decoded by mcap_ros2 (the standard decoder), and the fields of a decoded message."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def mcap_records(path: Path) -> list[tuple[str, int, int, int, bytes]]:
    """Every message of the log as (topic, log time ns, publish time ns, sequence, data), in file order."""
    from mcap.reader import make_reader

    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        return [
            (c.topic, m.log_time, m.publish_time, m.sequence, bytes(m.data))
            for _, c, m in reader.iter_messages(log_time_order=False)
        ]


def ros2_messages(path: Path) -> dict[str, list[Any]]:
    """Every message decoded by mcap_ros2 (the standard decoder, independent of ours), per topic."""
    from mcap_ros2.reader import read_ros2_messages

    out: dict[str, list[Any]] = {}
    for m in read_ros2_messages(str(path)):
        out.setdefault(m.channel.topic, []).append(m)
    return out


def stamp_ns(msg: Any) -> int:
    """The header stamp of a decoded message, ns."""
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def xyz(v: Any) -> list[float]:
    """[x, y, z] of a decoded Vector3."""
    return [v.x, v.y, v.z]
