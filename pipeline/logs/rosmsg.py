"""ROS 2 messages (CDR) in MCAP logs: the public API of the batch writer and the batch reader.

Both sides work on whole batches of messages with numpy instead of one Python object per message,
which is what makes multi-hour logs (millions of messages) practical. The parts live in their own
modules; import from here:

- `pipeline.logs.cdr`: message types, schemas, CDR layouts, stamps;
- `pipeline.logs.mcap_write`: `LogWriter` (+ `pipeline.logs.mcap_chunks`, the container);
- `pipeline.logs.mcap_read`: `LogReader` (+ `pipeline.logs.mcap_scan` for unindexed files);
- `pipeline.logs.decode`: `Batch` and the vectorised decoder.
"""

from __future__ import annotations

from pipeline.logs.cdr import (
    IMU,
    JOINT_STATE,
    MESSAGE_TYPES,
    SCHEMAS,
    STRING,
    TEMPERATURE,
    WRENCH_STAMPED,
    join_stamps,
    schema_layout,
    split_stamps,
)
from pipeline.logs.decode import Batch
from pipeline.logs.mcap_read import LogReader, TopicInfo, concat_batches
from pipeline.logs.mcap_write import LogWriter

__all__ = [
    "IMU",
    "JOINT_STATE",
    "MESSAGE_TYPES",
    "SCHEMAS",
    "STRING",
    "TEMPERATURE",
    "WRENCH_STAMPED",
    "Batch",
    "LogReader",
    "LogWriter",
    "TopicInfo",
    "concat_batches",
    "join_stamps",
    "schema_layout",
    "split_stamps",
]
