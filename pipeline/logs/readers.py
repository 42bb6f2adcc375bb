"""One reader per log format, each presenting the MCAP contract's topics to the same alignment.

`open_log` picks it: an MCAP file (`rosmsg.LogReader`), a YarpRobotLoggerDevice ``.mat`` file
(`pipeline.logs.matreader`), or a YARP dataDumper run directory (`pipeline.logs.dumper`). Every reader
has ``path``, ``size_bytes``, ``metadata`` (records of name -> str), ``topics`` (name -> TopicInfo) and
``iter_chunks(topics, progress=...)``, and is a context manager.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.core.config import TopicParams
from pipeline.core.errors import ConfigError

if TYPE_CHECKING:
    from pipeline.logs.params import IngestParams


def open_log(
    path: Path,
    cfg: IngestParams,
    topics: TopicParams,
    sensors: Sequence[str],
    joints: Sequence[str] | None,
) -> Any:
    """The reader of the log at `path` (`joints`: the URDF's, which a .mat must name; None: no check)."""
    if path.is_dir():
        from pipeline.logs.dumper import DumperRunReader

        if cfg.dumper is None:
            raise ConfigError(f"{path}: a dataDumper run needs the maps ingest.dumper in params")
        return DumperRunReader(path, topics, sensors, cfg.dumper, joints or (), max_gap_s=cfg.max_gap_s)
    if path.suffix.lower() != ".mat":
        from pipeline.logs import rosmsg

        return rosmsg.LogReader(path)
    from pipeline.logs.matreader import MatLogReader

    if cfg.mat is None:
        raise ConfigError(f"{path}: a .mat log needs the name map ingest.mat in params")
    return MatLogReader(path, topics, sensors, cfg.mat, joints)
