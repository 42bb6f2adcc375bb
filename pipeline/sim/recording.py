"""Writing one simulated log as ROS 2 MCAP, the way a robot's recorder would have.

Messages carry the robot's stamps (int64 ns since the epoch, jittered around the nominal period, the FT
board's clock lagging the joint states); a few are dropped or recorded twice, and each is logged after
an exponential transport delay. The truth topics (``/sim/...``) are complete and undelayed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.config import TopicParams
from pipeline.sim.params import TimingParams

EPOCH_NS = 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z: stamps look like a real recording's
BLOCK_S = 10.0  # messages are written in blocks of this much robot time, s (keeps the buffer small)


def stamps(rng: np.random.Generator, t: np.ndarray, offset_s: float, jitter_s: float) -> np.ndarray:
    """Monotonic int64 ns stamps: nominal times `t` (s) + offset + clipped jitter."""
    jitter = np.clip(rng.normal(0.0, jitter_s, t.shape), -3 * jitter_s, 3 * jitter_s)
    return EPOCH_NS + np.round((t + offset_s + jitter) * 1e9).astype(np.int64)


def thin(rng: np.random.Generator, n: int, timing: TimingParams) -> np.ndarray:
    """Indices of the messages that reach the log: some dropped, some duplicated (sorted)."""
    keep = np.flatnonzero(rng.random(n) >= timing.drop_rate)
    dup = keep[rng.random(keep.shape[0]) < timing.duplicate_rate]
    return np.sort(np.r_[keep, dup], kind="stable")


@dataclass
class Recording:
    """Everything one log publishes (N samples at the simulation rate).

    sensors: per FT sensor name, arrays over the FT stamps: ``raw``, ``true``, ``distorted``, ``oracle``
    (and ``external`` in logs with pushes or loads) (N, 6) N/Nm sensor frame; ``acc`` (N, 3) m/s^2;
    ``gyro`` (N, 3) rad/s; ``temp`` (N,) deg C.
    """

    metadata: dict[str, dict[str, str]]
    joint_names: list[str]
    js_stamps: np.ndarray  # (N,) int64 ns
    q: np.ndarray  # (N, n_joints) measured joint positions, rad
    dq: np.ndarray  # (N, n_joints) published joint velocities, rad/s
    contacts: np.ndarray  # (N,) object: true contact set as 'link,link'
    ft_stamps: np.ndarray  # (N,) int64 ns
    sensors: dict[str, dict[str, np.ndarray]]
    joint_torque: np.ndarray | None = None  # (N, n_joints) true joint torques, Nm (logs with pushes only)


class _Delays:
    """Transport delays of m messages, ns, drawn in call order from one generator."""

    def __init__(self, rng: np.random.Generator, mean_s: float) -> None:
        self.rng, self.mean_s = rng, mean_s

    def __call__(self, m: int) -> np.ndarray:
        return np.round(self.rng.exponential(self.mean_s, m) * 1e9).astype(np.int64)


def write_recording(
    path: Path,
    rec: Recording,
    topics: TopicParams,
    timing: TimingParams,
    rate_hz: float,
    rng: np.random.Generator,
) -> int:
    """Write `rec` to the MCAP file `path`; returns the number of messages written.

    `rng` draws, in this order, which messages are lost or duplicated and every transport delay.
    """
    from pipeline.logs.rosmsg import LogWriter

    n = rec.js_stamps.shape[0]
    keep_js = thin(rng, n, timing)
    keep_ft = {s: thin(rng, n, timing) for s in rec.sensors}
    delay = _Delays(rng, timing.delay_s)
    temp_every = max(1, int(round(rate_hz / timing.temperature_rate_hz)))
    block = int(BLOCK_S * rate_hz)
    messages = 0
    with LogWriter(path, metadata=rec.metadata) as writer:
        for b0 in range(0, n, block):
            rows = np.arange(b0, min(n, b0 + block))
            sel = keep_js[(keep_js >= rows[0]) & (keep_js <= rows[-1])]
            writer.joint_states(
                topics.joint_states,
                rec.js_stamps[sel],
                rec.joint_names,
                rec.q[sel],
                rec.dq[sel],
                log_times_ns=rec.js_stamps[sel] + delay(sel.size),
            )
            writer.strings(topics.sim_contacts, rec.js_stamps[rows], list(rec.contacts[rows]))
            messages += sel.size + rows.size
            if rec.joint_torque is not None:  # truth: every sample, undelayed; effort = true torque
                writer.joint_states(
                    topics.sim_joint_torques,
                    rec.js_stamps[rows],
                    rec.joint_names,
                    rec.q[rows],
                    rec.dq[rows],
                    rec.joint_torque[rows],
                )
                messages += rows.size
            for s in rec.sensors:
                sel = keep_ft[s][(keep_ft[s] >= rows[0]) & (keep_ft[s] <= rows[-1])]
                messages += _write_sensor(
                    writer, topics, rec, s, sel, rows, rows[rows % temp_every == 0], delay
                )
            writer.flush()
    return messages


def _write_sensor(
    writer,
    topics: TopicParams,
    rec: Recording,
    s: str,
    sel: np.ndarray,
    rows: np.ndarray,
    tsel: np.ndarray,
    delay: _Delays,
) -> int:
    """One block of sensor `s`'s messages: the published ones at `sel` (FT, IMU), the temperature at
    `tsel`, the truth at every row. Returns the number of messages."""
    d = rec.sensors[s]
    stamps_, logt = rec.ft_stamps[sel], rec.ft_stamps[sel] + delay(sel.size)
    writer.wrenches(topics.sensor_topic("ft_wrench", s), stamps_, s, d["raw"][sel], log_times_ns=logt)
    writer.imus(
        topics.sensor_topic("ft_imu", s), stamps_, s, d["acc"][sel], d["gyro"][sel], log_times_ns=logt
    )
    truth = [
        ("sim_wrench_true", "true"),
        ("sim_wrench_distorted", "distorted"),
        ("sim_wrench_oracle", "oracle"),
    ]
    if "external" in d:  # logs with pushes or loads: their share of the true wrench
        truth.append(("sim_wrench_external", "external"))
    for kind, key in truth:
        writer.wrenches(topics.sensor_topic(kind, s), rec.ft_stamps[rows], s, d[key][rows])
    writer.temperatures(
        topics.sensor_topic("ft_temperature", s),
        rec.ft_stamps[tsel],
        s,
        d["temp"][tsel],
        log_times_ns=rec.ft_stamps[tsel] + delay(tsel.size),
    )
    return 2 * sel.size + len(truth) * rows.size + tsel.size
