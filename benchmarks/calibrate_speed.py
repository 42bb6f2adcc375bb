"""Messages/s and peak memory of `ftcal calibrate` on a log of >= 1M messages, all 8 sensors modelled.

Writes a contract MCAP of iCubGenova09's 8 FT sensors (`tests/mcap_factory.py`: joint states, and per
sensor wrench and IMU at 100 Hz and temperature at 10 Hz, with stamp jitter and transport delays) and a
synthetic export of 13-input networks for every sensor (`benchmarks/export_fixture.py`), then runs
``ftcal calibrate`` on it in a fresh process and reports:

1. messages/s of the calibration itself (original + added messages over the time of reading, calibrating
   and writing, as the command prints it) and of the whole process (including Python start and imports);
2. the peak resident memory of that process (ru_maxrss: interpreter, torch-free onnxruntime, numpy).

Targets: >= 200k messages/s, peak RSS < 1 GiB. Also the same figures for a log of a tenth of the length,
to show that the memory does not grow with the log. The last line is the rate relative to the target.

    python benchmarks/calibrate_speed.py [--seconds 570] [--keep DIR]
    python benchmarks/calibrate_speed.py --quick    # logs of 0.5 and 5 s: for the test suite
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import QUICK  # noqa: E402
from benchmarks.export_fixture import GROUPS, synthetic_export, synthetic_models  # noqa: E402
from tests.mcap_factory import write_log  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TARGET = 200_000  # messages/s


def calibrate(log: Path, out: Path, models: Path) -> tuple[float, float, float]:
    """(messages/s reported by the command, messages/s of the whole process, peak RSS MiB)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t = time.perf_counter()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [
        sys.executable,
        "-m",
        "pipeline.cli",
        "calibrate",
        str(log),
        str(out),
        "--models",
        str(models),
        "--force",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, check=True)
    wall = time.perf_counter() - t
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    match = re.search(
        r"(\d+) messages copied, (\d+) calibrated wrenches added \((\d+) k messages/s\)", done.stdout
    )
    if match is None:
        raise RuntimeError(f"unexpected output: {done.stdout} {done.stderr}")
    total = int(match.group(1)) + int(match.group(2))
    return float(match.group(3)) * 1e3, total / wall, max(rss, before) / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=570.0, help="robot time of the log, s (1780 messages/s)")
    ap.add_argument("--keep", type=Path, default=None, help="keep the files in this directory")
    ap.add_argument("--quick", action="store_true", help=f"{QUICK}: logs of 0.5 and 5 s")
    args = ap.parse_args()
    if args.quick:
        args.seconds = 5.0
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        models, _ = synthetic_models(work / "models")
        synthetic_export(work / "export", models)
        sensors = [s for group in GROUPS.values() for s in group]
        for seconds in (args.seconds / 10, args.seconds):
            log = work / f"log_{seconds:g}s.mcap"
            t = time.perf_counter()
            n = write_log(log, sensors, seconds, seed=1)
            print(
                f"log: {n} messages, {log.stat().st_size / 2**20:.0f} MiB, "
                f"written in {time.perf_counter() - t:.1f} s"
            )
            rate, overall, rss = calibrate(log, work / f"calibrated_{seconds:g}s.mcap", work / "export")
            print(
                f"ftcal calibrate: {rate / 1e3:.0f} k messages/s (calibration), "
                f"{overall / 1e3:.0f} k messages/s "
                f"(whole process), peak RSS {rss:.0f} MiB"
            )
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"rate / target ({TARGET // 1000} k messages/s): {rate / TARGET:.2f}")


if __name__ == "__main__":
    main()
