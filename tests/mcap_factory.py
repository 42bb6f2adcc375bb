"""Synthetic contract MCAP logs for `ftcal calibrate` tests and benchmarks (real files, the project's writer).

Per sensor: raw wrenches at `rate_hz` with stamp jitter and transport delays, temperature at a tenth of
that rate, IMU at the wrench rate; plus joint states, so that the log carries the topics a robot records.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from pipeline.logs.rosmsg import LogWriter

SCALE = np.array([60.0, 60.0, 200.0, 4.0, 4.0, 1.5])  # N, N, N, Nm, Nm, Nm


def write_log(
    path: Path,
    sensors: Sequence[str],
    seconds: float,
    *,
    rate_hz: float = 100.0,
    seed: int = 0,
    robot: str = "iCubGenova09",
    temperature: bool = True,
    imu: bool = True,
    joints: int = 4,
    block_s: float = 20.0,
    chunk_size: int = 4 * 2**20,
    serials: dict[str, str] | None = None,
    edit: Callable[[str, np.ndarray, np.ndarray], None] | None = None,
) -> int:
    """Write a log of `seconds` of robot time in chunks of `chunk_size` bytes; the number of messages.
    `serials`: sensor -> serial of its board, in the experiment record (``serial.<sensor>``); `edit`: called
    with (sensor, times (n,) s, wrenches (n, 6)) of each block before it is written, may change them."""
    rng = np.random.default_rng(seed)
    meta = {"experiment": {"type": "walking", "robot": robot, "role": "test", "log": path.stem}}
    meta["experiment"] |= {f"serial.{s}": v for s, v in (serials or {}).items()}
    t0 = 1_700_000_000_000_000_000
    count = 0
    names = [f"joint_{k}" for k in range(joints)]
    with LogWriter(path, meta, chunk_size=chunk_size) as writer:
        start = 0.0
        while start < seconds:
            t = np.arange(start, min(start + block_s, seconds), 1.0 / rate_hz)
            start += block_s
            n = len(t)
            base = t0 + np.round(t * 1e9).astype(np.int64)
            q = np.sin(np.outer(t, np.arange(1, joints + 1)))
            writer.joint_states("/joint_states", base, names, q, np.cos(q), log_times_ns=base + 1000)
            count += n
            for s, sensor in enumerate(sensors):
                stamps = base + 2_000_000 + rng.normal(0, 5e5, n).astype(np.int64)
                delay = np.round(rng.exponential(3e6, n)).astype(np.int64)
                w = np.sin(2 * np.pi * 0.3 * t[:, None] + np.arange(6) + s) * SCALE + 20.0
                w += rng.normal(size=(n, 6)) * 0.05 * SCALE
                if edit is not None:
                    edit(sensor, t, w)
                writer.wrenches(
                    f"/ft/{sensor}/wrench", stamps, f"{sensor}_frame", w, log_times_ns=stamps + delay
                )
                count += n
                if temperature:
                    every = slice(0, n, 10)
                    temp = (
                        30 + 5 * np.sin(2 * np.pi * 0.01 * t[every] + s) + rng.normal(0, 0.05, len(t[every]))
                    )
                    writer.temperatures(
                        f"/ft/{sensor}/temperature",
                        stamps[every] + 1,
                        f"{sensor}_frame",
                        temp,
                        log_times_ns=stamps[every] + delay[every] + 1,
                    )
                    count += len(temp)
                if imu:
                    acc = rng.normal(size=(n, 3)) + [0, 0, 9.81]
                    gyr = rng.normal(size=(n, 3)) * 0.1
                    writer.imus(
                        f"/ft/{sensor}/imu",
                        stamps - 1,
                        f"{sensor}_imu",
                        acc,
                        gyr,
                        log_times_ns=stamps + delay,
                    )
                    count += n
    return count
