"""Benchmark: what `dvc repro` costs after one group's params change (the "edit params.yaml, repro" loop).

On an up-to-date pipeline (`dvc status` clean), writes ``lr: <value>`` under ``train.groups.<group>`` in
params.yaml, runs `dvc repro`, and prints the wall time of every stage that re-ran (from dvc's own output,
as it streams), their total, and the ratio of the total to the group's training (the part no pipeline
layout can avoid) measured in the same run. Then restores params.yaml and runs `dvc repro` again, which
takes the previous outputs back from DVC's run cache.

    python benchmarks/group_edit.py                      # r_arm_ft, lr 0.01
    python benchmarks/group_edit.py --group legs --lr 0.005
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOAL_S = 60.0  # the page and the exported graph up to date within this after one group's edit


def _repro() -> dict[str, float]:
    """Run `dvc repro`; seconds per stage that ran (by the time its "Running stage" line was printed)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "dvc", "repro"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert proc.stdout is not None
    starts: list[tuple[str, float]] = []
    t0 = time.monotonic()
    for line in proc.stdout:
        found = re.match(r"Running stage '([^']+)'", line)
        if found:
            starts.append((found.group(1), time.monotonic()))
    end = time.monotonic()
    if proc.wait() != 0:
        raise SystemExit("dvc repro failed")
    bounds = [t for _, t in starts[1:]] + ([end] if starts else [])
    stages = {name: stop - start for (name, start), stop in zip(starts, bounds, strict=True)}
    stages["(dvc before the first stage)"] = (starts[0][1] if starts else end) - t0
    return stages


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--group", default="r_arm_ft", help="a key of train.groups (default r_arm_ft)")
    parser.add_argument("--lr", type=float, default=0.01, help="the learning rate written (default 0.01)")
    args = parser.parse_args()
    params = ROOT / "params.yaml"
    original = params.read_text()
    pattern = rf"(\n    {re.escape(args.group)}: \{{)"
    if not re.search(pattern, original):
        raise SystemExit(f"params.yaml: no one-line entry `{args.group}: {{...}}` under train.groups")
    status = subprocess.run([sys.executable, "-m", "dvc", "status"], cwd=ROOT, capture_output=True, text=True)
    if "up to date" not in status.stdout:
        raise SystemExit("the pipeline is not up to date: run `dvc repro` first")
    params.write_text(re.sub(pattern, rf"\1lr: {args.lr}, ", original, count=1))
    try:
        stages = _repro()
    finally:
        params.write_text(original)
    if f"train@{args.group}" not in stages:  # DVC took the outputs of an earlier run of this edit back
        _repro()
        raise SystemExit(f"train@{args.group} did not run: DVC's run cache holds this edit; try another --lr")
    total = sum(stages.values())
    for name, seconds in stages.items():
        print(f"{name:32s} {seconds:7.1f} s")
    train = stages.get(f"train@{args.group}", float("nan"))
    print(f"{'total':32s} {total:7.1f} s  (goal {GOAL_S:.0f} s: {'met' if total <= GOAL_S else 'missed'})")
    print(f"total / train@{args.group}: {total / train:.2f}")
    print("restoring the previous outputs (dvc run cache) ...")
    _repro()
    return 0


if __name__ == "__main__":
    sys.exit(main())
