"""Simulated seconds per wall second of the `simulate` stage, and the share of each of its parts.

Runs the default params' logs (or a fraction of their durations) through `pipeline.stages.simulate.run` into a
temporary directory, with a throwaway MLflow store, and prints robot seconds per wall second last.

    python benchmarks/sim_speed.py [--scale 1.0] [--workers 0] [--urdf PATH]   (PATH: e.g. an ergoCub URDF)
    python benchmarks/sim_speed.py --quick     # one log of each type, 2 s each: for the test suite
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
import tempfile
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import QUICK  # noqa: E402
from pipeline.core.config import load_params  # noqa: E402
from pipeline.core.defaults import resolve  # noqa: E402
from pipeline.stages.simulate import run  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", type=float, default=1.0, help="fraction of every log's duration")
    parser.add_argument("--workers", type=int, default=0, help="processes (0: one per core)")
    parser.add_argument("--urdf", default=None, help="robot.urdf instead of the params' (e.g. ergoCub's)")
    parser.add_argument("--quick", action="store_true", help=f"{QUICK}: one log of each type, 2 s each")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = resolve(yaml.safe_load((REPO / "params.yaml").read_text()))[0]
        sim = copy.deepcopy(data["simulate"])
        if args.quick:
            sim["logs"] = list({log["type"]: log for log in reversed(sim["logs"])}.values())
        for log in sim["logs"]:
            log["duration_s"] = 2.0 if args.quick else max(2.0, log["duration_s"] * args.scale)
        sim.update({"workers": args.workers, "plots": False})
        data["simulate"] = sim
        if args.urdf:
            data["robot"]["urdf"] = args.urdf
        path = Path(tmp) / "params.yaml"
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{tmp}/mlflow.db"
        start = time.perf_counter()
        results = run(load_params(path), Path(tmp) / "sim", progress=False)
        wall = time.perf_counter() - start
        robot_seconds = sum(r.samples for r in results) / sim["rate_hz"]
        size = sum(p.stat().st_size for p in (Path(tmp) / "sim").glob("*.mcap"))
        messages = sum(r.messages for r in results)
        print(
            f"logs: {len(results)}, robot time {robot_seconds:.0f} s, {messages} messages, "
            f"{size / 2**20:.0f} MiB"
        )
        for r in results:
            robot = r.samples / sim["rate_hz"]
            print(f"  {r.name:34s} {robot:6.0f} s robot time in {r.seconds:6.1f} s (one worker)")
        workers = args.workers or os.cpu_count()
        print(f"wall time (incl. MLflow run and writing): {wall:.1f} s with {workers} workers")
        print(f"simulated seconds per wall second: {robot_seconds / wall:.1f}")


if __name__ == "__main__":
    main()
