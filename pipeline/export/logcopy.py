"""A log's copy with the exported calibration's wrenches added (what `ftcal calibrate` writes).

`calibrate_log` streams an MCAP log region by region (`LogReader.iter_regions`: a chunk of an indexed
file, a block of the data section of a file without chunk indexes, read by the scan ingest uses), runs the
causal calibrator of `pipeline.export.runtime` on the raw wrenches, and writes through
`pipeline.logs.augment.LogAugmenter` a copy in which every original record is kept byte for byte, plus per
raw wrench message of a modelled sensor one ``<wrench topic>_calibrated`` geometry_msgs/msg/WrenchStamped
with the same header (stamp, frame_id), log time and publish time. Memory is flat in the log length; the
output is written atomically (``<out>.part``, renamed when complete).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class CalibrateResult:
    source: Path
    out: Path
    messages: int  # original messages, copied
    added: int  # calibrated messages added
    seconds: float
    uncalibrated: dict[str, int] = field(default_factory=dict)  # sensor -> wrench messages without inputs yet
    warnings: list[str] = field(default_factory=list)
    offsets: str = ""  # which offsets the calibration ran with (`pipeline.export.offsets.summary`)

    @property
    def rate(self) -> float:
        """Messages (original + added) per second of wall time."""
        return (self.messages + self.added) / self.seconds if self.seconds > 0 else float("inf")


def _records(augmenter: Any, channels: dict[str, int], calibrated: list[Any]) -> list[tuple[int, Any, Any]]:
    """MCAP Message records of calibrated wrenches, per (channel, frame_id)."""
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
    """Write `out`: the log of `reader` with calibrated wrenches added (module docstring); `plans` from
    `pipeline.export.runtime.plan_log`."""
    from pipeline.export.runtime import CausalCalibrator
    from pipeline.logs.augment import LogAugmenter
    from pipeline.logs.rosmsg import WRENCH_STAMPED

    t0 = time.perf_counter()
    calibrator = CausalCalibrator(deployment, plans)
    with LogAugmenter(reader, out) as augmenter:
        channels = {p.sensor: augmenter.add_channel(p.out_topic, WRENCH_STAMPED) for p in plans}
        for end, batches in reader.iter_regions(calibrator.topics()):
            augmenter.copy_through(end)
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
