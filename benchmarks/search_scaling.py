"""Shared Optuna studies on PostgreSQL: coordination cost per trial, load, and one group's search wall time.

Starts its own PostgreSQL server (`pipeline.tools.db`, throwaway cluster, fsync off) and prints:

1. coordination cost per trial: one process runs trials of an empty objective (RandomSampler, so the
   sampler costs nothing) on the journal file and on PostgreSQL (heartbeat on);
2. load: W processes x T empty trials against one study on PostgreSQL: every slot run once, trials/s;
3. one group's search (`ftcal train`, nn7 only, n_trials trials) on the labelled directory: 1 process on
   the journal file vs the stage + N `ftcal worker` processes on PostgreSQL, wall time from launch to the
   stage's end (both log to MLflow on the same PostgreSQL).

    python benchmarks/search_scaling.py [--labelled /work/main/data/labelled] [--group r_leg_ft]
        [--trials 8] [--workers 4] [--load-workers 16] [--load-trials 50] [--empty-trials 200]
    python benchmarks/search_scaling.py --quick   # a few trials of tiny networks on synthetic labelled logs

``--group`` is a key of ``train.groups``, or an FT sensor trained alone (its group is added to the params).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks import QUICK  # noqa: E402
from pipeline.calib import studies  # noqa: E402
from pipeline.core.defaults import resolve  # noqa: E402
from pipeline.tools import db  # noqa: E402
from tests.factories.labelled import LEG, write_labelled_logs  # noqa: E402
from tests.pgserver import create_database, free_port  # noqa: E402

_LOAD_WORKER = """
import json, sys, time
from pathlib import Path
import optuna
from pipeline.calib import studies
url, name, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
storage = studies.open_storage(url, Path(), 5)
t0 = time.time()
ran = studies.run_worker(storage, name, None, lambda t: t.suggest_float("x", 0, 1), n,
                         lambda i: optuna.samplers.RandomSampler(seed=i), wait=120)
