"""Messages/s of our MCAP decoding and of the whole `ingest` of one log vs mcap_ros2's generic decoder.

Writes (with `pipeline.logs.rosmsg.LogWriter`) a simulated-log-shaped MCAP of iCubGenova09: joint states,
and per FT sensor wrench, IMU, temperature (10 Hz) and the three /sim/ wrenches, plus /sim/contacts,
with jitter, delays, lost and duplicated messages; >= 1M messages by default. Then, on that file:

1. our decoder (`LogReader.iter_chunks`, every topic): messages/s;
2. the whole ingest of the log (decode + align + write Parquet), in a fresh process: messages/s and
   its peak resident memory (ru_maxrss, including the interpreter and libraries);
3. mcap_ros2's standard decoder: ``make_reader(..., decoder_factories=[DecoderFactory()])
   .iter_decoded_messages()`` over every message: messages/s.

Both decoders are first checked to agree on a sample of messages. The last line is the ratio
ingest / mcap_ros2 decoding (target >= 3).

    python benchmarks/ingest_speed.py [--seconds 250] [--keep DIR]
    python benchmarks/ingest_speed.py --quick    # a log of 3 s: for the test suite
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import QUICK  # noqa: E402
from pipeline.core.config import load_params, stage_section  # noqa: E402
from pipeline.logs.mcap_table import ingest_log  # noqa: E402
from pipeline.logs.params import IngestParams  # noqa: E402
from pipeline.logs.rosmsg import LogReader, LogWriter  # noqa: E402
from pipeline.physics.robot import load_robot  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000 * 10**9


def write_log(path: Path, seconds: float, seed: int = 0) -> int:
    """A simulated-log-shaped MCAP of iCubGenova09 at 100 Hz; returns the number of messages."""
    params = load_params(ROOT / "params.yaml")
    topics = params.topics
    robot = load_robot("iCubGenova09")
    joints, sensors = robot.joint_names, list(robot.sensors)
    rng = np.random.default_rng(seed)
    count = 0

    def noisy(stamps: np.ndarray, drop: float = 0.001, dup: float = 0.0005) -> tuple[np.ndarray, np.ndarray]:
        """Stamps with jitter, lost and duplicated messages; log times with transport delay."""
        s = stamps + rng.normal(0, 5e5, len(stamps)).astype(np.int64)
        s = s[rng.random(len(s)) > drop]
        s = np.sort(np.concatenate([s, s[rng.random(len(s)) < dup]]))
        return s, s + rng.exponential(3e6, len(s)).astype(np.int64)

    meta = {"experiment": {"type": "walking", "robot": "iCubGenova09", "role": "train", "sim": "true"}}
    block = 10.0  # s per flush, as the simulator writes
    with LogWriter(path, meta) as w:
        for b in range(int(np.ceil(seconds / block))):
            base = T0 + int(b * block * 1e9) + np.arange(int(block * 100)) * 10_000_000
            js, js_log = noisy(base)
            t = (js - T0) / 1e9
            q = np.sin(t[:, None] * 0.5 + np.arange(len(joints)))
            w.joint_states(
                topics.joint_states, js, joints, q, q + rng.normal(0, 0.01, q.shape), log_times_ns=js_log
            )
            count += len(js)
            for s in sensors:
                for kind, make in (("ft_wrench", 6), ("ft_imu", 3), ("ft_temperature", 1)):
                    st, log = noisy(base[::10] if kind == "ft_temperature" else base)
                    n = len(st)
                    if kind == "ft_wrench":
                        w.wrenches(topics.sensor_topic(kind, s), st, s, rng.normal(0, 10, (n, make)), log)
                    elif kind == "ft_imu":
                        w.imus(
                            topics.sensor_topic(kind, s),
                            st,
                            s,
                            rng.normal(0, 1, (n, 3)),
                            rng.normal(0, 0.1, (n, 3)),
                            log,
                        )
                    else:
                        w.temperatures(topics.sensor_topic(kind, s), st, s, 30 + rng.normal(0, 0.1, n), log)
                    count += n
                for kind in ("sim_wrench_true", "sim_wrench_distorted", "sim_wrench_oracle"):
                    w.wrenches(topics.sensor_topic(kind, s), base, s, rng.normal(0, 10, (len(base), 6)))
                    count += len(base)
            w.strings(topics.sim_contacts, base[::100], ["l_sole,r_sole"] * len(base[::100]))
            count += len(base[::100])
            w.flush()
    return count


def decode_ours(path: Path) -> tuple[int, float]:
    start = time.perf_counter()
    n = 0
    with LogReader(path) as reader:
        for batches in reader.iter_chunks():
            n += sum(len(b) for b in batches)
    return n, time.perf_counter() - start


def decode_mcap_ros2(path: Path) -> tuple[int, float]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    start = time.perf_counter()
    n = 0
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _ in reader.iter_decoded_messages():
            n += 1
    return n, time.perf_counter() - start


def check_agreement(path: Path, topic: str) -> None:
    """Our decoder and mcap_ros2 agree on every message of one wrench topic."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        theirs = [m.wrench for _, _, _, m in reader.iter_decoded_messages([topic], log_time_order=False)]
    with LogReader(path) as reader:
        batches = reader.read([topic])[topic]
    order = np.argsort(np.concatenate([b.order for b in batches]))
    ours = np.concatenate([b.fields["wrench"] for b in batches])[order]
    ref = np.array([[w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z] for w in theirs])
    assert ours.shape == ref.shape and np.array_equal(ours, ref), "decoders disagree"


