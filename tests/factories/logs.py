"""Synthetic MCAP logs of a three-joint, two-sensor robot (the project's writer), the ingest settings that
read them, and logs of ours rewritten by the mcap package's own Writer in other recorders' layouts.

Times are ns since T0 (robot time); `write_log`'s signals are known in closed form (joint positions in rad,
wrenches linear in time, N and Nm), so that an ingested table can be checked sample by sample.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import IndexType, Writer

from pipeline.core.config import TopicParams, load_params, mat_section
from pipeline.logs.cdr import TEMPERATURE
from pipeline.logs.mcap_table import ingest_log
from pipeline.logs.params import IngestParams
from pipeline.logs.rosmsg import LogWriter
from pipeline.logs.tables import LogReport

ROOT = Path(__file__).resolve().parents[2]
T0 = 1_700_000_000 * 10**9  # ns
MS = 1_000_000  # ns
TOPICS = TopicParams(
    joint_states="/joint_states",
    ft_wrench="/ft/{sensor}/wrench",
    ft_imu="/ft/{sensor}/imu",
    ft_temperature="/ft/{sensor}/temperature",
    sim_wrench_true="/sim/ft/{sensor}/wrench_true",
    sim_wrench_distorted="/sim/ft/{sensor}/wrench_distorted",
    sim_wrench_oracle="/sim/ft/{sensor}/wrench_oracle",
    sim_contacts="/sim/contacts",
)
JOINTS = ["j_a", "j_b", "j_c"]
SENSORS = ["s_one", "s_two"]
CFG = IngestParams(
    source="data/sim",
    max_gap_s=0.025,
    max_gap_temperature_s=0.5,
    max_reorder_s=0.5,
    max_nonfinite_fraction=0.0,
    skip_bad_logs=False,
)
EXPERIMENT = {
    "type": "walking",
    "robot": "iCubGenova09",
    "role": "train",
    "contacts": "",
    "fixed_link": "",
    "gravity": "0 0 -9.80665",
    "seed": "3",
    "duration_s": "2",
    "sim": "true",
}


def joint_position(t: np.ndarray, k: int) -> np.ndarray:
    """rad: a smooth, distinct motion per joint."""
    return 0.1 * k + 0.5 * np.sin(2 * np.pi * 0.5 * t + k)


def linear_wrench(t: np.ndarray, k: int) -> np.ndarray:
    """(N, 6): linear in time, so that linear interpolation is exact."""
    return 10.0 * k + np.arange(6) + 3.0 * t[:, None]


def stamps(duration: float, rate: float, offset_ns: int = 0) -> np.ndarray:
    """(n,) int64 ns: `duration` s of stamps at `rate` Hz from T0 + `offset_ns`."""
    return T0 + offset_ns + np.round(np.arange(int(round(duration * rate))) * 1e9 / rate).astype(np.int64)


def write_log(
    path: Path,
    joints: Sequence[str] = JOINTS,
    sensors: Sequence[str] = SENSORS,
    *,
    topics: TopicParams = TOPICS,
    duration: float = 2.0,
    experiment: dict | None = None,
    skip: Sequence[str] = (),
    extra: Callable[[LogWriter], None] | None = None,
    truth: bool = True,
    chunk_size: int = 4 * 2**20,
) -> Path:
    """A valid log: joint states at 100 Hz, wrenches at 200 Hz, IMU at 100 Hz (delayed), temperature
    at 10 Hz, simulated truth and contacts; `skip` leaves topics out, `extra` writes more messages."""
    js = stamps(duration, 100.0)
    t_js = (js - T0) / 1e9
    meta = {"experiment": experiment if experiment is not None else EXPERIMENT}
    with LogWriter(path, meta, chunk_size=chunk_size) as w:
        if topics.joint_states not in skip:
            q = np.column_stack([joint_position(t_js, k) for k in range(len(joints))])
            w.joint_states(topics.joint_states, js, list(joints), q, np.gradient(q, t_js, axis=0))
        for k, s in enumerate(sensors):
            ft = stamps(duration, 200.0, offset_ns=1 * MS)
            t_ft = (ft - T0) / 1e9
            topic = topics.sensor_topic
            if topic("ft_wrench", s) not in skip:
                w.wrenches(topic("ft_wrench", s), ft, s, linear_wrench(t_ft, k), log_times_ns=ft + 3 * MS)
            if topic("ft_imu", s) not in skip:
                acc = np.column_stack([t_js, -t_js, 9.81 + 0 * t_js])
                w.imus(topic("ft_imu", s), js, s, acc, 0.1 * acc, log_times_ns=js + 7 * MS)
            if topic("ft_temperature", s) not in skip:
                tt = stamps(duration, 10.0)
                w.temperatures(topic("ft_temperature", s), tt, s, 30.0 + (tt - T0) / 1e9)
            if truth:
                for m, kind in enumerate(("sim_wrench_true", "sim_wrench_distorted", "sim_wrench_oracle")):
                    if topic(kind, s) not in skip:
                        w.wrenches(topic(kind, s), js, s, linear_wrench(t_js, k) + 100 * m)
        if truth and topics.sim_contacts not in skip:
            switch = js[::50]
            w.strings(
                topics.sim_contacts,
                switch,
                [("l_sole" if i % 2 else "l_sole,r_sole") for i in range(len(switch))],
            )
        if extra is not None:
            extra(w)
    return path


def run_one(path: Path, out: Path, cfg: IngestParams = CFG, joints: Sequence[str] = JOINTS) -> LogReport:
    """`path` ingested into `out` with the tests' topics, `joints` and SENSORS."""
    return ingest_log(path, out, path.stem, cfg, TOPICS, joints, SENSORS, ["iCubGenova09"])


# the ingest settings with the repository's MATLAB logger section (tests/matfile.py writes such files)
MAT = mat_section(load_params(ROOT / "params.yaml"))
CFG_MAT = IngestParams(**{**CFG.__dict__, "mat": MAT})


# --- other recorders' layouts: the same records, written by the mcap package ---

LAYOUTS = {
    "no_chunks": {"use_chunking": False},
    "chunks_without_chunk_index": {"index_types": IndexType.NONE},
    "no_statistics": {"use_statistics": False},
    "no_summary": {
        "index_types": IndexType.NONE,
        "use_statistics": False,
        "repeat_channels": False,
        "repeat_schemas": False,
        "use_summary_offsets": False,
    },
}


def copy_log(src: Path, dst: Path, *, idl_temperature: str | None = None, **writer_options: object) -> Path:
    """Every record of `src` rewritten by the mcap package's Writer with `writer_options`."""
    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        writer = Writer(f_out, chunk_size=4096, **writer_options)
        writer.start(profile="ros2", library="test")
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema.id not in schemas:
                encoding, data = schema.encoding, schema.data
                if schema.name == TEMPERATURE and idl_temperature is not None:
                    encoding, data = "ros2idl", idl_temperature.encode()
                schemas[schema.id] = writer.register_schema(schema.name, encoding, data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id]
                )
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time, message.sequence
            )
        writer.finish()
    return dst
