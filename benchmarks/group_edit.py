"""Benchmark: what `dvc repro` costs after one group's params change (the "edit params.yaml, repro" loop).

On an up-to-date pipeline (`dvc status` clean), writes ``lr: <value>`` under ``train.groups.<group>`` in
params.yaml, runs `dvc repro`, and prints the wall time of every stage that re-ran (from dvc's own output,
as it streams), their total, and the ratio of the total to the group's training (the part no pipeline
layout can avoid) measured in the same run. Each stage's time is split, from the MLflow runs of its steps
(tag ``dvc.stage``), into the steps' own work and what lies outside it (Python start-up, imports, DVC's
hashing and lock file); with the group's networks' training (its searches and cross-validation, from
``models/<group>/metrics.json``) that gives the least this edit could cost in this layout if every other
step took no time. Then restores params.yaml and runs `dvc repro` again, which takes the previous outputs
back from DVC's run cache.

    python benchmarks/group_edit.py                      # r_arm_ft, lr 0.01
    python benchmarks/group_edit.py --group legs --lr 0.005
"""

from __future__ import annotations

import argparse
import json
import os
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


def _in_runs(since_s: float) -> dict[str, float]:
    """Seconds of the top-level MLflow runs started after `since_s` (epoch s), summed per DVC stage."""
    import mlflow

    from pipeline.core.tracking import EXPERIMENT, quiet_mlflow, tracking_uri

    quiet_mlflow()
    client = mlflow.MlflowClient(tracking_uri())
    experiment = client.get_experiment_by_name(EXPERIMENT)
    if experiment is None:
        return {}
    runs = client.search_runs(
        [experiment.experiment_id], f"attributes.start_time >= {int(since_s * 1000)}", max_results=5000
    )
    seconds: dict[str, float] = {}
    for run in runs:
        tags = run.data.tags
        if "mlflow.parentRunId" in tags or run.info.end_time is None or "dvc.stage" not in tags:
            continue  # a trial of a search, or a run still open
        stage = tags["dvc.stage"]
        seconds[stage] = seconds.get(stage, 0.0) + (run.info.end_time - run.info.start_time) / 1000
    return seconds


def _networks_s(group: str) -> float:
    """Seconds of the group's networks' training: the searches (side by side) and cross-validation."""
    timings = json.loads((ROOT / "models" / group / "metrics.json").read_text()).get("seconds", {})
    searches = max((v for k, v in timings.items() if k.startswith("nn")), default=0.0)
    return searches + timings.get("cross_validation", 0.0)


def _print(stages: dict[str, float], in_runs: dict[str, float], group: str) -> None:
    """The table of stages and the least this layout could cost."""
    print(f"{'stage':32s} {'wall':>8s} {'steps':>8s} {'outside':>8s}  (steps: their MLflow runs)")
    outside = 0.0
    for name, seconds in stages.items():
        work = in_runs.get(name, 0.0)
        outside += seconds - work
        print(f"{name:32s} {seconds:7.1f}s {work:7.1f}s {seconds - work:7.1f}s")
    total = sum(stages.values())
    train = stages.get(f"train@{group}", float("nan"))
    print(f"{'total':32s} {total:7.1f}s  (goal {GOAL_S:.0f} s: {'met' if total <= GOAL_S else 'missed'})")
    print(f"total / train@{group}: {total / train:.2f}")
    networks = _networks_s(group)
    print(
        f"least this layout could cost: the networks' training {networks:.1f} s (searches side by side, "
        f"cross-validation) + outside the steps {outside:.1f} s = {networks + outside:.1f} s"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--group", default="r_arm_ft", help="a key of train.groups (default r_arm_ft)")
    parser.add_argument("--lr", type=float, default=0.01, help="the learning rate written (default 0.01)")
    args = parser.parse_args()
    os.chdir(ROOT)  # the pipeline's MLflow store is found from the working directory
    params = ROOT / "params.yaml"
    original = params.read_text()
    pattern = rf"(\n    {re.escape(args.group)}: \{{)"
    if not re.search(pattern, original):
        raise SystemExit(f"params.yaml: no one-line entry `{args.group}: {{...}}` under train.groups")
    status = subprocess.run([sys.executable, "-m", "dvc", "status"], cwd=ROOT, capture_output=True, text=True)
    if "up to date" not in status.stdout:
        raise SystemExit("the pipeline is not up to date: run `dvc repro` first")
    params.write_text(re.sub(pattern, rf"\1lr: {args.lr}, ", original, count=1))
    started = time.time()
    try:
        stages = _repro()
    finally:
        params.write_text(original)
    if f"train@{args.group}" not in stages:  # DVC took the outputs of an earlier run of this edit back
        _repro()
        raise SystemExit(f"train@{args.group} did not run: DVC's run cache holds this edit; try another --lr")
    _print(stages, _in_runs(started), args.group)
    print("restoring the previous outputs (dvc run cache) ...")
    _repro()
    return 0


if __name__ == "__main__":
    sys.exit(main())