print(json.dumps({"ran": ran, "start": t0, "end": time.time()}))
"""


def _empty(trial: object) -> float:
    return trial.suggest_float("x", 0.0, 1.0)  # type: ignore[attr-defined]


def coordination(url: str, tmp: Path, n: int) -> dict[str, float]:
    """Seconds per trial of an empty objective run by one process, journal file vs database."""
    import optuna

    out = {}
    for label, storage in (
        ("journal", studies.open_storage(None, tmp / "journal", 10)),
        ("postgresql", studies.open_storage(url, tmp, 10)),
    ):
        study = studies.open_study(storage, f"empty-{label}", None, n, {"x": 0.5})
        t0 = time.perf_counter()
        studies.run_trials(study, _empty, n, lambda i: optuna.samplers.RandomSampler(seed=i))
        out[label] = (time.perf_counter() - t0) / n
    return out


def load(url: str, workers: int, trials: int) -> dict[str, float]:
    """`workers` processes x `trials` empty trials on one study; checks every slot ran exactly once."""
    n = workers * trials
    storage = studies.open_storage(url, Path(), 5)
    study = studies.open_study(storage, "load", None, n, {"x": 0.5})
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _LOAD_WORKER, url, "load", str(n)],
            env=env,
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(workers)
    ]
    reports = [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in procs]
    trials_ = study.get_trials(deepcopy=False)
    indices = sorted(studies.trial_index(t) for t in trials_)
    assert indices == list(range(n)), "a slot was lost or run twice"
    assert all(t.state.name == "COMPLETE" for t in trials_) and sum(r["ran"] for r in reports) == n
    wall = max(r["end"] for r in reports) - min(r["start"] for r in reports)
    return {"trials": n, "wall_s": wall, "trials_per_s": n / wall, "max_connections_used": workers * 3}


def _params(tmp: Path, trials: int, group: str, quick: bool) -> Path:
    data = resolve(yaml.safe_load((ROOT / "params.yaml").read_text()))[0]
    data["train"]["defaults"].update(inputs=[7], n_trials=trials, tpe_startup_trials=trials)
    if quick:
        data["train"]["defaults"].update(hidden=16, epochs=2, batch_size=128, search={})
    data["train"]["groups"].setdefault(group, {"sensor": group})
    path = tmp / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def search(
    url: str, tmp: Path, labelled: Path, group: str, trials: int, workers: int, quick: bool = False
) -> dict[str, float]:
    """Wall time of one group's nn7 search: 1 process (journal) vs stage + `workers` workers (database)."""
    params = _params(tmp, trials, group, quick)
    mlflow_url = create_database(url, "mlflow").replace("postgresql://", "postgresql+psycopg://")
    base = {**os.environ, "PYTHONPATH": str(ROOT), "MLFLOW_TRACKING_URI": mlflow_url}
    base.pop(studies.ENV_STORAGE, None)
    ftcal = [sys.executable, "-m", "pipeline.cli"]
    train = [*ftcal, "train", group, str(labelled)]
    out = {}
    t0 = time.perf_counter()
    subprocess.run(
        [*train, str(tmp / "a"), "--studies", str(tmp / "sa"), "--params", str(params)], env=base, check=True
    )
    out["1 process (journal)"] = time.perf_counter() - t0

    env = {**base, studies.ENV_STORAGE: create_database(url, "search")}
    t0 = time.perf_counter()
    procs = [
        subprocess.Popen([*ftcal, "worker", group, str(labelled), "--params", str(params)], env=env)
        for _ in range(workers)
    ]
    subprocess.run(
        [*train, str(tmp / "b"), "--studies", str(tmp / "sb"), "--params", str(params)], env=env, check=True
    )
    out[f"stage + {workers} workers (postgresql)"] = time.perf_counter() - t0
    for p in procs:
        p.wait(120)
    for name in ("a", "b"):
        m = json.loads((tmp / name / "metrics.json").read_text())
        out[f"{name}: nn7 val rmse_labelled"] = m["networks"]["nn7"]["val_rmse_labelled"]
        out[f"{name}: nn7 search s (in metrics)"] = m["seconds"]["nn7"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--labelled", type=Path, default=Path("/work/main/data/labelled"))
    parser.add_argument("--group", default="r_leg_ft")
    parser.add_argument("--trials", type=int, default=8)
    parser.add_argument("--workers", type=int, default=4)
    parser.add_argument("--load-workers", type=int, default=16)
    parser.add_argument("--load-trials", type=int, default=50)
    parser.add_argument("--empty-trials", type=int, default=200)
    parser.add_argument("--skip-search", action="store_true", help="only the coordination and load figures")
    parser.add_argument("--only-search", action="store_true", help="only the search wall times")
    parser.add_argument(
        "--quick", action="store_true", help=f"{QUICK}: tiny networks on synthetic labelled logs"
    )
    args = parser.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="ftcal-bench-"))
    tmp.chmod(0o755)
    if args.quick:
        args.trials, args.workers, args.load_workers, args.load_trials, args.empty_trials = 2, 1, 2, 3, 5
        args.group, args.labelled = LEG, write_labelled_logs(tmp / "labelled", n=300)
    data = tmp / "pgdata"
    print(f"machine: {os.cpu_count()} cores; PostgreSQL cluster in {data}")
    pg = db.start(data, free_port(), {"fsync": "off", "synchronous_commit": "off"})
    try:
        url = studies.storage_url(create_database(pg, "bench"))
        if not args.only_search:
            per = coordination(url, tmp, args.empty_trials)
            print(f"coordination per empty trial, 1 process, {args.empty_trials} trials:")
            for k, v in per.items():
                print(f"  {k:<12} {1000 * v:7.1f} ms")
            print(f"  ratio postgresql / journal: {per['postgresql'] / per['journal']:.2f}")
            r = load(url, args.load_workers, args.load_trials)
            print(
                f"load: {args.load_workers} processes x {args.load_trials} empty trials = {r['trials']} "
                f"trials, each run once, in {r['wall_s']:.1f} s: {r['trials_per_s']:.1f} trials/s"
            )
        if not args.skip_search:
            s = search(pg, tmp, args.labelled, args.group, args.trials, args.workers, args.quick)
            print(f"one group's search ({args.group}, nn7, {args.trials} trials), launch to stage end:")
            for k, v in s.items():
                print(f"  {k:<40} {v:8.3f}")
            keys = list(s)
            print(f"  speed-up: {s[keys[0]] / s[keys[1]]:.2f}")
    finally:
        db.stop(data)
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
