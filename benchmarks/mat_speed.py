"""Ingest of a YarpRobotLoggerDevice .mat log vs the MCAP of the same content: wall time and peak RSS.

Writes (with `pipeline.logs.rosmsg.LogWriter`) a 30-minute, 100 Hz MCAP of iCubGenova09 with what a
logger file holds: joint states (positions, velocities, torques) and, per FT sensor (8), wrench, FT-board
IMU and temperature, every channel sampled at the loop instants with a few lost samples. The test
fixtures' writer (`tests.matfile.mcap_to_mat`) turns it into a logger-layout MATLAB v7.3 file (gzip
chunks, as matio writes with compression on) with its sidecar.
Each file is then ingested by `pipeline.logs.mcap_table.ingest_log` with the params of params.yaml, in a
fresh process per format: wall time of the ingest and peak resident memory of that process (its
VmHWM, including the interpreter and libraries). The last line is the ratio of times .mat / MCAP (target <= 1,
with both peaks < 1 GiB).

    python benchmarks/mat_speed.py [--seconds 1800] [--keep DIR]
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

from pipeline.core.config import load_params, resolve_urdf, stage_section  # noqa: E402
from pipeline.logs.mcap_table import ingest_log  # noqa: E402
from pipeline.logs.params import IngestParams  # noqa: E402
from pipeline.logs.rosmsg import LogWriter  # noqa: E402
from pipeline.physics.robot import load_robot  # noqa: E402
from tests.matfile import mcap_to_mat  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000 * 10**9
PERIOD_NS = 10_000_000  # 100 Hz loop
BLOCK_S = 10.0  # s of log per write flush


def write_mcap(path: Path, seconds: float, urdf: str, seed: int = 0) -> int:
    """A logger-content MCAP (see the module docstring); returns the number of messages."""
    params = load_params(ROOT / "params.yaml")
    topics = params.topics
    robot = load_robot(resolve_urdf(urdf, ROOT))
    joints, sensors = robot.joint_names, list(robot.sensors)
    rng = np.random.default_rng(seed)
    count = 0

    def sampled(loop: np.ndarray, lost: float = 0.001) -> tuple[np.ndarray, np.ndarray]:
        """Loop stamps of the samples read (a few lost), and their log times (transport delay)."""
        s = loop[rng.random(len(loop)) > lost]
        return s, s + rng.exponential(3e6, len(s)).astype(np.int64)

    meta = {"experiment": {"type": "walking", "robot": urdf, "role": "train", "contacts": "l_sole,r_sole"}}
    with LogWriter(path, meta) as w:
        for b in range(int(np.ceil(seconds / BLOCK_S))):
            n = int(min(BLOCK_S, seconds - b * BLOCK_S) * 1e9 / PERIOD_NS)
            loop = T0 + (round(b * BLOCK_S * 1e9) + np.arange(n) * PERIOD_NS)
            js, js_log = sampled(loop, lost=0.0)
            t = (js - T0) / 1e9
            q = np.sin(t[:, None] * 0.5 + np.arange(len(joints)))
            dq = 0.5 * np.cos(t[:, None] * 0.5 + np.arange(len(joints)))
            tau = rng.normal(0, 1, q.shape)
            w.joint_states(topics.joint_states, js, joints, q, dq, tau, log_times_ns=js_log)
            count += len(js)
            for s in sensors:
                st, log = sampled(loop)
                w.wrenches(topics.sensor_topic("ft_wrench", s), st, s, rng.normal(0, 10, (len(st), 6)), log)
                st, log = sampled(loop)
                acc, gyr = rng.normal(0, 1, (len(st), 3)), rng.normal(0, 0.1, (len(st), 3))
                w.imus(topics.sensor_topic("ft_imu", s), st, s, acc, gyr, log)
                count += 2 * len(st)
                st, log = sampled(loop)
                w.temperatures(
                    topics.sensor_topic("ft_temperature", s), st, s, 30 + rng.normal(0, 0.1, len(st)), log
                )
                count += len(st)
            w.flush()
    return count


def peak_rss_kib() -> int:
    """KiB: this process's peak resident memory since its exec (VmHWM). ru_maxrss is not used: Linux
    carries the forking parent's peak across fork + exec into it."""
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # not Linux: KiB (bytes on macOS)


def child_ingest(path: Path, out: Path) -> None:
    """Run in a fresh process: ingest one log, print JSON with rows, seconds and peak RSS."""
    params = load_params(ROOT / "params.yaml")
    cfg = stage_section(params, "ingest", IngestParams)
    urdf = params.robot.urdf
    robot = load_robot(resolve_urdf(urdf, ROOT))
    start = time.perf_counter()
    report = ingest_log(
        path, out, path.stem, cfg, params.topics, robot.joint_names, list(robot.sensors), [urdf]
    )
    seconds = time.perf_counter() - start
    peak_kib = peak_rss_kib()
    print(json.dumps({"samples": report.samples, "seconds": seconds, "peak_rss_mib": peak_kib / 1024}))


def run_child(log: Path, out: Path) -> dict[str, float]:
    child = subprocess.run(
        [sys.executable, __file__, "--child", str(log), str(out)], capture_output=True, text=True
    )
    if child.returncode:
        raise SystemExit(f"ingest of {log} failed:\n{child.stderr}")
    return json.loads(child.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=1800.0, help="log duration, s (30 min)")
    parser.add_argument(
        "--keep",
        type=Path,
        default=None,
        help="write the logs here and keep them; logs already there are reused",
    )
    parser.add_argument("--child", nargs=2, type=Path, metavar=("LOG", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child_ingest(*args.child)
        return

    params = load_params(ROOT / "params.yaml")
    urdf = params.robot.urdf
    sensors = list(load_robot(resolve_urdf(urdf, ROOT)).sensors)
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        mcap, mat = folder / "bench.mcap", folder / "bench.mat"
        start = time.perf_counter()
        if not mcap.exists() or args.keep is None:
            written = write_mcap(mcap, args.seconds, urdf)
            print(f"MCAP: {written} messages, {len(sensors)} FT sensors, {args.seconds:g} s at 100 Hz")
        if not mat.exists() or args.keep is None:
            mcap_to_mat(mcap, mat, params.topics, sensors, naming="2024")
        print(
            f"files: MCAP {mcap.stat().st_size / 2**20:.0f} MiB, .mat {mat.stat().st_size / 2**20:.0f} MiB "
            f"(gzip chunks); written in {time.perf_counter() - start:.1f} s"
        )
        results = {}
        for name, log in (("MCAP", mcap), (".mat", mat)):
            r = run_child(log, folder / f"out_{log.suffix[1:]}")
            results[name] = r
            print(
                f"ingest {name:5s}: {r['seconds']:7.2f} s  peak RSS {r['peak_rss_mib']:6.0f} MiB  "
                f"({r['samples']} samples)"
            )
        assert results["MCAP"]["samples"] == results[".mat"]["samples"], results
        print(f"ratio time .mat / MCAP: {results['.mat']['seconds'] / results['MCAP']['seconds']:.2f}")


if __name__ == "__main__":
    main()