def child_ingest(path: Path, out: Path) -> None:
    """Run in a fresh process: ingest the log, print JSON with messages, seconds and peak RSS."""
    params = load_params(ROOT / "params.yaml")
    cfg = stage_section(params, "ingest", IngestParams)
    robot = load_robot("iCubGenova09")
    start = time.perf_counter()
    report = ingest_log(path, out, path.stem, cfg, params.topics, robot.joint_names, list(robot.sensors))
    seconds = time.perf_counter() - start
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    print(
        json.dumps(
            {
                "messages": report.messages,
                "samples": report.samples,
                "seconds": seconds,
                "peak_rss_mib": peak_kib / 1024,
            }
        )
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=250.0, help="log duration (250 s: ~1.05M messages)")
    parser.add_argument("--keep", type=Path, default=None, help="write the log here and keep it")
    parser.add_argument("--child", nargs=2, type=Path, metavar=("LOG", "OUT"), help=argparse.SUPPRESS)
    parser.add_argument("--quick", action="store_true", help=f"{QUICK}: a log of 3 s")
    args = parser.parse_args()
    if args.child:
        child_ingest(*args.child)
        return
    if args.quick:
        args.seconds = 3.0

    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        log = folder / "bench.mcap"
        start = time.perf_counter()
        written = write_log(log, args.seconds)
        write_s = time.perf_counter() - start
        print(
            f"log: {written} messages, {args.seconds:g} s of iCubGenova09 at 100 Hz, "
            f"{log.stat().st_size / 2**20:.0f} MiB; written in {write_s:.1f} s "
            f"({written / write_s:,.0f} msg/s)"
        )
        check_agreement(log, "/ft/l_leg_ft/wrench")
        n_ours, s_ours = decode_ours(log)
        print(
            f"ftcal decoder (all topics):            {n_ours / s_ours:12,.0f} msg/s  "
            f"({n_ours} in {s_ours:.2f} s)"
        )
        child = subprocess.run(
            [sys.executable, __file__, "--child", str(log), str(folder / "out")],
            capture_output=True,
            text=True,
            check=True,
        )
        result = json.loads(child.stdout.strip().splitlines()[-1])
        rate_ingest = result["messages"] / result["seconds"]
        print(
            f"ftcal ingest (decode+align+Parquet):   {rate_ingest:12,.0f} msg/s  ({result['messages']} in "
            f"{result['seconds']:.2f} s, {result['samples']} samples)"
        )
        print(f"ftcal ingest peak memory (RSS):        {result['peak_rss_mib']:12,.0f} MiB")
        n_ref, s_ref = decode_mcap_ros2(log)
        rate_ref = n_ref / s_ref
        print(f"mcap_ros2 iter_decoded_messages:       {rate_ref:12,.0f} msg/s  ({n_ref} in {s_ref:.2f} s)")
        assert n_ref == n_ours == written, (n_ref, n_ours, written)
        print(f"ratio decoder / mcap_ros2: {n_ours / s_ours / rate_ref:.1f}")
        print(f"ratio ingest / mcap_ros2: {rate_ingest / rate_ref:.1f}")


if __name__ == "__main__":
    main()
